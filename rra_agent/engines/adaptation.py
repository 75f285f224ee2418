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

Why: the leader explains each change it decides (`rra_agent.engines.explain`): a selection
names the rules that changed it (``cause``), and for each feature and CV value it changes,
the values those rules read and the rules that were overruled, and why (``why``). A standby
keeps its leader's explanations. ``rra why`` asks the leader (`Explain`) about the current
state, and the configurations the rules can reach from it.

A measurement marked as an operator's override (``rra inject measurement``) is taken only
with the fence of the live Context Monitor leader: anyone else's is refused and counted.

It never publishes a default selection over a running system: before it evaluates anything
it resumes from the system's current selection and CV values, asked from the Run-time
Resolution Engine (``GetState``), and from the newest measurements, asked from the Context
Monitor. Replicas: every replica evaluates (a hot standby) and adopts each selection its
leader publishes; only the leader publishes. Evaluations are coalesced: a flood of
measurements costs one evaluation per main-loop turn, not one per sample.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from rra_agent import _compat, trace
from rra_agent.bus import messages as m
from rra_agent.bus.client import decoded, oks
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import Refused, receive
from rra_agent.core.adaptation import AdaptationEngine, TickResult
from rra_agent.core.availability import requirements, unavailable_features
from rra_agent.core.live_conflicts import ConflictTracker, LiveConflict
from rra_agent.core.monitor import measurement_problem
from rra_agent.core.overrides import OverrideError
from rra_agent.core.reachable import reachable
from rra_agent.core.reload import carry_over, engine_for
from rra_agent.deployment import Deployment
from rra_agent.engines.base import EngineProcess
from rra_agent.engines.events import EventSink
from rra_agent.engines.explain import causes, core_why, reachable_summary, wire_why
from rra_agent.engines.leaders import LeaderWatch
from rra_agent.engines.models import deploy_bundle
from rra_agent.errors import RraError, SelectionError
from rra_agent.package.bundle import ModelBundle
from rra_agent.record.hooks import AdaptationRecorder, open_writer
from rra_agent.viz.rerun_log import Logger, open_logger

NAME = "adaptation"
#: Overrides remembered to mark the values read that were an operator's (about 25 s of one
#: override re-sent ten times a second).
OVERRIDES_KEPT = 256
_CTX = m.Codec[m.CtxMessage](m.CtxMessage)
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
_STATE = m.Codec[m.StateMessage](m.StateMessage)
_ANY = m.Codec[Any](Any)


class AdaptationEngineProcess(EngineProcess[tuple[Deployment, AdaptationEngine]]):
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
        run_dir: Path | None = None,
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
        #: The Context Monitor leader: an operator's override carries its fence.
        self.monitor: LeaderWatch | None = None
        #: Rejections as unavailable already reported: (rule, feature).
        self._unavailable_told: set[tuple[str, str]] = set()
        self._reach: tuple[Any, dict[str, Any]] | None = None
        #: The operators' overrides received: (measurement, stamp) -> who (the newest
        #: `OVERRIDES_KEPT`), so that an explanation says which value read was one.
        self.overrides: dict[tuple[str, float], str] = {}
        #: The run's record (``<run>/record/``): every call on the core (docs/recording.md).
        self.run_dir = run_dir
        self.rec: AdaptationRecorder | None = None
        #: The Resolution Engine leader's unavailable implementations, as last received.
        self._unavailable_raw: list[m.Unavailable] = []
        #: The models the Run-time Resolution Engine leader runs (this replica switches to
        #: them: `follow_models`).
        self._leader_models = dep.models

    # ---- bus (Zenoh thread) ------------------------------------------------------------
    def _on_ctx(self, sample: zenoh.Sample) -> None:
        msg = receive(sample.payload, "ctx", _CTX)
        if isinstance(msg, Refused):
            return self.drop(msg.code, f"measurement: {msg.detail}")
        problem = measurement_problem(self.declared.get(msg.name), msg.value)
        if problem is not None:  # forged on the bus: the Context Monitor never sends these
            self.refuse(problem[0], f"measurement {msg.name}: {problem[1]}")
            return
        if msg.override and not self._from_monitor(msg):
            return
        if msg.override:
            self._note_override(msg)
        with self.lock:
            self.counters.received += 1
            self.measurements[msg.name] = (msg.value, msg.stamp)
            self.changed.add(msg.name)
            if self.rec is not None:
                self.rec.received(msg)
            schedule, self._scheduled = not self._scheduled, True
        if schedule and not self.loop.run_or_post(self._evaluate_posted):
            with self.lock:
                self._scheduled = False

    def _note_override(self, msg: m.Measurement) -> None:
        with self.lock:
            self.overrides[(msg.name, msg.stamp)] = msg.override
            while len(self.overrides) > OVERRIDES_KEPT:
                del self.overrides[next(iter(self.overrides))]

    def _from_monitor(self, msg: m.Measurement) -> bool:
        """An override comes only from the live Context Monitor leader (its fence)."""
        if self.monitor is not None and self.monitor.holds(msg.fence):
            return True
        who = msg.fence.leader if msg.fence else "nobody"
        self.refuse("forged override", f"override of {msg.name} by {msg.override} from {who}")
        return False

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
            self.loop.post(lambda: self._resolution_state(state))

    def _resolution_state(self, state: m.EngineState) -> None:
        """The leader's models first (a reload), then what is unavailable."""
        self.follow_models(state.models)
        self._availability(state.unavailable)

    def _availability(self, unavailable: list[m.Unavailable]) -> None:
        """Decide again without the features that need an unavailable implementation."""
        if unavailable != self._unavailable_raw and self.rec is not None:
            self.rec.avail(unavailable)
        self._unavailable_raw = list(unavailable)
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
            self.follow_models(state.models)
            self._adopt(state.selection, state.cv, "resumed from the system's state")
            self._availability(state.unavailable)
            self._set_forced(state.forced)
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
            for answer in oks(self.session.get(
                self.keys.engine_ctl("resolution"), payload=_ANY.encode(m.GetState()), timeout=1.0
            )):  # fmt: skip
                if answer.result:
                    with contextlib.suppress(msgspec.ValidationError):
                        return msgspec.convert(answer.result, m.EngineState)
            if time.monotonic() > deadline:
                print(f"rra {self.name}: no Run-time Resolution Engine answered", file=sys.stderr)
                return None
            self.loop.cycle(0.1)
        return None

    def _ask_measurements(self) -> None:
        assert self.session is not None
        for msg in decoded(self.session.get(self.keys.ctx_all, timeout=1.0), _CTX):
            if measurement_problem(self.declared.get(msg.name), msg.value) is not None:
                continue  # not a monitor's answer
            with self.lock:
                known = self.measurements.get(msg.name)
                if known is None or known[1] < msg.stamp:
                    self.measurements[msg.name] = (msg.value, msg.stamp)

    def _adopt(self, selection: list[str], cv: dict[str, float], why: str) -> None:
        error = ""
        try:
            self.engine.adopt(selection, cv)
        except SelectionError as e:
            error = str(e)
            self.refuse("selection", f"{why}: {e}")
        if self.rec is not None:
            self.rec.adopt(selection, cv, why, error)

    def _set_forced(self, forced: dict[str, bool]) -> None:
        if self.rec is not None and forced != self.engine.forced:
            self.rec.forced(forced)
        self.engine.forced = dict(forced)

    def _follow(self, msg: m.Selection) -> None:
        """A selection of the leader: a standby keeps the same state. Only the leader this
        replica's election sees is followed (a forged selection is refused)."""
        assert msg.fence is not None
        if self.election is None or self.leading:
            return
        if msg.fence.term != self.election.leader:
            self.refuse("selection from a non-leader", f"selection {msg.seq} of {msg.fence.leader}")
            return
        if msg.models != self.dep.models and not self.follow_models(msg.models):
            return  # models it cannot get: it keeps its own state (refused and counted)
        self._adopt(msg.features, msg.cv, f"selection {msg.seq} of {msg.fence.leader}")
        self.engine.note(core_why(w) for w in msg.why)
        self._set_forced(msg.forced)
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
        result = self.engine.tick(now, values, changed=changed, explain=self.leading)
        seq = self.seq
        try:
            return self._decided(result, values, now, force)
        finally:
            if self.rec is not None:
                self._record_tick(result, values, changed, force, seq)

    def _record_tick(
        self, result: TickResult, values: dict, changed: set[str], force: bool, seq: int
    ) -> None:
        assert self.rec is not None
        self.rec.tick(
            result.now, values, changed, force=force, lead=self.leading,
            selection=result.selection, cv=result.cv,
            fired=[f.rule if f.ruleset is None else f"{f.ruleset}.{f.rule}" for f in result.fired],
            seq=self.seq if self.seq != seq else 0,
        )  # fmt: skip

    def _decided(self, result: TickResult, values: dict, now: float, force: bool) -> TickResult:
        """The leader publishes what it decided (a change, an event, or a heartbeat due)."""
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
        why = [wire_why(w, self.overrides) for w in result.why]
        cause = causes(why)
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
                why=why,
                models=self.dep.models,
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
                why=why,
            )

    def _send(self, msg: m.Selection | m.ConflictReport) -> None:
        if self.publisher is not None:
            self.publisher.put(_SEL.encode(msg))

    # ---- operators' overrides (main thread) --------------------------------------------
    def serve(self, request: m.EngineRequest) -> m.Reply:
        match request:
            case m.ForceFeatures(features=features, operator=who):
                return self.force(dict(features), who)
            case m.Explain():
                return self.explain(request)
            case m.PrepareModels(bundle=bundle):
                return self.prepare(bundle)
        return super().serve(request)

    def explain(self, request: m.Explain) -> m.Reply:
        """Why the current features and CV values are what they are (``rra why``)."""
        if not self.resumed:
            return m.Err(message=f"{self.name} has not resumed yet", code="not_leader")
        try:
            why = self.engine.why(request.targets or None)
        except KeyError as e:
            return m.Err(message=str(e.args[0]), code="unknown")
        result: dict[str, Any] = {
            "why": [msgspec.to_builtins(wire_why(w, self.overrides)) for w in why],
            "selection": sorted(self.engine.selection),
            "forced": _choices(self.engine.forced),
        }
        if request.reachable:
            result["reachable"] = self._reachable()
        return m.Ok(result=result)

    def _reachable(self) -> dict[str, Any]:
        """The configurations the rules can reach from the current one (cached per state)."""
        e = self.engine
        key = (e.selection, tuple(sorted(e.forced.items())), frozenset(e.unavailable))
        if self._reach is None or self._reach[0] != key:
            pkg = self.dep.package
            assert pkg.adaptation is not None
            found = reachable(pkg.features, self.dep.selection, pkg.adaptation, e.selection,
                              forced=e.forced, unavailable=e.unavailable.keys())  # fmt: skip
            self._reach = (key, reachable_summary(found))
        return self._reach[1]

    def force(self, features: dict[str, str], who: str) -> m.Reply:
        """Force (or release) run-time features, then evaluate and publish at once."""
        if not self.leading or not self.resumed:
            return m.Err(message=f"{self.name} does not lead", code="not_leader")
        try:
            self.engine.force(features)
        except OverrideError as e:
            self.refuse("override", str(e))
            if self.rec is not None:
                self.rec.force(features, who, str(e))
            return m.Err(message=str(e), code="refused")
        if self.rec is not None:
            self.rec.force(features, who, "")
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
        writer = open_writer(self.run_dir, self.name, self.role, self.dep, self.host)
        self.rec = AdaptationRecorder(writer) if writer is not None else None
        self.viz = open_logger(self.name)
        self.events = EventSink(session, self.keys.events, None)
        self.publisher = session.declare_publisher(
            self.keys.selection,
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
            express=True,
        )
        self.resolution = LeaderWatch(session, self.keys, "resolution")
        self.monitor = LeaderWatch(session, self.keys, "monitor")
        return [
            self.publisher,
            self.events.publisher,
            self.resolution,
            self.monitor,
            session.declare_subscriber(self.keys.ctx_all, self._on_ctx),
            session.declare_subscriber(self.keys.selection, self._on_selection),
            session.declare_subscriber(self.keys.state("resolution"), self._on_state),
        ]

    def on_leadership(self, leading: bool) -> None:
        if self.rec is not None:
            self.rec.lead(leading, self.fence)
        if leading:
            self.follow_models(self._leader_models)  # never decide under other models
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
            "models": self.dep.models,
        }

    def extra_counters(self) -> dict[str, int]:
        return {"selections": self.seq}

    def stopping(self) -> None:
        self.publisher = None
        self.events = None
        if self.viz:
            self.viz.close()
        if self.rec is not None:
            self.rec.writer.close(end=time.time())

    # ---- reload: new models (``rra reload``, docs/recording.md) -------------------------------
    def load_models(self, bundle: ModelBundle) -> tuple[Deployment, AdaptationEngine]:
        """These models and their compiled rules."""
        dep = deploy_bundle(bundle, self.dep)
        if dep.package.adaptation is None:
            raise RraError("the new models have no adaptation model")
        return dep, engine_for(dep.package.features, dep.selection, dep.package.adaptation)

    def follow_models(self, digest: str) -> bool:
        """As every engine (`EngineProcess.follow_models`), remembering them as its leader's:
        while it cannot switch to them it decides nothing new (and only while it does not
        lead)."""
        if digest:
            self._leader_models = digest
        return super().follow_models(digest)

    def switch_models(self, loaded: tuple[Deployment, AdaptationEngine]) -> None:
        """Continue on new models: the core state carried over (`carry_over`), then an
        evaluation under them at once (the leader publishes it)."""
        dep, engine = loaded
        previous = self.dep.models
        self.needs = requirements(dep.package.features, dep.package.runtime)
        gone = {(u.component, u.implementation): u.reason for u in self._unavailable_raw}
        self.engine = carry_over(self.engine, engine, unavailable_features(self.needs, gone))
        self.dep = dep
        self.declared = {meas.name: meas for meas in dep.package.measurements.measurements}
        self._prepared.clear()
        self._unavailable_told.clear()
        if self.rec is not None:
            self.rec.reload(dep.models, previous)
        print(f"rra {self.name}: models {dep.models} (were {previous})", flush=True)
        if self.resumed:
            self.evaluate(force=True)


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
    from rra_agent.engines.launch import engine_setup, parse_engine_args, record_dir

    args = parse_engine_args(arguments, argv)
    setup = engine_setup(args, NAME)
    if setup is None:
        return 2
    dep, bus, host, name = setup
    try:
        proc = AdaptationEngineProcess(
            dep, bus, host=host, name=name, tick=args.tick, heartbeat=args.heartbeat,
            run_dir=record_dir(args),
        )  # fmt: skip
    except ValueError as e:
        print(f"rra adaptation: {e}", file=sys.stderr)
        return 2
    return proc.run()


if __name__ == "__main__":
    sys.exit(main())


__getattr__ = _compat.renamed(__name__)  # old names, for one release (docs/api.md)
