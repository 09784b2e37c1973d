#!/usr/bin/env python3
"""The speed–accuracy trade of `animate.cloth` in graphs/animate.ron: substeps and integrator
against time and against a fine reference run.

For each (integrator, substeps) the last frame's cloth (frame 47, `--frame 47 --output cloth`)
is emitted as OBJ and compared with the reference run (implicit Euler, 64 substeps): the mean
and largest vertex distance, in millimetres, over the 576 particles. Time is the `cloth` node's
median over --repeat runs from `--profile` (the simulation of all 48 frames; the other nodes run
for one frame). A diverged run (the node fails) is reported as such.

Usage (release build first: cargo build --release):
  python3 bench/cloth_sweep.py [--substeps 1 2 4 8 16] [--threads 1] [--repeat 3]
Needs only the Python standard library.
"""
import argparse
import json
import math
import os
import subprocess
import sys
import tempfile

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BIN = os.path.join(ROOT, "target", "release", "ocellus")
GRAPH = os.path.join(ROOT, "graphs", "animate.ron")


def run(integrator, substeps, threads, repeat, tmp):
    out = os.path.join(tmp, f"{integrator}-{substeps}")
    profile = os.path.join(tmp, f"{integrator}-{substeps}.json")
    cmd = [BIN, "run", GRAPH, "--frame", "47", "--output", "cloth", "--threads", str(threads),
           "--set", f"cloth.integrator={integrator}", "--set", f"cloth.substeps={substeps}",
           "--repeat", str(repeat), "--profile", profile, "--emit", out]
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        reason = "diverged" if "diverged" in p.stderr else p.stderr.strip().splitlines()[-1]
        return None, None, reason
    with open(profile) as f:
        ms = json.load(f)["nodes"]["cloth"]["median_ms"]
    vertices = []
    with open(os.path.join(out, "cloth.obj")) as f:
        for line in f:
            if line.startswith("v "):
                vertices.append(tuple(float(x) for x in line.split()[1:4]))
    return vertices, ms, None


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--substeps", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    ap.add_argument("--integrators", nargs="+",
                    default=["implicit_euler", "symplectic_euler", "velocity_verlet", "rk4"])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    if not os.path.exists(BIN):
        sys.exit("build first: cargo build --release")
    with tempfile.TemporaryDirectory() as tmp:
        reference, ref_ms, why = run("implicit_euler", 64, args.threads, 1, tmp)
        if reference is None:
            sys.exit(f"reference run failed: {why}")
        print(f"reference: implicit_euler, 64 substeps ({ref_ms:.1f} ms)")
        print("| integrator | substeps | cloth time (ms) | mean deviation (mm) | max deviation (mm) |")
        print("|---|---|---|---|---|")
        for integrator in args.integrators:
            for n in args.substeps:
                vertices, ms, why = run(integrator, n, args.threads, args.repeat, tmp)
                if vertices is None:
                    print(f"| {integrator} | {n} | – | {why} | – |")
                    continue
                d = [math.dist(a, b) * 1e3 for a, b in zip(vertices, reference)]
                print(f"| {integrator} | {n} | {ms:.1f} | {sum(d) / len(d):.2f} | {max(d):.2f} |")


if __name__ == "__main__":
    main()
