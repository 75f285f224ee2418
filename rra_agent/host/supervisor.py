"""Process supervision: one explicit state machine per node, driven by ``tick(now)``.

States (as in Supervisor): STOPPED, STARTING, RUNNING, BACKOFF, STOPPING, EXITED, FATAL.

::

    STOPPED --start--> STARTING --ready (liveliness token)--> RUNNING
    STARTING --exit | start timeout--> BACKOFF --backoff elapsed--> STARTING
    RUNNING --exit | token lost (frozen: killed first)--> BACKOFF (restart policy) | EXITED
    BACKOFF | STARTING | RUNNING --too many restarts | config error (exit 2)--> FATAL
    any live state --stop--> STOPPING: SIGINT, then SIGTERM, then SIGKILL --exit--> STOPPED

`_set` is the one place that changes a state; it emits a `Transition` to the listener. The
supervisor never reads a clock or sleeps: callers pass ``now`` (tests drive it with fake time,
the resolution engine with ``time.monotonic()``). Processes are started and signalled through
a `ProcessHost` (the local host, or a remote host agent), never directly.
"""

from __future__ import annotations

import signal
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Literal, Protocol

from rra_agent.bus.messages import NodeSpec

EXIT_CONFIG = 2  # rra_agent.node's exit status for an unusable spec: never restarted


class State(StrEnum):
    STOPPED = "STOPPED"
    STARTING = "STARTING"
    RUNNING = "RUNNING"
    BACKOFF = "BACKOFF"
    STOPPING = "STOPPING"
    EXITED = "EXITED"
    FATAL = "FATAL"


LIVE = frozenset({State.STARTING, State.RUNNING, State.STOPPING})


@dataclass(frozen=True)
class RestartPolicy:
    #: ``on-failure``: restart after a non-zero exit or a lost token; ``always``: also after 0.
    mode: Literal["always", "on-failure", "never"] = "on-failure"
    max_restarts: int = 5
    backoff_initial: float = 0.1
    backoff_factor: float = 2.0
    backoff_max: float = 5.0
    #: A run this long without failure resets the restart count.
    reset_after: float = 30.0
    #: Time allowed from spawn to the liveliness token (the ready handshake).
    start_timeout: float = 10.0

    def backoff(self, restarts: int) -> float:
        return min(self.backoff_max, self.backoff_initial * self.backoff_factor ** max(0, restarts))


@dataclass(frozen=True)
class StopPolicy:
    sigint_timeout: float = 2.0
    sigterm_timeout: float = 2.0


class ProcessHost(Protocol):
    """Where node processes run: this machine or a host agent elsewhere."""

    name: str

    def spawn(self, spec: NodeSpec) -> int:
        """Start the node's process; return its pid (raise OSError/RraError on failure)."""
        ...

    def signal(self, pid: int, sig: int) -> None: ...

    def poll(self, pid: int) -> int | None:
        """Exit status if the process has ended (negative: killed by that signal), else None."""
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


@dataclass
class Proc:
    """Supervision record of one node."""

    spec: NodeSpec
    host: ProcessHost
    state: State = State.STOPPED
    pid: int | None = None
    restarts: int = 0
    since: float = 0.0
    #: When the current wait ends: start timeout, backoff end, or stop escalation step.
    deadline: float | None = None
    escalation: list[int] = field(default_factory=list)
    alive: bool = False
    exit_status: int | None = None
    want_running: bool = False


class Supervisor:
    def __init__(
        self,
        *,
        restart: RestartPolicy | None = None,
        stop: StopPolicy | None = None,
        listener: Callable[[Transition], None] | None = None,
    ) -> None:
        self.restart = restart or RestartPolicy()
        self.stop_policy = stop or StopPolicy()
        self.listener = listener
        self.procs: dict[str, Proc] = {}

    # ---- the one place a state changes ---------------------------------------------------
    def _set(self, p: Proc, state: State, now: float, reason: str) -> None:
        previous = p.state
        p.state = state
        p.since = now
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
                )
            )

    # ---- commands ----------------------------------------------------------------------
    def add(self, spec: NodeSpec, host: ProcessHost) -> Proc:
        if spec.name in self.procs:
            raise ValueError(f"node {spec.name!r} is already supervised")
        p = Proc(spec=spec, host=host)
        self.procs[spec.name] = p
        return p

    def adopt(self, spec: NodeSpec, host: ProcessHost, pid: int, now: float) -> Proc:
        """Supervise an already running node (e.g. after an engine restart)."""
        p = self.add(spec, host)
        p.pid, p.alive, p.want_running = pid, True, True
        self._set(p, State.RUNNING, now, "adopted")
        return p

    def start(self, name: str, now: float) -> None:
        p = self.procs[name]
        p.want_running = True
        if p.state in (State.STOPPED, State.EXITED, State.FATAL):
            p.restarts = 0
            self._spawn(p, now, "start requested")

    def stop(self, name: str, now: float) -> None:
        p = self.procs[name]
        p.want_running = False
        if p.state in (State.STARTING, State.RUNNING):
            self._begin_stop(p, now, "stop requested")
        elif p.state == State.BACKOFF:
            p.deadline = None
            self._set(p, State.STOPPED, now, "stop requested during backoff")

    def remove(self, name: str) -> None:
        p = self.procs[name]
        if p.state in LIVE:
            raise ValueError(f"node {name!r} is {p.state}; stop it first")
        del self.procs[name]

    def replace_spec(self, name: str, spec: NodeSpec) -> None:
        """New spec (implementation, params, ports) used from the next spawn on."""
        self.procs[name].spec = spec

    # ---- observations ------------------------------------------------------------------
    def on_alive(self, name: str, alive: bool, now: float) -> None:
        """The node's liveliness token appeared (ready) or disappeared (gone or frozen)."""
        p = self.procs.get(name)
        if p is None:
            return
        p.alive = alive
        if alive and p.state == State.STARTING:
            p.deadline = None
            self._set(p, State.RUNNING, now, "ready")
        elif not alive and p.state == State.RUNNING:
            status = p.host.poll(p.pid) if p.pid is not None else None
            if status is not None:  # it died: report the exit, not the lost token
                self._on_exit(p, status, now)
                return
            # The token went but the process is there: frozen or disconnected. Kill it;
            # the restart policy decides what comes next.
            self._kill(p, "liveliness lost")
            self._failed(p, now, "liveliness lost (frozen or disconnected)")

    def tick(self, now: float) -> None:
        for p in list(self.procs.values()):
            self._tick_one(p, now)

    def _tick_one(self, p: Proc, now: float) -> None:
        if p.pid is not None and p.state in LIVE:
            status = p.host.poll(p.pid)
            if status is not None:
                self._on_exit(p, status, now)
                return
        if p.deadline is None or now < p.deadline:
            return
        match p.state:
            case State.STARTING:
                self._kill(p, "start timeout")
                self._failed(p, now, f"not ready within {self.restart.start_timeout:g} s")
            case State.BACKOFF:
                if p.pid is not None and p.host.poll(p.pid) is None:
                    self._kill(p, "still running after backoff")
                self._spawn(p, now, f"restart {p.restarts}")
            case State.STOPPING:
                self._escalate(p, now)

    # ---- internals ---------------------------------------------------------------------
    def _spawn(self, p: Proc, now: float, reason: str) -> None:
        p.alive = False
        p.exit_status = None
        try:
            p.pid = p.host.spawn(p.spec)
        except Exception as e:
            p.pid = None
            self._set(p, State.STARTING, now, reason)
            self._failed(p, now, f"spawn failed: {e}")
            return
        p.deadline = now + self.restart.start_timeout
        self._set(p, State.STARTING, now, reason)

    def _begin_stop(self, p: Proc, now: float, reason: str) -> None:
        p.escalation = [signal.SIGTERM, signal.SIGKILL]
        if p.pid is not None:
            p.host.signal(p.pid, signal.SIGINT)
        p.deadline = now + self.stop_policy.sigint_timeout
        self._set(p, State.STOPPING, now, reason)

    def _escalate(self, p: Proc, now: float) -> None:
        if not p.escalation or p.pid is None:
            return
        sig = p.escalation.pop(0)
        p.host.signal(p.pid, sig)
        p.deadline = now + (self.stop_policy.sigterm_timeout if p.escalation else 1.0)

    def _kill(self, p: Proc, _why: str) -> None:
        """SIGKILL a process that must not go on (frozen, or not ready in time)."""
        if p.pid is not None and p.host.poll(p.pid) is None:
            p.host.signal(p.pid, signal.SIGKILL)

    def _on_exit(self, p: Proc, status: int, now: float) -> None:
        p.exit_status = status
        p.alive = False
        if p.state == State.STOPPING:
            p.deadline = None
            self._set(p, State.STOPPED, now, f"stopped (exit status {status})")
            p.pid = None  # after the transition, which names the process that stopped
            return
        if status == EXIT_CONFIG:
            p.deadline = None
            self._set(p, State.FATAL, now, "unusable node spec or implementation (exit 2)")
            return
        if status == 0 and self.restart.mode != "always":
            p.deadline = None
            self._set(p, State.EXITED, now, "exited normally")
            return
        self._failed(p, now, f"exited with status {status}")

    def _failed(self, p: Proc, now: float, reason: str) -> None:
        if self.restart.mode == "never":
            p.deadline = None
            self._set(p, State.EXITED, now, reason)
            return
        if not self._count_failure(p, now):
            p.deadline = None
            self._set(p, State.FATAL, now, f"{reason}; gave up after {p.restarts} restarts")
            return
        p.deadline = now + self.restart.backoff(p.restarts - 1)
        self._set(p, State.BACKOFF, now, reason)

    def _count_failure(self, p: Proc, now: float) -> bool:
        """Count a restart; False when the budget is spent."""
        if p.state == State.RUNNING and now - p.since >= self.restart.reset_after:
            p.restarts = 0
        if p.restarts >= self.restart.max_restarts:
            return False
        p.restarts += 1
        return True

    # ---- queries -----------------------------------------------------------------------
    def state(self, name: str) -> State:
        return self.procs[name].state

    def all_stopped(self) -> bool:
        return all(p.state not in LIVE for p in self.procs.values())

    def stop_all(self, now: float) -> None:
        for name in list(self.procs):
            self.stop(name, now)
