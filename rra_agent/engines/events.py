"""Adaptation events: published on ``rra/<system>/events`` and appended to a JSON-lines log.

Each line of the log is one `AdaptationEvent` or `NodeState` as JSON (with its ``"t"`` tag),
flushed as written, so ``tail -f`` and ``rra events`` follow it live and a crash loses nothing.
Lines are in the order they reach their writer, not in time order (several processes append
and node states arrive over the bus): ``rra events --log`` sorts them by ``stamp``.

`phase_durations` computes an adaptation's phase timings (its event's ``durations``).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import IO

import msgspec
import zenoh

from rra_agent.bus import messages as m

_MSGPACK = m.Codec[m.EventMessage](m.EventMessage)
_JSON = msgspec.json.Encoder()


class EventSink:
    def __init__(self, session: zenoh.Session | None, key: str, log: Path | None) -> None:
        self.publisher = (
            session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
            if session is not None
            else None
        )
        self._file: IO[bytes] | None = None
        if log is not None:
            log.parent.mkdir(parents=True, exist_ok=True)
            self._file = log.open("ab")

    def emit(self, event: m.AdaptationEvent | m.NodeState, *, publish: bool = True) -> None:
        if publish and self.publisher is not None:
            self.publisher.put(_MSGPACK.encode(event))
        self.record(event)

    def record(self, event: m.AdaptationEvent | m.NodeState) -> None:
        """Only log (for events published by someone else, e.g. host agents' NodeStates)."""
        if self._file is not None:
            self._file.write(_JSON.encode(event) + b"\n")
            self._file.flush()

    def record_missing(
        self, events: Iterable[m.AdaptationEvent | m.NodeState]
    ) -> list[m.AdaptationEvent | m.NodeState]:
        """Log those of ``events`` that the log's last `TAIL` bytes do not hold (a standby
        taking over: what came while nobody led); those it wrote."""
        if self._file is None:
            return []
        held = set(_tail_lines(Path(self._file.name), TAIL))
        written = []
        for event in events:
            line = _JSON.encode(event)
            if line not in held:
                held.add(line)
                self.record(event)
                written.append(event)
        return written

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


#: How much of its log a new leader reads back to know what the previous one wrote (bytes).
TAIL = 256 * 1024


def _tail_lines(path: Path, size: int) -> list[bytes]:
    """The whole lines of the last ``size`` bytes of ``path`` (none if it is missing)."""
    try:
        with path.open("rb") as f:
            f.seek(0, 2)
            start = max(0, f.tell() - size)
            f.seek(start)
            data = f.read()
    except OSError:
        return []
    lines = data.splitlines()
    return lines[1:] if start > 0 and lines else lines


def read_events(path: str | Path) -> list[m.AdaptationEvent | m.NodeState]:
    """Every event of a JSON-lines log (a torn last line is ignored)."""
    dec = msgspec.json.Decoder(m.EventMessage)
    out = []
    for line in Path(path).read_bytes().splitlines():
        try:
            out.append(dec.decode(line))
        except msgspec.DecodeError:
            continue
    return out


def phase_durations(
    reads: Iterable[float],
    decided: float,
    received: float,
    plan: float,
    execute: float,
    switch: float | None = None,
) -> dict[str, float]:
    """The phases of one adaptation, in seconds (an `AdaptationEvent`'s ``durations``).

    ``reads``: the stamps of the context values the fired rules read (each when the Context
    Monitor computed it); ``decided``: the selection's stamp (the Adaptation Engine);
    ``received``: when the Run-time Resolution Engine got it; ``plan`` and ``execute``: how
    long it planned and executed; ``switch``: from the start of execution until the
    swapped-in nodes were switched to.

    The trigger is the newest value the rules read: the Adaptation Engine evaluates on every
    new value, so the evaluation that changed the decision is the one the newest value
    started. Older values (a flag set minutes ago, read again by every evaluation) are not
    the trigger. Without any value read (an operator's selection) the trigger is the decision.
    ``total`` runs from the trigger to the end of execution: ``decide + deliver + plan +
    execute``. Clocks of different hosts may disagree: no phase is negative.
    """
    stamps = list(reads)
    trigger = max(stamps) if stamps else decided
    durations = {
        "decide": max(0.0, decided - trigger),
        "deliver": max(0.0, received - decided),
        "plan": plan,
        "execute": execute,
    }
    durations["total"] = max(0.0, received - trigger) + plan + execute
    if switch is not None:
        durations["switch"] = switch
    return durations
