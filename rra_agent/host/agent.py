"""The host agent (``rra agent``): starts, supervises and stops the node processes of one host.

One per machine. It answers `HostRequest`s on ``rra/<system>/host/<host>/ctl``, runs a
`Supervisor` over its children and publishes every state transition as a `NodeState` on
``rra/<system>/events``. How it knows what its nodes do (docs/architecture.md, failure model):

- an exit from the OS at once: the nodes are its children (`rra_agent.host.processes`), and
  SIGCHLD wakes its loop, which reaps them;
- readiness from the node's liveliness token (or the ready flag of its heartbeat);
- a freeze from a heartbeat in shared memory older than the node's deadline, confirmed by a
  direct probe (a ``Ping`` to the node's control endpoint; a process the kernel shows
  stopped fails it at once). A token that disappears says nothing about the node (the bus
  or the router may have stalled) and is never a reason to kill it.

Requests that change what runs carry the leader fence of the Run-time Resolution Engine
that sends them; one older than the newest fence accepted is refused (counted and logged).
``StartNode`` of a node already running with the same spec and ``StopNode`` of a node that
is not running succeed without doing anything, so a new leader can repeat a plan safely.

It only runs what its own copy of the system model declares (`rra_agent.host.catalog`): a
request names a component and one of its declared implementations, and the command line,
environment, working directory, import path, parameter bounds and supervision come from the
model on this host; a name is a valid file name and key chunk. ``ListNodes`` and the
``NodeState`` events show an external command only as a hash.

Threading: Zenoh callbacks only post to the `MainLoop` (a bounded inbox: a flood of requests
is answered "busy"); the main thread owns the supervisor and spawns every process (the
children's parent-death signal is tied to the spawning thread).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from rra_agent import text, trace
from rra_agent.bus import counters
from rra_agent.bus import messages as m
from rra_agent.bus.client import decoded, oks
from rra_agent.bus.config import (
    KEEP_ALIVE,
    BusConfig,
    explain_open_failure,
    node_zid,
    ros2_zid,
)
from rra_agent.bus.counters import Counters, RateLimitedLog, receive, topic_limits
from rra_agent.bus.keys import Keys, check_chunk
from rra_agent.bus.loop import MainLoop
from rra_agent.bus.session import open_session
from rra_agent.core.election import Term, newer
from rra_agent.deployment import Deployment
from rra_agent.engines.models import deploy_bundle
from rra_agent.errors import RraError
from rra_agent.host import gate, links, procfs, scheduling, unique
from rra_agent.host.catalog import Catalog, Refused, check_name
from rra_agent.host.members import Member, Members
from rra_agent.host.processes import LocalHost, process_state
from rra_agent.host.supervisor import LIVE, Notice, Proc, State, StopPolicy, Supervisor, Transition
from rra_agent.models.manifest import AgentSettings
from rra_agent.package.bundle import ModelBundle
from rra_agent.ros2 import launch

TICK = 0.02
#: How long an agent waits for the state of a node it replaces (`ReplaceNode.export`): less
#: than the engines' 2 s request timeout, so that they learn why it failed.
EXPORT_TIMEOUT = 1.0
_REQ = m.Codec[m.HostRequest](m.HostRequest)
_EVT = m.Codec[m.EventMessage](m.EventMessage)
_REPLY = m.Codec[m.Reply](m.Reply)
_ANY = m.Codec[Any](Any)
_CREQ = m.Codec[m.ContainerRequest](m.ContainerRequest)
#: How long a container may take to load (start) or unload a component.
CONTAINER_TIMEOUT = 10.0
#: Signals a fault-injection request may send.
INJECTABLE = frozenset({signal.SIGKILL, signal.SIGSTOP, signal.SIGCONT, signal.SIGTERM})


class HostAgent:
    def __init__(
        self,
        system: str,
        host: str,
        bus: BusConfig,
        log_dir: str | Path,
        *,
        hub: bool = False,
        catalog: Catalog,
        certs: str | Path | None = None,
        access_control: dict[str, Any] | None = None,
        data_topics: Mapping[str, int] | None = None,
        stop: StopPolicy | None = None,
        clock: Callable[[], float] = time.monotonic,
        engines: bool = False,
        models: Deployment | None = None,
    ) -> None:
        self.keys = Keys(system)
        #: The deployment this host's catalog comes from, and the catalog of models a reload
        #: prepares (admitted beside the current one until the reload commits).
        self.models = models
        self._next: tuple[str, Catalog, Deployment] | None = None
        #: This agent starts the system's engines (``rra up``): a system whose engines run
        #: on the bus already is refused at start (`rra_agent.host.unique`).
        self.engines = engines
        self.host = check_chunk(host, "host")
        #: This agent's router is the hub (``rra up``): the tools' endpoint.
        self.hub = hub
        #: This host's Zenoh router (run by this agent) and how its children connect to it;
        #: it drops what is over its key family's or data topic's limit (``data_topics``).
        router = bus.host_router(hub=hub, system=system, topics=data_topics)
        self.bus = router.local_client()
        #: How this host's nodes join the bus (as peers, they apply the router's limits on
        #: their own links too: what they exchange directly never crosses the router).
        self.node_bus = self.bus.for_nodes(router.zenoh)
        if access_control is not None:
            router = msgspec.structs.replace(
                router, zenoh={**router.zenoh, "access_control": access_control}
            )
        self.session_bus = router
        #: The folder of this host's certificates (``rra certs``): each child's identity.
        self.certs = certs
        #: What this host may run (from its own copy of the system model).
        self.catalog = catalog
        # The fork server imports every implementation and warms it up (`Node.warm_up`),
        # and forks the built-ins that are this interpreter's `python -m` (the engines).
        self.local = LocalHost(
            host,
            self.bus,
            log_dir,
            preload=catalog.preload,
            forked=catalog.forked,
            prober=self._probe_later,
        )
        self.local.bus_for = self._child_bus
        self.local.env_for = self._child_env
        # Without certificates every node has this host's bus configuration: spares open
        # their sessions ahead (with them, a node's identity is its own, known at its start).
        self.local.spare_bus = self.node_bus if certs is None else None
        self.clock = clock
        self.supervisor = Supervisor(
            stop=stop, listener=self._on_transition, notices=self._on_notice
        )
        #: Components running inside this host's containers (`host/container.py`).
        self.members = Members(host, self._send_container, self._on_transition)
        #: Containers whose liveliness token this agent's session has seen since they
        #: started: see `_container_transition`.
        self._routed: set[str] = set()
        self.loop = MainLoop(clock)
        self.loop.on_wake = self._reap
        self.counters = Counters()
        self._refusals = RateLimitedLog(lambda text: print(f"rra agent {host}: {text}", flush=True))
        #: The newest fence of a Run-time Resolution Engine leader accepted.
        self.fence: Term | None = None
        self._publisher: zenoh.Publisher | None = None
        #: Called with every NodeState this agent emits (e.g. ``rra up`` prints them).
        self.observers: list[Callable[[m.NodeState], None]] = []
        #: Called with every AdaptationEvent this agent emits (supervision notices).
        self.event_observers: list[Callable[[m.AdaptationEvent], None]] = []
        self.session: zenoh.Session | None = None
        self._entities: list[Any] = []
        self._interrupts = 0
        #: Stopping every node (a normal shutdown): no node is started any more.
        self.stopping = False
        #: A host other than the first learns the run's Rerun configuration from the engine.
        self._rerun_known = hub
        #: `ReplaceNode`s under way: the node stopping -> its replacement, which starts
        #: once it is gone, and whether it was spawned already (gated) or waits here.
        self._after: dict[str, tuple[m.NodeSpec, bool]] = {}
        self.local.gate_for = self._gate_for
        self.log_dir = Path(log_dir)

    def _child_bus(self, spec: m.NodeSpec) -> BusConfig:
        """A child's bus identity: the engine or node certificate of this host, and for a
        node its fixed Zenoh id (the access control names both); without certificates, a
        node's is `node_bus` (a peer with ``--peer-nodes``)."""
        if self.certs is None:
            return self.bus if spec.name in self.catalog.builtins else self.node_bus
        if spec.name in self.catalog.builtins:
            return self.bus.with_identity(self.certs, "engine")
        cfg = self.bus.with_identity(self.certs, "node")
        return msgspec.structs.replace(cfg, zid=node_zid(self.keys.system, spec.name))

    def _child_env(self, spec: m.NodeSpec) -> dict[str, str]:
        """A ROS 2 executable's Zenoh session configuration on a bus with certificates:
        written for it (``<log_dir>/<node>.zenoh.json5``, mode 0600) and named in its node's
        environment (``ZENOH_SESSION_CONFIG_URI``), which passes it on to the executable."""
        if self.certs is None or spec.ros2 is None or not spec.ros2.executable:
            return {}
        bus = self._child_bus(spec)
        assert bus.tls is not None
        config = launch.session_config(
            bus.hub,
            zid=ros2_zid(self.keys.system, spec.name),
            ca=bus.tls.ca,
            cert=bus.tls.cert,
            key=bus.tls.key,
            lease_ms=bus.lease_ms,
            keep_alive=KEEP_ALIVE,
        )
        path = launch.write_session_config(self.log_dir / f"{spec.name}.zenoh.json5", config)
        return {launch.SESSION_CONFIG_ENV: str(path.resolve())}

    def request_stop(self, *_: Any) -> None:
        self.loop.request_stop()

    # ---- what this agent tells the world -----------------------------------------------
    def _on_transition(self, t: Transition) -> None:
        p = self.supervisor.procs.get(t.node) or self.members.members.get(t.node)
        trace.mark(f"agent:{t.state.value}", t.node)
        if t.node in self._after and t.state not in LIVE:
            self._release(t.node)
        if t.node in self.catalog.containers and t.node in self.supervisor.procs:
            self._container_transition(t)
        msg = m.NodeState(
            stamp=time.time(),
            node=t.node,
            host=t.host,
            state=t.state.wire,
            previous=t.previous.wire,
            pid=t.pid,
            implementation=m.implementation_id(p.spec) if p else "",
            active=p.spec.active if p else True,
            restarts=t.restarts,
            reason=t.reason,
            digest=m.spec_digest(p.spec) if p else "",
            failure=self._with_log(t.node, t.failure),
        )
        self._put(msg)
        for observe in self.observers:
            observe(msg)
        if t.state == State.RUNNING and t.node in self.supervisor.procs and t.pid:
            self._check_scheduling(self.supervisor.procs[t.node].spec, t.pid)

    def _with_log(self, name: str, failure: m.Failure | None) -> m.Failure | None:
        """``failure`` with the log that holds its traceback: a component's is its
        container's (a node's own report names its log already)."""
        if failure is None or failure.log:
            return failure
        container = self.catalog.container_of(name)
        log = self.local.log_path(container or name).resolve()
        return msgspec.structs.replace(failure, log=str(log))

    def _check_scheduling(self, spec: m.NodeSpec, pid: int) -> None:
        """A node asked for a scheduling the kernel did not grant: say so (it runs anyway)."""
        if spec.scheduling.is_default:
            return
        problems = scheduling.differences(spec.scheduling, pid)
        if problems:
            self.event(
                "scheduling",
                f"{spec.name}: " + "; ".join(problems),
                level="warning",
                nodes=(spec.name,),
            )

    def _on_notice(self, n: Notice) -> None:
        self.event(n.kind, n.message, level="warning", nodes=n.nodes)

    def event(
        self, kind: str, message: str, *, level: m.Level = "info", nodes: tuple[str, ...] = ()
    ) -> None:
        ev = m.AdaptationEvent(
            stamp=time.time(),
            kind=kind,
            message=f"host {self.host}: {message}",
            level=level,
            source=f"host/{self.host}",
            plan=list(nodes),
        )
        self._put(ev)
        for observe in self.event_observers:
            observe(ev)

    def _put(self, msg: m.NodeState | m.AdaptationEvent) -> None:
        if self._publisher is not None:
            self._publisher.put(_EVT.encode(msg))

    # ---- Zenoh callbacks (enqueue only) -------------------------------------------------
    def _on_query(self, query: zenoh.Query) -> None:
        req = receive(query.payload, "host_ctl", _REQ)
        if isinstance(req, counters.Refused):
            self._answer_now(query, req.code, req.err().message)
            return
        self.counters.received += 1
        if isinstance(req, m.Ping):  # answered here: a probe must not wait behind work
            query.reply(query.key_expr, _REPLY.encode(m.Ok(result=self.identity())))
            return
        if not self.loop.post(lambda: self._serve(query, req)):
            self._answer_now(query, "busy", "the host agent is overloaded; try again")

    def _answer_now(self, query: zenoh.Query, code: str, message: str) -> None:
        self.counters.dropped += 1
        self._refusals(f"dropped request ({code})", message)
        query.reply(query.key_expr, _REPLY.encode(m.Err(message=message, code=code)))

    def _on_alive(self, sample: zenoh.Sample) -> None:
        parsed = self.keys.parse_alive(str(sample.key_expr))
        if parsed is None or parsed[0] != self.host or sample.kind != zenoh.SampleKind.PUT:
            return  # a token's disappearance is not evidence about the process
        trace.mark("agent:alive", parsed[1])
        self.loop.post(lambda: self._on_ready(parsed[1]))

    def _on_ready(self, name: str) -> None:
        if name in self.members.members:
            self.members.on_ready(name, self.clock())
            return
        if name in self.catalog.containers and name not in self._routed:
            self._routed.add(name)
            box = self.supervisor.procs.get(name)
            if box is not None and box.state == State.RUNNING:  # its members waited for this
                self.members.on_container(name, State.RUNNING, box.pid, self.clock())
        self.supervisor.on_ready(name, self.clock())

    def _container_transition(self, t: Transition) -> None:
        """A container's state, for its members. RUNNING (its heartbeat's ready flag, local
        and immediate) counts for them only once this agent's session has seen its token:
        the token is declared after the container's control queryable, so only then does
        a load request find it (sent before, it found none: "no reply", seen with ten
        containers starting at once)."""
        if t.state != State.RUNNING:
            self._routed.discard(t.node)
        elif t.node not in self._routed:
            return  # `_on_ready` tells the members when the token comes
        self.members.on_container(t.node, t.state, t.pid, t.now)

    # ---- containers ------------------------------------------------------------------
    def _send_container(self, container: str, req: m.ContainerRequest, on_reply) -> None:
        """A request to one of this host's containers; ``on_reply`` runs on the main loop
        (an `Err` when the container does not answer in time)."""
        got: list[m.Reply] = []

        def on_sample(reply: zenoh.Reply) -> None:
            if reply.ok is not None and not got:
                with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
                    got.append(_REPLY.decode(reply.ok.payload.to_bytes()))

        def on_done() -> None:
            answer = got[0] if got else m.Err(message=f"container {container}: no reply",
                                               code="timeout")  # fmt: skip
            self.loop.post(lambda: on_reply(answer))

        if self.session is None:
            on_reply(m.Err(message="the host agent is not on the bus", code="unavailable"))
            return
        self.session.get(
            self.keys.node_ctl(container),
            zenoh.handlers.Callback(on_sample, on_done),
            payload=_CREQ.encode(req),
            timeout=CONTAINER_TIMEOUT,
        )

    def _ensure_container(self, container: str) -> None:
        sup = self.supervisor
        if container not in sup.procs:
            sup.add(self.catalog.container_spec(container), self.local)
        if not sup.procs[container].want_running:
            sup.start(container, self.clock())

    def _start_member(self, spec: m.NodeSpec, container: str) -> m.Reply:
        mb = self.members.members.get(spec.name)
        if mb is not None and mb.want_running and mb.state in (*LIVE, State.BACKOFF):
            if mb.state == State.STOPPING:
                return m.Err(message=f"node {spec.name} is stopping", code="busy")
            same = m.spec_digest(mb.spec) == m.spec_digest(spec)
            self.members.replace_spec(spec.name, spec)
            return m.Ok(result={"pid": mb.pid, "state": mb.state.value, "already": True,
                                "same": same})  # fmt: skip
        self._ensure_container(container)
        mb = self.members.start(spec, container, self.clock())
        return m.Ok(result={"pid": mb.pid, "state": mb.state.value, "container": container})

    def _stop_member(self, name: str) -> m.Reply:
        mb = self.members.members[name]
        if mb.state in (State.STOPPED, State.EXITED) and not mb.want_running:
            return m.Ok(result={"state": mb.state.value, "already": True})
        # The container stays, even empty, until the host agent stops: a swap inside it
        # (unload, load) must not race the container's own stop.
        self.members.stop(name, self.clock())
        return m.Ok(result={"state": mb.state.value})

    # ---- probes ----------------------------------------------------------------------
    def _probe_later(self, name: str, pid: int, timeout: float) -> None:
        """A direct probe: a stopped process fails at once, otherwise a Ping query."""
        if process_state(pid) in ("T", "t", ""):
            self.loop.post(lambda: self.supervisor.on_probe(name, pid, False, self.clock()))
            return
        if self.session is None:
            return
        answered: list[bool] = []

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                answered.append(True)

        def on_done() -> None:
            ok = bool(answered)
            self.loop.post(lambda: self.supervisor.on_probe(name, pid, ok, self.clock()))

        self.session.get(
            self.keys.node_ctl(name),
            zenoh.handlers.Callback(on_reply, on_done),
            payload=_ANY.encode(m.Ping()),
            timeout=timeout,
        )

    # ---- requests (main thread) ---------------------------------------------------------
    def _serve(self, query: zenoh.Query, request: m.HostRequest) -> None:
        def answer(reply: m.Reply) -> None:
            query.reply(query.key_expr, _REPLY.encode(reply))
            # Finalised now: a deferred answer's query is still referenced (by the callbacks
            # of the get that exported the state), and its querier would wait for the end.
            query.drop()

        try:
            reply = self.handle(request, trusted=False, answer=answer)
        except Exception as e:  # a bad request must never take the agent down
            reply = m.Err(message=f"{type(e).__name__}: {e}", code="error")
        if reply is not None:
            answer(reply)

    def _refuse(self, code: str, message: str) -> m.Err:
        self.counters.rejected += 1
        self._refusals(f"refused ({code})", message)
        return m.Err(message=message, code=code)

    def _admit(self, fence: m.Fence | None) -> bool:
        if fence is None:
            return True
        term = fence.term
        if not newer(term, self.fence):
            return False
        self.fence = term
        return True

    def handle(
        self,
        req: m.HostRequest,
        *,
        trusted: bool = True,
        answer: Callable[[m.Reply], None] | None = None,
    ) -> m.Reply | None:
        """Serve one request. Only this process's own calls are ``trusted`` (``rra up``
        starting its engines); a request from the bus is checked against the model. None:
        the reply goes to ``answer`` later (a `ReplaceNode` that exports the old node's
        state first)."""
        if not trusted:
            try:
                req = self._admitted(req)
            except Refused as e:
                return self._refuse("denied", str(e))
        fence = getattr(req, "fence", None)
        if not isinstance(req, m.Claim) and not self._admit(fence):
            return self._refuse(
                "stale_fence",
                f"{req.__struct_config__.tag} from leader {fence.leader} (epoch {fence.epoch}) "  # type: ignore[union-attr]
                f"refused: leader {self.fence[1]} (epoch {self.fence[0]}) has acted since",  # type: ignore[index]
            )
        match req:
            case m.StartNode(spec=spec):
                if self.stopping:  # e.g. a standby engine taking over as the leader stops
                    return m.Err(message=f"host {self.host} is shutting down", code="busy")
                return self._start(spec)
            case m.StopNode(node=name, deadline=deadline):
                return self._stop(name, deadline)
            case m.ReplaceNode(node=name, spec=spec, deadline=deadline, export=True):
                if answer is None:
                    return m.Err(message="a ReplaceNode that exports is answered later: "
                                 "send it on the bus", code="error")  # fmt: skip
                self._export_then_replace(name, spec, deadline, answer)
                return None
            case m.ReplaceNode(node=name, spec=spec, deadline=deadline):
                return self._replace(name, spec, deadline)
            case m.UpdateSpec(specs=specs):
                for spec in specs:
                    if spec.name in self.members.members:
                        self.members.replace_spec(spec.name, self._fenced(spec))
                    elif spec.name in self.supervisor.procs:
                        self.supervisor.replace_spec(spec.name, self._fenced(spec))
                return m.Ok()
            case m.SignalNode(node=name, signal=sig):
                p = self.supervisor.procs.get(name)
                if p is None or p.pid is None:
                    return m.Err(message=f"no running node {name!r}", code="unknown")
                if sig not in INJECTABLE:
                    return self._refuse("denied", f"signal {sig} is not a fault to inject")
                self.local.signal(p.pid, sig)
                return m.Ok(result={"pid": p.pid})
            case m.ListNodes():
                return m.Ok(result=[msgspec.to_builtins(s) for s in self.node_states()])
            case m.Stats():
                return m.Ok(result=self.stats())
            case m.Claim(fence=claim):
                accepted = self._admit(claim)
                return m.Ok(result={"accepted": accepted, "fence": list(self.fence or ())})
            case m.PrepareModels(bundle=bundle):
                return self.prepare_models(bundle)
            case m.CommitModels(digest=digest):
                return self.commit_models(digest)
        return m.Err(message=f"unsupported request {type(req).__name__}", code="unsupported")

    # ---- reload: the catalog of new models (``rra reload``) --------------------------------
    def prepare_models(self, bundle: ModelBundle) -> m.Reply:
        """Admit what the new models declare besides what the current ones do, until the
        reload commits (or is abandoned)."""
        if self.models is None:
            return m.Err(message=f"host {self.host}: started without a package", code="invalid")
        try:
            dep = deploy_bundle(bundle, self.models)
        except RraError as e:
            return m.Err(message=f"host {self.host}: {e}", code="invalid")
        catalog = Catalog.of(dep, self.host, default_host=self.catalog.default_host)
        catalog.add_builtins(self.catalog.builtins.values())
        self._next = (bundle.digest, catalog, dep)
        return m.Ok(result={"models": bundle.digest})

    def commit_models(self, digest: str) -> m.Reply:
        """Keep only the catalog of the models ``digest`` (the current ones: abandon)."""
        if self._next is not None and self._next[0] == digest:
            _, self.catalog, self.models = self._next
            print(f"rra agent {self.host}: models {digest}", flush=True)
        self._next = None
        return m.Ok(result={"models": self.models.models if self.models else ""})

    def _admitted(self, req: m.HostRequest) -> m.HostRequest:
        """The request with every spec derived from the model (`Refused` if it may not)."""
        match req:
            case m.StartNode(spec=spec):
                return msgspec.structs.replace(req, spec=self._admit_spec(spec))
            case m.ReplaceNode(node=name, spec=spec):
                check_name(name)
                return msgspec.structs.replace(req, spec=self._admit_spec(spec))
            case m.UpdateSpec(specs=specs):
                return msgspec.structs.replace(req, specs=[self._admit_spec(s) for s in specs])
            case m.StopNode(node=name) | m.SignalNode(node=name):
                check_name(name)
        return req

    def _admit_spec(self, spec: m.NodeSpec) -> m.NodeSpec:
        """The catalog's spec; during a reload, the new models' if they admit it."""
        if self._next is not None:
            try:
                return self._next[1].admit(spec)
            except Refused:
                pass
        return self.catalog.admit(spec)

    def _fenced(self, spec: m.NodeSpec) -> m.NodeSpec:
        """The spec with this agent's newest fence (the node refuses older leaders too)."""
        if self.fence is None:
            return spec
        return msgspec.structs.replace(spec, fence=m.Fence.of(self.fence))

    def _learn_rerun(self) -> None:
        """Log to the run's one Rerun recording, as the first host's nodes do: the engine's
        configuration; in ``save`` mode each node writes its file under this host's
        ``<log-dir>/rerun/<recording-id>/`` (merge with ``rerun rrd merge``)."""
        if self._rerun_known or self.session is None:
            return
        self._rerun_known = True  # one try: a start never waits on this twice
        from rra_agent.viz.rerun_log import ENV_VAR, RerunConfig

        for answer in oks(self.session.get(
            self.keys.engine_ctl("resolution"), payload=_ANY.encode(m.Status()), timeout=1.0
        )):  # fmt: skip
            if not isinstance(answer.result, dict):
                continue
            try:
                cfg = msgspec.convert(answer.result.get("rerun") or {}, RerunConfig)
            except msgspec.ValidationError:
                return
            if cfg.mode == "save":
                folder = (self.log_dir / "rerun" / cfg.recording_id).resolve()
                folder.mkdir(parents=True, exist_ok=True)
                cfg = msgspec.structs.replace(cfg, dir=str(folder))
                print(f"rra agent {self.host}: Rerun files of this host in {folder}", flush=True)
            if cfg.mode != "off":
                self.local.extra_env[ENV_VAR] = cfg.to_env()
            return

    def _start(self, spec: m.NodeSpec) -> m.Reply:
        trace.mark("agent:start", spec.name)
        self._learn_rerun()
        spec = self._fenced(spec)
        container = self.catalog.container_of(spec.name)
        if container is not None:
            return self._start_member(spec, container)
        sup, now = self.supervisor, self.clock()
        p = sup.procs.get(spec.name)
        if p is not None and p.state in (*LIVE, State.BACKOFF):
            same = m.spec_digest(p.spec) == m.spec_digest(spec)
            if p.state == State.STOPPING:
                return m.Err(message=f"node {spec.name} is stopping", code="busy")
            sup.replace_spec(spec.name, spec)
            return m.Ok(
                result={"pid": p.pid, "state": p.state.value, "already": True, "same": same}
            )
        if p is not None:
            sup.replace_spec(spec.name, spec)
        else:
            sup.add(spec, self.local)
        sup.start(spec.name, now)
        p = sup.procs[spec.name]
        trace.mark("agent:spawned", spec.name)
        return m.Ok(result={"pid": p.pid, "state": p.state.value})

    def _stop(self, name: str, deadline: float | None = None) -> m.Reply:
        if name in self.members.members:
            return self._stop_member(name)
        p = self.supervisor.procs.get(name)
        if p is None or p.state in (State.STOPPED, State.EXITED):
            return m.Ok(result={"state": p.state.value if p else "STOPPED", "already": True})
        self.supervisor.stop(name, self.clock(), deadline)
        self._tick_due()
        return m.Ok(result={"state": p.state.value})

    def _replace(self, old: str, spec: m.NodeSpec, deadline: float | None) -> m.Reply:
        """`ReplaceNode`: stop ``old`` and start ``spec`` once it is gone. A node the fork
        server can start gated is spawned first and prepares meanwhile
        (`_prepare_then_stop`); any other waits here until ``old`` is gone (`_release`)."""
        if self.stopping:
            return m.Err(message=f"host {self.host} is shutting down", code="busy")
        gateable = spec.name != old and self.catalog.container_of(spec.name) is None
        gated = gateable and self.local.can_gate(spec)
        p = self.supervisor.procs.get(old)
        if gated and p is not None and p.state in LIVE:
            return self._prepare_then_stop(old, spec, deadline)
        stopped = self._stop(old, deadline)
        if isinstance(stopped, m.Err):
            return stopped
        if not self._live(old):
            return self._start(spec)
        self._after[old] = (spec, gated)
        if not gated:
            return m.Ok(result={"state": State.STOPPED.value, "after": old})
        started = self._start(spec)  # gated: `self.local.gate_for` says so
        if isinstance(started, m.Err):
            self._after.pop(old, None)
        return started

    def _export_then_replace(
        self, old: str, spec: m.NodeSpec, deadline: float | None, answer: Callable[[m.Reply], None]
    ) -> None:
        """`ReplaceNode` with ``export``: ask ``old`` for its state through this host's router
        (the loop does not wait), then `_replace` it by ``spec`` with that state and answer.
        A node that does not answer, or refuses, is left running."""
        if self.session is None or not self._live(old):
            answer(m.Err(message=f"node {old} is not running: no state to export", code="export"))
            return
        done = threading.Lock()

        def finish(reply: m.Reply | None) -> None:
            if done.acquire(blocking=False):  # the first reply, or the end of the query
                self.loop.post(lambda: answer(self._replace_exported(old, spec, deadline, reply)))

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                bad = m.Err(message="a malformed answer", code="malformed")
                finish(next(decoded([reply], _REPLY), bad))

        trace.mark("agent:export", old)
        self.session.get(
            self.keys.node_ctl(old),
            zenoh.handlers.Callback(on_reply, lambda: finish(None)),
            payload=_ANY.encode(m.ExportState()),
            timeout=EXPORT_TIMEOUT,
        )

    def _replace_exported(
        self, old: str, spec: m.NodeSpec, deadline: float | None, reply: m.Reply | None
    ) -> m.Reply:
        """The rest of `_export_then_replace`, on the loop, given ``old``'s answer."""
        trace.mark("agent:exported", old)
        match reply:
            case m.Ok(result=state):
                return self._replace(old, msgspec.structs.replace(spec, state=state), deadline)
            case m.Err(message=message):
                why = f"node {old} did not export its state: {message}"
            case _:
                why = f"node {old} did not export its state within {EXPORT_TIMEOUT:g} s"
        return m.Err(message=f"{why}; it runs on, {spec.name} was not started", code="export")

    def _live(self, name: str) -> bool:
        """Whether ``name``'s process (or container member) exists."""
        mb = self.members.members.get(name)
        if mb is not None:
            return mb.state in LIVE
        p = self.supervisor.procs.get(name)
        return p is not None and p.state in LIVE

    def _prepare_then_stop(self, old: str, spec: m.NodeSpec, deadline: float | None) -> m.Reply:
        """`_replace` of the process ``old``: its replacement spawned first, gated on the end
        of that process (it prepares while ``old`` is told to stop), then ``old`` stopped. A
        replacement that cannot start leaves ``old`` running."""
        self._after[old] = (spec, True)
        started = self._start(spec)  # gated: `self.local.gate_for` says so
        if isinstance(started, m.Err):
            self._after.pop(old, None)
            return started
        self._stop(old, deadline)  # a live process: always Ok
        return started

    def _gate_for(self, spec: m.NodeSpec) -> gate.Gated | None:
        """How ``spec`` starts gated, as the replacement of a node stopping (None: it is
        not): on the end of that node's process, (pid, start time); where the node is no
        process of its own (a container member), on this agent's signal (`_release`)."""
        waiting = (o for o, (s, spawned) in self._after.items() if s.name == spec.name and spawned)
        old = next(waiting, None)
        if old is None:
            return None
        p = self.supervisor.procs.get(old)
        pid = p.pid if p is not None else None
        started = procfs.start_time(pid) if pid is not None else None  # not reaped yet
        return gate.Gated(None if pid is None or started is None else (pid, started))

    def _release(self, old: str) -> None:
        """``old`` is gone: its replacement's code may run (its gate opens), or the
        replacement is started now if it was not spawned yet."""
        spec, spawned = self._after.pop(old)
        if spawned:
            self.local.open_gate(spec.name)
            return

        def start() -> None:
            if self.stopping:
                return
            reply = self._start(spec)
            if isinstance(reply, m.Err):
                self.event("replace", f"{spec.name} not started after {old}: {reply.message}",
                           level="warning", nodes=(spec.name,))  # fmt: skip

        self.loop.post(start)

    def _tick_due(self) -> None:
        """Tick when the supervisor's next deadline ends (a stop deadline can be shorter
        than the tick period)."""
        at = self.supervisor.next_deadline()
        if at is not None:
            self.loop.due(at)

    def node_states(self) -> list[m.NodeState]:
        now = time.time()
        records: list[tuple[str, Proc | Member]] = [
            *self.supervisor.procs.items(),
            *self.members.members.items(),
        ]
        return [
            m.NodeState(
                stamp=now,
                node=name,
                host=self.host,
                state=p.state.wire,
                pid=p.pid,
                implementation=m.implementation_id(p.spec),
                active=p.spec.active,
                restarts=p.restarts,
                digest=m.spec_digest(p.spec),
                reason=p.last_failure,
                failure=self._with_log(name, p.failure),
            )
            for name, p in records
        ]

    def identity(self) -> dict[str, Any]:
        """Its answer to a ``Ping``: pid, host, its router's endpoints (``rra status``), its
        fork server's pid (None while it has none) and, while it holds a CPU latency request
        (``agents: cpu_latency_us``), the latency the kernel keeps (None otherwise)."""
        zygote = self.local.zygote
        return {
            "pid": os.getpid(),
            "host": self.host,
            "listen": list(self.session_bus.listen),
            "connect": list(self.session_bus.connect),
            "fork_server": zygote.pid if zygote is not None else None,
            "cpu_latency_us": scheduling.cpu_latency() if scheduling.holds_cpu_latency() else None,
        }

    def stats(self) -> m.ProcessStats:
        c = self.counters
        c.extra.update(
            refused_busy=self.loop.refused,
            fork_server_restarts=max(0, self.local.zygote_starts - 1),
            nodes=len(self.supervisor.procs),
        )
        if self.fence is not None:
            c.extra["fence_epoch"] = self.fence[0]
        return c.stats(self.host, "host", os.getpid())

    # ---- the loop ----------------------------------------------------------------------
    def _reap(self) -> None:
        """Feed the supervisor every exit the OS reported (runs on each wake-up)."""
        now = self.clock()
        for pid, status in self.local.reap():
            self.supervisor.on_exit(pid, status, now, self.local.failures.pop(pid, None))
        while self.local.zygote_exits:
            status = self.local.zygote_exits.pop(0)
            self.event(
                "fork_server",
                f"the fork server exited (status {status}); its nodes run on, a new one "
                "starts with the next node",
                level="warning",
            )

    def _tick(self, now: float) -> None:
        self._reap()
        self.supervisor.tick(now, self.local.beats())
        for name, p in list(self.supervisor.procs.items()):
            if p.state == State.STOPPED and not p.want_running:
                self.local.forget(name)
        self._tick_due()

    def _on_signal(self, signum: int) -> None:
        """A second Ctrl-C (or SIGTERM) during the shutdown kills what is left at once."""
        self._interrupts += 1
        if self._interrupts >= 2:
            for pid in list(self.local.running()):
                self.local.signal(pid, signal.SIGKILL)

    def run(self, *, install_signals: bool = True, on_ready: Callable[[], None] | None = None):
        if install_signals:
            self.loop.install_signals(on_signal=self._on_signal)
            self.loop.wake_on_sigchld()
            self.local.reap_orphans = True
        if exposed := self.session_bus.exposed():
            print(
                f"rra agent {self.host}: WARNING: --insecure: plain-text links on "
                f"{', '.join(exposed)}; anyone who reaches them can run this system",
                flush=True,
            )
        try:
            session = open_session(self.session_bus)
        except zenoh.ZError as e:  # e.g. the port is taken: one line, nothing left running
            self.local.kill_all()
            raise explain_open_failure(e, self.session_bus, hub=self.hub) from None
        self.session = session
        try:
            self._check_alone(session)
            self._publisher = session.declare_publisher(
                self.keys.events,
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.INTERACTIVE_HIGH,
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
            for entity in self._entities:
                entity.undeclare()
            self._entities = []
            try:
                session.close()
            except zenoh.ZError as e:  # Zenoh's 10 s: e.g. a link being opened to a router
                # that is gone (seen once when both hosts were stopped together)
                print(f"rra agent {self.host}: closing the bus session: {e}".split(" at /")[0])
            self.session = None

    def _check_alone(self, session: zenoh.Session) -> None:
        """Before declaring anything: refuse to be a second agent of this host, or (``rra
        up``) a second set of engines of this system, on this bus (one line)."""
        who = "rra up" if self.engines else "rra agent"
        why = unique.refusal(
            session, self.session_bus, self.keys, self.host, engines=self.engines, who=who
        )
        if why is not None:
            raise RraError(why)

    def _shutdown(self) -> None:
        """Stop every node with the escalation policy; wait until all have exited (the
        components in containers with their containers, which unload them first)."""
        sup = self.supervisor
        self.stopping = True
        for name in list(self.members.members):
            self.members.stop(name, self.clock())
        sup.stop_all(self.clock())
        pol = sup.stop_policy
        deadline = self.clock() + pol.sigint_timeout + pol.sigterm_timeout + 2.0
        while not sup.all_stopped() and self.clock() < deadline:
            self.loop.cycle(TICK)
            self._tick(self.clock())


def security(args, dep, host: str) -> dict[str, Any]:  # argparse.Namespace, Deployment
    """With ``--certs``: the certificate folder and the access control of this host's router,
    generated from the model."""
    if not getattr(args, "certs", None):
        return {}
    from rra_agent.security.acl import access_control

    contained = sorted(c.name for c in dep.configured.components if c.container)
    if contained:
        raise RraError(
            f"--certs: {', '.join(contained)} run in component containers, which share one "
            "Zenoh identity and cannot each get their own access control yet; run them as "
            "processes of their own (remove 'container') to use --certs"
        )

    return {"certs": args.certs, "access_control": access_control(dep, host)}


def state_printer(
    prefix: str = "", quiet: bool = False, wide: bool = False
) -> Callable[[m.NodeState], None]:
    """An observer printing each node-state change as one line (``rra up``, ``rra agent``),
    wrapped at `rra_agent.text.WIDTH` unless ``wide``."""

    def show(st: m.NodeState) -> None:
        if quiet:
            return
        pid = f" pid {st.pid}" if st.pid else ""
        why = f" ({st.reason})" if st.reason and st.state not in ("RUNNING", "STARTING") else ""
        line = f"[{time.strftime('%H:%M:%S')}] {prefix}{st.node:<24} {st.state}{pid}{why}"
        print("\n".join(text.wrap(line, indent=" " * 11, wide=wide)), flush=True)

    return show


def configure(parser) -> None:  # argparse.ArgumentParser
    from rra_agent.bus.config import add_bus_arguments, add_peer_nodes_argument

    parser.add_argument("--system", help="system name (checked against the package's)")
    parser.add_argument("--host", required=True, help="this host's name in the system model")
    parser.add_argument(
        "--package",
        required=True,
        help="the system package: this host runs only the components it places here",
    )
    parser.add_argument(
        "--select",
        "-s",
        action="append",
        default=[],
        help="deployment-time features, comma separated, as given to `rra up` (default: the "
        "manifest's): the model this host runs components of",
    )
    parser.add_argument("--log-dir", default="rra-logs", help="node logs go here")
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress lines")
    parser.add_argument(
        "--wide",
        action="store_true",
        help=f"the banner and progress lines on long lines, not fitted to {text.WIDTH} columns",
    )
    parser.add_argument(
        "--hub", action="store_true", help="listen on the hub endpoint (the first process)"
    )
    add_bus_arguments(parser)
    add_peer_nodes_argument(parser)


def schedule_self(settings: AgentSettings, who: str) -> None:
    """The host agent's own scheduling and its host's CPU wake-up latency (the manifest's
    ``agents``), before its session (and the router's threads) exists; a refusal is one
    warning line, a latency held one line too (it costs the host's idle power)."""
    problems = [] if settings.scheduling.is_default else scheduling.apply(
        settings.scheduling, reset_on_fork=True
    )
    for problem in problems:
        print(f"{who}: scheduling: {problem}; running without it", file=sys.stderr, flush=True)
    us = settings.cpu_latency_us
    if us is None:
        return
    refused = scheduling.hold_cpu_latency(us)
    line = (
        f"{refused}; running without it"
        if refused
        else f"CPU wake-up latency held at {us} us while this agent runs (PM QoS)"
    )
    print(f"{who}: {line}", file=sys.stderr, flush=True)


def run(args) -> int:  # argparse.Namespace
    """``rra agent``: serve one host until SIGINT/SIGTERM."""
    from rra_agent.bus.config import bus_from_args
    from rra_agent.deployment import deploy

    dep = deploy(args.package, [n.strip() for v in args.select for n in v.split(",") if n.strip()])
    if args.system and args.system != dep.system:
        raise RraError(f"--system {args.system}: the package's system is {dep.system}")
    catalog = Catalog.of(dep, args.host, default_host=args.hub)
    schedule_self(dep.package.manifest.agents, f"rra agent {args.host}")
    agent = HostAgent(
        dep.system,
        args.host,
        bus_from_args(args, role="agent"),
        args.log_dir,
        hub=args.hub,
        catalog=catalog,
        data_topics=topic_limits(dep.package.system),
        models=dep,
        **security(args, dep, args.host),
    )
    quiet = getattr(args, "quiet", False)
    wide = getattr(args, "wide", False)
    agent.observers.append(state_printer(quiet=quiet, wide=wide))
    watch: list[Any] = []

    def banner() -> None:
        if quiet:
            return
        head = f"rra agent: host {args.host} of system {dep.system!r}; Ctrl-C to stop"
        logs = [("logs", str(Path(args.log_dir).resolve()))]
        router = agent.session_bus
        lines, linked = links.banner(head, router, agent.session, logs, wide=wide)
        print(lines, flush=True)
        if agent.session is not None:
            say = links.printer("rra agent: ", wide=wide)
            watch.append(links.LinkWatch(agent.session, router.connect, say, linked=linked).start())

    agent.run(on_ready=banner)
    if not quiet:
        print(f"rra agent: host {args.host}: all processes stopped", flush=True)
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
