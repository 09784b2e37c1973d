#!/usr/bin/env python3
"""Poisson surface reconstruction: Ocellus's `mesh.poisson` beside Open3D's on the same points.

Input: graphs/data/poisson_points.ply, the oriented points that tests/poisson.rs generates on a
known closed shape (a union of a torus, a sphere and a capsule; the constants below must match
that file). Both reconstructions run at the same depth and scale (1.1) without density trimming;
each is scored against the analytic surface, both ways:
  mesh→truth: |signed distance| of 200 000 area-uniform samples of the mesh;
  truth→mesh: exact distance (Open3D's RaycastingScene) from 100 000 uniform samples of the
  true surface to the mesh.
Chamfer = the sum of the two means. Time: Open3D's call alone; Ocellus's `poisson` node from
`--profile` (median of --repeat runs, file reading excluded).

Usage (release build first: cargo build --release):
  python3 bench/poisson_open3d.py [--depths 7 8 9] [--threads 1 2] [--repeat 3] [--binary B]
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
POINTS = os.path.join(ROOT, "graphs", "data", "poisson_points.ply")
GRAPH = os.path.join(ROOT, "graphs", "poisson.ron")

RING, TUBE = 0.6, 0.2
BALL_CENTRE, BALL = np.array([0.6, 0.0, 0.2]), 0.3
BAR_HALF, BAR = 0.8, 0.1


def sdf(p):
    q = np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2) - RING
    torus = np.sqrt(q**2 + p[:, 2] ** 2) - TUBE
    ball = np.linalg.norm(p - BALL_CENTRE, axis=1) - BALL
    y = np.clip(p[:, 1], -BAR_HALF, BAR_HALF)
    bar = np.sqrt(p[:, 0] ** 2 + (p[:, 1] - y) ** 2 + p[:, 2] ** 2) - BAR
    return np.minimum(np.minimum(torus, ball), bar)


def truth_samples(n, rng):
    """Uniform samples of the union's surface: each primitive by area, points inside another
    primitive dropped (the surviving density is uniform)."""
    areas = np.array([4 * np.pi**2 * RING * TUBE, 4 * np.pi * BALL**2,
                      2 * np.pi * BAR * 2 * BAR_HALF + 4 * np.pi * BAR**2])
    out = []
    m = 4 * n
    counts = rng.multinomial(m, areas / areas.sum())
    # torus (rejection on the ring radius for area uniformity)
    u, v = rng.uniform(0, 2 * np.pi, (2, counts[0] * 2))
    keep = rng.uniform(0, RING + TUBE, u.size) <= RING + TUBE * np.cos(v)
    u, v = u[keep], v[keep]
    r = RING + TUBE * np.cos(v)
    out.append(np.stack([r * np.cos(u), r * np.sin(u), TUBE * np.sin(v)], 1))
    d = rng.normal(size=(counts[1], 3))
    out.append(BALL_CENTRE + BALL * d / np.linalg.norm(d, axis=1, keepdims=True))
    side = 2 * np.pi * BAR * 2 * BAR_HALF
    k = rng.uniform(0, side + 4 * np.pi * BAR**2, counts[2]) < side
    y = rng.uniform(-BAR_HALF, BAR_HALF, k.sum())
    t = rng.uniform(0, 2 * np.pi, k.sum())
    out.append(np.stack([BAR * np.cos(t), y, BAR * np.sin(t)], 1))
    d = rng.normal(size=((~k).sum(), 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out.append(np.stack([BAR * d[:, 0], np.where(d[:, 1] >= 0, BAR_HALF, -BAR_HALF) + BAR * d[:, 1],
                         BAR * d[:, 2]], 1))
    p = np.concatenate(out)
    p = p[np.abs(sdf(p)) < 1e-9]  # on the union's surface, i.e. not inside another primitive
    return p[rng.permutation(len(p))[:n]]


def score(mesh, truth):
    sampled = mesh.sample_points_uniformly(200_000)
    to_truth = np.abs(sdf(np.asarray(sampled.points))).mean()
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    to_mesh = scene.compute_distance(o3d.core.Tensor(truth.astype(np.float32))).numpy().mean()
    return to_truth, to_mesh


def open3d_run(binary, depth, threads, repeat):
    pcd = o3d.io.read_point_cloud(POINTS)
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=depth, scale=1.1, linear_fit=False, n_threads=threads)
        times.append(time.perf_counter() - t0)
    return mesh, float(np.median(times))


EXTRA_SETS = []


def ocellus_run(binary, depth, threads, repeat):
    with tempfile.TemporaryDirectory() as out:
        prof = os.path.join(out, "profile.json")
        sets = [a for s in EXTRA_SETS for a in ("--set", s)]
        subprocess.run([binary, "run", GRAPH, "--set", f"poisson.depth={depth}", *sets,
                        "--threads", str(threads), "--repeat", str(repeat), "--profile", prof,
                        "--emit", out], check=True, stdout=subprocess.DEVNULL)
        ms = json.load(open(prof))["nodes"]["poisson"]["median_ms"]
        mesh = o3d.io.read_triangle_mesh(os.path.join(out, "mesh.ply"))
    return mesh, ms / 1000.0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--depths", type=int, nargs="+", default=[7, 8])
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--binary", default=os.path.join(ROOT, "target", "release", "ocellus"))
    ap.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                    help="extra parameter for the Ocellus graph (repeatable)")
    ap.add_argument("--only", choices=["Ocellus", "Open3D"], help="run one tool only")
    args = ap.parse_args()
    EXTRA_SETS.extend(args.set)
    truth = truth_samples(100_000, np.random.default_rng(1))
    print(f"open3d {o3d.__version__}, {len(truth)} truth samples", file=sys.stderr)
    print("| depth | threads | tool | mesh→truth | truth→mesh | Chamfer | triangles | time (s) |")
    print("|---|---|---|---|---|---|---|---|")
    for depth in args.depths:
        for threads in args.threads:
            for name, run in (("Ocellus", ocellus_run), ("Open3D", open3d_run)):
                if args.only and name != args.only:
                    continue
                mesh, seconds = run(args.binary, depth, threads, args.repeat)
                a, b = score(mesh, truth)
                print(f"| {depth} | {threads} | {name} | {a:.5f} | {b:.5f} | {a + b:.5f} | "
                      f"{len(mesh.triangles)} | {seconds:.3f} |", flush=True)


if __name__ == "__main__":
    main()
