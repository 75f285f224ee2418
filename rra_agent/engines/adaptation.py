"""The Adaptation Engine process (paper Sec. III-D).

It listens to every Context Dependent Measurement on ``rra/<system>/ctx/*``, evaluates the
Adaptation Model with the pure engine (`rra_agent.core.adaptation.AdaptationEngine`) on each new
measurement (rules with ``period 0``) and periodically (rules with a period, every ``tick``
seconds), and publishes the run-time feature selection and the Continuous Variability values on
``rra/<system>/selection``: at once when they change, and as a heartbeat every
``heartbeat`` seconds. Each selection names its cause (the rules that fired and the stamps of
the measurements they read) and carries the fence of the leader that decided it.

Run-time conflicts (two rules whose latest wishes on one target differ) are adaptation
events: a `ConflictReport` on ``selection`` and an `AdaptationEvent` of kind ``conflict`` on
``events`` (the resolution engine writes it to ``events.jsonl``), with a log line, once when
a conflict starts and once when it ends; every `Selection` carries the conflicts in force.

Operators force run-time features on or off (``rra select``, `ForceFeatures` on
``engine/adaptation/ctl``): recorded as an ``override`` event, respected by the rules until
released, and carried in every `Selection` (``forced``), which the Run-time Resolution
Engine keeps in its state: a restarted Adaptation Engine resumes with them.

It never publishes a default selection over a running system: before it evaluates anything
it resumes from the system's current selection and CV values, asked from the Run-time
Resolution Engine (``GetState``), and from the newest measurements, asked from the Context
Monitor. Replicas: every replica evaluates (a hot standby) and adopts each selection its
leader publishes; only the leader publishes. Evaluations are coalesced: a flood of
measurements costs one evaluation per main-loop turn, not one per sample.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import msgspec
import zenoh

from rra_agent import _compat, trace
from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import Refused, receive
from rra_agent.core.adaptation import AdaptationEngine, TickResult
from rra_agent.core.availability import requirements, unavailable_features
from rra_agent.core.live_conflicts import ConflictTracker, LiveConflict
from rra_agent.core.monitor import measurement_problem
from rra_agent.core.overrides import OverrideError
from rra_agent.deployment import Deployment
from rra_agent.engines.base import EngineProcess
from rra_agent.engines.events import EventSink
from rra_agent.engines.leaders import LeaderWatch
from rra_agent.errors import SelectionError
from rra_agent.viz.rerun_log import Logger, open_logger

NAME = "adaptation"
_CTX = m.Codec[m.CtxMessage](m.CtxMessage)
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
_STATE = m.Codec[m.StateMessage](m.StateMessage)
_REPLY = m.Codec[m.Reply](m.Reply)
_ANY = m.Codec[Any](Any)


class AdaptationEngineProcess(EngineProcess):
    role = NAME

    def __init__(
        self,
        dep: Deployment,
        bus: BusConfig,
        *,
        host: str = "local",
        name: str = NAME,
        tick: float = 0.05,
        heartbeat: float = 1.0,
        resume_timeout: float = 60.0,
    ) -> None:
        if dep.package.adaptation is None:
            raise ValueError(f"package {dep.package.name!r} has no adaptation model")
        super().__init__(dep, bus, host=host, name=name)
        self.tick_period = tick
        self.heartbeat = heartbeat
        self.resume_timeout = resume_timeout
        self.engine = AdaptationEngine(dep.package.features, dep.selection, dep.package.adaptation)
        self.measurements: dict[str, tuple[object, float]] = {}
        #: The measurements of the model: a value on ``ctx/*`` is checked against its own.
        self.declared = {meas.name: meas for meas in dep.package.measurements.measurements}
        self.changed: set[str] = set()
        self.seq = 0
        self.last_sent = 0.0
        #: Resumed from the running system: only then does this replica evaluate.
        self.resumed = False
        self._scheduled = False
        self._floor = 0
        self.publisher: zenoh.Publisher | None = None
        self.viz: Logger | None = None  # Rerun, when RRA_RERUN says so
        #: The conflicts in force as announced (the leader's; a standby adopts them).
        self.conflicts = ConflictTracker()
        self.events: EventSink | None = None
        #: Feature -> the implementations it launches (failure as context), and the
        #: Run-time Resolution Engine leader whose state says which are unavailable.
        self.needs = requirements(dep.package.features, dep.package.runtime)
        self.resolution: LeaderWatch | None = None
        #: Rejections as unavailable already reported: (rule, feature).
        self._unavailable_told: set[tuple[str, str]] = set()

    # ---- bus (Zenoh thread) ------------------------------------------------------------
    def _on_ctx(self, sample: zenoh.Sample) -> None:
        msg = receive(sample.payload, "ctx", _CTX)
        if isinstance(msg, Refused):
            return self.drop(msg.code, f"measurement: {msg.detail}")
        problem = measurement_problem(self.declared.get(msg.name), msg.value)
        if problem is not None:  # forged on the bus: the Context Monitor never sends these
            self.refuse(problem[0], f"measurement {msg.name}: {problem[1]}")
            return
        with self.lock:
            self.counters.received += 1
            self.measurements[msg.name] = (msg.value, msg.stamp)
            self.changed.add(msg.name)
            schedule, self._scheduled = not self._scheduled, True
        if schedule and not self.loop.run_or_post(self._evaluate_posted):
            with self.lock:
                self._scheduled = False

    def _on_selection(self, sample: zenoh.Sample) -> None:
        msg = receive(sample.payload, "selection", _SEL)
        if isinstance(msg, Refused):
            return self.drop(msg.code, f"selection: {msg.detail}")
        if not isinstance(msg, m.Selection) or msg.fence is None:
            return
        if self.election is not None and msg.fence.instance == self.election.instance:
            return  # its own
        # The leader follows nobody: it drops the others' selections (forged ones, or a
        # deposed leader's) here rather than waking its main loop for each, which would
        # keep the next measurement from being evaluated inline. A replica stepping down
        # meanwhile catches up with its new leader's next selection (a heartbeat at least).
        if not self.leading:
            self.loop.post(lambda: self._follow(msg))

    def _on_state(self, sample: zenoh.Sample) -> None:
        """The Run-time Resolution Engine leader's state: which implementations are
        unavailable (only its live leader's state counts)."""
        state = self.leader_state(sample, self.resolution)
        if state is not None:
            self.loop.post(lambda: self._availability(state.unavailable))

    def _availability(self, unavailable: list[m.Unavailable]) -> None:
        """Decide again without the features that need an unavailable implementation."""
        gone = {(u.component, u.implementation): u.reason for u in unavailable}
        if self.engine.set_unavailable(unavailable_features(self.needs, gone)):
            self._unavailable_told.clear()
            if self.resumed:
                self.evaluate(force=True)

    # ---- resuming and following (main thread) -------------------------------------------
    def starting(self) -> None:
        """Resume from the running system before taking part in the election."""
        state = self._ask_state()
        if state is not None:
            self._adopt(state.selection, state.cv, "resumed from the system's state")
            self._availability(state.unavailable)
            self.engine.forced = dict(state.forced)
            self.conflicts.adopt(_live(c) for c in state.conflicts)
            if state.selection_fence is not None:
                self._floor = state.selection_fence.epoch
                self.seq = state.applied
        self._ask_measurements()
        self.resumed = True

    def epoch_floor(self) -> int:
        return self._floor

    def _ask_state(self) -> m.EngineState | None:
        """The Run-time Resolution Engine's state; waits for it (it deploys at start)."""
        assert self.session is not None
        deadline = time.monotonic() + self.resume_timeout
        while not self.loop.stopping:
            for reply in self.session.get(
                self.keys.engine_ctl("resolution"), payload=_ANY.encode(m.GetState()), timeout=1.0
            ):
                if reply.ok is None:
                    continue
                try:
                    answer = _REPLY.decode(reply.ok.payload.to_bytes())
                    if isinstance(answer, m.Ok) and answer.result:
                        return msgspec.convert(answer.result, m.EngineState)
                except (msgspec.DecodeError, msgspec.ValidationError):
                    continue
            if time.monotonic() > deadline:
                print(f"rra {self.name}: no Run-time Resolution Engine answered", file=sys.stderr)
                return None
            self.loop.cycle(0.1)
        return None

    def _ask_measurements(self) -> None:
        assert self.session is not None
        for reply in self.session.get(self.keys.ctx_all, timeout=1.0):
            if reply.ok is None:
                continue
            try:
                msg = _CTX.decode(reply.ok.payload.to_bytes())
            except (msgspec.DecodeError, msgspec.ValidationError):
                continue
            if measurement_problem(self.declared.get(msg.name), msg.value) is not None:
                continue  # not a monitor's answer
            with self.lock:
                known = self.measurements.get(msg.name)
                if known is None or known[1] < msg.stamp:
                    self.measurements[msg.name] = (msg.value, msg.stamp)

    def _adopt(self, selection: list[str], cv: dict[str, float], why: str) -> None:
        try:
            self.engine.adopt(selection, cv)
        except SelectionError as e:
            self.refuse("selection", f"{why}: {e}")

    def _follow(self, msg: m.Selection) -> None:
        """A selection of the leader: a standby keeps the same state. Only the leader this
        replica's election sees is followed (a forged selection is refused)."""
        assert msg.fence is not None
        if self.election is None or self.leading:
            return
        if msg.fence.term != self.election.leader:
            self.refuse("selection from a non-leader", f"selection {msg.seq} of {msg.fence.leader}")
            return
        self._adopt(msg.features, msg.cv, f"selection {msg.seq} of {msg.fence.leader}")
        self.engine.forced = dict(msg.forced)
        self.conflicts.adopt(_live(c) for c in msg.conflicts)
        self.seq = max(self.seq, msg.seq)

    # ---- evaluation (serialised by the main loop: its thread, or inline when idle) -----
    def _evaluate_posted(self) -> None:
        with self.lock:
            self._scheduled = False
        self.evaluate()

    def evaluate(self, *, force: bool = False) -> TickResult | None:
        if not self.resumed:
            return None
        with self.lock:
            values, changed = dict(self.measurements), self.changed
            self.changed = set()
        now = time.time()
        result = self.engine.tick(now, values, changed=changed)
        if not self.leading:
            return result
        started: list[LiveConflict] = []
        ended: list[tuple[LiveConflict, float]] = []
        if result.active or self.conflicts.known:
            context = {n: v for n, (v, _) in values.items()}
            started, ended = self.conflicts.update(result.active, now, context)
        if force or result.changed or started or ended or now - self.last_sent >= self.heartbeat:
            if result.changed:
                trace.mark("adaptation:selection", ",".join(sorted(result.selection)))
            for c, lasted in ended:
                self._conflict_event(c, now, lasted)
            for c in started:
                self._conflict_event(c, now, None)
            self.publish(result, values, now)
        self._tell_unavailable(result)
        return result

    def _tell_unavailable(self, result: TickResult) -> None:
        """An ``unavailable`` event for each rule asking for an unavailable feature (once
        per rule and feature until the availability changes): the configuration stays."""
        for r in result.rejected:
            key = (r.rule, r.unavailable)
            if not r.unavailable or key in self._unavailable_told:
                continue
            self._unavailable_told.add(key)
            text = f"rule {r.rule}: {r.action}: {r.reason}; the configuration stays"
            print(f"rra {self.name}: {text}", flush=True)
            self._emit("unavailable", text, level="warning")

    def _conflict_event(self, c: LiveConflict, now: float, lasted: float | None) -> None:
        """A conflict started (``lasted`` None) or ended: report, event, log line."""
        report = _report(c, now, lasted)
        self._send(report)
        if lasted is None:
            text = f"conflict started: {c.describe()}"
        else:
            text = (
                f"conflict ended after {lasted:.3f} s: rules {c.winner} and {c.loser} on {c.target}"
            )
        print(f"rra {self.name}: {text}", flush=True)
        self._emit(
            "conflict",
            text,
            level="warning" if lasted is None else "info",
            cause=[
                m.FiredRule(rule=r, action=c.actions.get(r, ""), where=c.where.get(r, ""))
                for r in (c.winner, c.loser)
            ],
            context=dict(c.context),
        )

    def _emit(self, kind: str, text: str, **fields: Any) -> None:
        """An adaptation event of this engine (the resolution engine logs it)."""
        if self.events is None:
            return
        event = m.AdaptationEvent(
            stamp=time.time(),
            kind=kind,
            message=text,
            source=self.name,
            fence=self.fence,
            selection=self.seq,
            **fields,
        )
        self.events.emit(event)
        if self.viz:
            self.viz.event(event)

    def publish(self, result: TickResult, values: dict, now: float) -> None:
        self.seq += 1
        cause = [
            m.FiredRule(
                rule=f.rule if f.ruleset is None else f"{f.ruleset}.{f.rule}",
                action=f.action,
                where=f"{f.span.file}:{f.span.line}:{f.span.col}" if f.span else "",
                reads={n: values[n][1] for n in f.reads if n in values},
            )
            for f in result.fired
        ]
        self._send(
            m.Selection(
                seq=self.seq,
                stamp=now,
                deployment=sorted(self.dep.selection),
                features=sorted(result.selection),
                cv=dict(result.cv),
                changed=result.changed,
                cause=cause,
                rejected=[f"{r.rule}: {r.action}: {r.reason}" for r in result.rejected],
                fence=self.fence,
                forced=dict(self.engine.forced),
                conflicts=[_report(c, c.since, None) for c in self.conflicts.current],
            )
        )
        self.last_sent = now
        if self.viz:
            self.viz.selection(
                result.selection,
                result.cv,
                now,
                universe=self.dep.package.features.runtime_features(),
                fired=[f"{c.rule}: {c.action}" for c in cause],
                changed=result.changed,
            )

    def _send(self, msg: m.Selection | m.ConflictReport) -> None:
        if self.publisher is not None:
            self.publisher.put(_SEL.encode(msg))

    # ---- operators' overrides (main thread) --------------------------------------------
    def serve(self, request: m.EngineRequest) -> m.Reply:
        match request:
            case m.ForceFeatures(features=features, operator=who):
                return self.force(dict(features), who)
        return super().serve(request)

    def force(self, features: dict[str, str], who: str) -> m.Reply:
        """Force (or release) run-time features, then evaluate and publish at once."""
        if not self.leading or not self.resumed:
            return m.Err(message=f"{self.name} does not lead", code="not_leader")
        try:
            self.engine.force(features)
        except OverrideError as e:
            self.refuse("override", str(e))
            return m.Err(message=str(e), code="refused")
        result = self.evaluate(force=True)
        forced = self.engine.forced
        asked = ", ".join(f"{f} {v}" for f, v in sorted(features.items()))
        now_ = ", ".join(f"{f} {'on' if on else 'off'}" for f, on in sorted(forced.items()))
        text = f"operator {who or 'unknown'} forced {asked}; forced now: {now_ or 'none'}"
        print(f"rra {self.name}: {text}", flush=True)
        self._emit("override", text)
        selection = sorted(result.selection) if result else sorted(self.engine.selection)
        return m.Ok(result={"forced": _choices(forced), "selection": selection})

    # ---- engine hooks ------------------------------------------------------------------
    def declare(self, session: zenoh.Session) -> list[Any]:
        self.viz = open_logger(self.name)
        self.events = EventSink(session, self.keys.events, None)
        self.publisher = session.declare_publisher(
            self.keys.selection,
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
            express=True,
        )
        self.resolution = LeaderWatch(session, self.keys, "resolution")
        return [
            self.publisher,
            self.events.publisher,
            self.resolution,
            session.declare_subscriber(self.keys.ctx_all, self._on_ctx),
            session.declare_subscriber(self.keys.selection, self._on_selection),
            session.declare_subscriber(self.keys.state("resolution"), self._on_state),
        ]

    def on_leadership(self, leading: bool) -> None:
        if leading:
            self.evaluate(force=True)  # the system learns the new leader's fence at once

    def tick(self, now: float) -> None:
        self.evaluate()
        self.publish_status()

    def status(self) -> dict[str, Any]:
        return {
            "selection": sorted(self.engine.selection),
            "cv": self.engine.cv,
            "seq": self.seq,
            "resumed": self.resumed,
            "forced": _choices(self.engine.forced),
            "unavailable": dict(self.engine.unavailable),
            "conflicts": [
                msgspec.to_builtins(_report(c, c.since, None)) for c in self.conflicts.current
            ],
        }

    def extra_counters(self) -> dict[str, int]:
        return {"selections": self.seq}

    def stopping(self) -> None:
        self.publisher = None
        self.events = None
        if self.viz:
            self.viz.close()


def _report(c: LiveConflict, now: float, lasted: float | None) -> m.ConflictReport:
    return m.ConflictReport(
        stamp=now,
        target=c.target,
        rules=[c.winner, c.loser],
        resolution=f"{c.kind}: {c.winner} wins (written later)",
        state="started" if lasted is None else "ended",
        id=c.id,
        kind=c.kind,
        wants=dict(c.wants),
        actions=dict(c.actions),
        where=dict(c.where),
        since=c.since,
        context=dict(c.context),
        duration=lasted,
    )


def _live(r: m.ConflictReport) -> LiveConflict:
    return LiveConflict(
        id=r.id,
        kind=r.kind,
        target=r.target,
        winner=r.rules[0] if r.rules else "",
        loser=r.rules[1] if len(r.rules) > 1 else "",
        wants=dict(r.wants),
        actions=dict(r.actions),
        where=dict(r.where),
        since=r.since,
        context=dict(r.context),
    )


def _choices(forced: dict[str, bool]) -> dict[str, str]:
    return {f: "on" if on else "off" for f, on in sorted(forced.items())}


def arguments() -> argparse.ArgumentParser:
    """The command line of ``python -m rra_agent.engines.adaptation``."""
    from rra_agent.engines.launch import engine_arguments

    parser = engine_arguments("rra adaptation", __doc__)
    parser.add_argument("--tick", type=float, default=0.05, help="periodic evaluation (s)")
    parser.add_argument("--heartbeat", type=float, default=1.0, help="selection heartbeat (s)")
    return parser


def warm_up(argv: list[str]) -> None:
    """The fork server's hook (`rra_agent.engines.launch.warm_up`)."""
    from rra_agent.engines import launch

    launch.warm_up(argv, arguments)


def main(argv: list[str] | None = None) -> int:
    """``python -m rra_agent.engines.adaptation --package PKG --select F,...``."""
    from rra_agent.engines.launch import engine_setup, parse_engine_args

    args = parse_engine_args(arguments, argv)
    setup = engine_setup(args, NAME)
    if setup is None:
        return 2
    dep, bus, host, name = setup
    try:
        proc = AdaptationEngineProcess(
            dep, bus, host=host, name=name, tick=args.tick, heartbeat=args.heartbeat
        )
    except ValueError as e:
        print(f"rra adaptation: {e}", file=sys.stderr)
        return 2
    return proc.run()


if __name__ == "__main__":
    sys.exit(main())


__getattr__ = _compat.renamed(__name__)  # old names, for one release (docs/api.md)
