"""Process supervision: one explicit state machine per node, driven by ``tick(now)``.

States (as in Supervisor, plus one for a suspected freeze)::

    STOPPED --start--> STARTING --ready--> RUNNING
    STARTING --exit | start timeout--> BACKOFF --backoff elapsed--> STARTING
    (a first crash in the restart window: BACKOFF --at once--> STARTING; `backoff`)
    RUNNING --heartbeat older than its deadline--> UNRESPONSIVE (a direct probe is sent)
    UNRESPONSIVE --probe answered | heartbeat again--> RUNNING
    UNRESPONSIVE --no answer within probe_timeout--> killed --> BACKOFF
    RUNNING | UNRESPONSIVE --exit--> BACKOFF (restart policy) | EXITED
    any failure beyond the restart budget (max_restarts in restart_window) --> FATAL
    FATAL --cool-down elapsed--> STARTING (the budget starts afresh)
    any live state --stop--> STOPPING: SIGINT, then SIGTERM, then SIGKILL --exit--> STOPPED
    (a STARTING one: SIGTERM, then SIGKILL: it may not handle SIGINT yet; a stop with a
    deadline: SIGKILL when the deadline passes, at once for 0)

How failures are told from a slow observer (docs/architecture.md, failure model):

- *Death* is an observation from the OS (`on_exit`, fed by the host agent's reaping of its
  children), never inferred from a lease or a liveliness token.
- *Freeze* needs two pieces of evidence: the node's heartbeat (written by the node into
  memory shared with its host agent) is older than its ``heartbeat_timeout``, and the node
  then fails a direct probe within ``probe_timeout``.
- A heartbeat loss seen for many nodes at once is *common-mode* (the machine or this
  observer stalled): it is reported and re-checked, never answered by killing anything. A
  tick that comes late (this observer itself stalled) first gives every node a grace period.

`_set` is the one place that changes a state; it emits a `Transition` to the listener.
The supervisor never reads a clock, sleeps or does I/O: callers pass ``now`` and the
heartbeats they read, and processes are started, signalled and probed through a
`ProcessHost`.
"""

from __future__ import annotations

import signal
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Protocol, cast

from rra_agent.bus.failure import reason as with_failure
from rra_agent.bus.heartbeat import Beat
from rra_agent.bus.messages import Failure, NodeSpec, NodeStateName
from rra_agent.models.system import Supervision

EXIT_CONFIG = 2  # rra_agent.node's exit status for an unusable spec or implementation
#: A tick this much later than expected means the observer itself stalled.
STALL = 0.5
#: At least this many stale nodes, and half of the watched ones, are common-mode.
COMMON_MODE_MIN = 2


class State(StrEnum):
    STOPPED = "STOPPED"
    STARTING = "STARTING"
    RUNNING = "RUNNING"
    UNRESPONSIVE = "UNRESPONSIVE"
    BACKOFF = "BACKOFF"
    STOPPING = "STOPPING"
    EXITED = "EXITED"
    FATAL = "FATAL"

    @property
    def wire(self) -> NodeStateName:
        """The state as a `NodeState` names it: its value (the states are NodeStateName's)."""
        return cast(NodeStateName, self.value)


#: States in which the node's process exists.
LIVE = frozenset({State.STARTING, State.RUNNING, State.UNRESPONSIVE, State.STOPPING})


@dataclass(frozen=True)
class StopPolicy:
    sigint_timeout: float = 2.0
    sigterm_timeout: float = 2.0


class ProcessHost(Protocol):
    """Where node processes run, and how they are probed."""

    name: str

    def spawn(self, spec: NodeSpec) -> int:
        """Start the node's process; return its pid (raise OSError/RraError on failure)."""
        ...

    def signal(self, pid: int, sig: int) -> None: ...

    def probe(self, name: str, pid: int, timeout: float) -> None:
        """Ask the node directly whether it is alive; the answer comes back through
        `Supervisor.on_probe` (later, from another thread's callback)."""
        ...


@dataclass(frozen=True)
class Transition:
    node: str
    host: str
    previous: State
    state: State
    now: float
    pid: int | None
    restarts: int
    reason: str
    #: The exception (or an external command's output) behind this transition.
    failure: Failure | None = None


@dataclass
class Proc:
    """Supervision record of one node."""

    spec: NodeSpec
    host: ProcessHost
    state: State = State.STOPPED
    pid: int | None = None
    since: float = 0.0
    #: When the current wait ends: start timeout, backoff end, probe deadline, stop
    #: escalation step or the end of the FATAL cool-down.
    deadline: float | None = None
    escalation: list[int] = field(default_factory=list)
    exit_status: int | None = None
    want_running: bool = False
    #: Times of the failures inside the restart window (the restart budget).
    failures: list[float] = field(default_factory=list)
    #: Restarts since the node was (re)started by request (reported).
    restarts: int = 0
    #: No freeze verdict before this time (after a start, a probe answered, a stall).
    grace_until: float = 0.0
    #: The last heartbeat seen (host monotonic time).
    last_beat: float | None = None
    #: Already given a second chance after a common-mode loss (reset by a fresh beat).
    rechecked: bool = False
    #: The reason of its last failure ("" if none yet), and what raised it if known.
    last_failure: str = ""
    failure: Failure | None = None

    @property
    def policy(self) -> Supervision:
        return self.spec.supervision


@dataclass
class Notice:
    """Something the supervisor saw that is not a state change (e.g. common-mode loss)."""

    now: float
    kind: str
    message: str
    nodes: tuple[str, ...] = ()


def backoff(policy: Supervision, failures: int, gone: bool) -> float:
    """The wait before a restart, with ``failures`` failures in the restart window (this one
    included): none for the first crash of a process that is gone (the OS reported its exit:
    nothing of it is left to wait for), else ``backoff_initial`` doubled with every further
    failure, up to ``backoff_max`` (a second crash waits ``backoff_initial``; a node killed
    for a freeze or a start timeout waits from its first failure on, while it is reaped)."""
    if gone and failures <= 1:
        return 0.0
    doublings = failures - 2 if gone else failures - 1
    return min(policy.backoff_max, policy.backoff_initial * 2**doublings)


class Supervisor:
    def __init__(
        self,
        *,
        stop: StopPolicy | None = None,
        listener: Callable[[Transition], None] | None = None,
        notices: Callable[[Notice], None] | None = None,
    ) -> None:
        self.stop_policy = stop or StopPolicy()
        self.listener = listener
        self.notices = notices
        self.procs: dict[str, Proc] = {}
        self._last_tick: float | None = None

    # ---- the one place a state changes ---------------------------------------------------
    def _set(
        self, p: Proc, state: State, now: float, reason: str, failure: Failure | None = None
    ) -> None:
        previous = p.state
        p.state = state
        p.since = now
        exited = state == State.EXITED and reason != "exited normally"
        if failure is not None or exited or state in (State.BACKOFF, State.FATAL):
            p.last_failure, p.failure = reason, failure
        if self.listener is not None and previous != state:
            self.listener(
                Transition(
                    node=p.spec.name,
                    host=p.host.name,
                    previous=previous,
                    state=state,
                    now=now,
                    pid=p.pid,
                    restarts=p.restarts,
                    reason=reason,
                    failure=failure,
                )
            )

    def _notice(self, now: float, kind: str, message: str, nodes: tuple[str, ...] = ()) -> None:
        if self.notices is not None:
            self.notices(Notice(now, kind, message, nodes))

    # ---- commands ----------------------------------------------------------------------
    def add(self, spec: NodeSpec, host: ProcessHost) -> Proc:
        if spec.name in self.procs:
            raise ValueError(f"node {spec.name!r} is already supervised")
        p = Proc(spec=spec, host=host)
        self.procs[spec.name] = p
        return p

    def start(self, name: str, now: float) -> None:
        p = self.procs[name]
        p.want_running = True
        if p.state in (State.STOPPED, State.EXITED, State.FATAL):
            p.failures.clear()
            p.restarts = 0
            self._spawn(p, now, "start requested")

    def stop(self, name: str, now: float, deadline: float | None = None) -> None:
        """Stop ``name``: SIGINT, SIGTERM and SIGKILL each after the stop policy's grace
        period, or, with ``deadline`` (seconds), SIGKILL once it has passed (0: at once)."""
        p = self.procs[name]
        p.want_running = False
        if p.state in (State.STARTING, State.RUNNING, State.UNRESPONSIVE):
            self._begin_stop(p, now, "stop requested", deadline)
        elif p.state == State.STOPPING and deadline is not None:
            if deadline <= 0:  # a second, stricter stop of one already stopping
                p.escalation = []
                self._kill(p)
            elif p.deadline is None or now + deadline < p.deadline:
                p.escalation = [signal.SIGKILL]
                p.deadline = now + deadline
        elif p.state in (State.BACKOFF, State.FATAL):
            p.deadline = None
            self._set(p, State.STOPPED, now, f"stop requested in {p.state}")

    def remove(self, name: str) -> None:
        p = self.procs[name]
        if p.state in LIVE:
            raise ValueError(f"node {name!r} is {p.state}; stop it first")
        del self.procs[name]

    def replace_spec(self, name: str, spec: NodeSpec) -> None:
        """New spec (implementation, params, ports, supervision) from the next spawn on."""
        self.procs[name].spec = spec

    # ---- observations ------------------------------------------------------------------
    def on_exit(self, pid: int, status: int, now: float, failure: Failure | None = None) -> None:
        """The OS reported that process ``pid`` ended (negative status: killed by -status);
        ``failure``: what the process reported raising (or an external command's output)."""
        p = self._by_pid(pid)
        if p is not None:
            self._on_exit(p, status, now, failure)

    def on_ready(self, name: str, now: float) -> None:
        """The node said it is ready (its liveliness token, or the ready flag of its
        heartbeat)."""
        p = self.procs.get(name)
        if p is not None and p.state == State.STARTING:
            p.deadline = None
            p.grace_until = now + p.policy.heartbeat_timeout
            self._set(p, State.RUNNING, now, "ready")

    def on_probe(self, name: str, pid: int, ok: bool, now: float) -> None:
        """The answer (or the failure) of a direct probe sent through `ProcessHost.probe`."""
        p = self.procs.get(name)
        if p is None or p.pid != pid or p.state != State.UNRESPONSIVE:
            return
        if ok:
            p.deadline = None
            p.grace_until = now + p.policy.heartbeat_timeout
            self._set(p, State.RUNNING, now, "answered the probe (heartbeat late)")
        else:
            self._frozen(p, now, "no answer to the probe")

    def tick(self, now: float, beats: Mapping[str, Beat] | None = None) -> None:
        """Advance every node to ``now``; ``beats``: the heartbeats read just before."""
        stalled = self._observer_stalled(now)
        beats = beats or {}
        for name, beat in beats.items():
            p = self.procs.get(name)
            if p is not None and p.state in LIVE:
                p.last_beat = beat.at
                if now - beat.at <= p.policy.heartbeat_timeout / 2:
                    p.rechecked = False
                if beat.ready:
                    self.on_ready(name, now)
        if stalled:
            for p in self.procs.values():
                p.grace_until = max(p.grace_until, now + self._grace(p))
        self._check_heartbeats(now)
        for p in list(self.procs.values()):
            self._tick_one(p, now)

    # ---- heartbeats --------------------------------------------------------------------
    def _observer_stalled(self, now: float) -> bool:
        """True when this tick comes much later than the previous ones did."""
        last, self._last_tick = self._last_tick, now
        return last is not None and now - last > STALL

    @staticmethod
    def _grace(p: Proc) -> float:
        """Time a node needs to show a fresh heartbeat: two beat periods."""
        return p.policy.heartbeat_timeout / 2

    def _stale(self, p: Proc, now: float) -> bool:
        timeout = p.policy.heartbeat_timeout
        if p.state != State.RUNNING or timeout <= 0 or now < p.grace_until:
            return False
        return p.last_beat is not None and now - p.last_beat > timeout

    def _check_heartbeats(self, now: float) -> None:
        watched = [
            p for p in self.procs.values() if p.state == State.RUNNING and p.last_beat is not None
        ]
        stale = [p for p in watched if self._stale(p, now)]
        if not stale:
            return
        common = len(stale) >= COMMON_MODE_MIN and 2 * len(stale) >= len(watched)
        if common and any(not p.rechecked for p in stale):
            # Many at once: the machine or this observer stalled. Look again after a grace
            # period; only nodes still silent then are probed one by one.
            names = tuple(sorted(p.spec.name for p in stale))
            self._notice(
                now,
                "common_mode",
                f"{len(stale)} of {len(watched)} nodes missed their heartbeat at once: "
                "the machine or this host agent stalled; re-checking, nothing restarted",
                names,
            )
            for p in stale:
                p.rechecked = True
                p.grace_until = now + self._grace(p)
            return
        for p in stale:
            age = now - p.last_beat  # type: ignore[operator]
            p.deadline = now + p.policy.probe_timeout
            self._set(p, State.UNRESPONSIVE, now, f"no heartbeat for {age:.1f} s; probing")
            if p.pid is not None:
                p.host.probe(p.spec.name, p.pid, p.policy.probe_timeout)

    # ---- deadlines ---------------------------------------------------------------------
    def _tick_one(self, p: Proc, now: float) -> None:
        if (
            p.state == State.UNRESPONSIVE
            and p.last_beat is not None
            and now - p.last_beat <= p.policy.heartbeat_timeout / 2
        ):
            p.deadline = None
            p.grace_until = now + self._grace(p)
            self._set(p, State.RUNNING, now, "heartbeat resumed")
            return
        if p.deadline is None or now < p.deadline:
            return
        match p.state:
            case State.STARTING:
                self._kill(p)
                self._failed(p, now, f"not ready within {p.policy.start_timeout:g} s")
            case State.UNRESPONSIVE:
                self._frozen(p, now, f"no answer to the probe within {p.policy.probe_timeout:g} s")
            case State.BACKOFF:
                self._spawn(p, now, f"restart {p.restarts}")
            case State.FATAL:
                if p.want_running:
                    p.failures.clear()
                    self._spawn(p, now, f"retry after the {p.policy.cooldown:g} s cool-down")
                else:
                    p.deadline = None
            case State.STOPPING:
                self._escalate(p, now)

    # ---- internals ---------------------------------------------------------------------
    def _by_pid(self, pid: int) -> Proc | None:
        return next((p for p in self.procs.values() if p.pid == pid), None)

    def _spawn(self, p: Proc, now: float, reason: str) -> None:
        p.exit_status = None
        p.last_beat = None
        try:
            p.pid = p.host.spawn(p.spec)
        except Exception as e:
            p.pid = None
            self._set(p, State.STARTING, now, reason)
            self._failed(p, now, f"spawn failed: {e}")
            return
        p.deadline = now + p.policy.start_timeout
        p.grace_until = now + p.policy.heartbeat_timeout
        self._set(p, State.STARTING, now, reason)

    def _begin_stop(self, p: Proc, now: float, reason: str, deadline: float | None = None) -> None:
        # A process still starting may not have its handlers yet: a SIGINT would interrupt
        # its imports (a KeyboardInterrupt traceback in its log). SIGTERM ends it silently
        # then, and is handled like SIGINT once the node runs.
        starting = p.state == State.STARTING
        first = signal.SIGTERM if starting else signal.SIGINT
        p.escalation = [signal.SIGKILL] if starting else [signal.SIGTERM, signal.SIGKILL]
        p.deadline = now + self.stop_policy.sigint_timeout
        if deadline is not None:  # no grace period: killed when the deadline passes
            first = signal.SIGKILL if deadline <= 0 else first
            p.escalation = [] if deadline <= 0 else [signal.SIGKILL]
            p.deadline = now + max(deadline, 0.0)
            reason = f"{reason} (deadline {deadline * 1e3:g} ms)"
        if p.pid is not None:
            p.host.signal(p.pid, first)
        self._set(p, State.STOPPING, now, reason)

    def _escalate(self, p: Proc, now: float) -> None:
        if not p.escalation or p.pid is None:
            p.deadline = None
            return
        sig = p.escalation.pop(0)
        p.host.signal(p.pid, sig)
        p.deadline = now + (self.stop_policy.sigterm_timeout if p.escalation else 1.0)

    @staticmethod
    def _kill(p: Proc) -> None:
        """SIGKILL a process that must not go on (frozen, or not ready in time)."""
        if p.pid is not None:
            p.host.signal(p.pid, signal.SIGKILL)

    def _frozen(self, p: Proc, now: float, why: str) -> None:
        age = "" if p.last_beat is None else f"no heartbeat for {now - p.last_beat:.1f} s, "
        self._kill(p)
        self._failed(p, now, f"frozen ({age}{why}): killed")

    def _on_exit(self, p: Proc, status: int, now: float, failure: Failure | None) -> None:
        p.exit_status = status
        if p.state == State.STOPPING:
            p.deadline = None
            why = with_failure(f"stopped (exit status {status})", failure)
            self._set(p, State.STOPPED, now, why, failure)
            p.pid = None  # after the transition, which names the process that stopped
            return
        if p.state not in LIVE:
            p.pid = None  # the one killed before its restart: already accounted for
            return
        if status == EXIT_CONFIG:
            why = "unusable node spec or implementation (exit 2; see its log)"
            self._fatal(p, now, why, failure)
            return
        if status == 0 and p.policy.restart != "always":
            p.deadline = None
            self._set(p, State.EXITED, now, with_failure("exited normally", failure), failure)
            return
        self._failed(p, now, f"exited with status {status}", failure, gone=True)

    def _failed(
        self,
        p: Proc,
        now: float,
        reason: str,
        failure: Failure | None = None,
        *,
        gone: bool = False,
    ) -> None:
        """A failure: EXITED (no restart wanted), FATAL (the restart budget spent) or a
        restart after `backoff`; ``gone``: the OS reported the process's exit, so a first
        failure in the window restarts it at once (through BACKOFF, which reports it)."""
        pol = p.policy
        if pol.restart == "never" or not p.want_running:
            p.deadline = None
            self._set(p, State.EXITED, now, with_failure(reason, failure), failure)
            return
        p.failures = [t for t in p.failures if now - t < pol.restart_window]
        if len(p.failures) >= pol.max_restarts:
            self._fatal(
                p,
                now,
                f"{reason}; {len(p.failures)} restarts within {pol.restart_window:g} s",
                failure,
            )
            return
        p.failures.append(now)
        p.restarts += 1
        delay = backoff(pol, len(p.failures), gone)
        p.deadline = now + delay
        self._set(p, State.BACKOFF, now, with_failure(reason, failure), failure)
        if delay == 0 and p.state == State.BACKOFF:
            self._spawn(p, now, f"restart {p.restarts} (at once: the first crash in the window)")

    def _fatal(self, p: Proc, now: float, reason: str, failure: Failure | None = None) -> None:
        cooldown = p.policy.cooldown
        p.deadline = now + cooldown
        why = with_failure(f"{reason}; retrying in {cooldown:g} s", failure)
        self._set(p, State.FATAL, now, why, failure)

    # ---- queries -----------------------------------------------------------------------
    def next_deadline(self) -> float | None:
        """When the earliest stop escalation is due (a stop deadline may be shorter than
        the tick period; every other wait is long enough for any tick)."""
        return min(
            (p.deadline for p in self.procs.values()
             if p.state == State.STOPPING and p.deadline is not None),
            default=None,
        )  # fmt: skip

    def state(self, name: str) -> State:
        return self.procs[name].state

    def all_stopped(self) -> bool:
        return all(p.state not in LIVE for p in self.procs.values())

    def stop_all(self, now: float) -> None:
        for name in list(self.procs):
            self.stop(name, now)
