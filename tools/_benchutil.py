"""Statistics and table helpers shared by the benchmarks in ``tools/``.

Samples are durations in **seconds** (e.g. differences of `time.perf_counter`); summaries are
reported in microseconds. Percentiles use the nearest-rank definition (the smallest sample
such that at least q % of the samples are less than or equal to it), so a p99 is always a
measured value, never an interpolation.

A benchmark script in ``tools/`` imports it as ``from _benchutil import ...`` (a script's own
directory is on ``sys.path``).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TextIO

US = 1e6


def percentile(samples: Iterable[float], q: float) -> float:
    """Nearest-rank ``q``-th percentile (0 < q <= 100) of ``samples``, in their own unit."""
    if not 0.0 < q <= 100.0:
        raise ValueError(f"percentile {q} is not in (0, 100]")
    ordered = sorted(samples)
    if not ordered:
        raise ValueError("no samples")
    rank = math.ceil(q / 100.0 * len(ordered))
    return ordered[max(rank, 1) - 1]


def median(samples: Iterable[float]) -> float:
    """The median (mean of the two middle samples for an even count)."""
    ordered = sorted(samples)
    n = len(ordered)
    if n == 0:
        raise ValueError("no samples")
    mid = n // 2
    return ordered[mid] if n % 2 else (ordered[mid - 1] + ordered[mid]) / 2.0


def p99(samples: Iterable[float]) -> float:
    return percentile(samples, 99.0)


@dataclass(frozen=True, slots=True)
class Stats:
    """Summary of a list of durations, in microseconds."""

    n: int
    median_us: float
    p99_us: float
    min_us: float
    max_us: float
    mean_us: float

    @classmethod
    def of(cls, samples_s: Sequence[float]) -> Stats:
        if not samples_s:
            raise ValueError("no samples")
        return cls(
            n=len(samples_s),
            median_us=median(samples_s) * US,
            p99_us=p99(samples_s) * US,
            min_us=min(samples_s) * US,
            max_us=max(samples_s) * US,
            mean_us=sum(samples_s) / len(samples_s) * US,
        )


def _cell(value: object, digits: int) -> str:
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def format_table(headers: Sequence[str], rows: Iterable[Sequence[object]], digits: int = 1) -> str:
    """A plain-text table: numbers right-aligned (floats with ``digits`` decimals), text left."""
    raw = [list(row) for row in rows]
    for row in raw:
        if len(row) != len(headers):
            raise ValueError(f"row {row} has {len(row)} cells, expected {len(headers)}")
    cells = [[_cell(v, digits) for v in row] for row in raw]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(headers)]
    numeric = [
        bool(raw) and all(isinstance(r[i], int | float) or r[i] == "" for r in raw)
        for i in range(len(headers))
    ]

    def line(row: Sequence[str]) -> str:
        out = [
            c.rjust(w) if num else c.ljust(w)
            for c, w, num in zip(row, widths, numeric, strict=True)
        ]
        return "  ".join(out).rstrip()

    out = [line(list(headers)), "  ".join("-" * w for w in widths)]
    out.extend(line(r) for r in cells)
    return "\n".join(out)


def print_table(
    headers: Sequence[str],
    rows: Iterable[Sequence[object]],
    digits: int = 1,
    file: TextIO | None = None,
) -> None:
    print(format_table(headers, rows, digits), file=file or sys.stdout, flush=True)


def interrupt(proc, timeout: float = 60.0) -> None:  # subprocess.Popen
    """Stop a process as Ctrl-C does (SIGINT); SIGKILL if it has not exited in ``timeout``."""
    import signal
    import subprocess

    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
