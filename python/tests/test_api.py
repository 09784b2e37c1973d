"""The Python API: the README example, conversions against the CLI's emitted files, errors."""

from __future__ import annotations

import json
import os
import re

import numpy as np
import pytest

import ocellus
from conftest import ROOT, read_image, read_json, run_cli


def readme_example() -> str:
    """The notebook-style example from README.md (the ```python block under "Python")."""
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## Python") :]
    match = re.search(r"```python\n(.*?)```", section, re.S)
    assert match, "README.md has no python example under ## Python"
    return match.group(1)


def test_readme_example_returns_what_the_cli_emits(tmp_path, monkeypatch):
    code = readme_example()
    assert len(code.strip().splitlines()) <= 10, "the README example should stay short"
    monkeypatch.chdir(ROOT)
    namespace: dict = {}
    exec(compile(code, "README.md", "exec"), namespace)
    out = namespace["out"]

    emit = tmp_path / "emit"
    run_cli(
        "run", "graphs/features.ron", "--set", "detect.method=orb", "--set", "detect.max_features=500",
        "--threads", "2", "--emit", str(emit),
    )
    for side in ("left", "right"):
        emitted = read_json(emit / f"keypoints_{side}.json")
        arr = out[f"keypoints_{side}"]
        assert arr.dtype == ocellus.KEYPOINT_DTYPE
        assert len(arr) == len(emitted) > 50
        for field in ("x", "y", "size", "angle", "response"):
            np.testing.assert_array_equal(arr[field], np.array([k[field] for k in emitted], dtype=np.float32))
        np.testing.assert_array_equal(arr["octave"], [k["octave"] for k in emitted])
    matches = read_json(emit / "matches.json")
    assert len(out["matches"]) == len(matches) > 20
    for field in ("query", "train"):
        np.testing.assert_array_equal(out["matches"][field], [m[field] for m in matches])
    np.testing.assert_array_equal(
        out["matches"]["distance"], np.array([m["distance"] for m in matches], dtype=np.float32)
    )
    drawing = read_image(emit / "drawing.png", tmp_path)
    assert out["drawing"].dtype == np.uint8 and out["drawing"].shape == drawing.shape
    np.testing.assert_array_equal(out["drawing"], drawing)


def test_matrices_integers_and_lists_match_the_cli(tmp_path):
    graph = ocellus.Graph.load(ROOT / "graphs" / "homography.ron")
    out = graph.run(threads=2)
    emit = tmp_path / "emit"
    run_cli("run", "graphs/homography.ron", "--threads", "2", "--emit", str(emit))
    h = read_json(emit / "H.json")
    assert out["H"].shape == (h["rows"], h["cols"]) == (3, 3)
    np.testing.assert_array_equal(out["H"].ravel(), h["data"])
    assert isinstance(out["inliers"], int) and out["inliers"] == read_json(emit / "inliers.json")

    views = ocellus.Graph.load(ROOT / "graphs" / "many_views.ron").run(outputs=["keypoints", "pairs"])
    assert len(views["keypoints"]) == 48 and all(k.dtype == ocellus.KEYPOINT_DTYPE for k in views["keypoints"])
    assert views["pairs"].shape == (138, 2)
    assert np.all(views["pairs"][:, 0] < views["pairs"][:, 1])


def test_ops_is_the_cli_reference():
    cli = json.loads(run_cli("ops", "--json").stdout)
    assert ocellus.ops() == cli
    assert any(op["id"] == "sfm.pair_lists" for op in cli)


def test_invalid_graph_raises_with_file_line_col(tmp_path):
    bad = tmp_path / "bad.ron"
    bad.write_text('Graph(\n  name: "bad",\n  nodes: { "a": (op: "filter.gausian", params: ()) },\n  outputs: {},\n)\n')
    with pytest.raises(ocellus.GraphError) as err:
        ocellus.Graph.load(bad)
    assert f"{bad}:3:" in str(err.value)
    diag = err.value.diagnostics[0]
    assert diag["location"].startswith(f"{bad}:3:")
    assert "filter.gaussian" in (diag["help"] or "") + diag["message"]

    malformed = tmp_path / "malformed.ron"
    malformed.write_text("Graph(\n  name: \"m\",\n  nodes: {\n")
    with pytest.raises(ocellus.GraphError, match=re.escape(str(malformed)) + r":\d+:\d+"):
        ocellus.Graph.load(malformed)


def test_set_checks_values_and_keeps_the_graph_on_error():
    graph = ocellus.Graph.load(ROOT / "graphs" / "features.ron")
    graph.set("detect.max_features", 300)
    with pytest.raises(ocellus.GraphError) as err:
        graph.set("detect.method", "surf")
    assert "--set" in str(err.value)
    with pytest.raises(ocellus.GraphError):
        graph.set("detcet.method", "orb")
    assert graph.overrides == ["detect.max_features=300"]
    out = graph.run(outputs=["keypoints_left"], threads=1)
    assert 0 < len(out["keypoints_left"]) <= 300


def test_node_failure_raises_run_error(tmp_path):
    graph = ocellus.Graph.load(ROOT / "graphs" / "features.ron")
    graph.set("left.path", str(tmp_path / "missing.png"))
    with pytest.raises(ocellus.RunError) as err:
        graph.run()
    assert err.value.failures[0]["node"] == "left"
    assert "features.ron" in err.value.failures[0]["location"]


def test_results_are_deterministic_across_thread_counts():
    graph = ocellus.Graph.load(ROOT / "graphs" / "features.ron")
    one = graph.run(threads=1)
    two = graph.run(threads=2)
    for name in one:
        assert one[name].tobytes() == two[name].tobytes(), name
    assert graph.last_report["summary"].startswith("5 computed")
