"""Throughput of graphs/many_views.ron with its list maps on Ray: 1 vs 2 worker processes (each
one CPU, on 127.0.0.1, head with no CPU), beside local runs, and the overhead per task.

    target/pyenv/bin/python python/bench/ray_workers.py [--repeat 3] [--set features.method=sift]

Per-task overhead is what a task costs beyond the operator's own work, from the run report:
(stage wall time × workers − Σ worker busy time) / tasks — payload encoding, the trip through
Ray, decoding and storing the results. A no-op Ray task's round trip is printed for scale.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import ray  # noqa: E402
from ray.cluster_utils import Cluster  # noqa: E402

import ocellus  # noqa: E402
import ocellus.ray  # noqa: E402

GRAPH = Path(__file__).resolve().parents[2] / "graphs" / "many_views.ron"


def median(xs):
    return statistics.median(xs)


SETS: list = []


def load() -> "ocellus.Graph":
    graph = ocellus.Graph.load(GRAPH)
    for item in SETS:
        key, value = item.split("=", 1)
        try:
            parsed = int(value)
        except ValueError:
            try:
                parsed = float(value)
            except ValueError:
                parsed = value
        graph.set(key, parsed)
    return graph


def local(threads: int, repeat: int) -> float:
    graph = load()
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        graph.run(threads=threads)
        times.append(time.perf_counter() - t)
    return median(times)


def distributed(workers: int, repeat: int, items_per_task: int) -> dict:
    cluster = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 0, "include_dashboard": False, "node_ip_address": "127.0.0.1"},
    )
    try:
        for _ in range(workers):
            cluster.add_node(num_cpus=1, node_ip_address="127.0.0.1")
        cluster.wait_for_nodes(timeout=120)
        ray.init(address=cluster.address, _node_ip_address="127.0.0.1", log_to_driver=False)
        graph = load()
        # Warm-up: worker processes start and import the package.
        ocellus.ray.run(graph, item_cache=None, progress=False, items_per_task=items_per_task)
        walls, stages = [], {}
        for _ in range(repeat):
            t = time.perf_counter()
            ocellus.ray.run(graph, item_cache=None, progress=False, items_per_task=items_per_task)
            walls.append(time.perf_counter() - t)
            for s in graph.last_report["distributed"]:
                busy = sum(w["busy_s"] for w in s["workers"].values())
                overhead = (s["elapsed_s"] * workers - busy) / s["tasks"]
                stages.setdefault(s["node"], []).append((s["elapsed_s"], busy, s["tasks"], overhead))

        @ray.remote(num_cpus=1)
        def noop(x):
            return x

        ray.get([noop.remote(b"") for _ in range(20)])
        t = time.perf_counter()
        for _ in range(200):
            ray.get(noop.remote(b""))
        noop_ms = (time.perf_counter() - t) / 200 * 1e3
        return {"wall": median(walls), "stages": stages, "noop_ms": noop_ms}
    finally:
        ray.shutdown()
        cluster.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--items-per-task", type=int, default=0)
    parser.add_argument("--set", action="append", default=[], help="node.param=value")
    args = parser.parse_args()
    SETS.extend(args.set)
    print(f"graph: {GRAPH.name} {' '.join(args.set)}, median of {args.repeat} runs, items per task {args.items_per_task or 'auto'}")
    for threads in (1, 2):
        print(f"local, {threads} thread(s): {local(threads, args.repeat):.2f} s")
    for workers in (1, 2):
        r = distributed(workers, args.repeat, args.items_per_task)
        print(f"ray, {workers} worker process(es): {r['wall']:.2f} s per run; no-op task round trip {r['noop_ms']:.2f} ms")
        for node, runs in r["stages"].items():
            elapsed = median([x[0] for x in runs])
            busy = median([x[1] for x in runs])
            tasks = runs[0][2]
            overhead = median([x[3] for x in runs])
            print(f"  {node}: {tasks} tasks, wall {elapsed:.2f} s, worker busy {busy:.2f} s, overhead {overhead * 1e3:.1f} ms/task")


if __name__ == "__main__":
    main()
