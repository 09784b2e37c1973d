"""The Ray driver behind ``ocellus run GRAPH --ray ADDRESS``.

The CLI runs the graph itself and starts ``python -m ocellus.ray_driver --address ADDRESS``;
for each distributable list map it sends the chunk payloads over this process's stdin, and this
process submits them as Ray tasks (see :mod:`ocellus.ray`) and streams results back on stdout
as they finish.

Frames are an unsigned 64-bit little-endian length, then that many bytes.

* driver → CLI at start: JSON ``{"ready": true, "cpus": N, "nodes": N}`` or ``{"error": "..."}``;
* CLI → driver per stage: JSON ``{"node", "op", "items", "reused", "tasks": N}``, then N payload
  frames; an empty JSON object ``{}`` asks the driver to exit;
* driver → CLI per finished task: JSON ``{"task", "ok", "worker", "seconds"}``, then the result
  bytes (or the UTF-8 error text); after the stage's last task (or its first failure):
  JSON ``{"end": true}``, with ``"error"`` when the stage could not finish.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import sys
from typing import BinaryIO, Optional


def _read_frame(stream: BinaryIO) -> Optional[bytes]:
    head = stream.read(8)
    if len(head) < 8:
        return None
    (n,) = struct.unpack("<Q", head)
    data = stream.read(n)
    if len(data) < n:
        return None
    return data


def _write_frame(stream: BinaryIO, data: bytes) -> None:
    stream.write(struct.pack("<Q", len(data)))
    stream.write(data)


def _write_json(stream: BinaryIO, value: object) -> None:
    _write_frame(stream, json.dumps(value).encode())


def main(argv: Optional[list] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m ocellus.ray_driver")
    parser.add_argument("--address", required=True, help="Ray cluster address, e.g. 127.0.0.1:6379 or auto")
    parser.add_argument("--max-retries", type=int, default=3)
    args = parser.parse_args(argv)

    # The protocol owns the real stdout; anything printed (Ray's own messages) goes to stderr.
    # Buffered: a write always writes everything; flushed after each frame group.
    proto = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    requests = sys.stdin.buffer

    try:
        import ray

        from .ray import init_args, submitter

        ray.init(**init_args(args.address, {"log_to_driver": False}))
        resources = ray.cluster_resources()
        submit = submitter(max_retries=args.max_retries)
    except Exception as e:  # cannot reach the cluster, Ray missing
        _write_json(proto, {"error": f"{type(e).__name__}: {e}"})
        return 1
    _write_json(proto, {"ready": True, "cpus": resources.get("CPU", 0), "nodes": len(ray.nodes())})
    proto.flush()

    while True:
        header = _read_frame(requests)
        if header is None:
            return 0
        stage = json.loads(header)
        if not stage:
            return 0
        payloads = []
        for _ in range(int(stage["tasks"])):
            frame = _read_frame(requests)
            if frame is None:
                return 1
            payloads.append(frame)
        end: dict = {"end": True}
        try:
            for task, ok, data, worker, seconds in submit(stage, payloads):
                _write_json(proto, {"task": task, "ok": ok, "worker": worker, "seconds": seconds})
                _write_frame(proto, data if isinstance(data, bytes) else str(data).encode())
                proto.flush()
        except Exception as e:  # the cluster went away mid-stage: say so, stay in step
            end["error"] = f"{type(e).__name__}: {e}"
        _write_json(proto, end)
        proto.flush()


if __name__ == "__main__":
    sys.exit(main())
