"""The supervision state machine, driven by tick(now) with fake time, a fake host and the
observations a host agent feeds it (exits from the OS, heartbeats, probe answers)."""

from __future__ import annotations

import signal
import typing

import pytest

from rra_agent.bus.messages import NodeSpec, NodeStateName
from rra_agent.host.supervisor import (
    Beat,
    Notice,
    State,
    StopPolicy,
    Supervisor,
    Transition,
    backoff,
)
from rra_agent.models.system import Supervision


class FakeHost:
    name = "fake"

    def __init__(self) -> None:
        self.next_pid = 100
        self.signals: list[tuple[int, int]] = []
        self.probes: list[tuple[str, int]] = []
        self.fail_spawn = False

    def spawn(self, spec: NodeSpec) -> int:
        if self.fail_spawn:
            raise OSError("no such file")
        self.next_pid += 1
        return self.next_pid

    def signal(self, pid: int, sig: int) -> None:
        self.signals.append((pid, sig))

    def probe(self, name: str, pid: int, timeout: float) -> None:
        self.probes.append((name, pid))


POLICY = Supervision(
    heartbeat_timeout=2.0,
    probe_timeout=0.5,
    start_timeout=5.0,
    max_restarts=2,
    restart_window=10.0,
    cooldown=30.0,
    backoff_initial=1.0,
    backoff_max=4.0,
)


def spec(name: str = "n", policy: Supervision = POLICY) -> NodeSpec:
    return NodeSpec(system="s", name=name, host="fake", implementation="x.Y", supervision=policy)


class Rig:
    def __init__(self) -> None:
        self.events: list[Transition] = []
        self.notices: list[Notice] = []
        self.host = FakeHost()
        self.sup = Supervisor(
            stop=StopPolicy(sigint_timeout=2.0, sigterm_timeout=2.0),
            listener=self.events.append,
            notices=self.notices.append,
        )
        self.now = 0.0

    def run(self, *names: str, policy: Supervision = POLICY) -> None:
        for n in names:
            self.sup.add(spec(n, policy), self.host)
            self.sup.start(n, self.now)
            self.sup.on_ready(n, self.now)

    def tick(self, dt: float, beats: dict[str, float | None] | None = None) -> None:
        """Advance by dt in steps of 0.1 s. ``beats``: node -> time of its last heartbeat,
        or None for a node that keeps beating (its last beat is always 0.05 s old)."""
        end = self.now + dt
        while self.now < end - 1e-9:
            self.now = round(self.now + 0.1, 6)
            seen = {
                n: Beat(self.now - 0.05 if at is None else at) for n, at in (beats or {}).items()
            }
            self.sup.tick(self.now, seen)

    def state(self, name: str = "n") -> State:
        return self.sup.state(name)

    def pid(self, name: str = "n") -> int:
        pid = self.sup.procs[name].pid
        assert pid is not None
        return pid

    def kills(self) -> list[int]:
        return [pid for pid, sig in self.host.signals if sig == signal.SIGKILL]


@pytest.fixture
def rig() -> Rig:
    return Rig()


def test_start_ready_running(rig: Rig) -> None:
    rig.sup.add(spec(), rig.host)
    rig.sup.start("n", 0.0)
    assert rig.state() == State.STARTING
    rig.sup.on_ready("n", 0.1)
    assert rig.state() == State.RUNNING
    assert [e.state for e in rig.events] == [State.STARTING, State.RUNNING]


def test_ready_flag_of_the_heartbeat_also_makes_it_running(rig: Rig) -> None:
    rig.sup.add(spec(), rig.host)
    rig.sup.start("n", 0.0)
    rig.sup.tick(0.1, {"n": Beat(0.05, ready=True)})
    assert rig.state() == State.RUNNING


def test_a_first_crash_restarts_at_once_a_second_waits_the_backoff(rig: Rig) -> None:
    rig.run("n")
    first = rig.pid()
    rig.sup.on_exit(first, -9, 1.0)
    # Reported (BACKOFF, with the exit status) and restarted in the same call: no tick.
    assert [e.state for e in rig.events[-2:]] == [State.BACKOFF, State.STARTING]
    assert "status -9" in rig.events[-2].reason
    assert "at once" in rig.events[-1].reason and rig.events[-1].now == 1.0
    assert rig.state() == State.STARTING and rig.pid() != first
    rig.now = 1.0
    rig.sup.on_ready("n", rig.now)
    second = rig.pid()
    rig.sup.on_exit(second, -9, rig.now)  # the second crash in the window waits 1 s
    assert rig.state() == State.BACKOFF and rig.pid() == second
    rig.tick(0.9)
    assert rig.state() == State.BACKOFF
    rig.tick(0.2)
    assert rig.state() == State.STARTING and rig.pid() != second
    rig.sup.on_ready("n", rig.now)
    rig.sup.on_exit(rig.pid(), -9, rig.now)  # a third: the budget (2) is spent
    assert rig.state() == State.FATAL


def test_the_backoff_grows_from_the_second_crash_on() -> None:
    policy = Supervision(backoff_initial=0.1, backoff_max=0.5)
    assert [backoff(policy, n, gone=True) for n in range(1, 6)] == [0.0, 0.1, 0.2, 0.4, 0.5]
    # A node killed (frozen, not ready in time) waits from its first failure on.
    assert [backoff(policy, n, gone=False) for n in range(1, 4)] == [0.1, 0.2, 0.4]


def test_a_crash_loop_still_goes_fatal_and_is_retried_after_the_cooldown(rig: Rig) -> None:
    """A node that dies as soon as it starts: the first restart at once, then the backoff,
    then FATAL once the budget is spent; the cool-down restarts it with a fresh budget,
    whose first crash again restarts at once."""
    rig.run("n")
    rig.sup.on_exit(rig.pid(), 1, rig.now)
    assert rig.state() == State.STARTING  # at once
    rig.sup.on_exit(rig.pid(), 1, rig.now)  # dies before it is ready
    assert rig.state() == State.BACKOFF
    rig.tick(1.1)
    assert rig.state() == State.STARTING
    rig.sup.on_exit(rig.pid(), 1, rig.now)
    assert rig.state() == State.FATAL
    assert "2 restarts within 10 s" in rig.events[-1].reason
    rig.tick(30.1)
    assert rig.state() == State.STARTING and "cool-down" in rig.events[-1].reason
    rig.sup.on_exit(rig.pid(), 1, rig.now)
    assert rig.state() == State.STARTING and "at once" in rig.events[-1].reason


def test_start_timeout_kills_and_backs_off(rig: Rig) -> None:
    rig.sup.add(spec(), rig.host)
    rig.sup.start("n", 0.0)
    pid = rig.pid()
    rig.tick(5.05)
    assert rig.state() == State.BACKOFF
    assert pid in rig.kills()
    rig.sup.on_exit(pid, -9, rig.now)  # the killed one's exit: no second failure
    assert rig.state() == State.BACKOFF and rig.sup.procs["n"].restarts == 1


def test_restart_budget_then_fatal_then_retry_after_cooldown(rig: Rig) -> None:
    rig.run("n")
    for state in (State.STARTING, State.BACKOFF):  # the first crash restarts at once
        rig.sup.on_exit(rig.pid(), 1, rig.now)
        assert rig.state() == state
        rig.tick(4.0)
        rig.sup.on_ready("n", rig.now)
    rig.sup.on_exit(rig.pid(), 1, rig.now)
    assert rig.state() == State.FATAL
    assert "2 restarts within 10 s" in rig.events[-1].reason
    assert "retrying in 30 s" in rig.events[-1].reason
    rig.tick(29.9)
    assert rig.state() == State.FATAL
    rig.tick(0.2)
    assert rig.state() == State.STARTING
    assert "cool-down" in rig.events[-1].reason
    rig.sup.on_ready("n", rig.now)
    rig.sup.on_exit(rig.pid(), 1, rig.now)
    assert rig.state() == State.STARTING  # a fresh budget: its first crash, at once


def test_failures_outside_the_window_do_not_count(rig: Rig) -> None:
    rig.run("n")
    for _ in range(5):
        rig.sup.on_exit(rig.pid(), 1, rig.now)
        assert rig.state() == State.STARTING  # each the first in its window: at once
        assert "at once" in rig.events[-1].reason
        rig.sup.on_ready("n", rig.now)
        rig.tick(11.0)
    assert rig.state() == State.RUNNING


def test_config_error_is_fatal_and_retried_after_cooldown(rig: Rig) -> None:
    rig.run("n")
    rig.sup.on_exit(rig.pid(), 2, 0.5)
    assert rig.state() == State.FATAL
    assert "exit 2" in rig.events[-1].reason
    rig.now = 0.5
    rig.tick(30.1)
    assert rig.state() == State.STARTING


def test_exit_zero_is_final_unless_restart_always(rig: Rig) -> None:
    rig.run("a")
    rig.run("b", policy=Supervision(restart="always"))
    rig.sup.on_exit(rig.pid("a"), 0, 0.1)
    rig.sup.on_exit(rig.pid("b"), 0, 0.1)
    assert rig.state("a") == State.EXITED
    assert rig.state("b") == State.STARTING  # restarted at once


def test_stale_heartbeat_probe_answered_keeps_the_process(rig: Rig) -> None:
    rig.run("n")
    rig.tick(1.0, {"n": None})
    rig.tick(2.0, {"n": 1.0})  # the last beat at t = 1.0
    assert rig.state() == State.RUNNING  # 2.0 s old is not older than the 2 s deadline
    rig.tick(0.2, {"n": 1.0})
    assert rig.state() == State.UNRESPONSIVE
    assert rig.host.probes == [("n", rig.pid())]
    rig.sup.on_probe("n", rig.pid(), True, rig.now)
    assert rig.state() == State.RUNNING
    rig.tick(1.5, {"n": 1.0})  # still no beat, but the answer bought a grace period
    assert rig.state() == State.RUNNING
    assert rig.kills() == []


def test_stale_heartbeat_and_failed_probe_kill_and_restart(rig: Rig) -> None:
    rig.run("n")
    pid = rig.pid()
    rig.tick(2.2, {"n": 0.0})
    assert rig.state() == State.UNRESPONSIVE
    rig.tick(0.3, {"n": 0.0})  # probed at 2.1 s: 0.4 s without an answer
    assert rig.state() == State.UNRESPONSIVE and rig.kills() == []
    rig.tick(0.2, {"n": 0.0})  # no answer within probe_timeout
    assert rig.kills() == [pid]
    assert rig.state() == State.BACKOFF
    assert "frozen" in rig.events[-1].reason


def test_a_refused_probe_kills_at_once(rig: Rig) -> None:
    rig.run("n")
    pid = rig.pid()
    rig.tick(2.2, {"n": 0.0})
    rig.sup.on_probe("n", pid, False, rig.now)
    assert rig.kills() == [pid] and rig.state() == State.BACKOFF


def test_heartbeat_resuming_while_probing_ends_the_suspicion(rig: Rig) -> None:
    rig.run("n")
    rig.tick(2.2, {"n": 0.0})
    assert rig.state() == State.UNRESPONSIVE
    rig.tick(0.1, {"n": None})
    assert rig.state() == State.RUNNING
    assert rig.kills() == []


def test_common_mode_loss_is_rechecked_not_killed(rig: Rig) -> None:
    rig.run("a", "b", "c", "d")
    rig.tick(2.2, {"a": 0.0, "b": 0.0, "c": 0.0, "d": None})
    assert rig.host.probes == [] and rig.kills() == []
    assert [n.kind for n in rig.notices] == ["common_mode"]
    assert rig.notices[0].nodes == ("a", "b", "c")
    rig.tick(5.0, {"a": None, "b": None, "c": None, "d": None})  # they beat again
    assert all(rig.state(n) == State.RUNNING for n in "abcd")
    assert rig.kills() == [] and rig.host.probes == []


def test_a_loss_that_outlasts_the_recheck_is_probed(rig: Rig) -> None:
    rig.run("a", "b", "c")
    rig.tick(2.2, {"a": 0.0, "b": 0.0, "c": 0.0})
    assert rig.host.probes == [] and len(rig.notices) == 1
    rig.tick(1.1, {"a": 0.0, "b": 0.0, "c": 0.0})
    assert {n for n, _ in rig.host.probes} == {"a", "b", "c"}
    for n in "ab":
        rig.sup.on_probe(n, rig.pid(n), True, rig.now)
    rig.tick(0.6, {"a": 0.0, "b": 0.0, "c": 0.0})
    assert rig.state("a") == rig.state("b") == State.RUNNING
    assert rig.state("c") == State.BACKOFF


def test_a_late_tick_gives_every_node_a_grace_period(rig: Rig) -> None:
    rig.run("n")
    rig.tick(2.5, {"n": None})
    last = rig.now - 0.05
    rig.now += 3.0  # every process stalled for 3 s (this observer too): a 3 s old beat
    rig.sup.tick(rig.now, {"n": Beat(last)})
    assert rig.state() == State.RUNNING and rig.host.probes == []
    rig.tick(0.3, {"n": None})
    assert rig.state() == State.RUNNING and rig.host.probes == []


def test_a_node_that_never_beat_is_not_judged_frozen(rig: Rig) -> None:
    rig.run("n")  # an external command that does not implement the heartbeat
    rig.tick(20.0)
    assert rig.state() == State.RUNNING and rig.host.probes == []


def test_stop_escalates_sigint_sigterm_sigkill(rig: Rig) -> None:
    rig.run("n")
    pid = rig.pid()
    rig.sup.stop("n", 0.0)
    assert rig.host.signals[-1] == (pid, signal.SIGINT)
    rig.now = 0.0
    rig.tick(2.05)
    assert rig.host.signals[-1] == (pid, signal.SIGTERM)
    rig.tick(2.05)
    assert rig.host.signals[-1] == (pid, signal.SIGKILL)
    rig.sup.on_exit(pid, -9, rig.now)
    assert rig.state() == State.STOPPED
    assert rig.sup.all_stopped()


def test_a_stop_with_deadline_0_kills_at_once(rig: Rig) -> None:
    """The strategy said the old node has no grace period: SIGKILL, no SIGINT first, and
    its exit is a stop (STOPPED), not a failure."""
    rig.run("n")
    pid = rig.pid()
    rig.sup.stop("n", 0.0, deadline=0.0)
    assert rig.host.signals == [(pid, signal.SIGKILL)]
    assert rig.state() == State.STOPPING and "deadline 0 ms" in rig.events[-1].reason
    rig.sup.on_exit(pid, -9, 0.001)
    assert rig.state() == State.STOPPED and rig.sup.procs["n"].restarts == 0


def test_a_stop_with_a_deadline_kills_when_it_passes_not_after_the_grace_periods(rig: Rig) -> None:
    rig.run("n")
    pid = rig.pid()
    rig.sup.stop("n", 0.0, deadline=0.05)
    assert rig.host.signals == [(pid, signal.SIGINT)]
    assert rig.sup.next_deadline() == pytest.approx(0.05)  # the host agent ticks then
    rig.sup.tick(0.04)
    assert rig.host.signals == [(pid, signal.SIGINT)]
    rig.sup.tick(0.05)
    assert rig.host.signals == [(pid, signal.SIGINT), (pid, signal.SIGKILL)]
    rig.sup.on_exit(pid, -9, 0.06)
    assert rig.state() == State.STOPPED and rig.sup.next_deadline() is None


def test_a_stricter_stop_of_a_stopping_node_shortens_its_wait(rig: Rig) -> None:
    rig.run("n")
    pid = rig.pid()
    rig.sup.stop("n", 0.0)
    assert rig.sup.next_deadline() == pytest.approx(2.0)
    rig.sup.stop("n", 0.5, deadline=0.1)
    assert rig.sup.next_deadline() == pytest.approx(0.6)
    rig.sup.stop("n", 0.55, deadline=0.0)
    assert rig.host.signals == [(pid, signal.SIGINT), (pid, signal.SIGKILL)]


def test_only_stop_escalations_ask_for_an_early_tick(rig: Rig) -> None:
    rig.run("n")  # its start deadline was cleared when ready; a backoff waits on the tick
    rig.sup.on_exit(rig.pid(), 1, 0.0)  # restarted at once
    rig.sup.on_ready("n", 0.0)
    rig.sup.on_exit(rig.pid(), 1, 0.0)  # the second crash waits its backoff
    assert rig.state() == State.BACKOFF and rig.sup.next_deadline() is None


def test_stop_during_backoff_or_fatal(rig: Rig) -> None:
    rig.run("a", "b")
    rig.sup.on_exit(rig.pid("a"), 1, 0.0)  # restarted at once; its second crash: BACKOFF
    rig.sup.on_exit(rig.pid("a"), 1, 0.0)
    rig.sup.on_exit(rig.pid("b"), 2, 0.0)
    rig.sup.stop("a", 0.1)
    rig.sup.stop("b", 0.1)
    assert rig.state("a") == rig.state("b") == State.STOPPED
    rig.tick(40.0)
    assert rig.state("a") == rig.state("b") == State.STOPPED


def test_spawn_failure_counts_as_a_failure(rig: Rig) -> None:
    rig.host.fail_spawn = True
    rig.sup.add(spec(), rig.host)
    rig.sup.start("n", 0.0)
    assert rig.state() == State.BACKOFF
    assert "spawn failed" in rig.events[-1].reason


def test_states_are_the_wire_names() -> None:
    # State.wire casts its value to NodeStateName: the two must list the same names.
    assert [s.wire for s in State] == [s.value for s in State]
    assert {s.wire for s in State} == set(typing.get_args(NodeStateName))
