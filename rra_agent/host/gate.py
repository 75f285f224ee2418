"""The start gate of a replacement: its process is prepared while the node it replaces stops.

A ``stop-then-start`` swap (`ReplaceNode`) must not run the replacement's code (constructor,
``import_state``, ``on_start``) before the old node is gone: the old one may hold what the
new one takes (a device, a port, a file lock). The process itself need not wait: the host
agent's fork server hands the request to a spare at once, marked *gated*, and the node opens
its session and declares its data ports (nothing it publishes, nothing delivered to its
code) while the old node is killed and reaped. The host agent then sends `SIGNAL` to it, and
only then does the node's code run.

`SIGNAL` is blocked in the fork server (`block`), so every process it forks starts with it
blocked: a gate opened early stays pending instead of killing the process (SIGUSR1's default
action). A node that is not gated unblocks it at once (`unblock`).
"""

from __future__ import annotations

import contextlib
import os
import signal
from collections.abc import Callable

#: What the host agent sends to open a gate.
SIGNAL = signal.SIGUSR1
#: How often a waiting node looks whether it was told to stop meanwhile (seconds).
_POLL = 0.05


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
