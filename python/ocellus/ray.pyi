import os
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple, Union

from . import Graph

TaskResult = Tuple[int, bool, Union[bytes, str], str, float]

def default_item_cache() -> str: ...
def run_chunk(payload: bytes, threads: int = 1) -> Tuple[bool, Union[bytes, str], str, float]: ...
def submitter(
    max_retries: int = 3, num_cpus: float = 1, max_in_flight: Optional[int] = None
) -> Callable[[Dict[str, Any], List[bytes]], Iterator[TaskResult]]: ...
def run(
    graph: Union[Graph, str, "os.PathLike[str]"],
    address: Optional[str] = None,
    outputs: Optional[Sequence[str]] = None,
    threads: int = 0,
    items_per_task: int = 0,
    cache_dir: Optional[Union[str, "os.PathLike[str]"]] = None,
    item_cache: Optional[Union[str, "os.PathLike[str]"]] = "default",
    progress: Union[bool, Callable[[str, int, int], None]] = True,
    max_retries: int = 3,
    init: Optional[Dict[str, Any]] = None,
) -> Dict[str, Any]: ...
def init_args(address: Optional[str], extra: Optional[Dict[str, Any]] = None) -> Dict[str, Any]: ...
