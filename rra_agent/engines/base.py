"""What the three engine processes share: their session, their replica's election, their
control endpoints, their heartbeat and a clean shutdown.

Each engine role (``monitor``, ``adaptation``, ``resolution``) may run as several replicas
(``rra up`` starts two: a leader and a hot standby). A replica

- declares ``engine/<replica>/ctl`` (its own status) and, while it leads,
  ``engine/<role>/ctl`` (what clients address: ``rra status``, ``rra param``);
- declares ``node/<replica>/ctl``, the endpoint its host agent probes (``Ping``, ``Stats``);
- takes part in the role's election (`rra_agent.engines.election`) and is told when it
  starts or stops leading (`on_leadership`);
- writes its heartbeat from its main loop and sets the ready flag once it is up;
- follows the models its leader runs (a reload, docs/recording.md): `prepare` loads a
  version beside its own (`PrepareModels`), `follow_models` switches to the version its
  leader names (prepared, else loaded now), each engine saying how it loads
  (`load_models`) and switches (`switch_models`).

Status-like requests are answered on the Zenoh thread from a snapshot, so a replica busy
with a plan still answers probes and ``rra status``; requests that change something run on
the main loop, after what was posted before them.
"""

from __future__ import annotations

import contextlib
import os
import threading
from pathlib import Path
from typing import Any, Generic, TypeVar

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import Counters, RateLimitedLog, Refused, receive
from rra_agent.bus.keys import Keys
from rra_agent.bus.loop import MainLoop
from rra_agent.bus.session import beat_period, open_session
from rra_agent.deployment import Deployment
from rra_agent.engines.election import Election
from rra_agent.engines.models import find_bundle
from rra_agent.engines.ros2 import EngineRos2, EventMirror, engine_ros2
from rra_agent.errors import RraError
from rra_agent.package.bundle import ModelBundle

_REQ = m.Codec[m.EngineRequest](m.EngineRequest)
_NODE_REQ = m.Codec[m.NodeRequest](m.NodeRequest)
_REPLY = m.Codec[m.Reply](m.Reply)
_STATE = m.Codec[m.StateMessage](m.StateMessage)

#: What an engine's `load_models` gives and its `switch_models` takes.
Loaded = TypeVar("Loaded")


class EngineProcess(Generic[Loaded]):
    """Base of the monitor, adaptation and resolution processes (see the module doc)."""

    role: str = ""
    #: How often ``tick`` runs (seconds).
    tick_period: float = 0.5
    #: Whether its leader puts the system's events on ROS 2 (a package with ``ros2:``).
    ros2_events: bool = False
    #: What `load_models` raises for models it cannot run (refused, never fatal).
    model_errors: tuple[type[Exception], ...] = (RraError,)

    def __init__(
        self, dep: Deployment, bus: BusConfig, *, host: str, name: str, heartbeat: float = 4.0
    ) -> None:
        self.dep = dep
        self.bus = bus
        self.host = host
        self.name = name
        self.keys = Keys(dep.system)
        self.loop = MainLoop(beat_every=beat_period(heartbeat))
        self.counters = Counters()
        self.lock = threading.Lock()
        self._refusals = RateLimitedLog(lambda text: print(f"rra {name}: {text}", flush=True))
        self.session: zenoh.Session | None = None
        self.election: Election | None = None
        self._role_ctl: Any = None
        self._snapshot: dict[str, Any] = {}
        #: Its ROS 2 node (a package with ``ros2:``; `rra_agent.engines.ros2`).
        self.ros2: EngineRos2 | None = None
        #: The run folder whose record holds the models of every version (None: none).
        self.run_dir: Path | None = None
        #: Models loaded for a reload (`prepare`), by digest, until a switch.
        self._prepared: dict[str, Loaded] = {}

    # ---- hooks for the engines ---------------------------------------------------------
    def declare(self, session: zenoh.Session) -> list[Any]:
        """Declare the engine's own subscriptions and publishers; return what to keep."""
        return []

    def starting(self) -> None:
        """Before the election: e.g. resume from the system's current state."""

    def epoch_floor(self) -> int:
        """An epoch the role has used before (e.g. learnt while resuming): claims go above."""
        return 0

    def on_leadership(self, leading: bool) -> None:
        """This replica started (True) or stopped (False) leading."""

    def stalled(self) -> None:
        """This replica was stalled (frozen, starved): what it mirrors may be out of date."""

    def tick(self, now: float) -> None:
        """Periodic work (every ``tick_period``)."""

    def serve(self, request: m.EngineRequest) -> m.Reply:
        """A request that changes something (main thread)."""
        return m.Err(message=f"unsupported request {type(request).__name__}", code="unsupported")

    def status(self) -> dict[str, Any]:
        """What ``Status`` returns (built on the main thread, see `publish_status`)."""
        return {}

    def extra_counters(self) -> dict[str, int]:
        return {}

    def load_models(self, bundle: ModelBundle) -> Loaded:
        """These models loaded (and compiled) beside the running ones, ready for
        `switch_models`; one of `model_errors` if this engine cannot run them."""
        raise NotImplementedError

    def switch_models(self, loaded: Loaded) -> None:
        """Run ``loaded`` from now on (and forget what was prepared)."""
        raise NotImplementedError

    def find_models(self, digest: str) -> ModelBundle:
        """The models ``digest``: the run's record, else the Resolution Engine leader's."""
        return find_bundle(digest, self.run_dir, self.session, self.keys)

    # ---- new models (a reload, or a replica following its leader) ------------------------
    def prepare(self, bundle: ModelBundle) -> m.Reply:
        """`PrepareModels`: load ``bundle`` beside the running models (nothing changes yet)."""
        try:
            self._prepared[bundle.digest] = self.load_models(bundle)
        except self.model_errors as e:
            return m.Err(message=f"{self.name}: {e}", code="invalid")
        return m.Ok(result={"models": bundle.digest})

    def follow_models(self, digest: str) -> bool:
        """Run the models ``digest`` (those its leader names): at once if prepared, else
        loaded now. False (refused and counted) when they cannot be had: the replica keeps
        its own. An empty digest names no models (a peer that does not say)."""
        if not digest or digest == self.dep.models:
            return True
        try:
            loaded = self._prepared.pop(digest, None)
            if loaded is None:
                loaded = self.load_models(self.find_models(digest))
        except self.model_errors as e:
            self.refuse("models", f"cannot switch to models {digest}: {e}")
            return False
        self.switch_models(loaded)
        return True

    # ---- helpers -----------------------------------------------------------------------
    @property
    def leading(self) -> bool:
        return self.election is not None and self.election.leading

    @property
    def fence(self) -> m.Fence | None:
        return self.election.fence if self.election is not None else None

    def publish_status(self) -> None:
        """Refresh the snapshot ``Status`` answers from (call after every change)."""
        status = {
            **self.status(),
            "replica": self.name,
            "role": self.role,
            "leading": self.leading,
            "leader": list(self.election.leader or ()) if self.election else [],
        }
        if self.ros2 is not None:  # where a tool finds the system's ROS 2 graph
            settings = self.ros2.settings
            status["ros2"] = {"domain": settings.domain, "distro": settings.distro}
        with self.lock:
            self._snapshot = status

    def snapshot(self) -> dict[str, Any]:
        """What ``Status`` answers (Zenoh thread): the last `publish_status`."""
        with self.lock:
            return dict(self._snapshot)

    def stats(self) -> m.ProcessStats:
        c = self.counters
        c.extra.update(self.extra_counters())
        c.extra["refused_busy"] = self.loop.refused
        c.extra["inline"] = self.loop.inline
        c.extra["leading"] = int(self.leading)
        return c.stats(self.name, self.role, os.getpid())

    def refuse(self, kind: str, detail: str, about: str = "") -> None:
        """Count a refused sample or request and log it (rate-limited per kind and
        ``about``)."""
        self.counters.rejected += 1
        self._refusals(f"refused ({kind})", detail, about)

    def leader_state(self, sample: zenoh.Sample, leaders: Any) -> m.EngineState | None:
        """The Run-time Resolution Engine's state in ``sample`` if it comes from its live
        leader (``leaders``: a `LeaderWatch` of that role); else None, counted."""
        state = receive(sample.payload, "state", _STATE)
        if isinstance(state, Refused):
            self.drop(state.code, f"engine state: {state.detail}")
            return None
        if leaders is None or not leaders.is_leader(state.fence):
            self.refuse("state from a non-leader", f"engine state of {state.fence.leader}")
            return None
        return state

    def drop(self, kind: str, detail: str, about: str = "") -> None:
        self.counters.dropped += 1
        self._refusals(f"dropped ({kind})", detail, about)

    # ---- control endpoints (Zenoh thread) ----------------------------------------------
    def _on_engine_query(self, query: zenoh.Query) -> None:
        req = receive(query.payload, "engine_ctl", _REQ)
        if isinstance(req, Refused):
            self.drop(req.code, f"engine request: {req.detail}")
            return self._reply(query, req.err())
        self.counters.received += 1
        match req:
            case m.Status() | m.Describe():
                return self._reply(query, m.Ok(result=self.snapshot()))
            case m.Ping():
                return self._reply(query, m.Ok(result={"pid": os.getpid(), "name": self.name}))
            case m.Stats():
                return self._reply(query, m.Ok(result=self.stats()))
        if isinstance(req, m.PrepareModels):  # loading models takes a while: not on the loop
            threading.Thread(target=lambda: self._reply(query, self._serve(req)),
                             name="prepare-models", daemon=True).start()  # fmt: skip
            return None
        if not self.loop.post(lambda: self._reply(query, self._serve(req))):
            self._reply(query, m.Err(message=f"{self.name} is overloaded", code="busy"))
        return None

    def _serve(self, req: m.EngineRequest) -> m.Reply:
        try:
            return self.serve(req)
        except Exception as e:  # a bad request must never take the engine down
            return m.Err(message=f"{type(e).__name__}: {e}", code="error")

    def _on_process_query(self, query: zenoh.Query) -> None:
        """The host agent's probe (and ``Stats``) on ``node/<replica>/ctl``."""
        raw = query.payload.to_bytes() if query.payload is not None else b""
        try:
            req = _NODE_REQ.decode(raw)
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            self.drop("malformed", f"process request: {e}")
            return self._reply(query, m.Err(message=f"malformed request: {e}", code="malformed"))
        match req:
            case m.Ping():
                reply: m.Reply = m.Ok(result={"pid": os.getpid(), "name": self.name})
            case m.Stats():
                reply = m.Ok(result=self.stats())
            case _:
                reply = m.Err(message=f"{self.name} is an engine, not a node", code="unsupported")
        self._reply(query, reply)

    @staticmethod
    def _reply(query: zenoh.Query, reply: m.Reply) -> None:
        query.reply(query.key_expr, _REPLY.encode(reply))

    # ---- leadership --------------------------------------------------------------------
    def _leadership_changed(self) -> None:
        """Take over (or step down), then answer for the role: the role's endpoint appears
        only once the snapshot it answers from is the new leader's (a client asking during
        a takeover waits for it rather than reading a standby's half state)."""
        leading = self.leading
        session = self.session
        if not leading and self._role_ctl is not None:
            with contextlib.suppress(Exception):
                self._role_ctl.undeclare()
            self._role_ctl = None
        self.on_leadership(leading)
        self.publish_status()
        if self.leading and self._role_ctl is None and session is not None:
            self._role_ctl = session.declare_queryable(
                self.keys.engine_ctl(self.role), self._on_engine_query
            )

    # ---- the process -------------------------------------------------------------------
    def run(self, *, install_signals: bool = True) -> int:
        if install_signals:
            self.loop.install_signals()
        self.session = session = open_session(self.bus, wait_connected=True)
        entities: list[Any] = []
        try:
            entities = [
                session.declare_queryable(self.keys.engine_ctl(self.name), self._on_engine_query),
                session.declare_queryable(self.keys.node_ctl(self.name), self._on_process_query),
                *self._declare_ros2(session),
                *self.declare(session),
            ]
            self.starting()
            self.election = Election(
                session,
                self.keys,
                self.role,
                self.name,
                self.loop,
                self._leadership_changed,
                tick_period=self.tick_period,
                on_stall=self.stalled,
            )
            self.election.max_epoch = self.epoch_floor()
            self.election.start()
            self.publish_status()
            entities.append(
                session.liveliness().declare_token(self.keys.alive(self.host, self.name))
            )
            self.loop.set_ready()
            self.loop.run(self._tick, self.tick_period)
            return 0
        finally:
            self.stopping()
            if self.election is not None:
                self.election.close()
            if self._role_ctl is not None:
                with contextlib.suppress(Exception):
                    self._role_ctl.undeclare()
            for entity in entities:
                with contextlib.suppress(Exception):
                    entity.undeclare()
            session.close()
            self.session = None

    def _declare_ros2(self, session: zenoh.Session) -> list[Any]:
        """Its ROS 2 node, and for the role that says so the events on ROS 2 (closed
        before the session, with the other entities)."""
        self.ros2 = engine_ros2(session, self.dep, self.name)
        if self.ros2 is None:
            return []
        out: list[Any] = [self.ros2]
        topic = self.ros2.settings.events
        if self.ros2_events and topic is not None:
            mirror = EventMirror(session, self.keys, self.ros2.node, topic, lambda: self.leading)
            out.insert(0, mirror)
        return out

    def _tick(self, now: float) -> None:
        if self.election is not None:
            self.election.tick()
        self.tick(now)

    def stopping(self) -> None:
        """Before the session closes (e.g. close the Rerun logger)."""
