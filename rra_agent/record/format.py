"""Record files: one per engine process of a run, append-only, one framed record each write.

A file ``<run>/record/<replica>-<pid>.rec`` is a sequence of *frames*::

    length : uint32, little endian   the payload's size in bytes
    crc    : uint32, little endian   CRC-32 (zlib) of the payload
    payload: msgpack                 one record: a map with a "t" tag (below)

Each frame is written with one ``write(2)`` of the whole frame, unbuffered, so a process
killed at any moment leaves every record it wrote before and at most one torn frame at the
end. A frame whose CRC does not match, or whose length runs past the end of the file but for
the last, is damage (`RecordError`); a torn last frame is the end of a killed process's file.

Records (docs/recording.md has the table):

- `Start` first, once per process: who writes (replica, role, pid), the models digest and the
  deployment-time selection it runs with;
- the Adaptation Engine's: `Tick` (one evaluation of the rules: its time, the measurements
  new since the previous tick as received, and its result), `Adopt`, `Forced`, `Force`,
  `Avail`, `Lead`, `Reload`: every call on the pure core, in the order made;
- the Context Monitor leader's: `Sample` (a source sample it computed from, raw);
- the Run-time Resolution Engine leader's: `State` (each version of its `EngineState`) and
  `Command` (operators' requests: ``param``, ``retry``, ``reload``; injections seen);
- `End` last, when the process stopped cleanly.
"""

from __future__ import annotations

import os
import struct
import threading
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec

from rra_agent.bus import messages as m
from rra_agent.errors import RraError

FORMAT = 1
SUFFIX = ".rec"
_HEAD = struct.Struct("<II")


class RecordError(RraError):
    """A record file that is damaged (its message names the file and the offset)."""


class Rec(msgspec.Struct, tag_field="t", kw_only=True, omit_defaults=True):
    """Base of every record."""


class Start(Rec, tag="start"):
    process: str
    role: str
    pid: int
    stamp: float
    system: str
    #: The digest of the models it starts with (``record/models/<digest>/``).
    models: str
    deployment: list[str]
    host: str = ""
    format: int = FORMAT


class Ctx(msgspec.Struct, kw_only=True, omit_defaults=True, array_like=True):
    """A measurement as the Adaptation Engine received it, and when (``at``, wall clock)."""

    name: str
    value: float | int | bool | str
    stamp: float
    at: float = 0.0
    sources: dict[str, float] = {}


class Tick(Rec, tag="tick"):
    """One evaluation: `AdaptationEngine.tick(now, measurements, changed=changed)`, where
    ``measurements`` is the previous tick's with ``ctx`` put in, and what it returned."""

    now: float
    changed: list[str] = []
    ctx: list[Ctx] = []
    #: The evaluation was forced (a leader change, an override, availability).
    force: bool = False
    #: This replica led when it evaluated.
    lead: bool = False
    selection: list[str] = []
    cv: dict[str, float] = {}
    #: The rules that fired (``ruleset.rule``), in order.
    fired: list[str] = []
    #: The ``seq`` of the `Selection` published from it (0: none).
    seq: int = 0


class Adopt(Rec, tag="adopt"):
    """`AdaptationEngine.adopt(selection, cv)`; ``error`` when it refused (nothing changed)."""

    stamp: float
    selection: list[str]
    cv: dict[str, float] = {}
    why: str = ""
    error: str = ""


class Forced(Rec, tag="forced"):
    """The forced features set as a whole (resumed or followed from the leader)."""

    stamp: float
    forced: dict[str, bool] = {}


class Force(Rec, tag="force"):
    """An operator's `AdaptationEngine.force` (``rra select``); ``error`` when refused."""

    stamp: float
    features: dict[str, str]
    operator: str = ""
    error: str = ""


class Avail(Rec, tag="avail"):
    """The Run-time Resolution Engine leader's unavailable implementations, as received."""

    stamp: float
    unavailable: list[m.Unavailable] = []


class Lead(Rec, tag="lead"):
    stamp: float
    leading: bool
    fence: m.Fence | None = None


class Reload(Rec, tag="reload"):
    """The process switched to other models (``rra reload``, or following its leader)."""

    stamp: float
    models: str
    previous: str = ""


class Sample(Rec, tag="sample"):
    """A source sample the Context Monitor computed from: ``component.port``, its raw bytes,
    its send time (``stamp``) and when it was processed (``at``)."""

    source: str
    data: bytes
    stamp: float
    at: float


class State(Rec, tag="state"):
    state: m.EngineState


class Command(Rec, tag="command"):
    """An operator's request or an injection: what, with which arguments, and the outcome."""

    stamp: float
    kind: str
    args: dict[str, Any] = {}
    operator: str = ""
    outcome: str = ""


class End(Rec, tag="end"):
    stamp: float
    records: int


Record = (
    Start | Tick | Adopt | Forced | Force | Avail | Lead | Reload | Sample | State | Command | End
)
_ENC = msgspec.msgpack.Encoder()
_DEC = msgspec.msgpack.Decoder(Record)


def frame(rec: Record) -> bytes:
    payload = _ENC.encode(rec)
    return _HEAD.pack(len(payload), zlib.crc32(payload)) + payload


class RecordWriter:
    """Appends records to one file, each with one unbuffered write (thread-safe). A write that
    fails (disk full) stops the recording with one line on stderr; it never raises."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._fd: int | None = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self._lock = threading.Lock()
        self.records = 0
        self.bytes = 0

    def write(self, rec: Record) -> None:
        data = frame(rec)
        with self._lock:
            if self._fd is None:
                return
            try:
                os.write(self._fd, data)
            except OSError as e:
                self._fail(e)
                return
            self.records += 1
            self.bytes += len(data)

    def _fail(self, e: OSError) -> None:
        import sys

        print(f"rra record: {self.path}: {e}; recording stops here", file=sys.stderr, flush=True)
        self.close(end=None)

    def close(self, end: float | None = None) -> None:
        """Close; with ``end`` (a stamp) write the `End` record first (a clean stop)."""
        if end is not None:
            self.write(End(stamp=end, records=self.records + 1))
        with self._lock:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None


class FileRecords(msgspec.Struct, kw_only=True):
    """The records of one file, and whether it ended in a torn frame (a killed writer)."""

    path: str
    records: list[Any]
    torn: bool = False


def frames(data: bytes, path: str) -> Iterator[tuple[int, bytes]]:
    """(offset, payload) of each whole frame; RecordError on a bad CRC; a torn last frame
    ends the iteration with offset -1."""
    pos, size = 0, len(data)
    while pos < size:
        if size - pos < _HEAD.size:
            yield -1, b""
            return
        length, crc = _HEAD.unpack_from(data, pos)
        end = pos + _HEAD.size + length
        if end > size:
            yield -1, b""
            return
        payload = data[pos + _HEAD.size : end]
        if zlib.crc32(payload) != crc:
            raise RecordError(f"{path}: damaged record at byte {pos} (CRC mismatch)")
        yield pos, payload
        pos = end


def read_file(path: Path) -> FileRecords:
    """Every record of one file (RecordError if one is damaged or not a record)."""
    try:
        data = path.read_bytes()
    except OSError as e:
        raise RecordError(f"{path}: cannot read: {e}") from None
    out: list[Any] = []
    torn = False
    for pos, payload in frames(data, str(path)):
        if pos < 0:
            torn = True
            break
        try:
            out.append(_DEC.decode(payload))
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            raise RecordError(f"{path}: not a record at byte {pos}: {e}") from None
    if out and not isinstance(out[0], Start):
        raise RecordError(f"{path}: does not begin with a start record")
    return FileRecords(path=str(path), records=out, torn=torn)
