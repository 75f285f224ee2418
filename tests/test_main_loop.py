"""The engines' main loop: work is serialised, and short work on the latency path runs on
the arriving thread when (and only when) the main thread is idle (issue 12)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from rra_agent.bus import loop as loop_mod
from rra_agent.bus.client import wait_until
from rra_agent.bus.loop import MainLoop


@pytest.fixture
def running() -> Iterator[tuple[MainLoop, threading.Thread]]:
    """A loop run by its own thread (as an engine's main thread runs it)."""
    box: dict[str, MainLoop] = {}
    made = threading.Event()

    def main() -> None:
        box["loop"] = MainLoop(beat_every=5.0)  # it wakes only for work
        made.set()
        box["loop"].run()

    t = threading.Thread(target=main, daemon=True)
    t.start()
    assert made.wait(5)
    loop = box["loop"]
    yield loop, t
    loop.request_stop()
    t.join(5)
    assert not t.is_alive()


def until_idle(loop: MainLoop) -> None:
    """The loop's thread is waiting in ``select`` (it has released the loop's lock)."""

    def idle() -> bool:
        if loop._owner.acquire(blocking=False):
            loop._owner.release()
            return True
        return False

    wait_until(idle, 5, "the loop idle in select", interval=0.001)


def test_an_idle_loop_lets_the_arriving_thread_run_the_job(running):
    loop, _main = running
    until_idle(loop)
    ran_on: list[int] = []
    assert loop.run_or_post(lambda: ran_on.append(threading.get_ident()))
    assert ran_on == [threading.get_ident()]  # done before run_or_post returned, right here
    assert loop.inline == 1


def test_a_busy_loop_gets_the_job_posted_and_runs_it_after_its_current_work(running):
    loop, main = running
    release, started = threading.Event(), threading.Event()
    order: list[str] = []

    def long_job() -> None:
        started.set()
        release.wait(5)
        order.append("long")

    loop.post(long_job)
    assert started.wait(5)
    ran_on: list[int] = []

    def job() -> None:
        ran_on.append(threading.get_ident())
        order.append("short")

    assert loop.run_or_post(job)
    assert ran_on == []  # not run concurrently with the main thread's job
    release.set()
    wait_until(lambda: len(order) == 2, 5, "both jobs")
    assert order == ["long", "short"] and ran_on == [main.ident]
    assert loop.inline == 0


def test_work_already_waiting_goes_first(running):
    loop, _main = running
    until_idle(loop)
    order: list[str] = []
    with loop._owner:  # the main thread is momentarily busy: the first job waits in the inbox
        loop.post(lambda: order.append("first"))
        assert loop.run_or_post(lambda: order.append("second"))
    wait_until(lambda: len(order) == 2, 5, "both jobs")
    assert order == ["first", "second"]


def test_a_loop_that_has_not_started_waiting_runs_nothing_inline():
    """Before the main thread first waits (it is still declaring), nothing runs inline."""
    loop = MainLoop()
    ran: list[int] = []
    done = threading.Event()

    def other() -> None:
        loop.run_or_post(lambda: ran.append(1))
        done.set()

    threading.Thread(target=other).start()
    assert done.wait(5)
    assert ran == [] and loop.inbox.qsize() == 1
    loop.cycle(0)
    assert ran == [1]


def test_a_flood_falls_back_to_the_hand_off(running, monkeypatch):
    """Inline work is capped at INLINE_SHARE of each WINDOW: a flood of jobs is handed to the
    main thread (where callers coalesce) instead of holding Zenoh's callback thread."""
    monkeypatch.setattr(loop_mod, "WINDOW", 2.0)  # one window for the whole test: 0.4 s inline
    loop, main = running
    threads: list[int] = []

    def slow() -> None:
        threads.append(threading.get_ident())
        time.sleep(0.05)  # the work of the job

    me = threading.get_ident()
    for _ in range(12):
        until_idle(loop)
        loop.run_or_post(slow)
    wait_until(lambda: len(threads) == 12, 5, "all twelve jobs")
    inline = threads.count(me)
    assert 1 <= inline <= 8 and threads == [me] * inline + [main.ident] * (12 - inline)
    assert loop.inline == inline


def test_a_failing_inline_job_is_counted_and_the_loop_goes_on(running, capsys):
    loop, _main = running
    until_idle(loop)

    def boom() -> None:
        raise RuntimeError("boom")

    assert loop.run_or_post(boom)
    assert loop.errors == 1
    assert "boom" in capsys.readouterr().out
    until_idle(loop)
    ran: list[int] = []
    assert loop.run_or_post(lambda: ran.append(1)) and ran == [1]


def test_due_brings_the_next_tick_forward():
    """A tick period of 60 s; a deadline 10 ms away (a stop deadline at a host agent) asks
    for a tick then, from another thread, and gets it long before the period ends."""
    ticks: list[float] = []
    box: dict[str, MainLoop] = {}
    made = threading.Event()

    def main() -> None:
        box["loop"] = MainLoop(beat_every=5.0)
        made.set()
        box["loop"].run(ticks.append, period=60.0)

    t = threading.Thread(target=main, daemon=True)
    t.start()
    assert made.wait(5)
    loop = box["loop"]
    try:
        wait_until(lambda: len(ticks) == 1, 5, "the first tick")
        loop.due(loop.clock() + 0.01)
        wait_until(lambda: len(ticks) == 2, 20, "the tick the deadline asked for")
        assert ticks[1] - ticks[0] < 30
    finally:
        loop.request_stop()
        t.join(5)
    assert not t.is_alive()
