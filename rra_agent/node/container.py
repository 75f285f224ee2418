"""A component container: several components in one process, as ROS 2 composition does.

``container: NAME`` in system.yaml puts a component in the container ``NAME`` of its host.
The host agent supervises the container as one process (started, restarted, probed and
stopped like a node) and loads and unloads its components one by one with `LoadNode` /
`UnloadNode` requests on the container's control key. Inside, every component keeps what a
node process has: its own ports (its own publishers and subscribers on the container's one
Zenoh session), parameters, control endpoint (``rra/<system>/node/<component>/ctl``),
liveliness token (its readiness) and state export; starts, stops, swaps and rewires are per
component. A component's callback that raises (even ``sys.exit``) is counted and logged with
its traceback by its `NodeCore`; one that raises while it is loaded does not start and is
answered with its `Failure`; either way its neighbours go on. One process for many
components saves the interpreter, the session and the scheduling of a process per component
(the memory and the switch of a hundred components).

What a container loads is what its host agent's model declares: the container's own spec
(from the host agent, never from the bus) lists its members' implementations and parameter
declarations, its ports' types and the data types they carry, and a `LoadNode` naming anything
else, a port it does not declare, or a value out of bounds, is refused.

The main loop steps every component at its ``rate_hz`` and beats the container's heartbeat
only while it can take every component's lock: a component stuck in a callback stops the
beat, and its host agent probes and restarts the container (with all its components).
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import socket
import sys
import time
from dataclasses import dataclass
from typing import Any

import msgspec
import zenoh

from rra_agent.bus import failure
from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import Counters, Refused, receive
from rra_agent.bus.heartbeat import Heartbeat
from rra_agent.bus.keys import Keys
from rra_agent.bus.session import CONTROL_QOS, beat_period, open_session
from rra_agent.models.measurements import DataType
from rra_agent.models.system import coerce_parameter
from rra_agent.node.api import NodeError
from rra_agent.node.core import NodeCore
from rra_agent.node.loading import load_node_class
from rra_agent.node.runtime import (
    ZenohTransport,
    bind_ports,
    control_callback,
    must_wake,
    reflex_reporter,
    rehearse_class,
)

_REQ = m.Codec[m.ContainerRequest](m.ContainerRequest)
_REPLY = m.Codec[m.Reply](m.Reply)


class MemberDecl(msgspec.Struct, frozen=True):
    """What a container may load under a name (from its host agent's model)."""

    implementations: list[str]
    decl: dict[str, m.ParamDecl] = {}
    #: Its ports' declared types (port name -> type), and the data types its inputs carry.
    ports: dict[str, str] = {}
    types: list[DataType] = []


def members_of(spec: m.NodeSpec) -> dict[str, MemberDecl]:
    """The members a container's spec declares (``params["members"]``)."""
    return msgspec.convert(spec.params.get("members") or {}, dict[str, MemberDecl])


@dataclass
class _Loaded:
    core: NodeCore
    transport: ZenohTransport
    queryable: Any
    token: Any
    next_step: float


class ContainerRuntime:
    """The container process: one session, many `NodeCore` s."""

    def __init__(self, spec: m.NodeSpec, bus: BusConfig) -> None:
        self.spec = spec
        self.bus = bus
        self.keys = Keys(spec.system)
        self.members = members_of(spec)
        self.loaded: dict[str, _Loaded] = {}
        self.counters = Counters()
        self.heartbeat = Heartbeat.from_env()
        self._rsock, self._wsock = socket.socketpair()
        self._rsock.setblocking(False)
        self._wsock.setblocking(False)
        self._signalled = False
        self._pending: list[tuple[zenoh.Query, m.ContainerRequest]] = []
        self.session: zenoh.Session | None = None

    # ---- process ---------------------------------------------------------------------
    def run(self) -> int:
        signal.set_wakeup_fd(self._wsock.fileno(), warn_on_full_buffer=False)
        signal.signal(signal.SIGINT, self._on_signal)
        signal.signal(signal.SIGTERM, self._on_signal)
        self.session = open_session(self.bus)
        token = queryable = None
        try:
            queryable = self.session.declare_queryable(
                self.keys.node_ctl(self.spec.name), self._on_query
            )
            token = self.session.liveliness().declare_token(
                self.keys.alive(self.spec.host, self.spec.name)
            )
            self.heartbeat.beat(ready=True)
            self._loop()
            return 0
        finally:
            for name in list(self.loaded):
                self._unload(name)
            if queryable is not None:
                queryable.undeclare()
            if token is not None:
                token.undeclare()
            self.session.close()
            signal.set_wakeup_fd(-1)

    def _on_signal(self, signum: int, _frame: Any) -> None:
        self._signalled = True

    def _wake(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            self._wsock.send(b"\0")

    # ---- the container's control endpoint (Zenoh thread: hand to the main loop) ---------
    def _on_query(self, query: zenoh.Query) -> None:
        req = receive(query.payload, "node_ctl", _REQ)
        if isinstance(req, Refused):
            self.counters.dropped += 1
            query.reply(query.key_expr, _REPLY.encode(req.err()))
            return
        self.counters.received += 1
        if isinstance(req, m.Ping):  # answered here: a probe must not wait behind a load
            query.reply(query.key_expr, _REPLY.encode(m.Ok(result={"pid": os.getpid()})))
            return
        if isinstance(req, m.NodeBatch):  # here too, as each component's endpoint would
            replies = [msgspec.to_builtins(self._call(c)) for c in req.calls]
            query.reply(query.key_expr, _REPLY.encode(m.Ok(result=replies)), **CONTROL_QOS)
            return
        self._pending.append((query, req))  # list.append is atomic; the loop drains it
        self._wake()

    def _call(self, call: m.NodeCall) -> m.Reply:
        """One request of a `NodeBatch`, handled by its component's core (under its lock,
        on this Zenoh thread, as its own control endpoint does)."""
        loaded = self.loaded.get(call.node)
        if loaded is None:
            return m.Err(message=f"no component {call.node!r} in {self.spec.name}",
                         code="unknown")  # fmt: skip
        core = loaded.core
        core.counters.received += 1
        self.counters.bump("batched")
        reply = core.handle(call.request)
        if must_wake(core, call.request):
            self._wake()
        return reply

    def _serve_pending(self) -> None:
        while self._pending:
            query, req = self._pending.pop(0)
            try:
                reply = self.handle(req)
            except Exception as e:  # a bad request must never take the container down
                reply = m.Err(message=f"{type(e).__name__}: {e}", code="error")
            query.reply(query.key_expr, _REPLY.encode(reply))

    def handle(self, req: m.ContainerRequest) -> m.Reply:
        match req:
            case m.LoadNode(spec=spec):
                return self._load(spec)
            case m.UnloadNode(node=name):
                if name not in self.loaded:
                    return m.Ok(result={"already": True})
                self._unload(name)
                return m.Ok()
            case m.Stats():
                return m.Ok(result={"loaded": sorted(self.loaded), "pid": os.getpid(),
                                    "counters": dict(self.counters.extra)})  # fmt: skip
            case m.Describe():
                return m.Ok(result={"name": self.spec.name, "loaded": sorted(self.loaded)})
        return m.Err(message=f"unsupported request {type(req).__name__}", code="refused")

    # ---- members -------------------------------------------------------------------------
    def _admit(self, spec: m.NodeSpec) -> m.NodeSpec:
        """The spec as this container's model allows it (`NodeError` otherwise)."""
        member = self.members.get(spec.name)
        if member is None:
            raise NodeError(f"{spec.name!r} is not a member of container {self.spec.name}")
        if spec.implementation not in member.implementations or spec.system != self.spec.system:
            raise NodeError(f"{spec.name}: not the implementation its model declares")
        for key, value in spec.params.items():
            d = member.decl.get(key)
            if d is None:
                raise NodeError(f"{spec.name}: parameter {key!r} is not declared")
            if value is not None:
                try:
                    coerce_parameter(d.type, value, d.min, d.max)
                except ValueError as e:
                    raise NodeError(f"{spec.name}: parameter {key}: {e}") from None
        try:
            ports = m.typed_ports(spec.name, spec.ports, member.ports)
        except ValueError as e:
            raise NodeError(str(e)) from None
        return msgspec.structs.replace(
            spec, decl=member.decl, host=self.spec.host, path=list(self.spec.path),
            ports=ports, types=list(member.types),
        )  # fmt: skip

    def _load(self, spec: m.NodeSpec) -> m.Reply:
        try:
            spec = self._admit(spec)
        except NodeError as e:
            self.counters.rejected += 1
            return m.Err(message=str(e), code="refused")
        if spec.name in self.loaded:
            return m.Ok(result={"already": True, "pid": os.getpid()})
        assert self.session is not None
        transport = ZenohTransport(self.session)
        queryable = None
        try:
            node_cls = load_node_class(spec.implementation, spec.path)  # type: ignore[arg-type]
            rehearse_class(node_cls, spec.name)
            # _stderr: the core prefixes its lines with the component's name itself.
            core = NodeCore(
                spec, node_cls, transport, logger=_stderr, pid=os.getpid(), contained=True,
                max_data=self.bus.max_data_bytes,
            )  # fmt: skip
            core.on_reflex = reflex_reporter(self.session, self.keys.reflex(spec.name))
            bind_ports(transport, core.ports)
            queryable = self.session.declare_queryable(
                self.keys.node_ctl(spec.name), control_callback(core, self._wake)
            )
            core.start()
        except (Exception, SystemExit) as e:  # it does not start; its neighbours go on
            if queryable is not None:
                queryable.undeclare()
            transport.close()
            return self._load_failed(spec, e)
        transport.start_delivery(core)
        token = self.session.liveliness().declare_token(self.keys.alive(spec.host, spec.name))
        rate = core.rate_hz
        first = time.time() + (1.0 / rate if rate > 0 else 0.0)
        self.loaded[spec.name] = _Loaded(core, transport, queryable, token, first)
        return m.Ok(result={"pid": os.getpid()})

    def _load_failed(self, spec: m.NodeSpec, e: BaseException) -> m.Err:
        """A component that raised while loading (import, constructor, ``on_start``, even
        ``sys.exit``): its traceback in the container's log, its `Failure` in the reply."""
        f = failure.describe(e, "load", spec.path)
        prefix = f"[{spec.name}] "
        text = f"did not start: {failure.summary(f)}\n{failure.formatted(e)}"
        _stderr(prefix + text.replace("\n", "\n" + prefix))
        return m.Err(message=f"{spec.name}: {failure.summary(f)}", code="node_error", failure=f)

    def _unload(self, name: str) -> None:
        entry = self.loaded.pop(name)
        with contextlib.suppress(Exception):
            entry.core.stop()
        entry.token.undeclare()
        entry.queryable.undeclare()
        entry.transport.close()

    # ---- main loop -----------------------------------------------------------------------
    def _loop(self) -> None:
        beat_every = beat_period(self.spec.supervision.heartbeat_timeout)
        next_beat = time.monotonic()
        while not self._signalled:
            if time.monotonic() >= next_beat:
                self._beat(beat_every)
                next_beat = time.monotonic() + beat_every
            self._serve_pending()
            self._reap_stopped()
            due = self._step_due()
            timeout = min(next_beat - time.monotonic(), due - time.time())
            ready, _, _ = select.select([self._rsock], [], [], max(0.0, timeout))
            if ready:
                with contextlib.suppress(BlockingIOError, OSError):
                    while self._rsock.recv(64):
                        pass

    def _step_due(self) -> float:
        """Step every component whose period has come; the wall time of the next step."""
        now = time.time()
        nexts = []
        for entry in self.loaded.values():
            rate = entry.core.rate_hz
            if rate <= 0:
                continue
            if now >= entry.next_step:
                entry.core.step(now)
                entry.next_step += 1.0 / rate
                if entry.next_step < now:  # fell behind: skip, don't burst
                    entry.next_step = now + 1.0 / rate
            nexts.append(entry.next_step)
        return min(nexts, default=now + 1.0)

    def _reap_stopped(self) -> None:
        """Components that asked to stop (`Shutdown`) are unloaded."""
        for name in [n for n, e in self.loaded.items() if e.core.stop_requested.is_set()]:
            self._unload(name)

    def _beat(self, wait: float) -> None:
        """Beat only if no component is stuck in a callback (all locks can be taken)."""
        taken = []
        try:
            for entry in self.loaded.values():
                if not entry.core.lock.acquire(timeout=wait):
                    return
                taken.append(entry.core.lock)
            self.heartbeat.beat()
        finally:
            for lock in taken:
                lock.release()


def _stderr(text: str) -> None:
    """A line of the container's log (its stderr)."""
    print(text, file=sys.stderr, flush=True)


def run_container(spec: m.NodeSpec, bus: BusConfig) -> int:
    """``run_node`` of a container's spec."""
    return ContainerRuntime(spec, bus).run()
