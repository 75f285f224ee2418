"""The supervision state machine, driven by tick(now) with fake time and a fake host."""

from __future__ import annotations

import signal

import pytest

from rra_agent.bus.messages import NodeSpec
from rra_agent.host.supervisor import (
    RestartPolicy,
    State,
    StopPolicy,
    Supervisor,
    Transition,
)


class FakeHost:
    name = "fake"

    def __init__(self) -> None:
        self.next_pid = 100
        self.running: dict[int, int | None] = {}  # pid -> exit status once exited
        self.signals: list[tuple[int, int]] = []
        self.fail_spawn = False
        self.ignore = set[int]()  # signals the process ignores

    def spawn(self, spec: NodeSpec) -> int:
        if self.fail_spawn:
            raise OSError("no such file")
        self.next_pid += 1
        self.running[self.next_pid] = None
        return self.next_pid

    def signal(self, pid: int, sig: int) -> None:
        self.signals.append((pid, sig))
        if sig not in self.ignore and self.running.get(pid) is None:
            self.running[pid] = -sig

    def poll(self, pid: int) -> int | None:
        return self.running.get(pid)

    def exit(self, pid: int, status: int) -> None:
        self.running[pid] = status


def spec(name: str = "n") -> NodeSpec:
    return NodeSpec(system="s", name=name, host="fake", implementation="x.Y")


@pytest.fixture
def sup() -> tuple[Supervisor, FakeHost, list[Transition]]:
    events: list[Transition] = []
    s = Supervisor(
        restart=RestartPolicy(max_restarts=2, backoff_initial=1.0, start_timeout=5.0),
        stop=StopPolicy(sigint_timeout=2.0, sigterm_timeout=2.0),
        listener=events.append,
    )
    host = FakeHost()
    s.add(spec(), host)
    return s, host, events


def states(events: list[Transition]) -> list[str]:
    return [e.state.value for e in events]


def test_start_ready_stop(sup):
    s, host, events = sup
    s.start("n", 0.0)
    assert s.state("n") == State.STARTING
    s.on_alive("n", True, 0.1)
    assert s.state("n") == State.RUNNING
    s.stop("n", 1.0)
    assert (101, signal.SIGINT) in host.signals
    s.tick(1.1)
    assert s.state("n") == State.STOPPED
    assert states(events) == ["STARTING", "RUNNING", "STOPPING", "STOPPED"]


def test_stop_escalates_sigint_sigterm_sigkill(sup):
    s, host, _ = sup
    host.ignore = {signal.SIGINT, signal.SIGTERM}
    s.start("n", 0.0)
    s.on_alive("n", True, 0.1)
    s.stop("n", 1.0)
    s.tick(2.9)
    assert host.signals == [(101, signal.SIGINT)]
    s.tick(3.0)  # sigint_timeout elapsed
    assert host.signals[-1] == (101, signal.SIGTERM)
    s.tick(5.0)  # sigterm_timeout elapsed
    assert host.signals[-1] == (101, signal.SIGKILL)
    s.tick(5.1)
    assert s.state("n") == State.STOPPED


def test_crash_restarts_with_backoff_then_fatal(sup):
    s, host, events = sup
    s.start("n", 0.0)
    s.on_alive("n", True, 0.1)
    host.exit(101, -9)
    s.tick(1.0)
    assert s.state("n") == State.BACKOFF
    s.tick(1.5)  # backoff 1.0 s not over
    assert s.state("n") == State.BACKOFF
    s.tick(2.0)
    assert s.state("n") == State.STARTING and s.procs["n"].pid == 102
    host.exit(102, 1)
    s.tick(2.1)
    assert s.state("n") == State.BACKOFF
    s.tick(4.1)  # second backoff doubles: 2.0 s
    assert s.state("n") == State.STARTING
    host.exit(103, 1)
    s.tick(4.2)
    assert s.state("n") == State.FATAL
    assert "gave up after 2 restarts" in events[-1].reason


def test_start_timeout_kills_and_backs_off(sup):
    s, host, _ = sup
    s.start("n", 0.0)
    s.tick(4.9)
    assert s.state("n") == State.STARTING
    s.tick(5.0)
    assert (101, signal.SIGKILL) in host.signals
    assert s.state("n") == State.BACKOFF


def test_lost_liveliness_of_running_process_kills_and_restarts(sup):
    s, host, events = sup
    s.start("n", 0.0)
    s.on_alive("n", True, 0.1)
    s.on_alive("n", False, 3.0)  # frozen: token lease expired, process still there
    assert (101, signal.SIGKILL) in host.signals
    assert s.state("n") == State.BACKOFF
    assert "liveliness lost" in events[-1].reason
    s.tick(4.0)
    assert s.state("n") == State.STARTING


def test_config_error_exit_is_fatal_without_restart(sup):
    s, host, _ = sup
    s.start("n", 0.0)
    host.exit(101, 2)
    s.tick(0.5)
    assert s.state("n") == State.FATAL
    assert host.next_pid == 101


def test_clean_exit_is_exited_not_restarted(sup):
    s, host, _ = sup
    s.start("n", 0.0)
    s.on_alive("n", True, 0.1)
    host.exit(101, 0)
    s.tick(0.5)
    s.tick(10.0)
    assert s.state("n") == State.EXITED


def test_spawn_failure_goes_to_backoff(sup):
    s, host, events = sup
    host.fail_spawn = True
    s.start("n", 0.0)
    assert s.state("n") == State.BACKOFF
    assert "spawn failed" in events[-1].reason


def test_long_stable_run_resets_restart_budget(sup):
    s, host, _ = sup
    s.start("n", 0.0)
    s.on_alive("n", True, 0.1)
    for pid, t in ((101, 1.0), (102, 100.0), (103, 200.0)):
        host.exit(pid, 1)
        s.tick(t)
        assert s.state("n") == State.BACKOFF, t
        s.tick(t + 1.0)
        s.on_alive("n", True, t + 1.1)
    assert s.procs["n"].restarts == 1


def test_stop_during_backoff_is_immediate(sup):
    s, host, _ = sup
    s.start("n", 0.0)
    host.exit(101, 1)
    s.tick(0.1)
    s.stop("n", 0.2)
    assert s.state("n") == State.STOPPED
    s.tick(10.0)
    assert s.state("n") == State.STOPPED


def test_token_lost_because_process_died_reports_the_exit(sup):
    s, host, events = sup
    s.start("n", 0.0)
    s.on_alive("n", True, 0.1)
    host.exit(101, -9)
    s.on_alive("n", False, 0.2)
    assert s.state("n") == State.BACKOFF
    assert "status -9" in events[-1].reason
    assert (101, signal.SIGKILL) not in host.signals


def test_stopped_transition_names_the_process_that_stopped(sup):
    s, _host, events = sup
    s.start("n", 0.0)
    s.on_alive("n", True, 0.1)
    s.stop("n", 1.0)
    s.tick(1.1)
    assert events[-1].state == State.STOPPED and events[-1].pid == 101
    assert s.procs["n"].pid is None
