"""The start gate of a replacement: its process is prepared while the node it replaces stops.

A ``stop-then-start`` swap (`ReplaceNode`) must not run the replacement's code (constructor,
``import_state``, ``on_start``) before the old node is gone: the old one may hold what the
new one takes (a device, a port, a file lock). The process itself need not wait: the host
agent's fork server hands the request to a spare, marked *gated*, before the old node is told
to stop, and the node opens its session and declares its data ports (nothing it publishes,
nothing delivered to its code) while the old node stops. Its code runs only once the old
node's process has ended.

The replacement learns that from the kernel itself where it can (`Exit`): it watches the old
process through a pidfd, which becomes readable as that process ends, its files and devices
released (it is then a zombie: its parent, the host agent, has not reaped it yet). No hop
through the host agent: a busy or stalled agent does not hold the swap. Where the old node
is not a process of its own (a member of a component container), the host agent opens the
gate when it is gone by sending `SIGNAL` (`wait`).

`SIGNAL` is blocked in the fork server (`block`), so every process it forks starts with it
blocked: a gate opened early stays pending instead of killing the process (SIGUSR1's default
action). A node that is not gated unblocks it at once (`unblock`).
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import time
from collections.abc import Callable
from typing import NamedTuple

from rra_agent.host import procfs

#: What the host agent sends to open a gate.
SIGNAL = signal.SIGUSR1
#: How often a waiting node looks whether it was told to stop meanwhile (seconds).
_POLL = 0.05
#: How often `Exit` reads the old process's state where the kernel gave it no pidfd.
_EXIT_POLL = 0.001


def block() -> None:
    """Block `SIGNAL` in this thread (and so in every thread and process it creates)."""
    signal.pthread_sigmask(signal.SIG_BLOCK, {SIGNAL})


def unblock() -> None:
    """Undo `block`: the node's own code may use `SIGNAL` as it likes."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {SIGNAL})


def wait(stopping: Callable[[], bool]) -> bool:
    """Wait until the gate opens (True), or until ``stopping()`` (False: the node was told to
    stop before it could start). `SIGNAL` is unblocked either way."""
    try:
        while not stopping():
            if signal.sigtimedwait({SIGNAL}, _POLL) is not None:
                return True
        return False
    finally:
        unblock()


def open_gate(pid: int) -> None:
    """Let the gated node ``pid`` run its code (nothing if it is gone)."""
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, SIGNAL)


class Gated(NamedTuple):
    """How a gated replacement's gate opens: as the process ``after`` (pid, start time)
    ends (`Exit`), or, without it, when the host agent sends `SIGNAL` (`wait`)."""

    after: tuple[int, int] | None


class Exit:
    """The end of the process a replacement waits for, ``(pid, start time)``: its gate.

    Watched from the moment the request comes (before the node prepares), through a pidfd
    that the kernel makes readable as the process ends; where ``pidfd_open`` is refused (an
    old kernel, no file descriptor left) its state is read every millisecond instead. A pid
    already gone, or reused by another process, means the process has ended."""

    def __init__(self, pid: int, started: int) -> None:
        self.pid, self.started = pid, started
        self.fd: int | None = None
        with contextlib.suppress(OSError):  # gone (`_gone` says so) or refused: polled
            self.fd = os.pidfd_open(pid)
        self.ended = self._gone()

    def wait(self, stopping: Callable[[], bool]) -> bool:
        """`wait`'s contract: True once the process has ended, False if ``stopping()``
        first. `SIGNAL` is unblocked either way (no host agent sends it for this gate)."""
        try:
            while not stopping():
                if self.ended or self._ended(_POLL):
                    return True
            return False
        finally:
            if self.fd is not None:
                os.close(self.fd)
                self.fd = None
            unblock()

    def _ended(self, timeout: float) -> bool:
        """Whether the process ends within ``timeout`` (a poll's period without a pidfd)."""
        if self.fd is not None:
            return bool(select.select([self.fd], [], [], timeout)[0])
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._gone():
                return True
            time.sleep(_EXIT_POLL)
        return False

    def _gone(self) -> bool:
        """Whether the process has ended by what ``/proc`` says now: no such pid, a zombie,
        or its pid taken by another process since."""
        fields = procfs.stat(self.pid)
        return fields is None or fields[0] in ("Z", "X") or int(fields[19]) != self.started
