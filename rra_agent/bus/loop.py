"""The main loop of an rra process: Zenoh callbacks enqueue, the main thread acts.

Zenoh runs callbacks on its own thread. Work that must be serialised (a supervisor, a plan
execution, anything that spawns processes) is posted here and runs on the main thread, which
sleeps in ``select`` on a self-pipe until work arrives, a periodic tick is due, or a signal
(SIGINT/SIGTERM, via ``signal.set_wakeup_fd``) asks it to stop.
"""

from __future__ import annotations

import contextlib
import queue
import select
import signal
import socket
import time
from collections.abc import Callable
from typing import Any


class MainLoop:
    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.inbox: queue.SimpleQueue[Callable[[], None]] = queue.SimpleQueue()
        self._rsock, self._wsock = socket.socketpair()
        self._rsock.setblocking(False)
        self._wsock.setblocking(False)
        self.stopping = False
        self.errors = 0

    def wake(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):  # a wake-up is already pending
            self._wsock.send(b"\0")

    def post(self, fn: Callable[[], None]) -> None:
        """Run ``fn`` on the main thread soon (safe from any thread)."""
        self.inbox.put(fn)
        self.wake()

    def request_stop(self, *_: Any) -> None:
        self.stopping = True
        self.wake()

    def install_signals(self) -> None:
        """SIGINT and SIGTERM end the loop (main thread only)."""
        signal.set_wakeup_fd(self._wsock.fileno(), warn_on_full_buffer=False)
        signal.signal(signal.SIGINT, self.request_stop)
        signal.signal(signal.SIGTERM, self.request_stop)

    def cycle(self, timeout: float | None) -> None:
        """Wait up to ``timeout`` for work, then run everything posted so far."""
        ready, _, _ = select.select([self._rsock], [], [], timeout)
        if ready:
            with contextlib.suppress(BlockingIOError, OSError):
                while self._rsock.recv(256):
                    pass
        while True:
            try:
                fn = self.inbox.get_nowait()
            except queue.Empty:
                return
            try:
                fn()
            except Exception as e:  # a failing job is reported, the loop goes on
                self.errors += 1
                print(f"rra: {type(e).__name__}: {e}", flush=True)

    def run(self, tick: Callable[[float], None] | None = None, period: float = 0.02) -> None:
        """Cycle until stopped, calling ``tick(now)`` about every ``period`` seconds."""
        next_tick = self.clock()
        while not self.stopping:
            self.cycle(max(0.0, next_tick - self.clock()) if tick else None)
            if tick is not None and self.clock() >= next_tick:
                tick(self.clock())
                next_tick = self.clock() + period
