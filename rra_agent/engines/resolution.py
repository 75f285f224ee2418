"""The Run-time Resolution Engine process (paper Sec. III-E).

It holds the Run-time Configured System Model: the run-time selection, the Continuous
Variability values and the parameters operators set (``rra param``). That model is the
*desired state*; the host agents report the observed one.

- For each new run-time selection the Adaptation Engine leader publishes on
  ``rra/<system>/selection`` it checks the selection (its fence, every feature known and
  selectable, CV values clamped into their bounds and the active NFRs), computes the target
  model (the configured model plus the Run-time Resolution Model's transformations for the
  selected features, CV values and operators' parameters included), diffs it against the
  current model and executes the plan transactionally (`rra_agent.engines.executor`).
- A reconcile loop (`rra_agent.engines.reconcile`) compares desired and observed state
  every ``reconcile_period`` and whenever a host reports a change, and starts, re-wires and
  re-parameterises what differs, or records a failed adaptation with an event.
- Operators' parameter values are checked against their declarations, applied to the
  running node and kept in the model, so a node restarted anywhere comes back with them.

Replicas (``rra up`` starts two): the leader acts and publishes its state on
``rra/<system>/state/resolution`` after every change (`EngineState`); a standby mirrors it
and the selections, and takes over within milliseconds when the leader dies: it makes its
fence known to every host agent and node (`Claim`), continues from the mirrored model,
applies a newer selection if there is one, and reconciles. Every request carries the
leader's fence, so a leader that was frozen and resumes cannot act once its successor has.

Every plan becomes an `AdaptationEvent` (cause, steps, outcome, phase durations, the fence
and the selection's ``seq``), published and written to ``<run-dir>/events.jsonl`` with the
host agents' `NodeState` transitions. On exit the engine leaves the nodes running: the host
agents own them. Status (selection, CV values, desired and observed nodes) is served on
``rra/<system>/engine/resolution/ctl`` by the leader and on ``engine/<replica>/ctl``.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Collection
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from rra_agent import _compat, trace
from rra_agent.bus import messages as m
from rra_agent.bus.client import oks
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import Refused, receive
from rra_agent.core import resolution as r
from rra_agent.core.availability import (
    Need,
    component_needs,
    needed_by,
    requirements,
    unavailable_features,
)
from rra_agent.core.cv import clamp_cv
from rra_agent.core.effect import effective_model, in_effect
from rra_agent.core.election import Term, newer
from rra_agent.core.features import check_selection, default_runtime_selection
from rra_agent.core.plan import (
    Plan,
    SetParameters,
    diff,
    standby_subscriptions,
    subscriptions,
    wiring,
)
from rra_agent.deployment import Deployment
from rra_agent.engines.actuator import ZenohActuator
from rra_agent.engines.base import EngineProcess
from rra_agent.engines.events import EventSink, phase_durations
from rra_agent.engines.executor import Ctl, Executor, Outcome, StepFailed, UnitFailure, spec_for
from rra_agent.engines.leaders import LeaderWatch
from rra_agent.engines.models import deploy_bundle
from rra_agent.engines.reconcile import Observed, observe, takeover_plan
from rra_agent.engines.reflexes import ReflexCompiler, ReflexKeeper, Situation
from rra_agent.engines.reload import (
    changed_decls,
    commit_hosts,
    engine_replicas,
    prepare_all,
    running_view,
    system_changed,
)
from rra_agent.errors import RraError
from rra_agent.model_changes import compare
from rra_agent.models.system import (
    Component,
    ParamValue,
    RuntimeConfiguredSystemModel,
    SystemModel,
    parse_endpoint,
)
from rra_agent.package.bundle import ModelBundle
from rra_agent.record.hooks import ResolutionRecorder, open_writer
from rra_agent.record.run import keep_models, read_models
from rra_agent.viz.rerun_log import Logger, open_logger

NAME = "resolution"
#: Benchmarks only (``tools/bench_recovery.py``): wait this long before executing a plan, to
#: emulate a slower adaptation pipeline such as the paper's 0.5 s.
EMULATED_DELAY = float(os.environ.get("RRA_EMULATED_SWAP_DELAY", "0") or 0)
#: The leader republishes its state at least this often (seconds).
STATE_EVERY = 1.0
#: After a host agent appears, how long to let the adaptation react before reconciling it.
HOST_SETTLE = 0.5
#: A decision not fully in effect is tried again after this long, doubling up to
#: ``retry_after`` (seconds).
RETRY_FIRST = 0.5
#: Failed starts without a crash (timeouts, no reply) before an implementation is taken
#: as unavailable (a crash makes it unavailable at once).
TIMEOUTS_UNAVAILABLE = 3
#: A probe of an unavailable implementation waits at most this long for it to be ready.
PROBE_TIMEOUT = 5.0
#: Probes of an unavailable implementation back off up to this (seconds).
PROBE_MAX = 300.0
#: A standby keeps the events it received in the last this many seconds (at most
#: `UNLOGGED_MAX`), to log at its takeover those that came while nobody led (longer than a
#: takeover takes: the leader's lease and the standby's claim).
UNLOGGED_HORIZON = 10.0
UNLOGGED_MAX = 512
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
_EVT = m.Codec[m.EventMessage](m.EventMessage)
_STATE = m.Codec[m.StateMessage](m.StateMessage)
_REPLY = m.Codec[m.Reply](m.Reply)
_ENGINE_REQ = m.Codec[m.EngineRequest](m.EngineRequest)
_REFLEX = m.Codec[m.ReflexMessage](m.ReflexMessage)
#: How often the leader checks, besides after every change, that the reflexes the
#: configuration allows are installed (a node restarted without them, a host back).
REFLEX_SYNC = 1.0


class ResolutionEngineProcess(EngineProcess[Deployment]):
    role = NAME
    ros2_events = True  # its leader puts the events on ROS 2 (`rra_agent.engines.ros2`)
    tick_period = 0.1

    def __init__(
        self,
        dep: Deployment,
        bus: BusConfig,
        *,
        host: str = "local",
        name: str = NAME,
        run_dir: Path | None = None,
        retry_after: float = 30.0,
        start_timeout: float = 15.0,
        reconcile_period: float = 1.0,
        reflexes: bool = True,
        record: bool = True,
    ) -> None:
        super().__init__(dep, bus, host=host, name=name)
        self.run_dir = run_dir
        #: The run's record: the leader's states and the operators' commands.
        self.rec: ResolutionRecorder | None = None
        self._recording = record
        #: The digests of the models before the current ones (``rra reload --undo``), the
        #: bundles known here, and the models prepared for a reload.
        self.history: list[str] = []
        self._bundles: dict[str, ModelBundle] = {dep.models: dep.bundle} if dep.bundle else {}
        self.retry_after = retry_after
        self.start_timeout = start_timeout
        self.reconcile_period = reconcile_period
        fm = dep.package.features
        # ---- the Run-time Configured System Model (the desired state) ----
        self.selection = default_runtime_selection(fm, dep.selection)
        self.cv: dict[str, float] = dep.initial_cv()
        self.overrides: dict[str, dict[str, ParamValue]] = {}
        #: Features operators forced and the conflicts in force, as the Adaptation Engine
        #: leader publishes them with its selections (kept so that it resumes with them).
        self.forced: dict[str, bool] = {}
        self.conflicts: list[m.ConflictReport] = []
        #: The Run-time Configured System Model in effect: what the running system realises
        #: (the target of what was decided, less what failed; `rra_agent.core.effect`).
        self.runtime_model: RuntimeConfiguredSystemModel = msgspec.structs.replace(
            dep.configured, components=[], connections=[]
        )
        #: What is in effect (the running system shows it), beside what was decided.
        self.effective: frozenset[str] = self.selection
        self.effective_cv: dict[str, float] = dict(self.cv)
        #: Implementations that cannot start or keep crashing, by (component, key).
        self.unavailable: dict[Need, m.Unavailable] = {}
        self.needs = requirements(fm, dep.package.runtime)
        #: Failed starts without a crash, by implementation (see TIMEOUTS_UNAVAILABLE).
        self._timeouts: dict[Need, int] = {}
        #: Why what runs differs from the decision (the failed steps of the last plan).
        self.degraded: list[str] = []
        self._retry_at: float | None = None
        self._backoff = RETRY_FIRST
        #: The implementation a probe is trying now (on its own thread), if any.
        self._probing: Need | None = None
        self._stamp = time.time()
        self.applied = 0
        self.selection_fence: Term | None = None
        self.version = 0
        # ---- what this replica knows of the running system ----
        self.observed: dict[str, m.NodeState] = {}
        #: Events received while standing by, with when (`_log_unlogged`).
        self._unlogged: deque[tuple[float, m.AdaptationEvent | m.NodeState]] = deque(
            maxlen=UNLOGGED_MAX
        )
        #: Hosts whose agent's liveliness token this replica sees (a partition hides it).
        self.present: set[str] = set()
        self.rerun: dict[str, Any] = _rerun_config()
        self.unreachable: set[str] = set()
        #: Nodes whose live configuration is known to match: name -> pid.
        self.verified: dict[str, int] = {}
        self.deployed = False
        #: This leader continues a deployment made before (the state it took over or saved
        #: says so): its first reconciliation adopts, it does not deploy.
        self.continues = False
        self.mirror: m.EngineState | None = None
        self.latest: m.Selection | None = None
        #: The selection last acted on (each is acted on once; a retry clears it).
        self._taken: m.Selection | None = None
        self._waiting_for_claim = False
        #: The Adaptation Engine's leader: whose selections count.
        self.adaptation: LeaderWatch | None = None
        self._next_reconcile = 0.0
        self._reconcile_soon = False
        self.seq = 0
        self.viz: Logger | None = None  # Rerun, when RRA_RERUN says so
        self.sink: EventSink | None = None
        self._state_pub: zenoh.Publisher | None = None
        self._state_sent = 0.0
        #: Reflexes: decisions compiled into the nodes that switch (`engines.reflexes`).
        settings = dep.package.manifest.reflexes
        self.reflexes = ReflexKeeper(
            ReflexCompiler(dep), self._reflex_send, self._reflex_event, self._spec_of,
            enabled=reflexes and settings.enabled, confirm_s=settings.confirm_ms / 1000.0,
            log=lambda text: print(f"rra {self.name}: {text}", flush=True), refuse=self.refuse,
        )  # fmt: skip
        self._reflexes_synced = 0.0

    # ---- the model side (pure, on the main thread) ---------------------------------------
    def target(self, selection: frozenset[str], cv: dict[str, float]) -> SystemModel:
        pkg = self.dep.package
        model = r.resolve_runtime(self.dep.configured, pkg.runtime, pkg.features, selection, cv)
        return r.with_parameters(model, self.overrides)

    def standby_specs(self, target: SystemModel) -> list[m.NodeSpec]:
        """Run-time components with the ``standby`` or ``hot-standby`` strategy not in
        ``target``: pre-start them wired as the configured model connects them to what runs."""
        running = {c.name for c in target.components}
        rep = self.dep.package.runtime.replacement
        standby = [
            c
            for c in r.with_parameters(self.dep.configured, self.overrides).components
            if c.name not in running and rep.pre_started(c.name)
        ]
        return self._specs(self.dep.configured, standby)

    def _specs(self, model: SystemModel, components: list[Component]) -> list[m.NodeSpec]:
        """The specs that run ``components`` wired as ``model`` connects them."""
        subs = subscriptions(model)
        path = (str(self.dep.package.root),)
        held = self.standby_inputs
        wired = {c.name: wiring(c, subs) for c in components}
        return [
            spec_for(
                self.keys, c, wired[c.name]["inputs"], wired[c.name]["outputs"],
                default_host=self.host, path=path, standby=held.get(c.name),
            )
            for c in components
        ]  # fmt: skip

    @property
    def standby_inputs(self) -> dict[str, dict[str, tuple[str, ...]]]:
        """What each consumer listens to in advance: the outputs of the hot standbys."""
        configured = self.dep.configured
        rep = self.dep.package.runtime.replacement
        hot = [c.name for c in configured.components if rep.hot(c.name)]
        return standby_subscriptions(configured, hot)

    @property
    def hosts(self) -> list[str]:
        return sorted({c.host or self.host for c in self.dep.configured.components})

    def reachable(self, host: str) -> bool:
        """Whether ``host``'s agent can be asked now (its token is seen here)."""
        return host in self.present

    # ---- bus callbacks (Zenoh thread) ----------------------------------------------------
    def _on_selection(self, sample: zenoh.Sample) -> None:
        msg = receive(sample.payload, "selection", _SEL)
        if isinstance(msg, Refused):
            return self.drop(msg.code, f"selection: {msg.detail}")
        self.counters.received += 1
        if isinstance(msg, m.Selection):
            if msg.changed:
                trace.mark("resolution:selection", ",".join(msg.features))
            with self.lock:
                if self.latest is not None and self.latest is not self._taken and self.leading:
                    self.counters.bump("coalesced")  # a newer one came first: it wins
                self.latest = msg
            if self.leading:  # a standby only keeps it (it acts on it when it takes over)
                self.loop.post(self._take_latest)

    def _on_state(self, sample: zenoh.Sample) -> None:
        state = receive(sample.payload, "state", _STATE)
        if isinstance(state, Refused):
            return self.drop(state.code, f"engine state: {state.detail}")
        if self.election is None or state.fence.instance != self.election.instance:
            self.loop.post(lambda: self._mirror(state))

    def _on_event(self, sample: zenoh.Sample) -> None:
        try:
            msg = _EVT.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        if isinstance(msg, m.NodeState):
            self.loop.post(lambda: self._node_state(msg))
        elif not msg.source.startswith(NAME):  # host agents' and the monitor's events
            self.loop.post(lambda: self._record(msg))

    def _record(self, ev: m.AdaptationEvent) -> None:
        if self.leading and self.sink is not None:
            self.sink.record(ev)
            if self.viz:
                self.viz.event(ev)
        else:
            self._unlogged.append((time.monotonic(), ev))
        if ev.injection is not None:
            self._record_injection(ev.injection, ev.operator)

    def _on_host(self, sample: zenoh.Sample) -> None:
        """A host agent appeared (or came back) or went away: reconcile soon."""
        host = str(sample.key_expr).rsplit("/", 1)[-1]
        alive = sample.kind == zenoh.SampleKind.PUT

        def seen() -> None:
            (self.present.add if alive else self.present.discard)(host)
            self.unreachable = set(self.hosts) - self.present
            if not alive:
                return  # nothing can be done on it; what it misses is deferred
            # Back (or new): reconcile once the context has had its say, so a selection
            # that follows the host's return (its reachability measurement) is planned
            # first, not undone by a reconcile towards the selection of the outage.
            self._next_reconcile = min(self._next_reconcile, time.monotonic() + HOST_SETTLE)

        self.loop.post(seen)

    # ---- following the leader (main thread) ----------------------------------------------
    def _mirror(self, state: m.EngineState, *, trusted: bool = False) -> None:
        """Keep the leader's state (a standby). Only the leader this replica's election sees
        is mirrored (``trusted``: the answer of the role's endpoint before the election)."""
        if self.leading:
            return
        if not trusted and (self.election is None or state.fence.term != self.election.leader):
            self.refuse("state from a non-leader", f"engine state of {state.fence.leader}")
            return
        old = self.mirror
        if old is not None and old.fence == state.fence and state.version < old.version:
            return  # an older publication of the same leader, overtaken
        self.follow_models(state.models)
        self.history = list(state.history)
        self.mirror = state
        self.selection, self.cv = frozenset(state.selection), dict(state.cv)
        self.overrides = {n: dict(v) for n, v in state.overrides.items()}
        self._take_state(state)
        self.publish_status()

    def _take_state(self, state: m.EngineState) -> None:
        """What a published or saved state says besides the selection and the parameters."""
        self.forced, self.conflicts = dict(state.forced), list(state.conflicts)
        self.applied = state.applied
        if state.selection_fence is not None:
            self.selection_fence = state.selection_fence.term
        old = not state.stamp  # a state of a version that did not say what is in effect
        self.effective = frozenset(state.selection if old else state.effective)
        self.effective_cv = dict(state.cv if old else state.effective_cv)
        self.unavailable = {(u.component, u.implementation): u for u in state.unavailable}
        self.degraded = list(state.degraded)
        self.reflexes.mirror(state.reflexes)

    def stalled(self) -> None:
        """Re-sync the mirror from the leader at once (publications were missed)."""
        if self.leading or self.session is None:
            return

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            try:
                answer = _REPLY.decode(reply.ok.payload.to_bytes())
                if isinstance(answer, m.Ok) and answer.result:
                    state = msgspec.convert(answer.result, m.EngineState)
                    self.loop.post(lambda: self._mirror(state))
            except (msgspec.DecodeError, msgspec.ValidationError):
                pass

        self.session.get(
            self.keys.engine_ctl(NAME),
            zenoh.handlers.Callback(on_reply),
            payload=_ENGINE_REQ.encode(m.GetState()),
            timeout=1.0,
        )

    def _node_state(self, st: m.NodeState) -> None:
        if self.leading and self.sink is not None:
            self.sink.record(st)
            if self.viz:
                self.viz.node_state(st)
        else:
            self._unlogged.append((time.monotonic(), st))
        if st.node in self.verified and st.pid != self.verified[st.node]:
            del self.verified[st.node]
        prev = self.observed.get(st.node)
        self.observed[st.node] = st
        if st.state in ("STOPPED", "EXITED", "FATAL") or (prev and prev.pid != st.pid):
            self._reconcile_soon = True
        if st.state == "FATAL" and self.leading:
            self._node_failed(st)

    # ---- taking over -------------------------------------------------------------------
    def on_leadership(self, leading: bool) -> None:
        self.actuator.fence = self.fence if leading else None
        self.actuator.superseded = False
        if self.rec is not None:
            self.rec.lead(leading, self.fence)
        if not leading:
            return
        fence = self.fence
        assert fence is not None and self.election is not None
        names = [s.name for s in [*self.executor.running.values(), *self.executor.standby.values()]]
        if self.mirror is not None:
            names += [s.name for s in [*self.mirror.running, *self.mirror.standby]]
        highest = self.actuator.claim(
            fence, [h for h in self.hosts if self.reachable(h)], sorted(set(names))
        )
        if highest > fence.epoch:  # receivers know a newer leader: claim again above it
            self.election.observe_epoch(highest)
            return
        self._event("takeover", f"{self.name} leads (epoch {fence.epoch})", None)
        self._log_unlogged()
        self.reflexes.take_over()
        if self.mirror is not None and self.mirror.deployed:
            self._adopt_mirror(self.mirror)
        else:  # no leader deployed before it (or none is mirrored): the saved state, if any
            self._restore()
        self._take_latest()
        self._reconcile_soon = True
        self.publish_status()

    def _log_unlogged(self) -> None:
        """Log the events this standby received lately that the log lacks: those that came
        after the previous leader died (a killed engine's own BACKOFF among them) and
        before this one led, which nobody logged."""
        horizon = time.monotonic() - UNLOGGED_HORIZON
        recent = [ev for at, ev in self._unlogged if at >= horizon]
        self._unlogged.clear()
        written = self.sink.record_missing(recent) if self.sink is not None else []
        if self.viz is None:
            return
        for ev in written:
            if isinstance(ev, m.NodeState):
                self.viz.node_state(ev)
            else:
                self.viz.event(ev)

    def _adopt_mirror(self, state: m.EngineState) -> None:
        """Continue from the state the previous leader published."""
        self.continues = True
        self.executor.running = {s.name: s for s in state.running}
        self.executor.standby = {s.name: s for s in state.standby}
        try:
            self.runtime_model = self.target(self.effective, self.effective_cv)
        except RraError as e:
            self._event("takeover", f"cannot rebuild the model: {e}", None, level="error")
            return
        self.version = state.version
        self.deployed = True

    # ---- adaptation (main thread) --------------------------------------------------------
    def _take_latest(self) -> None:
        """Act on the newest selection received, once (a standby only keeps it)."""
        with self.lock:
            msg = self.latest
        if msg is None or msg is self._taken or not (self.leading and self.deployed):
            return
        self._taken = msg
        if msg.seq != self.applied:
            self.adapt(msg)

    def check(self, msg: m.Selection) -> tuple[frozenset[str], dict[str, float]] | None:
        """The selection and CV values to apply, or None (refused and counted)."""
        fence = msg.fence
        if fence is None:
            self.refuse("unfenced selection", f"selection {msg.seq} carries no fence")
            return None
        term = fence.term
        if not self._from_adaptation_leader(term):
            self._waiting_for_claim = True  # acted on again when a new claim shows up
            self.refuse(
                "selection from a non-leader",
                f"selection {msg.seq} names leader {fence.leader} (epoch {fence.epoch}), "
                "which does not lead the Adaptation Engine",
            )
            return None
        if not newer(term, self.selection_fence):
            self.refuse(
                "stale_fence",
                f"selection {msg.seq} from {fence.leader} (epoch {fence.epoch}): "
                f"a newer Adaptation Engine leader has decided since",
            )
            return None
        if msg.models != self.dep.models:
            self.refuse(
                "models",
                f"selection {msg.seq} from {fence.leader} was decided under models "
                f"{msg.models or '(none named)'}; this engine runs {self.dep.models}",
            )
            return None
        fm, deployment = self.dep.package.features, self.dep.selection
        runtime = set(fm.runtime_features())
        unknown = sorted(set(msg.features) - runtime - deployment)
        problems = [f"unknown or not run-time feature(s): {', '.join(unknown)}"] if unknown else []
        selection = frozenset(msg.features) - deployment
        problems += [p.message for p in check_selection(fm, deployment | selection)]
        cv, bad_cv = clamp_cv(fm, deployment | selection, msg.cv)
        if bad_cv:
            problems.append(f"no such CV attribute (or not a number): {', '.join(sorted(bad_cv))}")
        if problems:
            self.refuse(
                "invalid selection",
                f"selection {msg.seq} from {fence.leader}: {'; '.join(problems)}",
            )
            return None
        self.selection_fence = term
        return selection, {**self.cv, **cv}

    def _from_adaptation_leader(self, term: Term) -> bool:
        """The term of the live Adaptation Engine leader (`LeaderWatch.is_leader`)."""
        return self.adaptation is not None and self.adaptation.is_leader(term)

    def _post_claims_changed(self) -> None:
        self.loop.post(self._adaptation_claims_changed)

    def _adaptation_claims_changed(self) -> None:
        """A claim or member of the Adaptation Engine came or went (main thread): a
        selection refused for want of its claim is acted on again."""
        if self._waiting_for_claim:
            self._waiting_for_claim, self._taken = False, None
            self._take_latest()

    def adapt(self, msg: m.Selection) -> Outcome | None:
        checked = self.check(msg)
        if checked is None:
            return None
        selection, cv = checked
        if selection != self.selection and self.reflexes.fired:
            self.reflexes.decided(selection)
        noted = (msg.forced, msg.conflicts) != (self.forced, self.conflicts)
        self.forced, self.conflicts = dict(msg.forced), list(msg.conflicts)
        readmitted = self._readmit_forced(msg)
        if selection == self.selection and cv == self.cv and not readmitted:
            self.applied = msg.seq
            if noted:
                self._changed()
            return None  # a heartbeat, or nothing this engine acts on
        self.selection, self.cv = selection, cv
        self.applied = msg.seq
        self._backoff = RETRY_FIRST
        return self.converge(msg)

    def converge(self, msg: m.Selection | None = None) -> Outcome | None:
        """Apply the plan from what is in effect to what was decided; what fails is undone
        unit by unit, reported, and tried again with a growing backoff (the implementations
        that cannot start become unavailable: the Adaptation Engine decides without them)."""
        t_recv = time.time()
        t0 = time.perf_counter()
        try:
            target = self.target(self.selection, self.cv)
            plan = diff(self.runtime_model, target)
        except RraError as e:
            self._retry_later()
            self._changed()
            self._event("adaptation", f"cannot resolve the selection: {e}", msg,
                        level="error", outcome="failed")  # fmt: skip
            return None
        t_plan = time.perf_counter()
        trace.mark("resolution:planned", f"{len(plan.steps)} steps")
        if EMULATED_DELAY > 0 and plan.steps:
            time.sleep(EMULATED_DELAY)  # benchmarks only: a slower pipeline, like the paper's
        skip = self._unavailable_components(target)
        outcome = self.executor.execute(plan, skip=skip)
        t_end = time.perf_counter()
        self._took_effect(target, outcome)
        durations = phase_durations(
            (t for f in msg.cause for t in f.reads.values()) if msg else (),
            decided=msg.stamp if msg else t_recv,
            received=t_recv,
            plan=t_plan - t0,
            execute=t_end - t_plan,
            switch=outcome.first_switch,
        )
        retry = self._failed_units(outcome, target)
        self._changed()
        if msg is None and not outcome.applied and all(f.skipped for f in outcome.failures):
            return outcome  # a retry that could try nothing: nothing to report
        self._adaptation_event(plan, outcome, msg, durations, retry)
        if not outcome.ok:
            self._reconcile_soon = True
        return outcome

    def _took_effect(self, target: SystemModel, outcome: Outcome) -> None:
        """The effective model and what it shows, after ``outcome``."""
        pkg = self.dep.package
        effective = effective_model(
            self.runtime_model, target, outcome.failed_structure, outcome.failed_parameters
        )
        self.effective, self.effective_cv = in_effect(
            pkg.features, pkg.runtime, self.selection, self.effective, effective, target,
            self.cv, self.effective_cv,
        )  # fmt: skip
        self.runtime_model = effective
        self.degraded = [f"{', '.join(f.steps)}: {f.error}" for f in outcome.failures]
        if outcome.ok:
            self._retry_at, self._backoff = None, RETRY_FIRST
        else:
            self._retry_later()

    def _retry_later(self) -> float:
        delay = self._backoff
        self._retry_at = time.monotonic() + delay
        self._backoff = min(self._backoff * 2, self.retry_after)
        return delay

    def _adaptation_event(self, plan, outcome: Outcome, msg, durations, retry: float) -> None:
        decided = f"selection {sorted(self.selection)}"
        if outcome.ok:
            text = f"applied {decided}" + (
                f", {_actions(outcome)}" if plan.steps else " (no change to the system)"
            )
            self._event("adaptation", text, msg, outcome="ok", plan=outcome, durations=durations)
            return
        failed = "; ".join(f"{', '.join(f.steps)}: {f.error}" for f in outcome.failures)
        if outcome.applied:
            head = (
                f"adaptation partly applied ({outcome.applied} of {outcome.steps} plan steps; "
                f"{_actions(outcome)})"
            )
            kind = "partial"
        elif outcome.rolled_back:
            head, kind = "adaptation failed, rolled back", "rolled_back"
        else:
            head, kind = "adaptation failed, ROLLBACK FAILED", "failed"
        self._event(
            "adaptation",
            f"{head}: {failed}; in effect: {sorted(self.effective)}; retry in {retry:.1f} s",
            msg,
            level="error" if not outcome.applied else "warning",
            outcome=kind,
            plan=outcome,
            durations=durations,
        )

    # ---- failure as context: unavailable implementations -----------------------------------
    def _unavailable_components(self, target: SystemModel) -> set[str]:
        """Components of ``target`` whose implementation there is unavailable (or being
        probed: a plan must not start a node its probe is about to stop)."""
        out = {self._probing[0]} if self._probing is not None else set()
        for c in target.components:
            need = component_needs(self.dep.configured, c.name, c.implementation)
            if need in self.unavailable:
                out.add(c.name)
        return out

    def _failed_units(self, outcome: Outcome, target: SystemModel) -> float:
        """Learn from the units that failed: a node that crashed at start makes its
        implementation unavailable at once, one that timed out after a few tries. Returns
        the delay before the decision is tried again."""
        for failure in outcome.failures:
            for node, why in failure.nodes.items():
                self._start_failed(node, why, failure, target)
        return 0.0 if self._retry_at is None else max(0.0, self._retry_at - time.monotonic())

    def _start_failed(self, node: str, why: str, failure: UnitFailure, target: SystemModel) -> None:
        c = target.component(node) or self.dep.configured.component(node)
        if c is None or failure.skipped or why == "unavailable":
            return
        need = component_needs(self.dep.configured, node, c.implementation)
        if need is None or need in self.unavailable:
            return
        crashed = why.split(" ", 1)[0] in _CRASHED
        self._timeouts[need] = self._timeouts.get(need, 0) + 1
        if crashed or self._timeouts[need] >= TIMEOUTS_UNAVAILABLE:
            self._mark_unavailable(need, why, c.supervision.cooldown)

    def _mark_unavailable(self, need: Need, why: str, cooldown: float) -> None:
        now = time.time()
        self._timeouts.pop(need, None)
        self.unavailable[need] = m.Unavailable(
            component=need[0], implementation=need[1], reason=why, since=now,
            failures=1, probe_at=now + cooldown,
        )  # fmt: skip
        what = need[0] if not need[1] else f"{need[0]} ({need[1]})"
        features = sorted(f for f, ns in self.needs.items() if need in ns)
        self._event(
            "unavailable",
            f"{what} is unavailable: {why}; the engines decide without "
            f"{', '.join(features) or 'it'}; probe in {cooldown:g} s (or: rra retry {need[0]})",
            None,
            level="warning",
        )

    def _readmit(self, needs: set[Need], why: str) -> bool:
        gone = [n for n in needs if n in self.unavailable]
        for need in gone:
            del self.unavailable[need]
            self._timeouts.pop(need, None)
            what = need[0] if not need[1] else f"{need[0]} ({need[1]})"
            self._event("available", f"{what} is available again ({why})", None)
        if gone:
            self._retry_at, self._backoff = time.monotonic(), RETRY_FIRST
        return bool(gone)

    def _readmit_forced(self, msg: m.Selection) -> bool:
        """An operator forcing a feature on re-admits what it needs."""
        forced_on = {f for f, on in msg.forced.items() if on}
        return self._readmit(needed_by(self.needs, forced_on), "an operator forced it on")

    def retry(self, components: list[str], who: str) -> m.Reply:
        """``rra retry``: re-admit unavailable implementations (all when none is named)."""
        known = {c.name for c in self.dep.configured.components}
        unknown = sorted(set(components) - known)
        if unknown:
            return m.Err(message=f"no component {', '.join(unknown)} in {self.dep.system}",
                         code="unknown")  # fmt: skip
        needs = {n for n in self.unavailable if not components or n[0] in components}
        readmitted = sorted(n[0] for n in needs)
        self._readmit(needs, f"operator {who or 'unknown'} asked")
        self._changed()
        if needs:
            self.converge()
        return m.Ok(result={"readmitted": readmitted,
                            "unavailable": sorted(n[0] for n in self.unavailable)})  # fmt: skip

    def _probe_spec(self, need: Need) -> m.NodeSpec | None:
        """The spec a probe starts (inactive), or None when the name is taken now (another
        implementation of the component runs)."""
        component, key = need
        c = self.dep.configured.component(component)
        if c is None or component in self.executor.running or component in self.executor.standby:
            return None
        impl = c.implementations.get(key, c.implementation) if key else c.implementation
        [spec] = self._specs(self.dep.configured, [msgspec.structs.replace(c, implementation=impl)])
        return msgspec.structs.replace(spec, active=False)

    def _probe(self, need: Need, spec: m.NodeSpec) -> None:
        """Try an unavailable implementation on a thread of its own (the main loop goes on
        adapting meanwhile): start it inactive, stop it again; the result goes back to the
        main loop (`_probed`)."""
        try:
            self.actuator.start([spec], timeout=PROBE_TIMEOUT)
            self.actuator.stop([spec])
            ok, why = True, ""
        except StepFailed as e:
            ok, why = False, str(e)
        except Exception as e:  # the session closing under it at exit
            ok, why = False, f"{type(e).__name__}: {e}"
        self.loop.post(lambda: self._probed(need, ok, why))

    def _probed(self, need: Need, ok: bool, why: str) -> None:
        """A probe's result: success re-admits the implementation; failure backs the next
        probe off (doubling, up to PROBE_MAX)."""
        self._probing = None
        record = self.unavailable.get(need)
        if record is None:
            return  # re-admitted meanwhile (an operator): it is tried again anyway
        if ok:
            self._readmit({need}, "a probe started it")
        else:
            delay = min(PROBE_MAX, max(1.0, record.probe_at - record.since) * 2)
            self.unavailable[need] = msgspec.structs.replace(
                record, reason=why, failures=record.failures + 1, probe_at=time.time() + delay
            )
        self._changed()

    def _node_failed(self, st: m.NodeState) -> None:
        """A node the system needs went FATAL (it keeps crashing): its implementation is
        unavailable, so the engines decide without it."""
        if st.node not in self.executor.running:
            return
        c = self.dep.configured.component(st.node)
        spec = self.executor.running[st.node]
        need = component_needs(self.dep.configured, st.node, spec.implementation)
        if c is None or need is None or need in self.unavailable:
            return
        self._mark_unavailable(need, f"FATAL ({st.reason})", c.supervision.cooldown)
        self._changed()

    # ---- operators' parameters -----------------------------------------------------------
    def serve(self, request: m.EngineRequest) -> m.Reply:
        match request:
            case m.SetParam(node=node, params=params, reset=reset):
                if not self.leading:
                    return m.Err(message=f"{self.name} does not lead", code="not_leader")
                answer = self.set_params(node, params, reset, request)
                what = {"node": node, "params": params, "reset": reset}
                return self._recorded("param", what, "", answer)
            case m.GetState():
                return m.Ok(result=msgspec.to_builtins(self.engine_state()))
            case m.GetParams(node=node):
                if not self.leading:
                    return m.Err(message=f"{self.name} does not lead", code="not_leader")
                return self.node_params(node)
            case m.Retry(components=components, operator=who):
                if not self.leading:
                    return m.Err(message=f"{self.name} does not lead", code="not_leader")
                return self._recorded("retry", {"components": components}, who,
                                      self.retry(list(components), who))  # fmt: skip
            case m.Reload():
                return self._recorded("reload", {"undo": request.undo, "base": request.base},
                                      request.operator, self.reload(request))  # fmt: skip
            case m.GetModels(digest=digest):
                return self.get_models(digest)
            case m.PrepareModels(bundle=bundle):
                return self.prepare(bundle)
        return super().serve(request)

    def _no_component(self, node: str) -> m.Err:
        self.refuse("param", f"no component {node!r}")
        names = ", ".join(sorted(c.name for c in self.dep.configured.components))
        return m.Err(
            message=f"no node {node!r} in system {self.dep.system!r} (its nodes: {names})",
            code="unknown",
        )

    def node_state(self, node: str) -> str:
        """``running``, ``standby`` (started, inactive) or ``stopped``."""
        if node in self.executor.standby:
            return "standby"
        return "running" if node in self.executor.running else "stopped"

    def node_params(self, node: str) -> m.Reply:
        """``GetParams``: the values a node runs with, or, not running, will start with (what
        a `SetParam` to it changes, either way)."""
        if self.dep.configured.component(node) is None:
            return self._no_component(node)
        spec = self.executor.running.get(node) or self.executor.standby.get(node)
        if spec is not None:
            params = dict(spec.params)
        else:
            try:  # in the model decided now (its CV values), else as configured
                c = self.target(self.selection, self.cv).component(node)
            except RraError:
                c = None
            if c is None:
                c = r.with_parameters(self.dep.configured, self.overrides).component(node)
            params = {k: p.value for k, p in c.parameters.items()} if c is not None else {}
        return m.Ok(
            result={
                "node": node,
                "state": self.node_state(node),
                "params": params,
                "overrides": dict(self.overrides.get(node, {})),
            }
        )

    def set_params(
        self,
        node: str,
        params: dict[str, Any],
        reset: list[str],
        request: m.SetParam | None = None,
    ) -> m.Reply:
        component = next((c for c in self.dep.configured.components if c.name == node), None)
        if component is None:
            return self._no_component(node)
        try:
            values = r.check_parameters(self.dep.configured, node, params)
            unknown = [n for n in reset if n not in component.parameters]
            if unknown:
                raise RraError(f"{node} has no parameter(s) {', '.join(unknown)}")
        except RraError as e:
            self.refuse("param", str(e))
            return m.Err(message=str(e), code="refused")
        before = {n: dict(v) for n, v in self.overrides.items()}
        mine = self.overrides.setdefault(node, {})
        for name in reset:
            mine.pop(name, None)
        mine.update(values)
        if not mine:
            del self.overrides[node]
        outcome = self._apply_overrides(node)
        if outcome is not None and not outcome.ok:
            self.overrides = before
            return m.Err(message=f"could not set {node}: {outcome.error}", code="failed")
        self._changed()
        self._param_event(node, values, reset, request)
        return m.Ok(
            result={
                "node": node,
                "params": values,
                "overrides": dict(self.overrides.get(node, {})),
                # not running: it will start with them (the read, GetParams, says the same)
                "state": self.node_state(node),
            }
        )

    def _param_event(
        self, node: str, values: dict[str, Any], reset: list[str], request: m.SetParam | None
    ) -> None:
        """A ``param`` event, or an ``injection`` one for ``rra inject set_params``."""
        if request is None or not request.injection:
            self._event("param", f"operator set {node}: {values or {}} reset {reset or []}", None)
            return
        who = request.operator or "unknown"
        text = f"operator {who} injected set_params {node}: " + (
            " ".join(f"{k}={v!r}" for k, v in sorted(values.items())) or "-"
        )
        injection = m.Inject(kind="set_params", target=node, args=values, stamp=time.time())
        self._event("injection", text, None, operator=who, injection=injection)

    def _apply_overrides(self, node: str) -> Outcome | None:
        """Push the changed desired parameters to the running (or standby) node."""
        try:
            target = self.target(self.selection, self.cv)
        except RraError as e:
            return Outcome(False, error=str(e))
        if node in self.executor.standby:
            spec = next((s for s in self.standby_specs(target) if s.name == node), None)
            if spec is not None:
                plan = Plan(steps=(SetParameters(component=node, values=dict(spec.params)),))
                self.executor.running[node] = self.executor.standby.pop(node)
                try:
                    return self.executor.execute(plan)
                finally:
                    self.executor.standby[node] = self.executor.running.pop(node)
            return None
        want, have = target.component(node), self.runtime_model.component(node)
        if want is None or have is None or want.parameters.keys() != have.parameters.keys():
            return None  # not running as such: it starts with the new values
        changed = msgspec.structs.replace(have, parameters=want.parameters)
        model = msgspec.structs.replace(
            self.runtime_model,
            components=[changed if c.name == node else c for c in self.runtime_model.components],
        )
        outcome = self.executor.execute(diff(self.runtime_model, model))
        if outcome.ok:
            self.runtime_model = model
        return outcome

    # ---- reconciliation ------------------------------------------------------------------
    def reconcile(self, reason: str = "periodic") -> Outcome | None:
        """Make the running system match the model in effect (at the first deployment: the
        decided one); see `rra_agent.engines.reconcile`."""
        try:
            target = self.runtime_model if self.deployed else self.target(self.selection, self.cv)
        except RraError as e:
            self._event("reconcile", f"cannot resolve the model: {e}", None, level="error")
            return None
        expected = {s.name: s for s in self._specs(target, target.components)}
        standby_specs = self.standby_specs(target)
        observed = self._observe(expected, standby_specs)
        candidates = {s.name for s in standby_specs}
        hot = {s.name for s in standby_specs if self.dep.package.runtime.replacement.hot(s.name)}
        plan, running, standby = takeover_plan(observed, expected, target, candidates, hot)
        missing = [
            s
            for s in standby_specs
            if s.name not in standby and s.name not in observed.pending
            and s.host not in observed.unreachable
        ]  # fmt: skip
        first = not self.deployed
        self.executor.running, self.executor.standby = running, standby
        if not plan.steps and not missing:
            self._adopt(target, observed, expected, first)
            return None
        outcome = self.executor.execute(plan, skip=self._unavailable_components(target))
        self._prestart_standbys(outcome, missing)
        self.verified.update(observed.described)
        self._failed_units(outcome, target)
        self._settle(target, outcome, first)
        self.deployed = True
        self._changed()
        self._reconciled(outcome, observed, first, reason)
        return outcome

    def _observe(
        self, expected: dict[str, m.NodeSpec], standby_specs: list[m.NodeSpec]
    ) -> Observed:
        """What the reachable host agents run, each node described against its spec (the
        desired one, its standby's, or the configured one); unreachable hosts marked."""
        known = {
            n: (pid, spec)
            for n, pid in self.verified.items()
            for spec in [self.executor.running.get(n) or self.executor.standby.get(n)]
            if spec is not None
        }
        configured = self.dep.configured
        templates = {
            **{s.name: s for s in self._specs(configured, configured.components)},
            **{s.name: s for s in standby_specs},
            **expected,
        }
        cut_off = {h for h in self.hosts if not self.reachable(h)}
        observed = observe(
            self.actuator.client, [h for h in self.hosts if h not in cut_off], templates,
            known=known,
        )  # fmt: skip
        observed.unreachable |= cut_off
        if self._probing is not None:  # the probe's node: its thread starts and stops it
            observed.forget(self._probing[0])
        self.unreachable = observed.unreachable
        self.observed.update(observed.states)
        return observed

    def _adopt(
        self, target: SystemModel, observed: Observed, expected: dict[str, m.NodeSpec], first: bool
    ) -> None:
        """Nothing to change: what runs is ``target`` (the nodes found running adopted)."""
        self.verified.update(observed.described)
        self.runtime_model, self.deployed = target, True
        self._update_hosts(expected, self.executor.standby, observed)
        if first:
            self._changed()
            self._event(
                self._kind(first),
                f"adopted {len(observed.nodes)} running node(s), nothing to change",
                None,
                outcome="ok",
            )

    def _prestart_standbys(self, outcome: Outcome, missing: list[m.NodeSpec]) -> None:
        """Start the standbys that ``outcome`` left missing (their components available),
        their records and failures added to it."""
        missing = [s for s in missing if not self._unavailable_components_of([s.name])]
        if not missing:
            return
        pre = self.executor.prestart_standby(missing)
        outcome.records.extend(pre.records)
        outcome.failures += pre.failures
        outcome.ok = outcome.ok and pre.ok
        outcome.error = outcome.error or pre.error

    def _reconciled(self, outcome: Outcome, observed: Observed, first: bool, reason: str) -> None:
        """The event of a reconciliation that changed something: what runs, what was done."""
        kind = self._kind(first)
        what = (
            f"{len(self.executor.running)} node(s) running, {len(self.executor.standby)} on standby"
        )
        if first and observed.nodes:
            what += f" ({len(observed.nodes)} found running)"
        failed = "; ".join(f"{', '.join(f.steps)}: {f.error}" for f in outcome.failures)
        self._event(
            kind,
            f"{what}, {_actions(outcome)} ({reason})"
            if outcome.ok
            else f"{kind} partly applied: {what}; not applied: {failed}",
            None,
            level="info" if outcome.ok else "error",
            outcome="ok" if outcome.ok else ("partial" if outcome.applied else "failed"),
            plan=outcome,
            durations={"execute": outcome.seconds},
        )

    def _kind(self, first: bool) -> str:
        """A reconciliation's event: ``deploy`` for the run's first deployment, even over
        nodes already running (a replica that claimed the lead at the same moment started
        them, or an earlier run left them on another host); ``adopt`` for a leader that
        continues a deployment made before it (the state it took over or saved says so)."""
        if not first:
            return "reconcile"
        return "adopt" if self.continues else "deploy"

    def _unavailable_components_of(self, names: list[str]) -> set[str]:
        """Which of these components run an unavailable implementation in the model."""
        return {
            n for n in names
            if component_needs(self.dep.configured, n, _impl(self.dep.configured, n))
            in self.unavailable
        }  # fmt: skip

    def _settle(self, desired: SystemModel, outcome: Outcome, first: bool) -> None:
        """After a reconcile: what did not start is not in effect (at the first deployment
        nothing ran before; later, a node that failed to start again is left out)."""
        if first:
            base = _without(desired, {c.name for c in desired.components})
            failed, params = outcome.failed_structure, outcome.failed_parameters
        else:
            running = {*self.executor.running, *self.executor.standby}
            failed = frozenset(n for n in outcome.failed_structure if n not in running)
            if not failed:
                return
            base, params = _without(desired, failed), frozenset()
        effective = effective_model(base, desired, failed, params)
        try:
            decided = self.target(self.selection, self.cv)
        except RraError:
            decided = desired
        pkg = self.dep.package
        self.effective, self.effective_cv = in_effect(
            pkg.features, pkg.runtime, self.selection, frozenset() if first else self.effective,
            effective, decided, self.cv, self.effective_cv,
        )  # fmt: skip
        self.runtime_model = effective
        if not outcome.ok:
            self.degraded = [f"{', '.join(f.steps)}: {f.error}" for f in outcome.failures]
            self._retry_later()

    def _update_hosts(self, expected, standby, observed) -> None:
        """Tell a host agent the spec it should restart a node with, where its copy differs."""
        stale = [
            spec
            for name, spec in [*expected.items(), *standby.items()]
            if name in observed.states
            and observed.states[name].digest not in ("", m.spec_digest(spec))
        ]
        if stale:
            self.actuator._update(stale)

    # ---- state -----------------------------------------------------------------------
    def engine_state(self) -> m.EngineState:
        fence = self.fence or (self.mirror.fence if self.mirror else m.Fence(epoch=0, leader=""))
        sel = self.selection_fence
        return m.EngineState(
            fence=fence,
            version=self.version,
            selection=sorted(self.selection),
            cv=dict(self.cv),
            overrides={n: dict(v) for n, v in self.overrides.items()},
            applied=self.applied,
            selection_fence=m.Fence.of(sel) if sel else None,
            running=list(self.executor.running.values()),
            standby=list(self.executor.standby.values()),
            forced=dict(self.forced),
            conflicts=list(self.conflicts),
            effective=sorted(self.effective),
            effective_cv=dict(self.effective_cv),
            unavailable=sorted(self.unavailable.values(), key=lambda u: (u.component, u.since)),
            degraded=list(self.degraded),
            stamp=self._stamp,
            reflexes=self.reflexes.state(),
            models=self.dep.models,
            history=list(self.history),
            deployed=self.deployed if self.leading or self.mirror is None else self.mirror.deployed,
        )

    def _changed(self) -> None:
        """The desired state changed: publish it (standbys mirror it), persist it, and keep
        the reflexes it allows installed."""
        self._sync_reflexes()
        self.version += 1
        self._stamp = time.time()
        state = self._publish_state()
        self._persist(state)
        if self.rec is not None and self.leading:
            self.rec.state(state)
        self.publish_status()

    def _publish_state(self) -> m.EngineState:
        """Publish the state (also every ``STATE_EVERY`` s: a standby that missed a change,
        stalled or reconnecting, is never more than that behind)."""
        state = self.engine_state()
        if self.leading and self._state_pub is not None:
            self._state_pub.put(_STATE.encode(state))
            self._state_sent = time.monotonic()
        return state

    @property
    def state_file(self) -> Path | None:
        return self.run_dir / f"{NAME}-state.json" if self.run_dir else None

    def _persist(self, state: m.EngineState) -> None:
        if self.state_file is not None:
            tmp = self.state_file.with_suffix(f".{self.name}.tmp")
            tmp.write_bytes(msgspec.json.encode(state))
            tmp.replace(self.state_file)

    def _saved_state(self) -> m.EngineState | None:
        if self.state_file is None or not self.state_file.exists():
            return None
        try:
            return msgspec.json.decode(self.state_file.read_bytes(), type=m.EngineState)
        except (OSError, msgspec.DecodeError, msgspec.ValidationError) as e:
            print(f"rra {self.name}: ignoring {self.state_file}: {e}", file=sys.stderr)
            return None

    def _restore(self) -> None:
        """No leader to continue from: the state saved before (a restart within a run)."""
        state = self._saved_state()
        if state is None:
            return
        self.continues = state.deployed
        self.follow_models(state.models)  # the models of that state (a reload before)
        self.history = list(state.history)
        self.selection, self.cv = frozenset(state.selection), {**self.cv, **state.cv}
        self.overrides = {n: dict(v) for n, v in state.overrides.items()}
        self._take_state(state)
        self.effective_cv = {**self.cv, **self.effective_cv}

    def status(self) -> dict[str, Any]:
        running, standby = self.executor.running, self.executor.standby
        desired = {
            n: {"host": s.host, "implementation": m.implementation_id(s), "active": s.active,
                "standby": n in standby}
            for n, s in [*running.items(), *standby.items()]
        }  # fmt: skip
        return {
            "system": self.dep.system,
            "deployment": sorted(self.dep.selection),
            "selection": sorted(self.selection),
            "cv": dict(self.cv),
            "effective": sorted(self.effective),
            "effective_cv": dict(self.effective_cv),
            "params": self._params_apart(),
            "unavailable": [msgspec.to_builtins(u) for u in self.unavailable.values()],
            "degraded": list(self.degraded),
            "overrides": {n: dict(v) for n, v in self.overrides.items()},
            "forced": {f: "on" if on else "off" for f, on in sorted(self.forced.items())},
            "conflicts": [msgspec.to_builtins(c) for c in self.conflicts],
            "desired": desired,
            "running": {n: d for n, d in desired.items() if not d["standby"]},
            "standby": sorted(standby),
            "observed": {n: _observed(st) for n, st in self.observed.items()},
            "hosts": {h: h not in self.unreachable for h in self.hosts},
            # How this run logs to Rerun: other hosts' agents give their nodes the same.
            "rerun": self.rerun,
            "unreachable": sorted(self.unreachable),
            "applied": self.applied,
            "version": self.version if self.leading or self.mirror is None else self.mirror.version,
            "seq": self.seq,
            "deployed": self.deployed,
            # What was decided is not all in effect: a plan failed in part.
            "failed": bool(self.degraded),
            "reflexes": self.reflexes.status(),
            "models": self.dep.models,
        }

    def _params_apart(self) -> dict[str, dict[str, dict[str, Any]]]:
        """Node -> {"decided": ..., "effective": ...}: the parameters whose value in the
        decided model differs from the one the node runs with (per successful requests)."""
        if not self.deployed:
            return {}
        try:
            decided = self.target(self.selection, self.cv)
        except RraError:
            return {}
        out: dict[str, dict[str, dict[str, Any]]] = {}
        for c in decided.components:
            spec = self.executor.running.get(c.name)
            if spec is None:
                continue  # not running: "degraded" says why
            want = {k: p.value for k, p in c.parameters.items()}
            have = spec.params
            apart = {k for k, v in want.items() if k not in have or have[k] != v}
            if apart:
                out[c.name] = {"decided": {k: want[k] for k in sorted(apart)},
                               "effective": {k: have.get(k) for k in sorted(apart)}}  # fmt: skip
        return out

    # ---- events ------------------------------------------------------------------------
    def _event(
        self,
        kind: str,
        text: str,
        msg: m.Selection | None,
        *,
        level: m.Level = "info",
        outcome: str = "",
        plan: Outcome | None = None,
        durations: dict[str, float] | None = None,
        operator: str = "",
        injection: m.Inject | None = None,
    ) -> None:
        if outcome in ("failed", "rolled_back") and self.actuator.superseded:
            # Not a failure of the plan: another leader acted first (both claimed at once).
            self.actuator.superseded = False
            kind, level, outcome = "superseded", "warning", ""
            text = f"{self.name} steps down: another leader has acted ({text})"
            if self.election is not None:
                self.loop.post(self.election.step_down)
        self.seq += 1
        event = m.AdaptationEvent(
            stamp=time.time(),
            kind=kind,
            message=text,
            level=level,
            source=self.name,
            cause=list(msg.cause) if msg else [],
            why=list(msg.why) if msg else [],
            plan=[rec.line() for rec in plan.records] if plan else [],
            outcome=outcome,  # type: ignore[arg-type]
            durations=durations or {},
            seq=self.seq,
            fence=self.fence,
            selection=msg.seq if msg else None,
            operator=operator,
            injection=injection,
        )
        if self.sink is not None:
            self.sink.emit(event, publish=self.leading)
        if self.viz:
            self.viz.event(event)

    # ---- reflexes (rra_agent.engines.reflexes) -------------------------------------------
    def _on_reflex(self, sample: zenoh.Sample) -> None:
        """A node's reflex fired (Zenoh thread): every replica records it."""
        msg = receive(sample.payload, "reflex", _REFLEX)
        if isinstance(msg, Refused):
            return self.drop(msg.code, f"reflex report: {msg.detail}")
        if str(sample.key_expr) != self.keys.reflex(msg.node):
            self.refuse("reflex", f"report of {msg.node} on {sample.key_expr}")
            return None
        self.counters.received += 1
        self.loop.post(lambda: self._reflex_fired(msg))
        return None

    def _reflex_fired(self, msg: m.ReflexFired) -> None:
        fired = self.reflexes.on_fired(msg)
        if fired is not None and self.leading:
            self.reflexes.decided(self.selection)  # the engines may have decided already
            self._changed()

    def _situation(self) -> Situation:
        gone = {need: u.reason for need, u in self.unavailable.items()}
        return Situation(
            selection=self.selection, cv=dict(self.cv), forced=dict(self.forced),
            unavailable=unavailable_features(self.needs, gone),
            conflicts=frozenset(r for c in self.conflicts for r in c.rules),
            runtime_model=self.runtime_model, running=dict(self.executor.running),
            standby=dict(self.executor.standby), reachable=self.reachable, target=self.target,
            degraded=bool(self.degraded) or self._retry_at is not None
            or self.effective != self.selection,
        )  # fmt: skip

    def _sync_reflexes(self) -> None:
        """Install what the configuration allows, withdraw what it does not (the leader)."""
        if not (self.leading and self.deployed):
            return
        self._reflexes_synced = time.monotonic()
        self.reflexes.sync(self._situation())

    def _reflexes_due(self) -> None:
        """Periodically: roll back what was not confirmed in time, re-check what is installed."""
        if not (self.leading and self.deployed):
            return
        if self.reflexes.fired:
            self.reflexes.tick()
        if time.monotonic() - self._reflexes_synced >= REFLEX_SYNC:
            self._sync_reflexes()

    def _reflex_send(self, batch: list[Ctl]) -> list[m.Reply]:
        return self.actuator.control(batch)

    def _spec_of(self, node: str) -> m.NodeSpec | None:
        return self.executor.running.get(node) or self.executor.standby.get(node)

    def _reflex_event(self, kind: str, text: str, **fields: Any) -> None:
        """An adaptation event about a reflex (fired and confirmed, or rolled back)."""
        self.seq += 1
        event = m.AdaptationEvent(
            stamp=time.time(), kind=kind, message=text, source=self.name, seq=self.seq,
            fence=self.fence, selection=self.applied, **fields,
        )  # fmt: skip
        if self.sink is not None:
            self.sink.emit(event, publish=self.leading)
        if self.viz:
            self.viz.event(event)

    # ---- lifecycle ---------------------------------------------------------------------
    def declare(self, session: zenoh.Session) -> list[Any]:
        writer = open_writer(self.run_dir if self._recording else None, self.name, self.role,
                             self.dep, self.host)  # fmt: skip
        self.rec = ResolutionRecorder(writer) if writer is not None else None
        self.viz = open_logger(self.name)
        log = self.run_dir / "events.jsonl" if self.run_dir else None
        self.sink = EventSink(session, self.keys.events, log)
        self.actuator = ZenohActuator(
            session,
            self.keys,
            start_timeout=self.start_timeout,
            reachable=self.reachable,
            container_of={
                c.name: c.container for c in self.dep.configured.components if c.container
            },
        )
        self.present = {
            str(reply.ok.key_expr).rsplit("/", 1)[-1]
            for reply in session.liveliness().get(self.keys.host_alive_all, timeout=1.0)
            if reply.ok is not None
        }
        self.unreachable = set(self.hosts) - self.present
        self.executor = Executor(
            self.actuator,
            self.keys,
            self.dep.package.runtime.replacement,
            default_host=self.host,
            path=(str(self.dep.package.root),),
            standby_inputs=self.standby_inputs,
        )
        self._state_pub = session.declare_publisher(
            self.keys.state(NAME),
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.INTERACTIVE_HIGH,
        )
        self.adaptation = LeaderWatch(
            session,
            self.keys,
            "adaptation",
            on_change=self._post_claims_changed,
        )
        lv = session.liveliness()
        return [
            self._state_pub,
            session.declare_subscriber(self.keys.selection, self._on_selection),
            session.declare_subscriber(self.keys.state(NAME), self._on_state),
            session.declare_subscriber(self.keys.events, self._on_event),
            session.declare_subscriber(self.keys.reflex_all, self._on_reflex),
            lv.declare_subscriber(self.keys.host_alive_all, self._on_host, history=True),
            self.adaptation,
        ]

    def starting(self) -> None:
        """Learn the current leader's state before the election (a standby that starts)."""
        assert self.session is not None
        for answer in oks(self.session.get(
            self.keys.engine_ctl(NAME),
            payload=m.Codec(m.EngineRequest).encode(m.GetState()),
            timeout=1.0,
        )):  # fmt: skip
            if answer.result:
                with contextlib.suppress(msgspec.ValidationError):
                    self._mirror(msgspec.convert(answer.result, m.EngineState), trusted=True)

    def epoch_floor(self) -> int:
        """Above the epoch of the leader this replica mirrors, or of the saved state."""
        if self.mirror is not None:
            return self.mirror.fence.epoch
        saved = self._saved_state()
        return saved.fence.epoch if saved is not None else 0

    def tick(self, now: float) -> None:
        self.publish_status()
        if not self.leading:
            return
        if self.deployed and time.monotonic() - self._state_sent >= STATE_EVERY:
            self._publish_state()
        if self.deployed and self._retry_at is not None and time.monotonic() >= self._retry_at:
            self._retry_at = None
            self.converge()  # what the last plan could not apply, again
        self._probe_due()
        self._reflexes_due()
        if self._reconcile_soon or now >= self._next_reconcile:
            reason = "a host reported a change" if self._reconcile_soon else "periodic"
            self._reconcile_soon = False
            self._next_reconcile = now + self.reconcile_period
            self.reconcile(reason if self.deployed else "deployment")
            self._take_latest()
        self._report_deferred()

    def _probe_due(self) -> None:
        """Start the probe of one unavailable implementation whose probe is due (one at a
        time, on its own thread)."""
        if self._probing is not None or not self.deployed:
            return
        now = time.time()
        due = [(u.probe_at, need) for need, u in self.unavailable.items() if u.probe_at <= now]
        if not due:
            return
        _, need = min(due)
        spec = self._probe_spec(need)
        if spec is None:  # its name is taken now: later
            record = self.unavailable[need]
            self.unavailable[need] = msgspec.structs.replace(record, probe_at=now + 1.0)
            return
        self._probing = need
        threading.Thread(
            target=self._probe, args=(need, spec), name=f"probe-{need[0]}", daemon=True
        ).start()

    def _report_deferred(self) -> None:
        """Steps left for unreachable hosts: one event; the reconcile loop applies them when
        the host is back."""
        deferred, self.actuator.deferred = self.actuator.deferred, []
        if deferred:
            hosts = sorted({h for h, _ in deferred})
            self._event(
                "deferred",
                f"host(s) {', '.join(hosts)} unreachable: "
                f"{'; '.join(what for _, what in deferred)} deferred until reconnection",
                None,
                level="warning",
            )

    def stopping(self) -> None:
        self.actuator.close()
        if self.sink is not None:
            self.sink.close()
        if self.viz:
            self.viz.close()
        if self.rec is not None:
            self.rec.writer.close(end=time.time())

    # ---- the run's record (docs/recording.md) -----------------------------------------------
    def _recorded(self, kind: str, args: dict[str, Any], who: str, reply: m.Reply) -> m.Reply:
        """An operator's command in the record, with its outcome (the leader's)."""
        if self.rec is not None and self.leading:
            outcome = "ok" if isinstance(reply, m.Ok) else f"{reply.code}: {reply.message}"
            self.rec.command(kind, msgspec.to_builtins(args), who, outcome)
        return reply

    def _record_injection(self, msg: m.Inject, operator: str) -> None:
        """An operator's injection (its ``injection`` event), in the record. The record does
        not subscribe to the injections themselves: ``rra inject`` refuses a kind no process
        takes, and a recorder listening would be taken for one."""
        if self.rec is None or not self.leading:
            return
        args = {"kind": msg.kind, "target": msg.target, "args": msg.args, "stamp": msg.stamp}
        self.rec.command("inject", args, operator, "")

    # ---- reload: new models (``rra reload``, docs/recording.md) -------------------------------
    def reload(self, req: m.Reload) -> m.Reply:
        """Check the new models against what runs, have every replica and host agent
        prepare them, switch, and apply what they change (main thread: after any plan in
        progress). Nothing changes when anything refuses."""
        if not self.leading or not self.deployed:
            return m.Err(message=f"{self.name} does not lead (or has not deployed yet)",
                         code="not_leader")  # fmt: skip
        try:
            bundle = self._reload_bundle(req)
            if bundle.digest == self.dep.models:
                return m.Ok(result={"models": bundle.digest, "previous": bundle.digest,
                                    "changes": [], "unchanged": True})  # fmt: skip
            new = self._deploy_models(bundle)
        except RraError as e:
            return m.Err(message=str(e), code="invalid")
        comparison = compare(self.dep, new, self._running())
        if not comparison.allowed:
            lines = [str(e).splitlines()[0] for e in comparison.refusals]
            return m.Err(message="\n".join(lines), code="refused")
        session: Any = self.session
        changed = system_changed(self.dep, new)
        hosts = [h for h in self.hosts if self.reachable(h)] if changed else []
        replicas = [r for r in engine_replicas(session, self.keys) if r != self.name]
        refused, silent = prepare_all(
            session, self.keys, bundle, self.fence, replicas=replicas, hosts=hosts
        )
        silent_hosts = [s for s in silent if s.startswith("host ")]
        if refused or silent_hosts:
            commit_hosts(session, self.keys, self.dep.models, self.fence, hosts)
            why = "; ".join(refused + [f"{s} did not answer" for s in silent_hosts])
            return m.Err(message=f"not reloaded: {why}", code="refused")
        return self._commit(new, comparison.changes, req.undo)

    def _reload_bundle(self, req: m.Reload) -> ModelBundle:
        if req.undo:
            if not self.history:
                raise RraError("nothing to undo: no reload since the system started")
            return self._bundle(self.history[-1])
        if req.bundle is None:
            raise RraError("a reload needs the models (or --undo)")
        bundle = req.bundle.verified()
        if req.base and req.base != self.dep.models:
            raise RraError(
                f"the running models changed since the edit was checked (now {self.dep.models}, "
                f"checked against {req.base}): run rra reload again"
            )
        return bundle

    def _bundle(self, digest: str) -> ModelBundle:
        if digest in self._bundles:
            return self._bundles[digest]
        if self.run_dir is None:
            raise RraError(f"models {digest} are not kept here")
        return read_models(self.run_dir, digest)

    def _deploy_models(self, bundle: ModelBundle) -> Deployment:
        """Load the new models (kept in the run's record first: replicas may read them)."""
        if self.run_dir is not None:
            keep_models(self.run_dir, bundle)
        self._bundles[bundle.digest] = bundle
        return deploy_bundle(bundle, self.dep)

    def _running(self) -> Any:
        return running_view(self.executor.running, self.executor.standby, self.selection)

    def _commit(self, new: Deployment, changes: list[str], undo: bool) -> m.Reply:
        """Switch to ``new``: publish the state naming it (the commit every replica follows),
        tell the host agents, apply the plan it implies and the new parameter bounds."""
        old, t0 = self.dep, time.perf_counter()
        self.switch_models(new)
        self.history = self.history[:-1] if undo else [*self.history, old.models][-10:]
        self._changed()
        session: Any = self.session
        commit_hosts(session, self.keys, new.models, self.fence,
                     [h for h in self.hosts if self.reachable(h)])  # fmt: skip
        outcome = self.converge()
        failed = self._push_decls(old, new)
        what = "; ".join(changes) or "nothing the engines use"
        text = (f"{'undo: ' if undo else ''}models {new.models} (were {old.models}): {what}"
                + (f"; bounds not applied to {', '.join(failed)}" if failed else ""))  # fmt: skip
        self._event("reload", text, None, level="warning" if failed else "info")
        print(f"rra {self.name}: reload: {text}", flush=True)
        plan = [rec.line() for rec in outcome.records] if outcome is not None else []
        return m.Ok(result={
            "models": new.models, "previous": old.models, "changes": changes, "plan": plan,
            "seconds": time.perf_counter() - t0,
        })  # fmt: skip

    def _push_decls(self, old: Deployment, new: Deployment) -> list[str]:
        """New parameter bounds to the running nodes (no restart); the nodes that refused."""
        from rra_agent.engines.executor import Ctl

        decls = changed_decls(old, new, self.executor.running)
        if not decls:
            return []
        batch = [Ctl(self.executor.running[n], m.SetParams(params={}, decl=d))
                 for n, d in decls.items()]  # fmt: skip
        replies = self.actuator.control(batch)
        for ctl, reply in zip(batch, replies, strict=True):
            if isinstance(reply, m.Ok):
                self.executor.running[ctl.spec.name] = msgspec.structs.replace(
                    ctl.spec, decl={**ctl.spec.decl, **decls[ctl.spec.name]})  # fmt: skip
        return [c.spec.name for c, r in zip(batch, replies, strict=True) if isinstance(r, m.Err)]

    def switch_models(self, new: Deployment) -> None:
        """Run ``new`` from now on (a reload, or a standby following its leader)."""
        previous, self.dep = self.dep.models, new
        if new.bundle is not None:
            self._bundles[new.models] = new.bundle
        fm = new.package.features
        self.needs = requirements(fm, new.package.runtime)
        attributes = {name for name, (_, a) in fm.attributes.items() if a.kind == "cv"}
        self.cv = {k: v for k, v in self.cv.items() if k in attributes}
        self.effective_cv = {k: v for k, v in self.effective_cv.items() if k in attributes}
        if hasattr(self, "executor"):
            self.executor.replacement = new.package.runtime.replacement
            self.executor.standby_inputs = self.standby_inputs
            self.actuator.container_of = {
                c.name: c.container for c in new.configured.components if c.container
            }
        self._prepared.clear()
        if self.rec is not None:
            self.rec.reload(new.models, previous)

    def load_models(self, bundle: ModelBundle) -> Deployment:
        """These models (their bundle kept: a replica asks the leader for it)."""
        new = deploy_bundle(bundle, self.dep)
        self._bundles[bundle.digest] = bundle
        return new

    def find_models(self, digest: str) -> ModelBundle:
        """The bundle known here, else the run's record's, else the leader's."""
        return self._bundles.get(digest) or super().find_models(digest)

    def get_models(self, digest: str) -> m.Reply:
        try:
            bundle = self._bundle(digest or self.dep.models)
        except RraError as e:
            return m.Err(message=str(e), code="unknown")
        return m.Ok(result=msgspec.to_builtins(bundle))


#: The first word of a failed start that says the node itself crashed (its host agent saw
#: it exit), not that it was slow or unreachable.
_CRASHED = ("BACKOFF", "EXITED", "FATAL")


def _without(model: SystemModel, names: Collection[str]) -> SystemModel:
    """``model`` without these components and the connections that touch them."""
    keep = [c for c in model.components if c.name not in names]
    ends = {c.name for c in keep}
    conns = [
        c for c in model.connections
        if parse_endpoint(c.source).component in ends and parse_endpoint(c.target).component in ends
    ]  # fmt: skip
    return msgspec.structs.replace(model, components=keep, connections=conns)


def _impl(model: SystemModel, name: str) -> Any:
    c = model.component(name)
    return None if c is None else c.implementation


def _actions(outcome: Outcome) -> str:
    """``5 actions``: how many actions an event's plan lists (its lines but the notes), the
    number it says being the number of lines it shows (``rra events``)."""
    n = sum(1 for rec in outcome.records if rec.action != "note")
    return f"{n} action" + ("" if n == 1 else "s")


def _rerun_config() -> dict[str, Any]:
    """This run's Rerun configuration (``RRA_RERUN``, from ``rra up --rerun``)."""
    from rra_agent.viz.rerun_log import RerunConfig

    try:
        return msgspec.to_builtins(RerunConfig.from_env())
    except ValueError:
        return {}


def _observed(st: m.NodeState) -> dict[str, Any]:
    """A node as its host agent last reported it (``rra status`` shows it, with what it
    raised if that report was a failure)."""
    return {
        "state": st.state,
        "pid": st.pid,
        "host": st.host,
        "restarts": st.restarts,
        "active": st.active,
        "implementation": st.implementation,
        **({"reason": st.reason, "failure": msgspec.to_builtins(st.failure)} if st.failure else {}),
    }


def arguments() -> argparse.ArgumentParser:
    """The command line of ``python -m rra_agent.engines.resolution``."""
    from rra_agent.engines.launch import engine_arguments

    parser = engine_arguments("rra resolution", __doc__)
    parser.add_argument("--retry-after", type=float, default=5.0)
    parser.add_argument("--start-timeout", type=float, default=15.0)
    parser.add_argument("--reconcile-period", type=float, default=1.0)
    parser.add_argument(
        "--no-reflexes", action="store_true", help="never delegate a decision to a node"
    )
    return parser


def warm_up(argv: list[str]) -> None:
    """The fork server's hook (`rra_agent.engines.launch.warm_up`)."""
    from rra_agent.engines import launch

    launch.warm_up(argv, arguments)


def main(argv: list[str] | None = None) -> int:
    """``python -m rra_agent.engines.resolution --package PKG --select F,...``."""
    from rra_agent.engines.launch import engine_setup, parse_engine_args

    args = parse_engine_args(arguments, argv)
    setup = engine_setup(args, NAME)
    if setup is None:
        return 2
    dep, bus, host, name = setup
    engine = ResolutionEngineProcess(
        dep,
        bus,
        host=host,
        name=name,
        run_dir=Path(args.run_dir) if args.run_dir else None,
        retry_after=args.retry_after,
        start_timeout=args.start_timeout,
        reconcile_period=args.reconcile_period,
        reflexes=not args.no_reflexes,
        record=not args.no_record,
    )
    return engine.run()


if __name__ == "__main__":
    sys.exit(main())


__getattr__ = _compat.renamed(__name__)  # old names, for one release (docs/api.md)
