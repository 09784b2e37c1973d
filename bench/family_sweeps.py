#!/usr/bin/env python3
"""Speed–accuracy tables of the learn, sensor, texture and visual-hull operators.

Every row is one `ocellus run` of a graph in `graphs/` with parameters overridden by `--set`,
`--repeat N` runs without the cache; the time is the node's median from `--profile`, the accuracy
the metrics the run emits. Prints Markdown tables (the ones in BENCHMARKS.md).

    cargo build --release
    python3 bench/family_sweeps.py [--bin target/release/ocellus] [--threads 2] [--repeat 3]
        [--only learn,sensor,texture,hull]
"""

import argparse
import json
import pathlib
import subprocess
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent


class Runner:
    def __init__(self, binary, threads, repeat):
        self.binary, self.threads, self.repeat = binary, threads, repeat

    def __call__(self, graph, settings, outputs, repeat=None):
        """Runs `graph` with `settings`, producing `outputs`; returns (metrics, node medians ms)."""
        with tempfile.TemporaryDirectory() as out:
            profile = pathlib.Path(out) / "p.json"
            args = [self.binary, "run", str(ROOT / "graphs" / graph), "--threads",
                    str(self.threads), "--repeat", str(repeat or self.repeat),
                    "--profile", str(profile), "--emit", out]
            for s in settings:
                args += ["--set", s]
            for o in outputs:
                args += ["--output", o]
            done = subprocess.run(args, capture_output=True, text=True)
            if done.returncode != 0:
                raise SystemExit(f"{graph} {settings}: {done.stderr.strip()[-600:]}")
            metrics = {o: json.loads((pathlib.Path(out) / f"{o}.json").read_text())
                       for o in outputs}
            nodes = json.loads(profile.read_text())["nodes"]
            return metrics, {n: v["median_ms"] for n, v in nodes.items()}


def learn(run):
    n = 200_000
    print(f"### Linear regression, {n} samples × 3 features (noise σ = 0.1)\n")
    print("| solver | iterations | stopped after | time ms | loss − optimum | max weight error |")
    print("|---|---:|---:|---:|---:|---:|")
    base = [f"line.samples={n}"]
    m, t = run("learn.ron", base, ["exact_metrics", "exact_weights", "true_weights"])
    optimum = m["exact_metrics"]["loss"]
    exact_w = m["exact_weights"]

    def weight_error(w):
        return max(abs(a - b) for a, b in zip(w["data"], exact_w["data"]))

    print(f"| normal_equation (QR) | – | – | {t['exact']:.1f} | 0 | 0 |", flush=True)
    for solver, rate, iters in [("batch_gd", 0.5, [5, 10, 20, 50, 100]),
                                ("sgd", 0.02, [1, 2, 5, 10, 30])]:
        for k in iters:
            m, t = run("learn.ron", base + [f"sgd.solver={solver}", f"sgd.learning_rate={rate}",
                                            f"sgd.iterations={k}"], ["sgd_metrics", "sgd_weights"])
            s = m["sgd_metrics"]
            print(f"| {solver} (η = {rate}) | {k} | {s['iterations']:.0f} | {t['sgd']:.1f} | "
                  f"{s['loss'] - optimum:.3g} | {weight_error(m['sgd_weights']):.3g} |", flush=True)

    n = 100_000
    print(f"\n### Logistic regression, {n} samples, 3 blobs one-vs-all (L2 = 0.001)\n")
    print("| solver | max iterations | iterations | time ms | gradient norm | log-loss | accuracy |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for solver, caps in [("gd", [10, 100, 1000]), ("newton", [3, 10, 100]),
                         ("lbfgs", [10, 30, 100])]:
        for cap in caps:
            m, t = run("learn.ron", [f"blobs.samples={n}", f"classify.solver={solver}",
                                     f"classify.max_iterations={cap}"], ["classifier_metrics"])
            s = m["classifier_metrics"]
            print(f"| {solver} | {cap} | {s['iterations']:.0f} | {t['classify']:.1f} | "
                  f"{s['gradient_norm']:.2e} | {s['log_loss']:.6f} | {s['accuracy']:.4f} |",
                  flush=True)

    print("\n### HOG detector (192×128 scene, 3 figures): stride and scale step\n")
    print("| stride_cells | scale_step | windows | levels | time ms | AP | precision | recall |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|")
    for stride in [1, 2]:
        for step in [1.1, 1.2, 1.4]:
            m, t = run("learn.ron", [f"detector.stride_cells={stride}",
                                     f"detector.scale_step={step}"], ["detector_metrics"])
            s = m["detector_metrics"]
            print(f"| {stride} | {step} | {s['windows']:.0f} | {s['levels']:.0f} | "
                  f"{t['detector']:.1f} | {s['average_precision']:.3f} | {s['precision']:.3f} | "
                  f"{s['recall']:.3f} |", flush=True)


def sensor(run):
    print("### Demosaicing at 1280×720 (noisy ISO-200 capture, corrected, vs the radiance)\n")
    print("| method | demosaic ms | PSNR dB | SSIM |")
    print("|---|---:|---:|---:|")
    m, t = run("sensor.ron", ["scene.width=1280", "scene.height=720"],
               ["quality_bilinear", "quality_malvar", "quality_hamilton_adams"])
    for method, node, out in [("bilinear", "bilinear", "quality_bilinear"),
                              ("malvar", "malvar", "quality_malvar"),
                              ("hamilton_adams", "hamilton", "quality_hamilton_adams")]:
        q = m[out]
        print(f"| {method} | {t[node]:.1f} | {q['psnr_db']:.2f} | {q['ssim']:.4f} |")
    print(f"\nRaw capture {t['raw']:.1f} ms, radiometric correction {t['lin_malvar']:.1f} ms, "
          f"quality {t['q_malvar']:.1f} ms at 1280×720.\n", flush=True)

    print("### Event camera (96×72 × 12 frames): contrast threshold vs events and error\n")
    print("| contrast C | events | reconstruction RMS (log) | RMS / C | time ms |")
    print("|---:|---:|---:|---:|---:|")
    for c in [0.05, 0.1, 0.2, 0.4, 0.8]:
        m, t = run("sensor.ron", [f"dvs.contrast_threshold={c}"], ["event_metrics"])
        s = m["event_metrics"]
        print(f"| {c} | {s['events']:.0f} | {s['reconstruction_rms_log']:.4f} | "
              f"{s['reconstruction_rms_log'] / c:.3f} | {t['dvs']:.2f} |", flush=True)


def texture(run):
    print("### Efros–Leung, 32×32 from the 48×48 source: window vs time and match\n")
    print("| window_px | time ms | match_rms | patch_match_rms |")
    print("|---:|---:|---:|---:|")
    for w in [3, 5, 7, 9, 11, 15]:
        m, t = run("texture.ron", [f"grow.window_px={w}"], ["grow_metrics"])
        s = m["grow_metrics"]
        print(f"| {w} | {t['grow']:.1f} | {s['match_rms']:.2f} | {s['patch_match_rms']:.2f} |",
              flush=True)

    print("\n### Quilting, 96×96 from the 48×48 source: block, overlap and cut\n")
    print("| block_px | overlap_px | boundary_cut | time ms | overlap_rms | seam_rms |")
    print("|---:|---:|---|---:|---:|---:|")
    for block, overlap, cut in [(8, 2, True), (12, 3, True), (16, 4, True), (16, 4, False),
                                (16, 2, True), (16, 6, True), (24, 6, True)]:
        m, t = run("texture.ron", [f"quilt.block_px={block}", f"quilt.overlap_px={overlap}",
                                   f"quilt.boundary_cut={'true' if cut else 'false'}"],
                   ["quilt_metrics"])
        s = m["quilt_metrics"]
        print(f"| {block} | {overlap} | {cut} | {t['quilt']:.2f} | {s['overlap_rms']:.2f} | "
              f"{s['seam_rms']:.2f} |", flush=True)

    print("\n### Sparse-coding denoising, 96×96 test card (levels 51–204), σ = 20 (noisy input: PSNR below)\n")
    print("| dictionary | atoms | stride_px | time ms | PSNR dB | SSIM |")
    print("|---|---:|---:|---:|---:|---:|")
    m, _ = run("texture.ron", [], ["noisy_score"])
    noisy = m["noisy_score"]
    for atoms, stride in [(64, 1), (64, 2), (64, 4), (256, 1), (256, 2), (256, 4)]:
        m, t = run("texture.ron", [f"dct.atoms={atoms}", f"dct.stride_px={stride}"], ["dct_score"])
        s = m["dct_score"]
        print(f"| dct | {atoms} | {stride} | {t['dct']:.1f} | {s['psnr_db']:.2f} | "
              f"{s['ssim']:.4f} |", flush=True)
    for iters in [1, 3, 10]:
        m, t = run("texture.ron", [f"ksvd.ksvd_iterations={iters}"], ["ksvd_score"])
        s = m["ksvd_score"]
        print(f"| ksvd ({iters} iterations) | 256 | 2 | {t['ksvd']:.1f} | {s['psnr_db']:.2f} | "
              f"{s['ssim']:.4f} |", flush=True)
    print(f"\nNoisy input: {noisy['psnr_db']:.2f} dB, SSIM {noisy['ssim']:.4f}.")


def hull(run):
    print("### Visual hull (nine 160×120 silhouettes): resolution vs volume and time\n")
    print("| resolution | voxels | time ms | volume | triangles |")
    print("|---:|---:|---:|---:|---:|")
    for r in [24, 32, 48, 64, 96, 128, 192, 256]:
        m, t = run("hull.ron", [f"hull.resolution={r}"], ["metrics"])
        s = m["metrics"]
        print(f"| {r} | {s['voxels']:.0f} | {t['hull']:.1f} | {s['volume']:.4f} | "
              f"{s['triangles']:.0f} |", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bin", default=str(ROOT / "target" / "release" / "ocellus"))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--only", default="learn,sensor,texture,hull")
    a = parser.parse_args()
    run = Runner(a.bin, a.threads, a.repeat)
    for family in a.only.split(","):
        {"learn": learn, "sensor": sensor, "texture": texture, "hull": hull}[family](run)
        print()


if __name__ == "__main__":
    main()
