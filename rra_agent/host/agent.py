"""The host agent (``rra agent``): starts, supervises and stops the node processes of one host.

One per machine. It answers `HostRequest`s on ``rra/<system>/host/<host>/ctl``, runs a
`Supervisor` over its children (restart policy, backoff, SIGINT -> SIGTERM -> SIGKILL), follows
their liveliness tokens on ``rra/<system>/alive/<host>/*`` (ready handshake; a frozen process
loses its token at lease expiry and is killed and restarted), and publishes every state
transition as a `NodeState` on ``rra/<system>/events``.

It only starts implementations the system model declares: ``allowed`` is the set of
implementations of the package it serves (None accepts any, for tests and tools).

Threading: Zenoh callbacks only post to the `MainLoop`; the main thread owns the supervisor and
spawns every process (the children's parent-death signal is tied to the spawning thread).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.keys import Keys
from rra_agent.bus.loop import MainLoop
from rra_agent.bus.runtime import open_session
from rra_agent.host.processes import LocalHost
from rra_agent.host.supervisor import RestartPolicy, StopPolicy, Supervisor, Transition

TICK = 0.02
_REQ = m.Codec[m.HostRequest](m.HostRequest)
_EVT = m.Codec[m.EventMessage](m.EventMessage)
_REPLY = m.Codec[m.Reply](m.Reply)


def implementation_id(impl: m.NodeSpec | Any) -> str:
    i = impl.implementation if isinstance(impl, m.NodeSpec) else impl
    return i if isinstance(i, str) else " ".join(i.command)


@dataclass
class _Request:
    query: zenoh.Query | None
    request: m.HostRequest | None
    error: str | None = None


class HostAgent:
    def __init__(
        self,
        system: str,
        host: str,
        bus: BusConfig,
        log_dir: str | Path,
        *,
        hub: bool = False,
        allowed: Collection[str] | None = None,
        restart: RestartPolicy | None = None,
        stop: StopPolicy | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.keys = Keys(system)
        self.host = host
        #: Children connect with ``bus``; the agent itself listens on the hub endpoint if ``hub``.
        self.bus = bus
        self.session_bus = bus.as_hub() if hub else bus
        preload = {i.rpartition(".")[0] for i in (allowed or ()) if " " not in i and "." in i}
        self.local = LocalHost(host, bus, log_dir, preload=sorted(preload))
        self.allowed = frozenset(allowed) if allowed is not None else None
        self.clock = clock
        self.supervisor = Supervisor(restart=restart, stop=stop, listener=self._on_transition)
        self.loop = MainLoop(clock)
        self.dropped = 0
        self._publisher: zenoh.Publisher | None = None
        #: Called with every NodeState this agent emits (e.g. ``rra up`` prints them).
        self.observers: list[Callable[[m.NodeState], None]] = []
        self.session: zenoh.Session | None = None
        self._entities: list[Any] = []

    def request_stop(self, *_: Any) -> None:
        self.loop.request_stop()

    def _on_transition(self, t: Transition) -> None:
        p = self.supervisor.procs.get(t.node)
        msg = m.NodeState(
            stamp=time.time(),
            node=t.node,
            host=t.host,
            state=t.state.value,  # type: ignore[arg-type]
            previous=t.previous.value,  # type: ignore[arg-type]
            pid=t.pid,
            implementation=implementation_id(p.spec) if p else "",
            active=p.spec.active if p else True,
            restarts=t.restarts,
            reason=t.reason,
        )
        if self._publisher is not None:
            self._publisher.put(_EVT.encode(msg))
        for observe in self.observers:
            observe(msg)

    # ---- Zenoh callbacks (enqueue only) -------------------------------------------------
    def _on_query(self, query: zenoh.Query) -> None:
        payload = query.payload
        try:
            req: m.HostRequest | None = _REQ.decode(payload.to_bytes() if payload else b"")
            err = None
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            req, err = None, f"malformed request: {e}"
        item = _Request(query, req, err)
        self.loop.post(lambda: self._serve(item))

    def _on_alive(self, sample: zenoh.Sample) -> None:
        parsed = self.keys.parse_alive(str(sample.key_expr))
        if parsed is None or parsed[0] != self.host:
            return
        alive = sample.kind == zenoh.SampleKind.PUT
        self.loop.post(lambda: self.supervisor.on_alive(parsed[1], alive, self.clock()))

    # ---- requests (main thread) ---------------------------------------------------------
    def _serve(self, item: _Request) -> None:
        if item.request is None:
            self.dropped += 1
            reply: m.Reply = m.Err(message=item.error or "malformed", code="malformed")
        else:
            try:
                reply = self.handle(item.request)
            except Exception as e:  # a bad request must never take the agent down
                reply = m.Err(message=f"{type(e).__name__}: {e}", code="error")
        if item.query is not None:
            item.query.reply(item.query.key_expr, _REPLY.encode(reply))
            item.query.drop()
            item.query = None

    def handle(self, req: m.HostRequest) -> m.Reply:
        now = self.clock()
        sup = self.supervisor
        match req:
            case m.StartNode(spec=spec):
                impl = implementation_id(spec)
                if self.allowed is not None and impl not in self.allowed:
                    return m.Err(message=f"implementation {impl!r} is not declared", code="denied")
                if spec.name in sup.procs:
                    p = sup.procs[spec.name]
                    if p.state.value in ("STARTING", "RUNNING", "STOPPING"):
                        return m.Err(message=f"node {spec.name} is {p.state}", code="busy")
                    sup.remove(spec.name)
                sup.add(spec, self.local)
                sup.start(spec.name, now)
                p = sup.procs[spec.name]
                return m.Ok(result={"pid": p.pid, "state": p.state.value})
            case m.StopNode(node=name):
                if name not in sup.procs:
                    return m.Err(message=f"no node {name!r} on host {self.host}", code="unknown")
                sup.stop(name, now)
                return m.Ok(result={"state": sup.state(name).value})
            case m.UpdateSpec(specs=specs):
                unknown = [s.name for s in specs if s.name not in sup.procs]
                for spec in specs:
                    if spec.name in sup.procs:
                        sup.replace_spec(spec.name, spec)
                if unknown:
                    names = ", ".join(unknown)
                    return m.Err(message=f"no node(s) {names} on {self.host}", code="unknown")
                return m.Ok()
            case m.SignalNode(node=name, signal=sig):
                p = sup.procs.get(name)
                if p is None or p.pid is None:
                    return m.Err(message=f"no running node {name!r}", code="unknown")
                self.local.signal(p.pid, sig)
                return m.Ok(result={"pid": p.pid})
            case m.ListNodes():
                return m.Ok(result=[msgspec.to_builtins(s) for s in self.node_states()])
        return m.Err(message=f"unsupported request {type(req).__name__}", code="unsupported")

    def node_states(self) -> list[m.NodeState]:
        now = time.time()
        return [
            m.NodeState(
                stamp=now,
                node=name,
                host=self.host,
                state=p.state.value,  # type: ignore[arg-type]
                pid=p.pid,
                implementation=implementation_id(p.spec),
                active=p.spec.active,
                restarts=p.restarts,
            )
            for name, p in self.supervisor.procs.items()
        ]

    # ---- main loop ---------------------------------------------------------------------
    def run(self, *, install_signals: bool = True, on_ready: Callable[[], None] | None = None):
        if install_signals:
            self.loop.install_signals()
        self.session = session = open_session(self.session_bus)
        try:
            self._publisher = session.declare_publisher(
                self.keys.events, congestion_control=zenoh.CongestionControl.BLOCK
            )
            # Keep every declared entity referenced: a dropped one is undeclared.
            self._entities = [
                session.liveliness().declare_subscriber(
                    f"{self.keys.prefix}/alive/{self.host}/*", self._on_alive, history=True
                ),
                session.declare_queryable(self.keys.host_ctl(self.host), self._on_query),
                session.liveliness().declare_token(self.keys.host_alive(self.host)),
            ]
            if on_ready is not None:
                on_ready()
            self.loop.run(self._tick, TICK)
            self._shutdown()
        finally:
            self._publisher = None
            self.local.kill_all()
            session.close()

    def _tick(self, now: float) -> None:
        self.supervisor.tick(now)
        self.local.forget_exited(keep={p.pid for p in self.supervisor.procs.values() if p.pid})

    def _shutdown(self) -> None:
        """Stop every node with the escalation policy; wait until all have exited."""
        sup = self.supervisor
        sup.stop_all(self.clock())
        pol = sup.stop_policy
        deadline = self.clock() + pol.sigint_timeout + pol.sigterm_timeout + 2.0
        while not sup.all_stopped() and self.clock() < deadline:
            self.loop.cycle(TICK)
            self._tick(self.clock())


def configure(parser) -> None:  # argparse.ArgumentParser
    from rra_agent.bus.config import add_bus_arguments

    parser.add_argument("--system", required=True, help="system name (key-expression prefix)")
    parser.add_argument("--host", required=True, help="this host's name in the system model")
    parser.add_argument("--package", help="serve only the implementations this package declares")
    parser.add_argument("--log-dir", default="rra-logs", help="node logs go here")
    parser.add_argument(
        "--hub", action="store_true", help="listen on the hub endpoint (the first process)"
    )
    add_bus_arguments(parser)


def run(args) -> int:  # argparse.Namespace
    """``rra agent``: serve one host until SIGINT/SIGTERM."""
    from rra_agent.bus.config import bus_from_args

    allowed = None
    if args.package:
        from rra_agent.deployment import deploy

        allowed = deploy(args.package).implementations
    agent = HostAgent(
        args.system, args.host, bus_from_args(args), args.log_dir, hub=args.hub, allowed=allowed
    )
    agent.run()
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m rra_agent.host.agent``: the same as ``rra agent``."""
    import argparse

    parser = argparse.ArgumentParser(prog="rra agent", description=__doc__.split("\n\n")[0])
    configure(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    import sys

    sys.exit(main())
