"""Heartbeats from supervised processes to their host agent, through shared memory.

A host agent creates one memory file (``memfd``) with a 16-byte slot per supervised process
and hands each child its slot in ``RRA_HEARTBEAT=<fd>:<slot>`` (the descriptor is
inherited). The process writes, several times per heartbeat deadline, its
``CLOCK_MONOTONIC`` time into the slot; the host agent reads the slots on its ticks.

Why not over the bus: a heartbeat must say whether *the process* is alive, not whether the
bus, the router or the observer happen to be. A stalled router (or a stalled host agent)
delays nothing here: the beats keep being written and are fresh when the agent looks again.
Reading costs a memory read, so a thousand processes cost nothing.

Slot layout (little endian): ``f64`` beat time (seconds, CLOCK_MONOTONIC; 0 = never beat),
``u32`` beat count, ``u32`` flags (bit 0: ready, i.e. the process has declared its
liveliness token after its ports and control endpoint). A process in another language does
the same with ``mmap`` on the inherited descriptor (docs/protocol.md, 5.3).
"""

from __future__ import annotations

import contextlib
import mmap
import os
import struct
import time
from dataclasses import dataclass

ENV = "RRA_HEARTBEAT"
_SLOT = struct.Struct("<dII")
READY = 1


@dataclass(frozen=True)
class Beat:
    """A heartbeat as the host agent read it: when (the host's monotonic clock) and whether
    the process has declared itself ready."""

    at: float
    ready: bool = False


class HeartbeatTable:
    """The host agent's side: slots to hand out, beats to read."""

    def __init__(self, slots: int = 4096) -> None:
        self.size = slots * _SLOT.size
        self.fd = os.memfd_create("rra-heartbeats", 0)
        os.ftruncate(self.fd, self.size)
        self.mm = mmap.mmap(self.fd, self.size)
        self._free = list(range(slots - 1, -1, -1))
        self.slots: dict[str, int] = {}

    def allocate(self, name: str) -> str:
        """A cleared slot for ``name`` (reused if it had one); the ``RRA_HEARTBEAT`` value."""
        slot = self.slots.get(name)
        if slot is None:
            if not self._free:
                raise OSError("no free heartbeat slot")
            slot = self.slots[name] = self._free.pop()
        _SLOT.pack_into(self.mm, slot * _SLOT.size, 0.0, 0, 0)
        return f"{self.fd}:{slot}"

    def release(self, name: str) -> None:
        slot = self.slots.pop(name, None)
        if slot is not None:
            self._free.append(slot)

    def read(self, name: str) -> Beat | None:
        slot = self.slots.get(name)
        if slot is None:
            return None
        at, _, flags = _SLOT.unpack_from(self.mm, slot * _SLOT.size)
        return Beat(at, bool(flags & READY)) if at > 0 else None

    def read_all(self) -> dict[str, Beat]:
        out = {}
        for name in self.slots:
            beat = self.read(name)
            if beat is not None:
                out[name] = beat
        return out

    def close(self) -> None:
        with contextlib.suppress(BufferError, ValueError):
            self.mm.close()
        with contextlib.suppress(OSError):
            os.close(self.fd)


class Heartbeat:
    """The supervised process's side: `beat` writes its slot (a no-op without one)."""

    def __init__(self, mm: mmap.mmap | None, offset: int) -> None:
        self._mm = mm
        self._offset = offset
        self._count = 0
        self._flags = 0

    @classmethod
    def from_env(cls) -> Heartbeat:
        """The slot named by ``RRA_HEARTBEAT`` (none when started by hand)."""
        raw = os.environ.get(ENV, "")
        fd_text, _, slot_text = raw.partition(":")
        if not (fd_text.isdigit() and slot_text.isdigit()):
            return cls(None, 0)
        fd, slot = int(fd_text), int(slot_text)
        try:
            mm = mmap.mmap(fd, os.fstat(fd).st_size)
        except (OSError, ValueError):
            return cls(None, 0)
        offset = slot * _SLOT.size
        if offset + _SLOT.size > len(mm):
            return cls(None, 0)
        return cls(mm, offset)

    @property
    def enabled(self) -> bool:
        return self._mm is not None

    def beat(self, *, ready: bool | None = None) -> None:
        if self._mm is None:
            return
        if ready is not None:
            self._flags = READY if ready else 0
        self._count = (self._count + 1) & 0xFFFFFFFF
        _SLOT.pack_into(self._mm, self._offset, time.monotonic(), self._count, self._flags)
