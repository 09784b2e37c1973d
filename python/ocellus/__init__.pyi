import os
from typing import Any, Dict, Iterable, List, Optional, Sequence, Union

import numpy as np

from ._ocellus import GraphError as GraphError, RunError as RunError, TaskError as TaskError

__version__: str
KEYPOINT_DTYPE: np.dtype
MATCH_DTYPE: np.dtype

_PathLike = Union[str, "os.PathLike[str]"]

#: What a graph output becomes in Python: arrays for images, keypoints, matches, descriptors,
#: matrices and points; dicts for Metrics, Camera, Pose, PointCloud, Mesh, Reconstruction;
#: float/int/bool/str for scalars; lists for List values.
Output = Any

class Graph:
    last_report: Optional[Dict[str, Any]]
    @classmethod
    def load(cls, path: _PathLike, plugins: Iterable[_PathLike] = ()) -> Graph: ...
    @property
    def path(self) -> str: ...
    @property
    def nodes(self) -> List[str]: ...
    @property
    def outputs(self) -> List[str]: ...
    @property
    def overrides(self) -> List[str]: ...
    def set(self, key: str, value: Any) -> Graph: ...
    def run(
        self,
        outputs: Optional[Sequence[str]] = None,
        threads: int = 0,
        cache_dir: Optional[_PathLike] = None,
    ) -> Dict[str, Output]: ...

def ops(plugins: Iterable[_PathLike] = ()) -> List[Dict[str, Any]]: ...
