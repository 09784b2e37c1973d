"""Ocellus from Python: load a graph, change parameters, run it, get NumPy arrays back.

    import ocellus
    g = ocellus.Graph.load("graphs/features.ron")
    g.set("detect.method", "orb")
    out = g.run(outputs=["keypoints_left", "matches"], threads=2)
    out["keypoints_left"]["x"]          # structured array: x, y, size, angle, response, octave

Values come back as:

* Image: ``numpy.ndarray`` of shape (H, W) or (H, W, C), dtype uint8, uint16 or float32;
* Keypoints: structured array with fields ``x y size angle response octave`` (KEYPOINT_DTYPE);
* Matches: structured array with fields ``query train distance`` (MATCH_DTYPE);
* Descriptors: (N, D) float32 or (N, bytes) uint8;
* Matrix: (rows, cols) float64; Points2D: (N, 2) float64;
* PointCloud and Mesh: dicts of arrays; Reconstruction: a dict (cameras, images, points);
* Metrics, Camera, Pose and other JSON-shaped values: what ``ocellus run --emit`` writes, as
  dicts, lists and numbers (a Scalar is a float, an Integer an int);
* List: a Python list of the above.

Errors: :class:`GraphError` (with ``diagnostics``: every problem with its ``file:line:col``) for an
invalid graph or override, :class:`RunError` (with ``failures``) when a node fails.
"""

from __future__ import annotations

import json
import os
from typing import Any, Dict, Iterable, List, Optional, Sequence

import numpy as np

from . import _ocellus
from ._ocellus import GraphError, RunError, TaskError

__all__ = [
    "Graph",
    "GraphError",
    "RunError",
    "TaskError",
    "ops",
    "KEYPOINT_DTYPE",
    "MATCH_DTYPE",
    "__version__",
]

__version__: str = _ocellus.version()

#: Keypoints as NumPy records (pixels, 0-based, x right, y down; angle in degrees).
KEYPOINT_DTYPE = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("size", "<f4"),
        ("angle", "<f4"),
        ("response", "<f4"),
        ("octave", "<i4"),
    ]
)
#: Matches as NumPy records (indices into the query and train keypoints).
MATCH_DTYPE = np.dtype([("query", "<u4"), ("train", "<u4"), ("distance", "<f4")])

_IMAGE_DTYPES = {"u8": np.dtype("u1"), "u16": np.dtype("<u2"), "f32": np.dtype("<f4")}


def _array(data: bytes, dtype: Any, shape: Sequence[int]) -> np.ndarray:
    # A writable copy: users modify results freely.
    return np.frombuffer(data, dtype=dtype).reshape(shape).copy()


def _convert(tagged: tuple) -> Any:
    """Turns the native module's tagged tuple into NumPy arrays and dicts."""
    kind = tagged[0]
    if kind == "image":
        _, data, height, width, channels, dtype = tagged
        shape = (height, width) if channels == 1 else (height, width, channels)
        return _array(data, _IMAGE_DTYPES[dtype], shape)
    if kind == "keypoints":
        return np.frombuffer(tagged[1], dtype=KEYPOINT_DTYPE).copy()
    if kind == "matches":
        return np.frombuffer(tagged[1], dtype=MATCH_DTYPE).copy()
    if kind == "descriptors":
        _, flavour, data, rows, cols = tagged
        dtype = np.dtype("<f4") if flavour == "float" else np.dtype("u1")
        return _array(data, dtype, (rows, cols))
    if kind == "matrix":
        _, data, rows, cols = tagged
        return _array(data, "<f8", (rows, cols))
    if kind == "points2d":
        _, data, n = tagged
        return _array(data, "<f8", (n, 2))
    if kind == "point_cloud":
        _, positions, n, colors, normals = tagged
        cloud = {"points": _array(positions, "<f4", (n, 3))}
        if colors is not None:
            cloud["colors"] = _array(colors, "u1", (n, 3))
        if normals is not None:
            cloud["normals"] = _array(normals, "<f4", (n, 3))
        return cloud
    if kind == "mesh":
        _, positions, n, triangles, m, normals, uvs, colors, tangents = tagged
        mesh = {
            "positions": _array(positions, "<f4", (n, 3)),
            "triangles": _array(triangles, "<u4", (m, 3)),
        }
        for name, data, width in (
            ("normals", normals, 3),
            ("uvs", uvs, 2),
            ("colors", colors, 3),
            ("tangents", tangents, 4),
        ):
            if data is not None:
                mesh[name] = _array(data, "<f4", (n, width))
        return mesh
    if kind == "reconstruction":
        _, cameras, images, points = tagged
        ids, xyz, rgb, err, tracks = points
        n = len(tracks)
        return {
            "cameras": {int(k): json.loads(v) for k, v in cameras.items()},
            "images": [
                {
                    "id": image_id,
                    "camera_id": camera_id,
                    "name": name,
                    "pose": json.loads(pose),
                    "points2d": _array(xy, "<f8", (len(xy) // 16, 2)),
                    "point_ids": np.frombuffer(pids, dtype="<i8").copy(),
                }
                for image_id, camera_id, name, pose, xy, pids in images
            ],
            "points": {
                "ids": np.frombuffer(ids, dtype="<u8").copy(),
                "xyz": _array(xyz, "<f8", (n, 3)),
                "rgb": _array(rgb, "u1", (n, 3)),
                "error_px": np.frombuffer(err, dtype="<f8").copy(),
                "tracks": [list(t) for t in tracks],
            },
        }
    if kind == "list":
        return [_convert(item) for item in tagged[1]]
    if kind == "json":
        return json.loads(tagged[1])
    raise TypeError(f"unknown value kind {kind!r}")


def _ron(value: Any) -> str:
    """A Python value as the RON text of a `--set` override."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "None"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, os.PathLike):
        return json.dumps(os.fspath(value))
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, tuple):
        return "(" + ", ".join(_ron(v) for v in value) + ")"
    if isinstance(value, (list, np.ndarray)):
        return "[" + ", ".join(_ron(v) for v in list(value)) + "]"
    raise TypeError(f"cannot use a {type(value).__name__} as a graph parameter")


class Graph:
    """A graph file, checked and ready to run; parameters can be changed with :meth:`set`."""

    def __init__(self, native: Any, path: str, sets: List[str], plugins: List[str]):
        self._native = native
        self._path = path
        self._sets = sets
        self._plugins = plugins
        #: The report of the last :meth:`run`: per-node status and time, distributed stages.
        self.last_report: Optional[Dict[str, Any]] = None

    @classmethod
    def load(cls, path: "str | os.PathLike[str]", plugins: Iterable["str | os.PathLike[str]"] = ()) -> "Graph":
        """Loads and checks a graph file; raises :class:`GraphError` with every problem."""
        path = os.fspath(path)
        plugin_list = [os.fspath(p) for p in plugins]
        return cls(_ocellus.Graph.load(path, [], plugin_list), path, [], plugin_list)

    @property
    def path(self) -> str:
        """The graph file."""
        return self._path

    @property
    def nodes(self) -> List[str]:
        """Node names, in the order they run."""
        return list(self._native.nodes)

    @property
    def outputs(self) -> List[str]:
        """Output names, in declaration order."""
        return list(self._native.outputs)

    @property
    def overrides(self) -> List[str]:
        """The parameter changes made so far, as `--set` arguments."""
        return list(self._sets)

    def set(self, key: str, value: Any) -> "Graph":
        """Sets ``node.param`` (like ``ocellus run --set node.param=value``) and re-checks the
        graph; raises :class:`GraphError` (and changes nothing) when the value is invalid."""
        sets = self._sets + [f"{key}={_ron(value)}"]
        self._native = _ocellus.Graph.load(self._path, sets, self._plugins)
        self._sets = sets
        return self

    def run(
        self,
        outputs: Optional[Sequence[str]] = None,
        threads: int = 0,
        cache_dir: "Optional[str | os.PathLike[str]]" = None,
    ) -> Dict[str, Any]:
        """Runs the graph on this machine and returns ``{output name: value}``.

        ``outputs`` limits the run to those outputs (and the nodes they need); ``threads`` is
        the worker count (0 = every core); ``cache_dir`` reuses results across runs, like
        ``ocellus run --cache``. Raises :class:`RunError` when a node fails."""
        return self._run(outputs, threads, cache_dir)

    def _run(self, outputs, threads, cache_dir, **distribution) -> Dict[str, Any]:
        result, report = self._native.run(
            list(outputs or []),
            threads,
            os.fspath(cache_dir) if cache_dir is not None else None,
            **distribution,
        )
        self.last_report = report
        return {name: _convert(value) for name, value in result}

    def __repr__(self) -> str:
        sets = "".join(f", set {s}" for s in self._sets)
        return f"<ocellus.Graph {self._path!r}: {len(self.nodes)} nodes{sets}>"


def ops(plugins: Iterable["str | os.PathLike[str]"] = ()) -> List[Dict[str, Any]]:
    """Every operator with its ports and parameters: the data of ``ocellus ops --json``."""
    return json.loads(_ocellus.ops_json([os.fspath(p) for p in plugins]))
