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

import os
import sys
import time
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from rra_agent import trace
from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import too_large
from rra_agent.core import resolution as r
from rra_agent.core.election import Term, newer, parse_claim
from rra_agent.core.features import check_selection, default_runtime_selection
from rra_agent.core.rules import clamp_cv
from rra_agent.deployment import Deployment
from rra_agent.engines.actuator import ZenohActuator
from rra_agent.engines.base import EngineProcess
from rra_agent.engines.events import EventSink, phase_durations
from rra_agent.engines.executor import Executor, Outcome, spec_for
from rra_agent.engines.launch import warm_up as warm_up  # the fork server's hook
from rra_agent.engines.reconcile import observe, takeover_plan
from rra_agent.errors import RraError
from rra_agent.models.system import Component, ParamValue, SystemModel
from rra_agent.viz.rerun_log import Logger, open_logger

NAME = "resolution"
#: Benchmarks only (``tools/bench_recovery.py``): wait this long before executing a plan, to
#: emulate a slower adaptation pipeline such as the paper's 0.5 s.
EMULATED_DELAY = float(os.environ.get("RRA_EMULATED_SWAP_DELAY", "0") or 0)
#: The leader republishes its state at least this often (seconds).
STATE_EVERY = 1.0
#: After a host agent appears, how long to let the adaptation react before reconciling it.
HOST_SETTLE = 0.5
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
_EVT = m.Codec[m.EventMessage](m.EventMessage)
_STATE = m.Codec[m.StateMessage](m.StateMessage)
_REPLY = m.Codec[m.Reply](m.Reply)
_ENGINE_REQ = m.Codec[m.EngineRequest](m.EngineRequest)


class ResolutionEngine(EngineProcess):
    role = NAME
    tick_period = 0.1

    def __init__(
        self,
        dep: Deployment,
        bus: BusConfig,
        *,
        host: str = "local",
        name: str = NAME,
        run_dir: Path | None = None,
        retry_after: float = 5.0,
        start_timeout: float = 15.0,
        reconcile_period: float = 1.0,
    ) -> None:
        super().__init__(dep, bus, host=host, name=name)
        self.run_dir = run_dir
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
        self.current = msgspec.structs.replace(dep.configured, components=[], connections=[])
        self.applied = 0
        self.selection_fence: Term | None = None
        self.version = 0
        # ---- what this replica knows of the running system ----
        self.observed: dict[str, m.NodeState] = {}
        #: Hosts whose agent's liveliness token this replica sees (a partition hides it).
        self.present: set[str] = set()
        self.rerun: dict[str, Any] = _rerun_config()
        self.unreachable: set[str] = set()
        #: Nodes whose live configuration is known to match: name -> pid.
        self.verified: dict[str, int] = {}
        self.deployed = False
        self.mirror: m.EngineState | None = None
        self.latest: m.Selection | None = None
        #: The selection last acted on (each is acted on once; a retry clears it).
        self._taken: m.Selection | None = None
        self._waiting_for_claim = False
        #: Live Adaptation Engine claims ((replica, instance) -> epoch) and members (names):
        #: whose selections count.
        self.adaptation_claims: dict[tuple[str, str], int] = {}
        self.adaptation_members: set[str] = set()
        self.failed: tuple[frozenset[str], tuple, float] | None = None
        self._next_reconcile = 0.0
        self._reconcile_soon = False
        self.seq = 0
        self.viz: Logger | None = None  # Rerun, when RRA_RERUN says so
        self.sink: EventSink | None = None
        self._state_pub: zenoh.Publisher | None = None
        self._state_sent = 0.0

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
        subs = r.subscriptions(model)
        path = (str(self.dep.package.root),)
        held = self.standby_inputs
        wired = {c.name: r.wiring(c, subs) for c in components}
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
        return r.standby_subscriptions(configured, hot)

    @property
    def hosts(self) -> list[str]:
        return sorted({c.host or self.host for c in self.dep.configured.components})

    def reachable(self, host: str) -> bool:
        """Whether ``host``'s agent can be asked now (its token is seen here)."""
        return host in self.present

    # ---- bus callbacks (Zenoh thread) ----------------------------------------------------
    def _on_selection(self, sample: zenoh.Sample) -> None:
        raw = sample.payload.to_bytes()
        if too_large("selection", len(raw)):
            self.drop("too_large", f"selection of {len(raw)} bytes")
            return
        try:
            msg = _SEL.decode(raw)
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            self.drop("malformed", f"selection: {e}")
            return
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
        raw = sample.payload.to_bytes()
        if too_large("state", len(raw)):
            return
        try:
            state = _STATE.decode(raw)
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            self.drop("malformed", f"engine state: {e}")
            return
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
        self.mirror = state
        self.selection, self.cv = frozenset(state.selection), dict(state.cv)
        self.overrides = {n: dict(v) for n, v in state.overrides.items()}
        self.forced, self.conflicts = dict(state.forced), list(state.conflicts)
        self.applied = state.applied
        if state.selection_fence is not None:
            self.selection_fence = state.selection_fence.term
        self.publish_status()

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
        if st.node in self.verified and st.pid != self.verified[st.node]:
            del self.verified[st.node]
        prev = self.observed.get(st.node)
        self.observed[st.node] = st
        if st.state in ("STOPPED", "EXITED", "FATAL") or (prev and prev.pid != st.pid):
            self._reconcile_soon = True

    # ---- taking over -------------------------------------------------------------------
    def on_leadership(self, leading: bool) -> None:
        self.actuator.fence = self.fence if leading else None
        self.actuator.superseded = False
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
        if self.mirror is not None:
            self._adopt_mirror(self.mirror)
        else:
            self._restore()
        self._take_latest()
        self._reconcile_soon = True
        self.publish_status()

    def _adopt_mirror(self, state: m.EngineState) -> None:
        """Continue from the state the previous leader published."""
        self.executor.running = {s.name: s for s in state.running}
        self.executor.standby = {s.name: s for s in state.standby}
        try:
            self.current = self.target(self.selection, self.cv)
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
        """The term of a live Adaptation Engine claim (or of a live replica claiming above
        every claim seen: its claim token may still be on its way)."""
        epoch, leader, instance = term
        if self.adaptation_claims.get((leader, instance)) == epoch:
            return True
        newest = max(self.adaptation_claims.values(), default=0)
        return leader in self.adaptation_members and epoch > newest

    def _on_adaptation_token(self, sample: zenoh.Sample) -> None:
        key, alive = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT
        parts = key.split("/")

        def update() -> None:
            if parts[-3] == "member":
                (self.adaptation_members.add if alive else self.adaptation_members.discard)(
                    parts[-1]
                )
            elif (term := parse_claim(parts[-3:])) is not None:
                epoch, who = term[0], term[1:]
                if alive:
                    self.adaptation_claims[who] = epoch
                elif self.adaptation_claims.get(who) == epoch:
                    del self.adaptation_claims[who]
            if self._waiting_for_claim:
                self._waiting_for_claim, self._taken = False, None
                self._take_latest()

        self.loop.post(update)

    def adapt(self, msg: m.Selection) -> Outcome | None:
        checked = self.check(msg)
        if checked is None:
            return None
        selection, cv = checked
        noted = (msg.forced, msg.conflicts) != (self.forced, self.conflicts)
        self.forced, self.conflicts = dict(msg.forced), list(msg.conflicts)
        if selection == self.selection and cv == self.cv:
            self.applied = msg.seq
            if noted:
                self._changed()
            return None  # a heartbeat, or nothing this engine acts on
        key = (selection, tuple(sorted(cv.items())))
        now = time.monotonic()
        if self.failed and self.failed[:2] == key and now - self.failed[2] < self.retry_after:
            if noted:
                self._changed()
            return None
        t_recv = time.time()
        t0 = time.perf_counter()
        try:
            target = self.target(selection, cv)
            plan = r.diff(self.current, target)
        except RraError as e:
            self.failed = (*key, now)
            self._event(
                "adaptation",
                f"cannot resolve the selection: {e}",
                msg,
                level="error",
                outcome="failed",
            )
            return None
        t_plan = time.perf_counter()
        trace.mark("resolution:planned", f"{len(plan.steps)} steps")
        if EMULATED_DELAY > 0 and plan.steps:
            time.sleep(EMULATED_DELAY)  # benchmarks only: a slower pipeline, like the paper's
        outcome = self.executor.execute(plan)
        t_end = time.perf_counter()
        durations = phase_durations(
            (t for f in msg.cause for t in f.reads.values()),
            decided=msg.stamp,
            received=t_recv,
            plan=t_plan - t0,
            execute=t_end - t_plan,
            switch=outcome.first_switch,
        )
        if outcome.ok:
            self.current, self.selection, self.cv, self.failed = target, selection, cv, None
            self.applied = msg.seq
            self._changed()
            text = f"applied selection {sorted(selection)}" + (
                f", {len(plan.steps)} step(s)" if plan.steps else " (no change to the system)"
            )
            self._event("adaptation", text, msg, outcome="ok", plan=outcome, durations=durations)
        else:
            self.failed = (*key, now)
            self._changed()
            state = "rolled back" if outcome.rolled_back else "ROLLBACK FAILED"
            self._event(
                "adaptation",
                f"adaptation failed, {state}: {outcome.error}",
                msg,
                level="error",
                outcome="rolled_back" if outcome.rolled_back else "failed",
                plan=outcome,
                durations=durations,
            )
            self._reconcile_soon = True
        return outcome

    # ---- operators' parameters -----------------------------------------------------------
    def serve(self, request: m.EngineRequest) -> m.Reply:
        match request:
            case m.SetParam(node=node, params=params, reset=reset):
                if not self.leading:
                    return m.Err(message=f"{self.name} does not lead", code="not_leader")
                return self.set_params(node, params, reset)
            case m.GetState():
                return m.Ok(result=msgspec.to_builtins(self.engine_state()))
        return super().serve(request)

    def set_params(self, node: str, params: dict[str, Any], reset: list[str]) -> m.Reply:
        component = next((c for c in self.dep.configured.components if c.name == node), None)
        if component is None:
            self.refuse("param", f"no component {node!r}")
            return m.Err(
                message=f"no component {node!r} in system {self.dep.system}", code="unknown"
            )
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
        self._event("param", f"operator set {node}: {values or {}} reset {reset or []}", None)
        return m.Ok(
            result={"node": node, "params": values, "overrides": dict(self.overrides.get(node, {}))}
        )

    def _apply_overrides(self, node: str) -> Outcome | None:
        """Push the changed desired parameters to the running (or standby) node."""
        try:
            target = self.target(self.selection, self.cv)
        except RraError as e:
            return Outcome(False, error=str(e))
        if node in self.executor.standby:
            spec = next((s for s in self.standby_specs(target) if s.name == node), None)
            if spec is not None:
                plan = r.Plan(steps=(r.SetParameters(component=node, values=dict(spec.params)),))
                self.executor.running[node] = self.executor.standby.pop(node)
                try:
                    return self.executor.execute(plan)
                finally:
                    self.executor.standby[node] = self.executor.running.pop(node)
            return None
        outcome = self.executor.execute(r.diff(self.current, target))
        if outcome.ok:
            self.current = target
        return outcome

    # ---- reconciliation ------------------------------------------------------------------
    def reconcile(self, reason: str = "periodic") -> Outcome | None:
        """Make the running system match the desired model (see `rra_agent.engines.reconcile`)."""
        try:
            target = self.target(self.selection, self.cv)
        except RraError as e:
            self._event("reconcile", f"cannot resolve the model: {e}", None, level="error")
            return None
        known = {
            n: (pid, spec)
            for n, pid in self.verified.items()
            for spec in [self.executor.running.get(n) or self.executor.standby.get(n)]
            if spec is not None
        }
        expected = {s.name: s for s in self._specs(target, target.components)}
        standby_specs = self.standby_specs(target)
        templates = {
            **{s.name: s for s in self._specs(self.dep.configured, self.dep.configured.components)},
            **{s.name: s for s in standby_specs},
            **expected,
        }
        cut_off = {h for h in self.hosts if not self.reachable(h)}
        observed = observe(
            self.actuator.client, [h for h in self.hosts if h not in cut_off], templates,
            known=known,
        )  # fmt: skip
        observed.unreachable |= cut_off
        self.unreachable = observed.unreachable
        self.observed.update(observed.states)
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
            self.verified.update(observed.described)
            self.current, self.deployed = target, True
            self._update_hosts(expected, standby, observed)
            if first:
                self._changed()
                self._event(
                    "adopt",
                    f"adopted {len(observed.nodes)} running node(s), nothing to change",
                    None,
                    outcome="ok",
                )
            return None
        outcome = self.executor.execute(plan)
        if outcome.ok and missing:
            pre = self.executor.prestart_standby(missing)
            outcome.records.extend(pre.records)
            if not pre.ok:
                outcome.ok, outcome.error = False, pre.error
        if outcome.ok:
            self.current, self.deployed = target, True
            self.verified.update(observed.described)
        self._changed()
        kind = "deploy" if first and not observed.nodes else ("adopt" if first else "reconcile")
        what = (
            f"{len(self.executor.running)} node(s) running, {len(self.executor.standby)} on standby"
        )
        self._event(
            kind,
            f"{what}, {len(plan.steps) + len(missing)} step(s) ({reason})"
            if outcome.ok
            else f"{kind} failed: {outcome.error}",
            None,
            level="info" if outcome.ok else "error",
            outcome="ok" if outcome.ok else "failed",
            plan=outcome,
            durations={"execute": outcome.seconds},
        )
        return outcome

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
        )

    def _changed(self) -> None:
        """The desired state changed: publish it (standbys mirror it), persist it."""
        self.version += 1
        state = self._publish_state()
        self._persist(state)
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
        self.selection, self.cv = frozenset(state.selection), {**self.cv, **state.cv}
        self.overrides = {n: dict(v) for n, v in state.overrides.items()}
        self.forced, self.conflicts = dict(state.forced), list(state.conflicts)
        self.applied = state.applied
        if state.selection_fence is not None:
            self.selection_fence = state.selection_fence.term

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
            "failed": bool(self.failed),
        }

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
            plan=[rec.line() for rec in plan.records] if plan else [],
            outcome=outcome,  # type: ignore[arg-type]
            durations=durations or {},
            seq=self.seq,
            fence=self.fence,
            selection=msg.seq if msg else None,
        )
        if self.sink is not None:
            self.sink.emit(event, publish=self.leading)
        if self.viz:
            self.viz.event(event)

    # ---- lifecycle ---------------------------------------------------------------------
    def declare(self, session: zenoh.Session) -> list[Any]:
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
        lv = session.liveliness()
        return [
            self._state_pub,
            session.declare_subscriber(self.keys.selection, self._on_selection),
            session.declare_subscriber(self.keys.state(NAME), self._on_state),
            session.declare_subscriber(self.keys.events, self._on_event),
            lv.declare_subscriber(self.keys.host_alive_all, self._on_host, history=True),
            lv.declare_subscriber(
                f"{self.keys.lead('adaptation')}/**", self._on_adaptation_token, history=True
            ),
            lv.declare_subscriber(
                self.keys.member("adaptation", "*"), self._on_adaptation_token, history=True
            ),
        ]

    def starting(self) -> None:
        """Learn the current leader's state before the election (a standby that starts)."""
        assert self.session is not None
        for reply in self.session.get(
            self.keys.engine_ctl(NAME),
            payload=m.Codec(m.EngineRequest).encode(m.GetState()),
            timeout=1.0,
        ):
            if reply.ok is None:
                continue
            try:
                answer = m.Codec[m.Reply](m.Reply).decode(reply.ok.payload.to_bytes())
                if isinstance(answer, m.Ok) and answer.result:
                    self._mirror(msgspec.convert(answer.result, m.EngineState), trusted=True)
            except (msgspec.DecodeError, msgspec.ValidationError):
                continue

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
        if self.failed and now - self.failed[2] >= self.retry_after:
            self.failed, self._taken = None, None  # try the newest selection again
            self._take_latest()
        if self._reconcile_soon or now >= self._next_reconcile:
            reason = "a host reported a change" if self._reconcile_soon else "periodic"
            self._reconcile_soon = False
            self._next_reconcile = now + self.reconcile_period
            self.reconcile(reason if self.deployed else "deployment")
            self._take_latest()
        self._report_deferred()

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


def _rerun_config() -> dict[str, Any]:
    """This run's Rerun configuration (``RRA_RERUN``, from ``rra up --rerun``)."""
    from rra_agent.viz.rerun_log import RerunConfig

    try:
        return msgspec.to_builtins(RerunConfig.from_env())
    except ValueError:
        return {}


def _observed(st: m.NodeState) -> dict[str, Any]:
    """A node as its host agent last reported it (``rra status`` shows it)."""
    return {
        "state": st.state,
        "pid": st.pid,
        "host": st.host,
        "restarts": st.restarts,
        "active": st.active,
        "implementation": st.implementation,
    }


def main(argv: list[str] | None = None) -> int:
    """``python -m rra_agent.engines.resolution --package PKG --select F,...``."""
    from rra_agent.engines.launch import engine_arguments, engine_setup

    parser = engine_arguments("rra resolution", __doc__)
    parser.add_argument("--retry-after", type=float, default=5.0)
    parser.add_argument("--start-timeout", type=float, default=15.0)
    parser.add_argument("--reconcile-period", type=float, default=1.0)
    args = parser.parse_args(argv)
    setup = engine_setup(args, NAME)
    if setup is None:
        return 2
    dep, bus, host, name = setup
    engine = ResolutionEngine(
        dep,
        bus,
        host=host,
        name=name,
        run_dir=Path(args.run_dir) if args.run_dir else None,
        retry_after=args.retry_after,
        start_timeout=args.start_timeout,
        reconcile_period=args.reconcile_period,
    )
    return engine.run()


if __name__ == "__main__":
    sys.exit(main())
