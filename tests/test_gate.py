"""A replacement's gate on the end of the old node's process (`rra_agent.host.gate.Exit`):
opened by the kernel's word that the process ended (a pidfd, or its state read where no
pidfd is given), never while it runs, and at once when its pid is gone or taken since."""

from __future__ import annotations

import errno
import os
import subprocess
from collections.abc import Iterator

import pytest

from rra_agent.bus.client import wait_until
from rra_agent.host import gate, procfs

pytestmark = pytest.mark.system  # it starts processes


@pytest.fixture
def sleeper() -> Iterator[subprocess.Popen[bytes]]:
    proc = subprocess.Popen(["sleep", "60"])
    yield proc
    proc.kill()
    proc.wait()


@pytest.fixture(params=["pidfd", "polled"])
def watch(request, monkeypatch):
    """`gate.Exit` as the kernel gives it (a pidfd), and where ``pidfd_open`` is refused."""
    if request.param == "polled":

        def refused(pid: int, flags: int = 0) -> int:
            raise OSError(errno.EMFILE, "Too many open files")

        monkeypatch.setattr(os, "pidfd_open", refused)
    return request.param


def test_the_gate_opens_as_the_process_ends_not_before(sleeper, watch) -> None:
    started = procfs.start_time(sleeper.pid)
    assert started is not None
    ended = gate.Exit(sleeper.pid, started)
    assert (ended.fd is not None) == (watch == "pidfd")
    polls = []

    def stopping() -> bool:  # asked between polls: the process runs, the gate stays shut
        polls.append(1)
        return len(polls) > 2

    assert ended.wait(stopping) is False
    ended = gate.Exit(sleeper.pid, started)
    sleeper.kill()
    wait_until(lambda: procfs.state(sleeper.pid) == "Z", 5, "a zombie")
    assert ended.wait(lambda: False) is True  # ended, not reaped yet: its files are closed
    assert ended.fd is None  # closed once passed


def test_a_pid_gone_or_taken_since_is_an_ended_process(sleeper, watch) -> None:
    started = procfs.start_time(sleeper.pid)
    assert started is not None
    assert gate.Exit(sleeper.pid, started + 1).ended  # same pid, another process
    sleeper.kill()
    sleeper.wait()  # reaped: the pid is free
    assert procfs.start_time(sleeper.pid) is None
    assert gate.Exit(sleeper.pid, started).wait(lambda: False) is True
