"""The Context Monitor process (paper Sec. III-C), configured from ``measurements.yaml``.

The paper generated a monitor per system by model-to-text transformation; this process
interprets the model instead: it subscribes to every source interface the measurements name
(the publisher's topic in the Deployment-time Configured System Model), feeds the samples to
`rra_agent.core.monitor.ContextMonitor`, and publishes each Context Dependent Measurement on
``rra/<system>/ctx/<name>`` with its computation time and the send times of its sources.

Trust: a sample is decoded against its port's declared data type as it arrives, on the Zenoh
thread (`rra_agent.core.samples`); one that is too large, not msgpack, ill-typed, or holds
a non-finite or implausible value a measurement reads is refused: it never reaches the
rules, never displaces the newest good sample of its source, and is counted per source and
reason (``rra status``) and logged at most once per 10 s per source and reason.

Overload: the Zenoh callback only keeps the newest good sample of each source; the main loop
computes from those (latest-value coalescing: both synchronisation policies only ever use
the newest sample of each source). A flood of samples on one source costs the others
nothing but a dictionary write per sample, and is counted (``coalesced``).

Partitions are context: the monitor follows the liveliness token of every host agent of the
model (gone when its link is lost, after the bus lease; back when it returns). The leader
publishes each transition as an adaptation event (``host_unreachable`` /
``host_reachable``, once per transition: only the leader does) with a line in its log, and
as the value of each ``reachable: HOST`` measurement the model declares, if any.

Failure is context: an ``available: COMPONENT`` measurement is false while the Run-time
Resolution Engine leader's state lists an implementation of that component as unavailable
(it could not start, or kept crashing), true otherwise; its first value comes with the first
state the leader publishes (at least one a second).

Publishing: a measurement is published when its value changes, and unchanged at most every
quarter of its ``max_age_ms`` (every second without one), so that the rules never see it
stale while its sources live. Sending every computed value (400 Hz of an unchanged
WorkingMotors) made every Adaptation Engine replica evaluate its rules 400 times a second
on a 2-core machine, which slowed every other process on the path of an adaptation.

Replicas: every replica computes every measurement (a hot standby); only the leader of the
``monitor`` role publishes. Every replica answers a query on ``rra/<system>/ctx/*`` with the
newest value of each measurement, so a restarted Adaptation Engine resumes from them.

Operators (``rra inject``, `rra_agent.engines.injection`): the leader publishes an
injection on ``inject/<kind>`` for the nodes that take them, and overrides a measurement
with a given value for a while; both are ``injection`` events. Its status lists every
measurement with its newest value, when it was computed and from what (``rra status``).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from rra_agent import _compat, trace
from rra_agent.bus import messages as m
from rra_agent.bus.client import oks
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import data_limit
from rra_agent.bus.keys import check_topic
from rra_agent.core.monitor import ContextMonitor
from rra_agent.core.plan import topic_of
from rra_agent.core.samples import MALFORMED, Refusal
from rra_agent.deployment import Deployment
from rra_agent.engines.base import EngineProcess
from rra_agent.engines.injection import (
    InjectionError,
    Overrides,
    context_view,
    find,
    inject_text,
    typed_value,
)
from rra_agent.engines.leaders import LeaderWatch
from rra_agent.engines.models import deploy_bundle
from rra_agent.engines.ros2 import TopicSources
from rra_agent.errors import RraError
from rra_agent.models.measurements import is_ros2_source
from rra_agent.models.system import parse_endpoint
from rra_agent.package.bundle import ModelBundle
from rra_agent.package.functions import measurement_functions as package_measurement_functions
from rra_agent.package.imports import import_dotted as import_dotted
from rra_agent.record.hooks import MonitorRecorder, open_writer
from rra_agent.viz.rerun_log import Logger, open_logger

NAME = "monitor"
#: Seconds between publications of an unchanged measurement that has no ``max_age_ms``.
REFRESH = 1.0
_CTX = m.Codec[m.CtxMessage](m.CtxMessage)
_EVT = m.Codec[m.EventMessage](m.EventMessage)
_STATE = m.Codec[m.StateMessage](m.StateMessage)
_INJ = m.Codec[m.Injection](m.Injection)
_REQ = m.Codec[m.EngineRequest](m.EngineRequest)


def measurement_functions(dep: Deployment) -> dict[str, Callable[..., Any]]:
    """Measurement name -> its function (`rra_agent.package.functions.measurement_functions`)."""
    return package_measurement_functions(dep.package)


def model_hosts(dep: Deployment, default: str) -> list[str]:
    """Every host of the model: declared, or running a component (``default``: the engines'
    host, where a component without one runs)."""
    configured = dep.configured
    return sorted(
        {h.name for h in configured.hosts} | {c.host or default for c in configured.components}
    )


class ContextMonitorProcess(EngineProcess[tuple[Deployment, ContextMonitor]]):
    """The Context Monitor (one replica of the ``monitor`` role)."""

    role = NAME
    #: Loading new models imports their measurement functions.
    model_errors = (RraError, ImportError, AttributeError, ValueError)

    def __init__(
        self,
        dep: Deployment,
        bus: BusConfig,
        *,
        host: str = "local",
        name: str = NAME,
        run_dir: Path | None = None,
    ):
        super().__init__(dep, bus, host=host, name=name)
        self.core = ContextMonitor(
            dep.package.measurements, measurement_functions(dep), self._port_types()
        )
        self.core.refusals.observer = self._refused
        #: The largest sample accepted from each source (its port's limit).
        self.limits = {
            src: self._limit(src) for src in self.core.sources if not is_ros2_source(src)
        }
        #: The ROS 2 topics it reads (`rra_agent.engines.ros2.TopicSources`), once declared.
        self.topics: TopicSources | None = None
        self.published = 0
        self.publishers: dict[str, zenoh.Publisher] = {}
        #: The newest measurement of each name (answered to a restarted Adaptation Engine).
        self.latest: dict[str, m.Measurement] = {}
        #: The last one published of each name, and how often one unchanged is sent again.
        self.sent: dict[str, m.Measurement] = {}
        self.refresh = _refresh(dep)
        #: Samples waiting to be processed: the newest per source (older ones coalesced),
        #: with its send time and raw bytes.
        self._pending: dict[str, tuple[Any, float, bytes | None]] = {}
        #: The subscriber of each source (re-declared when a reload changes the sources).
        self._sources: dict[str, zenoh.Subscriber[None]] = {}
        self._source_keys: dict[str, tuple[str, int]] = {}
        #: The run's record: the source samples the leader computed from.
        self.run_dir = run_dir
        self.rec: MonitorRecorder | None = None
        self._scheduled = False
        self.viz: Logger | None = None  # Rerun, when RRA_RERUN says so
        #: Every host of the model with its reachability measurements (none, unless the
        #: model declares ``reachable: HOST``) and the availability measurements of each
        #: component (`_derived`); whether each host is reachable and each is available now.
        self.reachability: dict[str, list[str]] = {}
        self.availability: dict[str, list[str]] = {}
        self.reachable: dict[str, bool] = {}
        self.available: dict[str, bool] = {}
        self._derived(dep)
        self.resolution: LeaderWatch | None = None
        #: Hosts the start-up query did not find (not yet known to be cut off: the query
        #: may run before this session has heard of their tokens).
        self._seed_absent: set[str] = set()
        self._events: zenoh.Publisher | None = None
        #: Operators' overrides, the computed values they hide, the injection publishers.
        self.declared = {meas.name: meas for meas in dep.package.measurements.measurements}
        self.overrides = Overrides(self.refresh)
        self._shadowed: dict[str, m.Measurement] = {}
        self._inject_pubs: dict[str, zenoh.Publisher] = {}

    def source_key(self, source: str) -> str:
        ep = parse_endpoint(source)
        return self.keys.data(topic_of(self.dep.package.system, ep.component, ep.port))

    def _port_types(self, dep: Deployment | None = None) -> dict[str, str]:
        """``component.port`` -> the type its port declares, for every measured source."""
        dep = dep or self.dep
        system = dep.package.system
        out = {}
        for meas in dep.package.measurements.measurements:
            for src in meas.inputs if meas.ros2_topic is None else ():
                ep = parse_endpoint(src)
                comp = system.component(ep.component)
                port = comp.port(ep.port) if comp is not None else None
                if port is not None:
                    out[src] = port.type
        return out

    def _limit(self, source: str) -> int:
        ep = parse_endpoint(source)
        comp = self.dep.package.system.component(ep.component)
        port = comp.port(ep.port) if comp is not None else None
        return data_limit(port.max_bytes if port is not None else None)

    def _refused(self, refusal: Refusal) -> None:
        """Count a refused sample as the process's (dropped: malformed; else rejected),
        logged once per 10 s per source and reason: junk on one key (or on the control
        endpoint) never hides the first refusal of another source."""
        detail = f"{refusal.source}: {refusal.detail}"
        if refusal.reason in MALFORMED:
            self.drop(refusal.reason, detail, refusal.source)
        else:
            self.refuse(refusal.reason, detail, refusal.source)

    # ---- bus (Zenoh thread): keep the newest good sample per source, compute if idle ------
    def _on_sample(self, source: str) -> Callable[[zenoh.Sample], None]:
        limit = self.limits[source]

        def callback(sample: zenoh.Sample) -> None:
            size = len(sample.payload)
            if size > limit:  # Zenoh's router stops these first: defence in depth
                detail = f"{size} bytes, more than the {limit} allowed"
                self.core.refusals.add(Refusal(source, "too_large", detail))
                return
            raw = sample.payload.to_bytes()
            data = self.core.decode(source, raw)
            if data is None:
                return  # refused and counted: the newest good sample stays pending
            att = sample.attachment
            stamp = m.unpack_stamp(att.to_bytes() if att else None) or time.time()
            self._take(source, data, stamp, raw)

        return callback

    def _take(self, source: str, data: Any, stamp: float, raw: bytes | None = None) -> None:
        """A good sample of ``source`` (a port's, or a ROS 2 topic's, decoded already: then
        ``raw`` is None and the record keeps it as msgpack): the newest pending one of its
        source; computing is scheduled if it is not already."""
        with self.lock:
            self.counters.received += 1
            if source in self._pending:
                self.counters.bump("coalesced")
            self._pending[source] = (data, stamp, raw)
            schedule, self._scheduled = not self._scheduled, True
        if schedule and not self.loop.run_or_post(self._process):
            with self.lock:
                self._scheduled = False

    def _on_latest(self, query: zenoh.Query) -> None:
        with self.lock:
            latest = list(self.latest.values())
        for msg in latest:
            query.reply(self.keys.ctx(msg.name), _CTX.encode(msg))

    # ---- computing (serialised by the main loop: its thread, or inline when idle) ----------
    def _process(self) -> None:
        with self.lock:
            batch, self._pending = self._pending, {}
            self._scheduled = False
        rec = self.rec if self.leading else None
        for source, (data, stamp, raw) in batch.items():
            if rec is not None:
                rec.sample(source, raw if raw is not None else _plain(data), stamp)
            for c in self.core.on_sample(source, data, stamp):
                self._emit(
                    m.Measurement(name=c.name, value=c.value, stamp=time.time(), sources=c.sources)
                )

    def _emit(self, msg: m.Measurement) -> None:
        if msg.name in self.overrides.active:  # an operator's value is in effect
            self._shadowed[msg.name] = msg
            return
        with self.lock:
            self.latest[msg.name] = msg
        if not self.leading:
            return  # a hot standby computes everything, publishes nothing
        last = self.sent.get(msg.name)
        if (
            last is None
            or last.value != msg.value
            or msg.stamp - last.stamp >= self.refresh.get(msg.name, REFRESH)
        ):
            self._publish(msg)

    def _publish(self, msg: m.Measurement) -> None:
        trace.mark("monitor:measurement", msg.name)
        self.sent[msg.name] = msg
        self.publishers[msg.name].put(_CTX.encode(msg))
        self.published += 1
        if self.viz:
            self.viz.measurement(msg.name, msg.value, msg.stamp)

    # ---- host reachability ----------------------------------------------------------------
    def _on_host(self, sample: zenoh.Sample) -> None:
        host = str(sample.key_expr).rsplit("/", 1)[-1]
        alive = sample.kind == zenoh.SampleKind.PUT
        self.loop.post(lambda: self._host_seen(host, alive))

    def _host_seen(self, host: str, alive: bool, *, seed: bool = False) -> None:
        """A host agent's token appeared or vanished: a new value when it changes, and an
        event when it was known before (a partition or its end; a host that only joins,
        or whose token reaches this session just after the start-up query missed it, is
        no transition)."""
        if host not in self.reachability or self.reachable.get(host) == alive:
            return
        transition = host in self.reachable and host not in self._seed_absent
        self.reachable[host] = alive
        (self._seed_absent.add if seed and not alive else self._seed_absent.discard)(host)
        for name in self.reachability[host]:
            self._emit(m.Measurement(name=name, value=alive, stamp=time.time()))
        if transition:
            self._host_event(host, alive)

    # ---- availability (failure as context) ------------------------------------------------
    def _on_state(self, sample: zenoh.Sample) -> None:
        state = self.leader_state(sample, self.resolution)
        if state is not None:
            self.loop.post(lambda: self._resolution_state(state))

    def _resolution_state(self, state: m.EngineState) -> None:
        """The leader's models first (a reload), then what is unavailable."""
        self.follow_models(state.models)
        self._availability(state.unavailable)

    def _availability(self, unavailable: list[m.Unavailable]) -> None:
        """A new value of each availability measurement whose component changed."""
        gone = {u.component for u in unavailable}
        for component, names in self.availability.items():
            alive = component not in gone
            if self.available.get(component) == alive:
                continue
            self.available[component] = alive
            for name in names:
                self._emit(m.Measurement(name=name, value=alive, stamp=time.time()))

    def on_leadership(self, leading: bool) -> None:
        """A new leader publishes what it knows at once: the newest value of each measurement
        it computed while no replica led (at start-up the sources publish before the
        election ends; a value computed then would otherwise reach the rules only with the
        source's next sample, up to a second later for a 1 Hz battery state), and the hosts'
        reachability (a value its predecessor published may predate what this replica has
        seen since). A replica that stops leading drops its operators' overrides."""
        if self.rec is not None:
            self.rec.lead(leading, self.fence)
        if not leading:
            self._end_overrides(list(self.overrides.active), "its Context Monitor stopped leading")
            return
        derived = {n for names in self.reachability.values() for n in names}
        derived |= {n for names in self.availability.values() for n in names}
        with self.lock:
            latest = [msg for name, msg in self.latest.items() if name not in derived]
        for msg in latest:
            self._publish(msg)
        for host, alive in self.reachable.items():
            for name in self.reachability[host]:
                self._emit(m.Measurement(name=name, value=alive, stamp=time.time()))
        for component, alive in self.available.items():
            for name in self.availability[component]:
                self._emit(m.Measurement(name=name, value=alive, stamp=time.time()))

    def _host_event(self, host: str, alive: bool) -> None:
        if not self.leading or self._events is None:
            return
        message = (
            f"host {host} is reachable again: its agent's token is back; steps deferred for "
            "it are applied"
            if alive
            else f"host {host} is unreachable: its agent's token is gone (the link to it "
            "dropped, or the agent stopped); its nodes run on under their agent, steps for "
            "it are deferred until it is back"
        )
        ev = m.AdaptationEvent(
            stamp=time.time(),
            kind="host_reachable" if alive else "host_unreachable",
            message=message,
            level="info" if alive else "warning",
            source=self.name,
        )
        self._events.put(_EVT.encode(ev))
        print(f"rra {self.name}: {message}", flush=True)

    def _seed_hosts(self, session: zenoh.Session) -> None:
        """The hosts whose agent is reachable at start; the others are unreachable."""
        if not self.reachability:
            return
        present = {
            str(reply.ok.key_expr).rsplit("/", 1)[-1]
            for reply in session.liveliness().get(self.keys.host_alive_all, timeout=1.0)
            if reply.ok is not None
        }
        for host in self.reachability:
            self._host_seen(host, host in present, seed=True)

    def extra_counters(self) -> dict[str, int]:
        return {
            "published": self.published,
            "failures": sum(self.core.failures.values()),
            "refused": self.core.refusals.count(),
        }

    def stats(self) -> m.ProcessStats:
        rows = self.core.refusals.rows()
        refused = [m.RefusedSamples(source=s, reason=r, count=n, last=d) for s, r, n, d in rows]
        return msgspec.structs.replace(super().stats(), refused=refused)

    # ---- lifecycle ---------------------------------------------------------------------
    def declare(self, session: zenoh.Session) -> list[Any]:
        writer = open_writer(self.run_dir, self.name, self.role, self.dep, self.host)
        self.rec = MonitorRecorder(writer) if writer is not None else None
        self.viz = open_logger(self.name)
        self._declare_publishers(session)
        self._subscribe_sources(session)
        entities: list[Any] = [session.declare_queryable(self.keys.ctx_all, self._on_latest)]
        if self.ros2 is not None:
            self.topics = TopicSources(
                self.ros2.node,
                self.dep.package.measurements.measurements,
                self._take,
                self.core.refusals.add,
            )
            entities.append(self.topics)
        self._events = session.declare_publisher(
            self.keys.events, congestion_control=zenoh.CongestionControl.BLOCK
        )
        entities.append(self._events)
        if self.reachability:
            # With history: a token that exists already is delivered too (the seed's query
            # may run before this session has heard of it, and would call it unreachable).
            entities.append(
                session.liveliness().declare_subscriber(
                    self.keys.host_alive_all, self._on_host, history=True
                )
            )
            self._seed_hosts(session)
        # The Resolution Engine leader's state: availability, and the models it runs.
        self.resolution = LeaderWatch(session, self.keys, "resolution")
        entities += [
            self.resolution,
            session.declare_subscriber(self.keys.state("resolution"), self._on_state),
        ]
        return entities

    def _declare_publishers(self, session: zenoh.Session) -> None:
        for meas in self.dep.package.measurements.measurements:
            if meas.name not in self.publishers:
                self.publishers[meas.name] = session.declare_publisher(
                    self.keys.ctx(meas.name),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    priority=zenoh.Priority.INTERACTIVE_HIGH,
                    express=True,
                )

    def _subscribe_sources(self, session: zenoh.Session) -> None:
        """A subscriber for every source of the model (those it has already are kept)."""
        wanted = {
            src: (self.source_key(src), self.limits[src])
            for src in self.core.sources
            if not is_ros2_source(src)
        }
        for src in list(self._sources):
            if src not in wanted or self._source_keys.get(src) != wanted[src]:
                with contextlib.suppress(Exception):
                    self._sources.pop(src).undeclare()
        for src, key in wanted.items():
            if src not in self._sources:
                self._sources[src] = session.declare_subscriber(key[0], self._on_sample(src))
        self._source_keys = wanted

    def status(self) -> dict[str, Any]:
        with self.lock:
            latest = dict(self.latest)
        return {
            "measurements": {n: msg.value for n, msg in latest.items()},
            "context": context_view(self.declared.values(), latest),
            "models": self.dep.models,
        }

    def snapshot(self) -> dict[str, Any]:
        """The status, with the measurements as they are now (not as at the last tick)."""
        with self.lock:
            latest = dict(self.latest)
        return {**super().snapshot(), "context": context_view(self.declared.values(), latest)}

    def tick(self, now: float) -> None:
        if self.overrides.active:
            self._overrides_due(now)
        self.publish_status()

    # ---- operators' injections (main thread) -------------------------------------------
    def serve(self, request: m.EngineRequest) -> m.Reply:
        match request:
            case m.Inject() | m.OverrideMeasurement():
                if not self.leading:
                    return m.Err(message=f"{self.name} does not lead", code="not_leader")
                try:
                    if isinstance(request, m.Inject):
                        return self._inject(request)
                    return self._override(request)
                except InjectionError as e:
                    self.refuse("injection", str(e))
                    return m.Err(message=str(e), code=e.code)
            case m.PrepareModels(bundle=bundle):
                return self.prepare(bundle)
        return super().serve(request)

    def _inject(self, req: m.Inject) -> m.Reply:
        """Publish an injection where the nodes that take them listen; an event."""
        try:
            key = self.keys.inject(check_topic(req.kind))
        except ValueError as e:
            raise InjectionError(f"{req.kind!r} is no injection kind: {e}") from None
        pub = self._inject_pubs.get(key)
        if pub is None:
            assert self.session is not None
            pub = self._inject_pubs[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
        deadline = time.monotonic() + 0.25  # a new publisher learns its subscribers at once
        while not _matching(pub) and time.monotonic() < deadline:
            time.sleep(0.002)
        if not _matching(pub):
            raise InjectionError(
                f"no process of system {self.dep.system} takes injections of kind "
                f"{req.kind}: nothing injected",
                code="nobody",
            )
        msg = msgspec.structs.replace(req, stamp=time.time())
        pub.put(_INJ.encode(msg))
        who = req.operator or "unknown"
        self._injection_event(f"operator {who} injected {inject_text(req)}", who, msg)
        return m.Ok(result={"injected": inject_text(req), "key": key, "stamp": msg.stamp})

    def _override(self, req: m.OverrideMeasurement) -> m.Reply:
        """Publish the operator's value of a measurement instead of the computed one."""
        meas = find(self.declared, req.name, self.dep.system)
        who = req.operator or "unknown"
        if req.duration == 0:
            ended = req.name in self.overrides.active
            self._end_overrides([req.name], f"operator {who} ended it")
            return m.Ok(result={"name": req.name, "ended": ended})
        value = typed_value(meas, req.value)
        o = self.overrides.set(req.name, value, who, time.time(), self.loop.clock(), req.duration)
        with self.lock:
            shadowed = self.latest.get(req.name)
        if shadowed is not None and not shadowed.override:
            self._shadowed.setdefault(req.name, shadowed)
        self._overrides_due(self.loop.clock())
        text = f"operator {who} overrode measurement {req.name} = {value!r} for {req.duration:g} s"
        inj = m.Inject(kind="measurement", target=req.name, stamp=time.time(), operator=who,
                       args={"value": value, "duration": req.duration})  # fmt: skip
        self._injection_event(text, who, inj)
        self.publish_status()
        return m.Ok(result={"name": req.name, "value": value, "until": o.until, "operator": who})

    def _overrides_due(self, now: float) -> None:
        """Re-send the overrides due, end the expired ones, and wake for the next."""
        send, ended = self.overrides.due(now)
        for name in send:
            msg = self.overrides.message(name, time.time(), self.fence)
            with self.lock:
                self.latest[name] = msg
            if self.leading:
                self._publish(msg)
        if ended:
            self._end_overrides(ended, "its time is up")
        at = self.overrides.next_at()
        if at is not None:
            self.loop.due(at)

    def _end_overrides(self, names: list[str], why: str) -> None:
        """End these overrides: the newest computed value is in effect again."""
        for name in names:
            o = self.overrides.active.pop(name, None)
            computed = self._shadowed.pop(name, None)
            with self.lock:
                if computed is not None:
                    self.latest[name] = computed
                elif o is not None:
                    self.latest.pop(name, None)
            if o is None:
                continue
            if computed is not None and self.leading:
                self._publish(computed)
            now = "computed values again" if computed is not None else "no computed value yet"
            text = f"override of measurement {name} by {o.operator} ended ({why}): {now}"
            inj = m.Inject(kind="measurement", target=name, stamp=time.time(),
                           operator=o.operator, args={"ended": True})  # fmt: skip
            self._injection_event(text, o.operator, inj)
        self.publish_status()

    def _injection_event(self, text: str, who: str, inj: m.Inject) -> None:
        print(f"rra {self.name}: {text}", flush=True)
        if self._events is None or not self.leading:
            return
        ev = m.AdaptationEvent(stamp=time.time(), kind="injection", message=text,
                               source=self.name, operator=who, injection=inj)  # fmt: skip
        self._events.put(_EVT.encode(ev))

    def stopping(self) -> None:
        for pub in self._inject_pubs.values():
            with contextlib.suppress(Exception):
                pub.undeclare()
        for sub in self._sources.values():
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._sources.clear()
        if self.viz:
            self.viz.close()
        if self.rec is not None:
            self.rec.writer.close(end=time.time())

    # ---- reload: new models (``rra reload``, docs/recording.md) -------------------------------
    def starting(self) -> None:
        """A replica started after a reload runs the models the system runs."""
        assert self.session is not None
        key = self.keys.engine_ctl("resolution")
        for answer in oks(self.session.get(key, payload=_REQ.encode(m.GetState()), timeout=1.0)):
            if isinstance(answer.result, dict):
                self.follow_models(str(answer.result.get("models", "")))
                return

    def load_models(self, bundle: ModelBundle) -> tuple[Deployment, ContextMonitor]:
        """These models and their core, their measurement functions imported."""
        dep = deploy_bundle(bundle, self.dep)
        return dep, ContextMonitor(dep.package.measurements, measurement_functions(dep),
                                   self._port_types(dep))  # fmt: skip

    def switch_models(self, loaded: tuple[Deployment, ContextMonitor]) -> None:
        """Compute the new measurements from now on: a new core, subscribers for the new
        sources, publishers for the new measurements; values of removed ones forgotten."""
        dep, core = loaded
        core.refusals = self.core.refusals
        previous, self.dep, self.core = self.dep.models, dep, core
        self.limits = {src: self._limit(src) for src in core.sources if not is_ros2_source(src)}
        self.refresh = _refresh(dep)
        names = {meas.name for meas in dep.package.measurements.measurements}
        with self.lock:
            self.latest = {n: v for n, v in self.latest.items() if n in names}
        self.sent = {n: v for n, v in self.sent.items() if n in names}
        self._derived(dep)
        if self.session is not None:
            self._declare_publishers(self.session)
            self._subscribe_sources(self.session)
        self._prepared.clear()
        if self.rec is not None:
            self.rec.reload(dep.models, previous)
        print(f"rra {self.name}: models {dep.models} (were {previous})", flush=True)

    def _derived(self, dep: Deployment) -> None:
        """The reachability and availability measurements of the new models."""
        hosts: dict[str, list[str]] = {h: [] for h in model_hosts(dep, self.host)}
        for meas in dep.package.measurements.measurements:
            if meas.reachable is not None:
                hosts.setdefault(meas.reachable, []).append(meas.name)
        self.reachability = hosts
        self.availability = {}
        for meas in dep.package.measurements.measurements:
            if meas.available is not None:
                self.availability.setdefault(meas.available, []).append(meas.name)
        self.available = {c: v for c, v in self.available.items() if c in self.availability}


def _plain(data: Any) -> bytes:
    """A decoded sample as msgpack, for the record (arrays as lists, the rest as text)."""
    return msgspec.msgpack.encode(data, enc_hook=_plain_value)


def _plain_value(o: Any) -> Any:
    return o.tolist() if hasattr(o, "tolist") else str(o)


def _refresh(dep: Deployment) -> dict[str, float]:
    """How often each measurement is sent again unchanged (a quarter of its max age)."""
    return {
        meas.name: REFRESH if meas.max_age_ms is None else meas.max_age_ms / 4000.0
        for meas in dep.package.measurements.measurements
    }


def _matching(pub: zenoh.Publisher) -> bool:
    """Whether a subscriber matches the publisher (zenoh's status object, or a bool)."""
    status: Any = pub.matching_status
    return bool(getattr(status, "matching", status))


def arguments() -> argparse.ArgumentParser:
    """The command line of ``python -m rra_agent.engines.monitor``."""
    from rra_agent.engines.launch import engine_arguments

    return engine_arguments("rra monitor", __doc__)


def warm_up(argv: list[str]) -> None:
    """The fork server's hook (`rra_agent.engines.launch.warm_up`)."""
    from rra_agent.engines import launch

    launch.warm_up(argv, arguments)


def main(argv: list[str] | None = None) -> int:
    """``python -m rra_agent.engines.monitor --package PKG --select F,...``."""
    from rra_agent.engines.launch import engine_setup, parse_engine_args, record_dir

    args = parse_engine_args(arguments, argv)
    setup = engine_setup(args, NAME)
    if setup is None:
        return 2
    dep, bus, host, name = setup
    try:
        proc = ContextMonitorProcess(dep, bus, host=host, name=name, run_dir=record_dir(args))
    except (RraError, ImportError, AttributeError, ValueError) as e:
        print(f"rra monitor: {e}", file=sys.stderr)
        return 2
    return proc.run()


if __name__ == "__main__":
    sys.exit(main())


__getattr__ = _compat.renamed(__name__)  # old names, for one release (docs/api.md)
