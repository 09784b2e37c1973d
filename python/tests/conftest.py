"""Shared fixtures: the repository root, the CLI binary, a small PNG reader, and a Ray cluster on
loopback (a head and two worker processes, stopped when the test ends)."""

from __future__ import annotations

import os

# Ray announces the machine's network address unless told to stay on loopback; set before Ray is
# imported anywhere in the session.
os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


def ocellus_bin() -> str:
    """The CLI: $OCELLUS_BIN, else the cargo build in target/."""
    explicit = os.environ.get("OCELLUS_BIN")
    if explicit:
        return explicit
    for profile in ("debug", "release"):
        candidate = ROOT / "target" / profile / "ocellus"
        if candidate.exists():
            return str(candidate)
    pytest.fail("no ocellus binary: build it with `cargo build` or set OCELLUS_BIN")


def run_cli(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    full_env = dict(os.environ, **(env or {}))
    out = subprocess.run(
        [ocellus_bin(), *args], cwd=ROOT, capture_output=True, text=True, env=full_env, timeout=600
    )
    assert out.returncode == 0, f"ocellus {' '.join(args)} failed:\n{out.stderr}"
    return out


def read_image(path: Path, tmp_path: Path) -> np.ndarray:
    """An emitted image file decoded by the engine's own reader, through the Python API."""
    import ocellus

    graph = tmp_path / "read_image.ron"
    graph.write_text(
        'Graph(name: "read", nodes: { "img": (op: "io.read_image", params: (path: %s)) },'
        ' outputs: { "image": "img.image" })' % json.dumps(str(path))
    )
    return ocellus.Graph.load(graph).run()["image"]


def read_json(path: Path):
    return json.loads(path.read_text())


@pytest.fixture
def ray_cluster():
    """A Ray head (no CPUs: it only schedules) and two worker processes, each with one CPU,
    all on 127.0.0.1. Yields (cluster, [worker node handles]); everything is stopped after."""
    import ray
    from ray.cluster_utils import Cluster

    cluster = Cluster(
        initialize_head=True,
        head_node_args={"num_cpus": 0, "include_dashboard": False, "node_ip_address": "127.0.0.1"},
    )
    try:
        workers = [cluster.add_node(num_cpus=1, node_ip_address="127.0.0.1") for _ in range(2)]
        cluster.wait_for_nodes(timeout=120)
        yield cluster, workers
    finally:
        if ray.is_initialized():
            ray.shutdown()
        cluster.shutdown()
