#!/usr/bin/env python3
"""Quadric simplification: Ocellus's `mesh.simplify` beside Open3D's
`simplify_quadric_decimation` on the same mesh and target.

Input: a closed mesh of about 1.1 M triangles that this project makes: graphs/poisson.ron at
depth 9 (screened Poisson of the generated genus-2 points), emitted by the Ocellus binary (or
any OBJ/PLY with --mesh). Both tools simplify it to each target; each result is scored against
the input mesh, both ways, with Open3D's RaycastingScene (exact point-to-triangle distances):
  simplified→input: distance of 200 000 area-uniform samples of the simplified mesh;
  input→simplified: distance of 200 000 samples of the input.
Reported: the mean of each direction, Chamfer (their sum) and Hausdorff (the larger maximum).
Time: Open3D's call alone; Ocellus's `simplify` node from `--profile` (median of --repeat runs,
file reading excluded).

Usage (release build first: cargo build --release):
  python3 bench/simplify_open3d.py [--targets 100000 10000 1000] [--threads 1 2] [--repeat 3]
Needs numpy and open3d (pip install open3d numpy).
"""
import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import open3d as o3d

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
GRAPH = os.path.join(ROOT, "bench", "simplify.ron")


def make_input(binary, out):
    subprocess.run([binary, "run", os.path.join(ROOT, "graphs", "poisson.ron"), "--set",
                    "poisson.depth=9", "--emit", out], check=True, stdout=subprocess.DEVNULL)
    return os.path.join(out, "mesh.ply")


def distances(mesh, points):
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def score(simplified, original, original_samples):
    a = distances(original, np.asarray(simplified.sample_points_uniformly(200_000).points))
    b = distances(simplified, original_samples)
    return a.mean(), b.mean(), max(a.max(), b.max())


def open3d_run(binary, path, target, threads, repeat):
    mesh = o3d.io.read_triangle_mesh(path)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = mesh.simplify_quadric_decimation(target_number_of_triangles=target)
        times.append(time.perf_counter() - t0)
    return out, float(np.median(times))


def ocellus_run(binary, path, target, threads, repeat):
    with tempfile.TemporaryDirectory() as out:
        prof = os.path.join(out, "profile.json")
        subprocess.run([binary, "run", GRAPH, "--set", f"mesh.path={path}", "--set",
                        f"simplify.target_triangles={target}", "--threads", str(threads),
                        "--repeat", str(repeat), "--profile", prof, "--emit", out],
                       check=True, stdout=subprocess.DEVNULL)
        ms = json.load(open(prof))["nodes"]["simplify"]["median_ms"]
        mesh = o3d.io.read_triangle_mesh(os.path.join(out, "mesh.ply"))
    return mesh, ms / 1000.0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--targets", type=int, nargs="+", default=[100_000, 10_000, 1000])
    ap.add_argument("--threads", type=int, nargs="+", default=[1])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--mesh", help="input OBJ/PLY (default: graphs/poisson.ron at depth 9)")
    ap.add_argument("--binary", default=os.path.join(ROOT, "target", "release", "ocellus"))
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.abspath(args.mesh) if args.mesh else make_input(args.binary, tmp)
        original = o3d.io.read_triangle_mesh(path)
        samples = np.asarray(original.sample_points_uniformly(200_000).points)
        print(f"open3d {o3d.__version__}; input {len(original.triangles)} triangles",
              file=sys.stderr)
        print("| target | threads | tool | simplified→input | input→simplified | Chamfer | "
              "Hausdorff | triangles | time (s) |")
        print("|---|---|---|---|---|---|---|---|---|")
        for target in args.targets:
            for threads in args.threads:
                for name, run in (("Ocellus", ocellus_run), ("Open3D", open3d_run)):
                    mesh, seconds = run(args.binary, path, target, threads, args.repeat)
                    a, b, h = score(mesh, original, samples)
                    print(f"| {target} | {threads} | {name} | {a:.6f} | {b:.6f} | {a + b:.6f} | "
                          f"{h:.5f} | {len(mesh.triangles)} | {seconds:.3f} |", flush=True)


if __name__ == "__main__":
    main()
