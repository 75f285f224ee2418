"""Adaptation events: published on ``rra/<system>/events`` and appended to a JSON-lines log.

Each line of the log is one `AdaptationEvent` or `NodeState` as JSON (with its ``"t"`` tag),
flushed as written, so ``tail -f`` and ``rra events`` follow it live and a crash loses nothing.
"""

from __future__ import annotations

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

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


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
