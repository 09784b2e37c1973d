#!/usr/bin/env python3
"""Rate–distortion and speed sweeps of the block video codec (graphs/codec.ron).

Each setting runs
    ocellus run graphs/codec.ron --set clip.width=320 --set clip.height=240 --set clip.frames=30
        --set enc.PARAM=VALUE ... --output rate_distortion --repeat 3 --profile P --emit DIR
and reads `rate_distortion.json` (bits, bpp, PSNR of `video.encode`) and the median time of the
`enc` node from the profile. Prints three Markdown tables: quantizer (and matrix) vs bpp vs PSNR,
search method/range vs bits vs time, GOP vs bits.

    cargo build --release
    python3 bench/codec_sweep.py [--bin target/release/ocellus] [--threads 2]
"""

import argparse
import json
import pathlib
import subprocess
import tempfile

ROOT = pathlib.Path(__file__).resolve().parent.parent
CLIP = ["clip.width=320", "clip.height=240", "clip.frames=30"]


def run(binary, settings, threads, repeat):
    with tempfile.TemporaryDirectory() as out:
        profile = pathlib.Path(out) / "p.json"
        args = [binary, "run", str(ROOT / "graphs" / "codec.ron"), "--threads", str(threads),
                "--output", "rate_distortion", "--repeat", str(repeat),
                "--profile", str(profile), "--emit", out]
        for s in CLIP + settings:
            args += ["--set", s]
        done = subprocess.run(args, capture_output=True, text=True)
        if done.returncode != 0:
            raise SystemExit(f"{settings}: {done.stderr.strip()[-400:]}")
        metrics = json.loads((pathlib.Path(out) / "rate_distortion.json").read_text())
        prof = json.loads(profile.read_text())
        metrics["enc_ms"] = prof["nodes"]["enc"]["median_ms"]
        return metrics


def row(label, m):
    p_kbit = f"{m['p_bits_mean'] / 1000:.1f}" if m["p_frames"] > 0 else "–"
    return (f"| {label} | {m['bpp']:.4f} | {m['bits'] / 1000:.1f} | {m['psnr_mean_db']:.2f} | "
            f"{m['psnr_min_db']:.2f} | {m['i_bits_mean'] / 1000:.1f} | {p_kbit} | "
            f"{m['enc_ms']:.0f} |")


HEAD = ("| setting | bpp | kbit | PSNR mean dB | PSNR min dB | I kbit/frame | P kbit/frame | "
        "encode ms |\n|---|---:|---:|---:|---:|---:|---:|---:|")


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--bin", default=str(ROOT / "target" / "release" / "ocellus"))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeat", type=int, default=3)
    a = parser.parse_args()
    go = lambda s: run(a.bin, s, a.threads, a.repeat)  # noqa: E731

    print("### Quantizer (gop 8, full search ±8)\n")
    print(HEAD)
    for matrix in ["jpeg", "flat"]:
        for q in [1, 2, 4, 8, 16, 32, 64]:
            m = go([f"enc.quantizer={q}.0", f"enc.matrix={matrix}"])
            print(row(f"{matrix} q={q}", m), flush=True)

    print("\n### Motion search (quantizer 12, gop 30: one I-frame)\n")
    print(HEAD)
    for method in ["full", "coarse_to_fine"]:
        for r in [0, 2, 4, 8, 16]:
            if method == "coarse_to_fine" and r == 0:
                continue
            m = go([f"enc.search={method}", f"enc.search_px={r}", "enc.gop=30"])
            print(row(f"{method} ±{r}", m), flush=True)

    print("\n### GOP (quantizer 12, full search ±8)\n")
    print(HEAD)
    for gop in [1, 2, 4, 8, 15, 30]:
        m = go([f"enc.gop={gop}"])
        print(row(f"gop {gop}", m), flush=True)


if __name__ == "__main__":
    main()
