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
reason (``rra status``) and logged at most once per 10 s per kind.

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
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from typing import Any

import msgspec
import zenoh

from rra_agent import _compat, trace
from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import data_limit
from rra_agent.core.monitor import ContextMonitor
from rra_agent.core.plan import topic_of
from rra_agent.core.samples import MALFORMED, Refusal
from rra_agent.deployment import Deployment
from rra_agent.engines.base import EngineProcess
from rra_agent.engines.leaders import LeaderWatch
from rra_agent.errors import RraError
from rra_agent.models.system import parse_endpoint
from rra_agent.package.functions import function_path, load_function
from rra_agent.package.functions import import_dotted as import_dotted
from rra_agent.package.imports import add_package_path
from rra_agent.viz.rerun_log import Logger, open_logger

NAME = "monitor"
#: Seconds between publications of an unchanged measurement that has no ``max_age_ms``.
REFRESH = 1.0
_CTX = m.Codec[m.CtxMessage](m.CtxMessage)
_EVT = m.Codec[m.EventMessage](m.EventMessage)
_STATE = m.Codec[m.StateMessage](m.StateMessage)


def measurement_functions(dep: Deployment) -> dict[str, Callable[..., Any]]:
    """Measurement name -> its function: a function of the source data type, or a dotted path
    (`rra_agent.package.functions`, as a node evaluating a reflex resolves it).

    The package folder is appended to ``sys.path`` (`rra_agent.package.imports`) so a
    package may ship its own functions.
    """
    pkg = dep.package
    add_package_path([pkg.root])
    out = {}
    for meas in pkg.measurements.measurements:
        types = []
        for src in meas.inputs:
            ep = parse_endpoint(src)
            comp = pkg.system.component(ep.component)
            port = comp.port(ep.port) if comp else None
            types.append(port.type if port else None)
        dotted = function_path(pkg.measurements, meas, types)
        if dotted is not None:
            out[meas.name] = load_function(dotted)
    return out


def model_hosts(dep: Deployment, default: str) -> list[str]:
    """Every host of the model: declared, or running a component (``default``: the engines'
    host, where a component without one runs)."""
    configured = dep.configured
    return sorted(
        {h.name for h in configured.hosts} | {c.host or default for c in configured.components}
    )


class ContextMonitorProcess(EngineProcess):
    """The Context Monitor (one replica of the ``monitor`` role)."""

    role = NAME

    def __init__(self, dep: Deployment, bus: BusConfig, *, host: str = "local", name: str = NAME):
        super().__init__(dep, bus, host=host, name=name)
        self.core = ContextMonitor(
            dep.package.measurements, measurement_functions(dep), self._port_types()
        )
        self.core.refusals.observer = self._refused
        #: The largest sample accepted from each source (its port's limit).
        self.limits = {src: self._limit(src) for src in self.core.sources}
        self.published = 0
        self.publishers: dict[str, zenoh.Publisher] = {}
        #: The newest measurement of each name (answered to a restarted Adaptation Engine).
        self.latest: dict[str, m.Measurement] = {}
        #: The last one published of each name, and how often one unchanged is sent again.
        self.sent: dict[str, m.Measurement] = {}
        self.refresh = {
            meas.name: REFRESH if meas.max_age_ms is None else meas.max_age_ms / 4000.0
            for meas in dep.package.measurements.measurements
        }
        #: Samples waiting to be processed: the newest per source (older ones coalesced).
        self._pending: dict[str, tuple[Any, float]] = {}
        self._scheduled = False
        self.viz: Logger | None = None  # Rerun, when RRA_RERUN says so
        #: Every host of the model with its reachability measurements (none, unless the
        #: model declares ``reachable: HOST``), and the hosts whose agent is reachable now.
        self.reachability: dict[str, list[str]] = {h: [] for h in model_hosts(dep, host)}
        for meas in dep.package.measurements.measurements:
            if meas.reachable is not None:
                self.reachability.setdefault(meas.reachable, []).append(meas.name)
        self.reachable: dict[str, bool] = {}
        #: Availability measurements by component, and whether each is available now.
        self.availability: dict[str, list[str]] = {}
        for meas in dep.package.measurements.measurements:
            if meas.available is not None:
                self.availability.setdefault(meas.available, []).append(meas.name)
        self.available: dict[str, bool] = {}
        self.resolution: LeaderWatch | None = None
        #: Hosts the start-up query did not find (not yet known to be cut off: the query
        #: may run before this session has heard of their tokens).
        self._seed_absent: set[str] = set()
        self._events: zenoh.Publisher | None = None

    def source_key(self, source: str) -> str:
        ep = parse_endpoint(source)
        return self.keys.data(topic_of(self.dep.package.system, ep.component, ep.port))

    def _port_types(self) -> dict[str, str]:
        """``component.port`` -> the type its port declares, for every measured source."""
        system = self.dep.package.system
        out = {}
        for meas in self.dep.package.measurements.measurements:
            for src in meas.inputs:
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
        """Count a refused sample as the process's (dropped: malformed; else rejected)."""
        detail = f"{refusal.source}: {refusal.detail}"
        if refusal.reason in MALFORMED:
            self.drop(refusal.reason, detail)
        else:
            self.refuse(refusal.reason, detail)

    # ---- bus (Zenoh thread): keep the newest good sample per source, compute if idle ------
    def _on_sample(self, source: str) -> Callable[[zenoh.Sample], None]:
        limit = self.limits[source]

        def callback(sample: zenoh.Sample) -> None:
            size = len(sample.payload)
            if size > limit:  # Zenoh's router stops these first: defence in depth
                detail = f"{size} bytes, more than the {limit} allowed"
                self.core.refusals.add(Refusal(source, "too_large", detail))
                return
            data = self.core.decode(source, sample.payload.to_bytes())
            if data is None:
                return  # refused and counted: the newest good sample stays pending
            att = sample.attachment
            stamp = m.unpack_stamp(att.to_bytes() if att else None) or time.time()
            with self.lock:
                self.counters.received += 1
                if source in self._pending:
                    self.counters.bump("coalesced")
                self._pending[source] = (data, stamp)
                schedule, self._scheduled = not self._scheduled, True
            if schedule and not self.loop.run_or_post(self._process):
                with self.lock:
                    self._scheduled = False

        return callback

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
        for source, (data, stamp) in batch.items():
            for c in self.core.on_sample(source, data, stamp):
                self._emit(
                    m.Measurement(name=c.name, value=c.value, stamp=time.time(), sources=c.sources)
                )

    def _emit(self, msg: m.Measurement) -> None:
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
            self.loop.post(lambda: self._availability(state.unavailable))

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
        seen since)."""
        if not leading:
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
        self.viz = open_logger(self.name)
        for meas in self.dep.package.measurements.measurements:
            self.publishers[meas.name] = session.declare_publisher(
                self.keys.ctx(meas.name),
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.INTERACTIVE_HIGH,
                express=True,
            )
        entities: list[Any] = [
            session.declare_subscriber(self.source_key(src), self._on_sample(src))
            for src in self.core.sources
        ]
        entities.append(session.declare_queryable(self.keys.ctx_all, self._on_latest))
        if self.reachability:
            self._events = session.declare_publisher(
                self.keys.events, congestion_control=zenoh.CongestionControl.BLOCK
            )
            # With history: a token that exists already is delivered too (the seed's query
            # may run before this session has heard of it, and would call it unreachable).
            entities.append(
                session.liveliness().declare_subscriber(
                    self.keys.host_alive_all, self._on_host, history=True
                )
            )
            self._seed_hosts(session)
        if self.availability:
            self.resolution = LeaderWatch(session, self.keys, "resolution")
            entities += [
                self.resolution,
                session.declare_subscriber(self.keys.state("resolution"), self._on_state),
            ]
        return entities

    def status(self) -> dict[str, Any]:
        return {"measurements": {n: msg.value for n, msg in self.latest.items()}}

    def tick(self, now: float) -> None:
        self.publish_status()

    def stopping(self) -> None:
        if self.viz:
            self.viz.close()


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
    from rra_agent.engines.launch import engine_setup, parse_engine_args

    args = parse_engine_args(arguments, argv)
    setup = engine_setup(args, NAME)
    if setup is None:
        return 2
    dep, bus, host, name = setup
    try:
        proc = ContextMonitorProcess(dep, bus, host=host, name=name)
    except (RraError, ImportError, AttributeError, ValueError) as e:
        print(f"rra monitor: {e}", file=sys.stderr)
        return 2
    return proc.run()


if __name__ == "__main__":
    sys.exit(main())


__getattr__ = _compat.renamed(__name__)  # old names, for one release (docs/api.md)
