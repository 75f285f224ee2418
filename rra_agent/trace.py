"""Phase trace of a reconfiguration across processes, for benchmarks (off unless asked).

With ``RRA_TRACE=<file>`` in the environment (inherited by every process of a run: engines,
host agents, the fork server, the nodes), `mark` appends one JSON line per call to that
file: ``{"t": <CLOCK_MONOTONIC s>, "pid": ..., "what": ..., "node": ...}``. CLOCK_MONOTONIC
is one clock for every process of a host, so the lines of several processes order into one
timeline (`tools/bench_recovery.py` reads them into a per-phase breakdown). Lines are
written with one ``write`` to an ``O_APPEND`` file, so processes do not interleave them.

Unset, `mark` is one global lookup and returns: the hot path pays nothing measurable.
"""

from __future__ import annotations

import json
import os
import time

ENV = "RRA_TRACE"
_fd: int | None = None
_path = os.environ.get(ENV) or None


def enabled() -> bool:
    return _path is not None


def mark(what: str, node: str = "", **extra: object) -> None:
    """Record that ``what`` happened now (for ``node``), if tracing is on."""
    if _path is None:
        return
    _write({"t": time.monotonic(), "pid": os.getpid(), "what": what, "node": node, **extra})


def _write(line: dict[str, object]) -> None:
    global _fd
    if _fd is None:
        _fd = os.open(_path or os.devnull, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.write(_fd, (json.dumps(line) + "\n").encode())


def read(path: str | os.PathLike[str]) -> list[dict[str, object]]:
    """The trace lines of a file, in time order."""
    with open(path) as f:
        lines = [json.loads(x) for x in f if x.strip()]
    return sorted(lines, key=lambda x: float(x["t"]))  # type: ignore[arg-type]
