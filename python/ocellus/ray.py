"""Run a graph with its list maps spread over a Ray cluster.

    import ocellus, ocellus.ray
    out = ocellus.ray.run("graphs/features.ron", address="127.0.0.1:6379")

The graph runs in this process, in the Rust engine. Every *mapped* node (a node fed a list where
it takes one value: per-image feature extraction, per-pair matching, …) of a built-in operator
without side effects is cut into chunks of elements, and each chunk becomes one Ray task that
runs the operator in the Rust engine on a worker. Values cross as the engine's own serialized
form, and each worker runs the same code as a local run, so outputs are byte-identical to
``Graph.run``.

Every finished element is stored under its content key (operator, parameters, input contents)
in the item cache as soon as its task returns, so a run that failed or was interrupted loses
only the chunks in flight: run it again and the finished elements are reused. Ray retries a
task whose worker died (``max_retries``); an operator's own error fails the run at once.

Workers need the same ``ocellus`` package (and see the same files, for readers); plugins loaded
at run time and writers run on the driver.
"""

from __future__ import annotations

import os
import socket
import sys
import time
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple, Union

from . import Graph, _ocellus

__all__ = ["run", "default_item_cache", "init_args", "run_chunk", "submitter"]

#: What ``submit`` yields per finished task: (task index, ok, result bytes or error text,
#: worker name, seconds the worker spent).
TaskResult = Tuple[int, bool, Union[bytes, str], str, float]


def default_item_cache() -> str:
    """Where finished elements are kept by default: ``$OCELLUS_ITEM_CACHE``, else
    ``$XDG_CACHE_HOME/ocellus/items``, else ``~/.cache/ocellus/items``."""
    explicit = os.environ.get("OCELLUS_ITEM_CACHE")
    if explicit:
        return explicit
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "ocellus", "items")


def _worker_name() -> str:
    try:
        import ray

        host = ray.util.get_node_ip_address()
    except Exception:  # not inside Ray (tests call run_chunk directly)
        host = socket.gethostname()
    return f"{host} pid {os.getpid()}"


def run_chunk(payload: bytes, threads: int = 1) -> Tuple[bool, Union[bytes, str], str, float]:
    """The Ray task: runs one chunk payload in the Rust engine on ``threads`` threads (the
    task's CPUs). Returns (ok, result bytes or the operator's error, worker name, seconds).
    Operator errors are returned, not raised, so Ray does not retry them; a crash of the worker
    process is retried by Ray."""
    started = time.perf_counter()
    try:
        result: Union[bytes, str] = _ocellus.run_task(payload, threads)
        ok = True
    except _ocellus.TaskError as e:
        result, ok = str(e), False
    return ok, result, _worker_name(), time.perf_counter() - started


def submitter(
    max_retries: int = 3, num_cpus: float = 1, max_in_flight: Optional[int] = None
) -> Callable[[Dict[str, Any], List[bytes]], Iterator[TaskResult]]:
    """A ``submit(stage, payloads)`` that sends payloads as Ray tasks and yields results as
    they finish (Ray must be initialized). At most ``max_in_flight`` tasks are submitted at
    once (default: twice the cluster's CPUs), so payloads wait in this process, not in the
    cluster's object store, and a worker that joins or leaves mid-run changes where the rest
    go."""
    import ray

    remote = ray.remote(num_cpus=num_cpus, max_retries=max_retries)(run_chunk)
    threads = max(1, int(num_cpus))

    def submit(stage: Dict[str, Any], payloads: List[bytes]) -> Iterator[TaskResult]:
        limit = max_in_flight or max(2, int(2 * ray.cluster_resources().get("CPU", 1)))
        index: Dict[Any, int] = {}
        pending: List[Any] = []
        next_task = 0
        try:
            while next_task < len(payloads) or pending:
                while next_task < len(payloads) and len(pending) < limit:
                    ref = remote.remote(payloads[next_task], threads)
                    payloads[next_task] = b""  # sent: free it here
                    index[ref] = next_task
                    pending.append(ref)
                    next_task += 1
                ready, pending = ray.wait(pending, num_returns=1)
                for ref in ready:
                    i = index.pop(ref)
                    try:
                        ok, data, worker, seconds = ray.get(ref)
                    except Exception as e:  # retries exhausted, cluster gone
                        yield (i, False, f"{type(e).__name__}: {e}", "ray", 0.0)
                        return
                    yield (i, ok, data, worker, seconds)
                    if not ok:
                        return  # an operator's error fails the map: stop at once
        finally:
            # The engine stopped listening (a failed chunk): free the cluster.
            for ref in pending:
                try:
                    ray.cancel(ref, force=False)
                except Exception:
                    pass

    return submit


def init_args(address: Optional[str], extra: Optional[Dict[str, Any]] = None) -> Dict[str, Any]:
    """``ray.init`` arguments for ``address``: a loopback address keeps this driver on loopback
    too (Ray would otherwise announce the machine's network address)."""
    args: Dict[str, Any] = {"address": address}
    host = (address or "").rsplit(":", 1)[0]
    if host in ("127.0.0.1", "localhost") or host.startswith("127."):
        args["_node_ip_address"] = "127.0.0.1"
    args.update(extra or {})
    return args


def _print_progress(node: str, done: int, total: int) -> None:
    end = "\n" if done >= total else "\r"
    print(f"ocellus.ray: {node}: {done}/{total} items", end=end, file=sys.stderr, flush=True)


def run(
    graph: "Graph | str | os.PathLike[str]",
    address: Optional[str] = None,
    outputs: Optional[Sequence[str]] = None,
    threads: int = 0,
    items_per_task: int = 0,
    cache_dir: "Optional[str | os.PathLike[str]]" = None,
    item_cache: "Optional[str | os.PathLike[str]]" = "default",
    progress: Union[bool, Callable[[str, int, int], None]] = True,
    max_retries: int = 3,
    init: Optional[Dict[str, Any]] = None,
) -> Dict[str, Any]:
    """Runs ``graph`` (a :class:`ocellus.Graph` or a path) with its list maps on Ray.

    ``address``: the cluster (``"127.0.0.1:6379"``, ``"auto"``); ``None`` joins the cluster
    this process already initialized, or starts a local one. ``items_per_task``: elements per
    task (0 picks about 64 tasks per map, up to 16 elements each). ``cache_dir``: node result
    cache, as in :meth:`Graph.run`. ``item_cache``: where finished elements are kept by content
    key (``"default"``: ``cache_dir``/items, else :func:`default_item_cache`; ``None`` keeps
    nothing). ``progress``:
    print ``items done/total`` per map to stderr, or a callback ``(node, done, total)``.
    ``max_retries``: Ray's retries of a task whose worker died. ``init``: extra
    ``ray.init`` arguments. The run's report, with each distributed map and its per-worker
    time, is in ``graph.last_report["distributed"]``."""
    import ray

    if not isinstance(graph, Graph):
        graph = Graph.load(graph)
    if not ray.is_initialized():
        ray.init(**init_args(address, init))
    if item_cache == "default":
        item_cache = (
            os.path.join(os.fspath(cache_dir), "items") if cache_dir is not None else default_item_cache()
        )
    callback = _print_progress if progress is True else (progress or None)
    return graph._run(
        outputs,
        threads,
        cache_dir,
        submit=submitter(max_retries=max_retries),
        items_per_task=items_per_task,
        item_cache=os.fspath(item_cache) if item_cache is not None else None,
        progress=callback,
    )
