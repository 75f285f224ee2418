"""The main loop of an rra process: Zenoh callbacks enqueue, the main thread acts.

Zenoh runs callbacks on its own thread. Work that must be serialised (a supervisor, a plan
execution, anything that spawns processes) is posted here and runs on the main thread, which
sleeps in ``select`` on a self-pipe until work arrives, a periodic tick is due, or a signal
(SIGINT/SIGTERM, and SIGCHLD where asked, via ``signal.set_wakeup_fd``) wakes it.

The inbox is bounded: a flood of requests cannot grow memory without limit; `post` refuses
the work (and counts it) when the inbox is full, and the caller answers "busy".

Short work on the latency path (a measurement to compute, rules to evaluate) may instead be
run *on the arriving thread* with `run_or_post`, when the main thread is idle in ``select``
and nothing is waiting in the inbox: that saves the wake-up of the main thread and the GIL's
hand-over, 0.1-0.25 ms per process in the traces of a busy two-core machine (issue 12). The main
thread holds the loop's lock at all times except while it waits, so such a job is still
serialised with everything else the loop runs. Like interrupt mitigation in a network
driver, this is for sparse events only: a job runs inline only while the inline share of
the last `WINDOW` seconds is under `INLINE_SHARE`, so a flood falls back to the hand-off,
where callers coalesce, and a Zenoh callback thread is never held for long (its channel
is bounded: a blocked callback stalls the whole session once ~256 samples wait). The loop
writes the process's heartbeat (`rra_agent.bus.heartbeat`) while it runs, so a process whose
main thread is stuck stops beating.
"""

from __future__ import annotations

import contextlib
import queue
import select
import signal
import socket
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

from rra_agent.bus.heartbeat import Heartbeat

#: Work items waiting at most; more are refused.
INBOX = 10_000
#: Run inline (`MainLoop.run_or_post`) only while it took under this share of the window.
INLINE_SHARE = 0.2
WINDOW = 0.1


class MainLoop:
    def __init__(
        self,
        clock: Callable[[], float] = time.monotonic,
        *,
        inbox: int = INBOX,
        beat_every: float = 0.5,
    ) -> None:
        self.clock = clock
        self.inbox: queue.Queue[Callable[[], None]] = queue.Queue(inbox)
        self._rsock, self._wsock = socket.socketpair()
        self._rsock.setblocking(False)
        self._wsock.setblocking(False)
        self.stopping = False
        self.errors = 0
        #: Work refused because the inbox was full.
        self.refused = 0
        #: Called after every wake-up, before the posted work (e.g. reaping children).
        self.on_wake: Callable[[], None] | None = None
        self.heartbeat = Heartbeat.from_env()
        self.beat_every = beat_every
        self._next_beat = 0.0
        self._signals: set[int] = set()
        #: Held by the thread running the loop except while it waits in ``select``.
        self._owner = threading.Lock()
        self._owner.acquire()
        #: Jobs run inline on a calling thread, and the inline time of the current window.
        self.inline = 0
        self._window = (0.0, 0.0)
        #: The next tick is due no later than this (`due`), whatever the period says.
        self._due = float("inf")

    def wake(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):  # a wake-up is already pending
            self._wsock.send(b"\0")

    def post(self, fn: Callable[[], None]) -> bool:
        """Run ``fn`` on the main thread soon (safe from any thread); False when the inbox
        is full (the work is dropped and counted)."""
        try:
            self.inbox.put_nowait(fn)
        except queue.Full:
            self.refused += 1
            return False
        self.wake()
        return True

    def run_or_post(self, fn: Callable[[], None]) -> bool:
        """Run ``fn`` now on the calling thread if the main thread is idle, nothing is
        waiting before it and the inline budget allows; otherwise `post` it."""
        if self.inbox.empty() and self._within_budget() and self._owner.acquire(blocking=False):
            try:
                if self.inbox.empty() and not self.stopping:
                    self._run_inline(fn)
                    return True
            finally:
                self._owner.release()
        return self.post(fn)

    def _within_budget(self) -> bool:
        start, spent = self._window
        return time.monotonic() - start >= WINDOW or spent < WINDOW * INLINE_SHARE

    def _run_inline(self, fn: Callable[[], None]) -> None:
        t0 = time.monotonic()
        self._run(fn)
        t1 = time.monotonic()
        start, spent = self._window
        self._window = (t0, t1 - t0) if t0 - start >= WINDOW else (start, spent + t1 - t0)
        self.inline += 1

    def request_stop(self, *_: Any) -> None:
        self.stopping = True
        self.wake()

    def install_signals(self, *, on_signal: Callable[[int], None] | None = None) -> None:
        """SIGINT and SIGTERM end the loop (main thread only); ``on_signal`` sees each."""

        def handler(signum: int, _frame: Any) -> None:
            self._signals.add(signum)
            if on_signal is not None:
                on_signal(signum)
            self.request_stop()

        signal.set_wakeup_fd(self._wsock.fileno(), warn_on_full_buffer=False)
        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)

    def wake_on_sigchld(self) -> None:
        """Let a child's exit wake the loop at once (its ``on_wake`` reaps it)."""
        signal.signal(signal.SIGCHLD, lambda *_: None)

    def cycle(self, timeout: float | None) -> None:
        """Wait up to ``timeout`` for work, then run everything posted so far."""
        self._owner.release()
        try:
            ready, _, _ = select.select([self._rsock], [], [], timeout)
        finally:
            self._owner.acquire()
        if ready:
            with contextlib.suppress(BlockingIOError, OSError):
                while self._rsock.recv(256):
                    pass
        if self.on_wake is not None:
            self._run(self.on_wake)
        while True:
            try:
                fn = self.inbox.get_nowait()
            except queue.Empty:
                break
            self._run(fn)
        self._beat()

    def _run(self, fn: Callable[[], None]) -> None:
        try:
            fn()
        except Exception:  # a failing job is reported (with where it failed), the loop goes on
            self.errors += 1
            print(f"rra: a job of the main loop failed:\n{traceback.format_exc()}", flush=True)

    def _beat(self) -> None:
        now = time.monotonic()
        if now >= self._next_beat:
            self.heartbeat.beat()
            self._next_beat = now + self.beat_every

    def due(self, at: float) -> None:
        """Run the next tick no later than ``at`` (this loop's clock), e.g. when a deadline
        shorter than the tick period ends; safe from any thread."""
        if at < self._due:
            self._due = at
            self.wake()

    def run(self, tick: Callable[[float], None] | None = None, period: float = 0.02) -> None:
        """Cycle until stopped, calling ``tick(now)`` about every ``period`` seconds, and
        sooner when `due` asks."""
        next_tick = self.clock()
        while not self.stopping:
            at = min(next_tick, self._due)
            wait = self.beat_every if tick is None else max(0.0, at - self.clock())
            self.cycle(min(wait, self.beat_every))
            if tick is not None and self.clock() >= min(next_tick, self._due):
                self._due = float("inf")
                self._run(lambda: tick(self.clock()))
                next_tick = self.clock() + period

    def set_ready(self) -> None:
        """The process is up (its token declared): the heartbeat's ready flag."""
        self.heartbeat.beat(ready=True)
