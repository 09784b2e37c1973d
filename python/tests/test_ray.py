"""ocellus.ray and `ocellus run --ray` on a Ray cluster of two worker processes on 127.0.0.1:
outputs byte-identical to a local run, a worker killed mid-run, the run report."""

from __future__ import annotations

import sys
import threading

import numpy as np

import ocellus
import ocellus.ray
from conftest import ROOT, run_cli

GRAPH = ROOT / "graphs" / "many_views.ron"


def same(a, b) -> bool:
    """Byte-identical values (arrays, lists of arrays, dicts, numbers)."""
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()
    if isinstance(a, list):
        return isinstance(b, list) and len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    return a == b


def local_outputs():
    return ocellus.Graph.load(GRAPH).run(threads=2)


def test_distributed_run_is_byte_identical_to_local(ray_cluster, tmp_path):
    cluster, _ = ray_cluster
    local = local_outputs()
    graph = ocellus.Graph.load(GRAPH)
    seen = []
    out = ocellus.ray.run(
        graph, address=cluster.address, item_cache=None, progress=lambda *p: seen.append(p)
    )
    assert out.keys() == local.keys()
    for name in local:
        assert same(out[name], local[name]), name
    stages = {s["node"]: s for s in graph.last_report["distributed"]}
    assert stages["features"]["items"] == 48 and stages["match"]["items"] == 138
    # Both worker processes took part, and every element is accounted for.
    assert len(stages["features"]["workers"]) == 2
    assert sum(w["items"] for w in stages["features"]["workers"].values()) == 48
    assert ("features", 48, 48) in seen and ("match", 138, 138) in seen

    # The CLI with --ray (it starts the Python driver) emits the same files as a local run.
    ray_dir, local_dir = tmp_path / "ray", tmp_path / "local"
    env = {"OCELLUS_PYTHON": sys.executable, "OCELLUS_ITEM_CACHE": str(tmp_path / "items")}
    cli = run_cli(
        "run", str(GRAPH), "--ray", cluster.address, "--emit", str(ray_dir), "--report",
        str(tmp_path / "report.html"), env=env,
    )
    assert "ray: features: 48/48 items" in cli.stderr
    run_cli("run", str(GRAPH), "--threads", "2", "--emit", str(local_dir))
    ray_files = sorted(p.relative_to(ray_dir) for p in ray_dir.rglob("*") if p.is_file())
    local_files = sorted(p.relative_to(local_dir) for p in local_dir.rglob("*") if p.is_file())
    assert ray_files == local_files and len(ray_files) == 48 + 138 + 1
    for rel in ray_files:
        assert (ray_dir / rel).read_bytes() == (local_dir / rel).read_bytes(), rel
    report = (tmp_path / "report.html").read_text()
    assert "Distributed list maps" in report and "Per-worker time" in report

    # A second CLI run finds every element in the item cache.
    again = run_cli("run", str(GRAPH), "--ray", cluster.address, "--emit", str(ray_dir), env=env)
    assert "ray: features: 48/48 items" in again.stderr
    assert "ray: features: 0/48 items" not in again.stderr


def test_a_worker_killed_mid_run_still_gives_identical_outputs(ray_cluster):
    cluster, workers = ray_cluster
    graph = ocellus.Graph.load(GRAPH)
    # SIFT with more features: a longer feature map, so the kill lands while it runs.
    graph.set("features.method", "sift").set("features.max_features", 1500)
    local = ocellus.Graph.load(GRAPH).set("features.method", "sift").set("features.max_features", 1500).run(threads=2)

    progress = {}
    started = threading.Event()

    def on_progress(node, done, total):
        progress[node] = (done, total)
        if node == "features" and done >= 4:
            started.set()

    result = {}

    def run():
        try:
            result["out"] = ocellus.ray.run(
                graph, address=cluster.address, item_cache=None, items_per_task=1,
                progress=on_progress, max_retries=5,
            )
        except BaseException as e:  # reported below
            result["error"] = e

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    assert started.wait(timeout=300), "the distributed run did not start"
    done_at_kill = progress["features"][0]
    cluster.remove_node(workers[1], allow_graceful=False)
    thread.join(timeout=600)
    assert not thread.is_alive(), "the run did not finish after a worker was killed"
    assert "error" not in result, result.get("error")
    assert done_at_kill < 48, "the kill came after the feature map had finished"
    out = result["out"]
    for name in local:
        assert same(out[name], local[name]), name
    stages = {s["node"]: s for s in graph.last_report["distributed"]}
    assert stages["features"]["failed_tasks"] == 0
    assert sum(w["items"] for w in stages["features"]["workers"].values()) == 48
