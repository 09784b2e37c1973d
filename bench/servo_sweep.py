#!/usr/bin/env python3
"""Speed–accuracy sweep of graphs/servo.ron: control gain and rasterizer samples against the
frames the loop needs and how close the camera ends to the goal.

For each setting, runs `ocellus run graphs/servo.ron --emit DIR` (release build) and reads the
emitted per-frame `error` and `poses` and the `goal_pose`. Reports the wall time of the run, the
first frame whose camera is within 1 mm and 0.1° of the goal, and the final pose error.

    cargo build --release
    python3 bench/servo_sweep.py --gains 1 2 3 5 8 --samples 1 4 --frames 90
"""

import argparse
import json
import math
import pathlib
import subprocess
import tempfile
import time

ROOT = pathlib.Path(__file__).resolve().parent.parent
BIN = ROOT / "target" / "release" / "ocellus"


def pose_error(a, b):
    """(centre distance in mm, rotation angle in degrees) between two camera_from_world poses."""
    ra, rb = a["rotation"], b["rotation"]
    ta, tb = a["translation"], b["translation"]

    def centre(r, t):
        # c = −Rᵀ t
        return [-(r[0 + i] * t[0] + r[3 + i] * t[1] + r[6 + i] * t[2]) for i in range(3)]

    ca, cb = centre(ra, ta), centre(rb, tb)
    dist_mm = 1000.0 * math.dist(ca, cb)
    # trace(Ra Rbᵀ)
    trace = sum(ra[3 * i + k] * rb[3 * i + k] for i in range(3) for k in range(3))
    angle = math.degrees(math.acos(max(-1.0, min(1.0, (trace - 1.0) / 2.0))))
    return dist_mm, angle


def run(gain, samples, frames, threads):
    with tempfile.TemporaryDirectory() as out:
        args = [
            str(BIN), "run", str(ROOT / "graphs" / "servo.ron"), "--emit", out,
            "--threads", str(threads),
            "--set", f"servo.gain={gain}",
            "--set", f"eye.samples={samples}",
            "--set", f"eye.frames={frames}",
        ]
        start = time.perf_counter()
        done = subprocess.run(args, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if done.returncode != 0:
            return {"gain": gain, "samples": samples, "failed": done.stderr.strip()[-300:]}
        out = pathlib.Path(out)
        goal = json.loads((out / "goal_pose.json").read_text())
        errors = []
        for k in range(frames):
            pose = json.loads((out / "poses" / f"{k:0{len(str(frames - 1))}d}.json").read_text())
            errors.append(pose_error(pose, goal))
        reached = next(
            (k for k, (d, a) in enumerate(errors) if d < 1.0 and a < 0.1), None
        )
        return {
            "gain": gain,
            "samples": samples,
            "wall_s": wall,
            "reached": reached,
            "final_mm": errors[-1][0],
            "final_deg": errors[-1][1],
        }


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--gains", type=float, nargs="+", default=[1, 2, 3, 5, 8])
    parser.add_argument("--samples", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    print("| gain | samples | run (s) | first frame within 1 mm and 0.1° | final error (mm) | final error (°) |")
    print("|---|---|---|---|---|---|")
    for samples in args.samples:
        for gain in args.gains:
            r = run(gain, samples, args.frames, args.threads)
            if "failed" in r:
                print(f"| {gain:g} | {samples} | failed: {r['failed']} | | | |")
                continue
            reached = "never" if r["reached"] is None else str(r["reached"])
            print(
                f"| {gain:g} | {samples} | {r['wall_s']:.2f} | {reached} | "
                f"{r['final_mm']:.4f} | {r['final_deg']:.4f} |"
            )


if __name__ == "__main__":
    main()
