"""Native half of the ocellus package (see ocellus/__init__.py for the public API)."""

from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

class GraphError(Exception):
    """An invalid graph file or override. ``diagnostics``: dicts with location, message, code, help."""

    diagnostics: List[Dict[str, Any]]

class RunError(Exception):
    """A node failed. ``failures``: dicts with node, op, location, message."""

    failures: List[Dict[str, Any]]

class TaskError(Exception):
    """A distributed task could not run on this worker."""

class Graph:
    @staticmethod
    def load(path: str, sets: List[str] = ..., plugins: List[str] = ...) -> Graph: ...
    @property
    def nodes(self) -> List[str]: ...
    @property
    def outputs(self) -> List[str]: ...
    def run(
        self,
        outputs: List[str] = ...,
        threads: int = ...,
        cache_dir: Optional[str] = ...,
        submit: Optional[Callable[[Dict[str, Any], List[bytes]], Iterator[Tuple[int, bool, Any, str, float]]]] = ...,
        items_per_task: int = ...,
        item_cache: Optional[str] = ...,
        progress: Optional[Callable[[str, int, int], None]] = ...,
    ) -> Tuple[List[Tuple[str, tuple]], Dict[str, Any]]: ...
    def op_ids(self) -> List[str]: ...

def run_task(payload: bytes, threads: int = 1) -> bytes: ...
def ops_json(plugins: List[str] = ...) -> str: ...
def version() -> str: ...
