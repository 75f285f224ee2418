"""The host agent's record of the components that run inside component containers.

A container (`rra_agent.node.container`) is supervised as one process by the `Supervisor`;
its components are not processes, so they get this smaller state machine, with the same
states and the same `Transition` events as nodes (``rra status``, the actuator and the
reconcile loop see a component in a container as they see a node, with the container's
pid)::

    STOPPED --start--> STARTING --loaded, token seen--> RUNNING
    STARTING --load refused (bad spec, on_start raised)--> FATAL
    STARTING | RUNNING --the container is not running--> BACKOFF --it runs again--> STARTING
    any --stop--> STOPPING --unloaded (or the container gone)--> STOPPED

`_set` is the one place a state changes. Like the supervisor, the table does no I/O and
reads no clock: the host agent passes ``now``, sends the container requests it asks for
(``send``) and feeds back their replies, the tokens and the containers' own transitions.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from rra_agent.bus import messages as m
from rra_agent.bus.failure import reason as with_failure
from rra_agent.host.supervisor import State, Transition


@dataclass
class Member:
    spec: m.NodeSpec
    container: str
    state: State = State.STOPPED
    pid: int | None = None
    want_running: bool = False
    restarts: int = 0
    #: A load or unload is in flight (its reply has not come yet).
    busy: bool = False
    #: The reason of its last failure ("" if none yet), and what raised it if known.
    last_failure: str = ""
    failure: m.Failure | None = None


#: ``send(container, request, on_reply)``: the host agent delivers ``request`` to the
#: container's control endpoint and calls ``on_reply(reply)`` (on its main loop).
Send = Callable[[str, m.ContainerRequest, Callable[[m.Reply], None]], None]


class Members:
    def __init__(self, host: str, send: Send, listener: Callable[[Transition], None]) -> None:
        self.host = host
        self.send = send
        self.listener = listener
        self.members: dict[str, Member] = {}
        #: Each container's pid while it runs (None: not running).
        self.containers: dict[str, int | None] = {}

    # ---- the one place a state changes ---------------------------------------------------
    def _set(
        self, mb: Member, state: State, now: float, reason: str, failure: m.Failure | None = None
    ) -> None:
        previous, mb.state = mb.state, state
        if state in (State.BACKOFF, State.FATAL) or failure is not None:
            mb.last_failure, mb.failure = reason, failure
        if previous != state:
            self.listener(
                Transition(
                    node=mb.spec.name,
                    host=self.host,
                    previous=previous,
                    state=state,
                    now=now,
                    pid=mb.pid,
                    restarts=mb.restarts,
                    reason=reason,
                    failure=failure,
                )
            )

    # ---- commands ----------------------------------------------------------------------
    def start(self, spec: m.NodeSpec, container: str, now: float) -> Member:
        mb = self.members.get(spec.name)
        if mb is None:
            mb = self.members[spec.name] = Member(spec, container)
        mb.spec, mb.want_running, mb.restarts = spec, True, 0
        if mb.state in (State.STOPPED, State.EXITED, State.FATAL):
            self._load(mb, now, "start requested")
        return mb

    def stop(self, name: str, now: float) -> None:
        mb = self.members[name]
        mb.want_running = False
        if mb.state in (State.STARTING, State.RUNNING) and self.containers.get(mb.container):
            self._set(mb, State.STOPPING, now, "stop requested")
            mb.busy = True
            self.send(mb.container, m.UnloadNode(node=name), lambda r: self._unloaded(mb, r, now))
        elif mb.state != State.STOPPED:
            self._set(mb, State.STOPPED, now, "stop requested")

    def replace_spec(self, name: str, spec: m.NodeSpec) -> None:
        self.members[name].spec = spec

    # ---- observations ------------------------------------------------------------------
    def on_container(self, container: str, state: State, pid: int | None, now: float) -> None:
        """The container's own transition (from the supervisor)."""
        running = state == State.RUNNING
        self.containers[container] = pid if running else None
        for mb in self.members.values():
            if mb.container != container:
                continue
            if running and mb.want_running and mb.state in (State.BACKOFF, State.STARTING):
                self._load(mb, now, f"container {container} running")
            elif not running and state not in (State.UNRESPONSIVE,):
                if mb.state == State.STOPPING or not mb.want_running:
                    self._set(mb, State.STOPPED, now, f"container {container} {state.value}")
                elif state == State.FATAL:
                    mb.want_running = False
                    self._set(mb, State.FATAL, now, f"container {container} is FATAL")
                elif mb.state in (State.STARTING, State.RUNNING):
                    mb.restarts += mb.state == State.RUNNING
                    self._set(mb, State.BACKOFF, now, f"container {container} {state.value}")

    def on_ready(self, name: str, now: float) -> None:
        """The component's liveliness token appeared."""
        mb = self.members.get(name)
        if mb is not None and mb.state == State.STARTING and not mb.busy:
            self._set(mb, State.RUNNING, now, "ready")

    # ---- internals ---------------------------------------------------------------------
    def _load(self, mb: Member, now: float, reason: str) -> None:
        pid = self.containers.get(mb.container)
        mb.pid = pid
        self._set(mb, State.STARTING, now, reason)
        if pid is None:
            return  # loaded when the container runs (on_container)
        mb.busy = True
        spec = mb.spec
        self.send(mb.container, m.LoadNode(spec=spec), lambda r: self._loaded(mb, spec, r, now))

    def _loaded(self, mb: Member, spec: m.NodeSpec, reply: m.Reply, now: float) -> None:
        mb.busy = False
        if mb.state != State.STARTING or mb.spec is not spec:
            return  # stopped or respecified meanwhile: a later request decides
        if isinstance(reply, m.Err):
            mb.want_running = False
            why = "load refused" + ("" if reply.failure else f": {reply.message}")
            self._set(mb, State.FATAL, now, with_failure(why, reply.failure), reply.failure)
            return
        # Loaded means on_start ran and the token is declared: the component is ready.
        self._set(mb, State.RUNNING, now, "ready")

    def _unloaded(self, mb: Member, reply: m.Reply, now: float) -> None:
        mb.busy = False
        if mb.state == State.STOPPING:
            self._set(mb, State.STOPPED, now, "unloaded")
