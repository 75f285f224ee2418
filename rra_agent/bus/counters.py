"""What a process accepts from the bus, and how it counts and reports what it refuses.

Every process (node, engine, host agent) keeps `Counters`: samples and requests received,
*dropped* (malformed, larger than the limit of their key family, or coalesced away under
load) and *rejected* (well-formed but refused: out of bounds, unknown names, stale leader
fences). ``rra status`` shows them (`ProcessStats`). Refusals are logged through a
`RateLimitedLog`: the first of each kind at once, then at most one line per period with
the count since the last line, so a flood of junk costs a counter increment, not a log line.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from rra_agent.bus import messages as m

KiB = 1024
MiB = 1024 * KiB

#: The largest payload accepted per key family (bytes). Larger ones are dropped and counted.
MAX_PAYLOAD: dict[str, int] = {
    "data": 16 * MiB,  # point clouds, images
    "ctx": 16 * KiB,
    "selection": 256 * KiB,
    "events": 256 * KiB,
    "state": 16 * MiB,
    "node_ctl": 4 * MiB,  # exported state of a node being replaced
    "host_ctl": 4 * MiB,  # node specs
    "engine_ctl": 64 * KiB,
    "inject": 64 * KiB,
}


def too_large(family: str, size: int) -> bool:
    return size > MAX_PAYLOAD[family]


class RateLimitedLog:
    """Log the first refusal of each kind at once, then one line per ``period`` at most."""

    def __init__(
        self,
        emit: Callable[[str], None],
        period: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.emit = emit
        self.period = period
        self.clock = clock
        self._lock = threading.Lock()
        self._last: dict[str, float] = {}
        self._pending: dict[str, int] = {}

    def __call__(self, kind: str, detail: str) -> None:
        now = self.clock()
        with self._lock:
            last = self._last.get(kind)
            self._pending[kind] = self._pending.get(kind, 0) + 1
            if last is not None and now - last < self.period:
                return
            count = self._pending.pop(kind)
            self._last[kind] = now
        more = f" ({count} since the last report)" if last is not None and count > 1 else ""
        self.emit(f"{kind}: {detail}{more}")


@dataclass
class Counters:
    """A process's counters; increments are atomic enough under the GIL for counting."""

    received: int = 0
    dropped: int = 0
    rejected: int = 0
    extra: dict[str, int] = field(default_factory=dict)

    def bump(self, name: str, n: int = 1) -> None:
        self.extra[name] = self.extra.get(name, 0) + n

    def stats(self, name: str, role: str, pid: int) -> m.ProcessStats:
        return m.ProcessStats(
            name=name,
            role=role,  # type: ignore[arg-type]
            pid=pid,
            received=self.received,
            dropped=self.dropped,
            rejected=self.rejected,
            counters=dict(self.extra),
        )
