"""Execute a reconfiguration `Plan` on the running system, transactionally.

The Run-time Resolution Engine computes a `Plan` (`rra_agent.core.resolution.diff`); this
module carries it out through an `Actuator` (host agents and node control endpoints on the
bus, or a fake in unit tests). Every action that changed the running system is recorded
with its inverse; if a step fails (a node not ready in time, a control request refused),
the inverses run in reverse order and the system is back in its previous configuration.

Phases (from the plan's canonical order). Independent actions of a phase go out together
as one batch — all starts, all stops, all control requests of a phase — so a phase costs
about one round trip (or one process start), not one per node:

1. **start** the new components;
2. **prepare** the swaps, per the replacement strategy of the component swapped in:
   ``start-then-stop`` (make before break) starts the new one inactive; ``standby`` finds
   it already running inactive (pre-started at deployment; if it is not, make before
   break); restarts (`SetImplementation`) stop and start again (a name is a node's identity
   on the bus, so old and new cannot overlap);
3. **connect**, one batch: rewire subscribers (of swapped peers, of standby nodes' own
   inputs, and the plan's `Rewire` steps) and export the state of the old nodes of every
   swap. Every subscriber listens to the new producers *before* they produce: a
   replacement publishes its first command the moment it is activated (or, cold, as soon
   as it runs), and a sample published before its subscriber is declared is lost (one
   producer period late; measured 3-5 ms of a 10 ms standby switch);
4. ``stop-then-start``: the old nodes **stop**, then their replacements **start** (active,
   with the exported state in their spec);
5. **switch**, one batch: activate the new nodes (with the exported state), deactivate the
   old ones (unless they are stopped next and publish on other keys than their
   replacements: then the connect batch already cut them off), set parameters;
6. **stop** the components that go, with the swapped-out nodes (an inactive node publishes
   nothing, so stopping it last costs the switch nothing), unless a swapped-out node's own
   strategy is ``standby``: then it stays, inactive, for the way back.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Protocol

import msgspec

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.bus.messages import NodeSpec, ParamDecl, PortSpec
from rra_agent.core import resolution as r
from rra_agent.errors import RraError
from rra_agent.models.resolution import PRE_STARTED, Replacement
from rra_agent.models.system import Component


class StepFailed(RraError):
    """An action on the running system failed; the plan is rolled back."""


class Actuator(Protocol):
    """What the executor needs from the running system."""

    def start(self, specs: list[NodeSpec]) -> None:
        """Start the nodes and return once all are ready; raise StepFailed otherwise (after
        stopping those of them that did start)."""
        ...

    def stop(self, nodes: list[NodeSpec], deadlines: Mapping[str, float] | None = None) -> None:
        """Stop the nodes and return once all are gone; raise StepFailed otherwise.
        ``deadlines``: seconds by node name after which its host agent kills it (0: at
        once) instead of its grace periods."""
        ...

    def control(self, batch: list[Ctl]) -> list[m.Reply]:
        """Send every request of the batch at once; one reply per request, in order.

        A node that does not answer in time yields an `Err`; nothing is raised."""
        ...


@dataclass(frozen=True)
class Ctl:
    """One control request: the node's spec before and after it, and its inverse."""

    spec: NodeSpec
    request: m.NodeRequest
    after: NodeSpec | None = None
    inverse: m.NodeRequest | None = None

    @property
    def label(self) -> str:
        match self.request:
            case m.Rewire(port=port):
                return f"rewire {port} of {self.spec.name}"
        return f"{self.request.__struct_config__.tag} {self.spec.name}"


@dataclass
class StepRecord:
    """What one action did and how long it took (the adaptation event's plan lines)."""

    action: str
    node: str
    seconds: float
    ok: bool = True
    detail: str = ""

    def line(self) -> str:
        if self.action == "note":
            return f"note: {self.detail}"
        status = "ok" if self.ok else f"FAILED: {self.detail}"
        return f"{self.action} {self.node} ({self.seconds * 1e3:.1f} ms) {status}"


@dataclass
class Outcome:
    ok: bool
    records: list[StepRecord] = field(default_factory=list)
    error: str = ""
    rolled_back: bool = False
    rollback_error: str = ""
    seconds: float = 0.0
    #: Time from the start of execution until the swapped-in nodes were switched to.
    first_switch: float | None = None


def spec_for(
    keys: Keys,
    c: Component,
    inputs: dict[str, tuple[str, ...]],
    outputs: dict[str, str],
    *,
    default_host: str,
    active: bool = True,
    state: Any = None,
    path: tuple[str, ...] = (),
    standby: dict[str, tuple[str, ...]] | None = None,
) -> NodeSpec:
    """The `NodeSpec` that runs component ``c`` with the given wiring (topics -> keys);
    ``path``: folders its implementation is imported from first (the system package's);
    ``standby``: per subscriber port, the topics of hot standbys it may be switched to."""
    ports: dict[str, PortSpec] = {}
    for p in c.ports:
        if p.direction == "publish":
            topic = outputs.get(p.name, p.topic or f"{c.name}/{p.name}")
            ports[p.name] = PortSpec(direction="publish", type=p.type, keys=[keys.data(topic)])
        else:
            topics = inputs.get(p.name, ())
            held = (standby or {}).get(p.name, ())
            ports[p.name] = PortSpec(
                direction="subscribe",
                type=p.type,
                keys=[keys.data(t) for t in topics],
                standby=[keys.data(t) for t in held],
            )
    return NodeSpec(
        system=keys.system,
        name=c.name,
        host=c.host or default_host,
        implementation=c.implementation,
        params={k: p.value for k, p in c.parameters.items()},
        ports=ports,
        active=active,
        state=state,
        decl={k: ParamDecl(type=p.type, min=p.min, max=p.max) for k, p in c.parameters.items()},
        supervision=c.supervision,
        scheduling=c.scheduling,
        path=list(path),
    )


def _names(specs: list[NodeSpec]) -> str:
    return ",".join(s.name for s in specs)


class Transaction:
    """Runs actions, remembers how to undo each, and undoes them all on failure."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self.clock = clock
        self.records: list[StepRecord] = []
        self.undo: list[tuple[str, Callable[[], None]]] = []

    def run(self, action: str, node: str, do: Callable[[], Any], undo: Callable[[], None] | None):
        t0 = self.clock()
        try:
            result = do()
        except StepFailed as e:
            self.records.append(StepRecord(action, node, self.clock() - t0, False, str(e)))
            raise
        self.records.append(StepRecord(action, node, self.clock() - t0))
        if undo is not None:
            self.undo.append((f"undo {action} {node}", undo))
        return result

    def rollback(self) -> str:
        """Undo in reverse order; returns the first undo failure ('' when all went well)."""
        first = ""
        for what, fn in reversed(self.undo):
            try:
                fn()
            except Exception as e:  # keep undoing the rest
                first = first or f"{what}: {e}"
        self.undo.clear()
        return first


@dataclass
class _Swap:
    step: r.SwapComponent
    old: NodeSpec
    new: NodeSpec
    strategy: str


class Executor:
    """Holds the running nodes' specs and applies plans to them."""

    def __init__(
        self,
        actuator: Actuator,
        keys: Keys,
        replacement: Replacement,
        *,
        default_host: str,
        path: tuple[str, ...] = (),
        clock: Callable[[], float] = time.monotonic,
        standby_inputs: dict[str, dict[str, tuple[str, ...]]] | None = None,
    ) -> None:
        self.actuator = actuator
        self.path = path
        #: component -> subscriber port -> topics of hot standbys it listens to in advance
        #: (`rra_agent.core.resolution.standby_subscriptions`).
        self.standby_inputs = standby_inputs or {}
        self.keys = keys
        self.replacement = replacement
        self.default_host = default_host
        self.clock = clock
        #: Nodes of the Run-time Configured System Model, by name.
        self.running: dict[str, NodeSpec] = {}
        #: Pre-started replacements, by name: inactive (``standby``) or active on keys their
        #: consumers do not select yet (``hot-standby``).
        self.standby: dict[str, NodeSpec] = {}

    # ---- public ------------------------------------------------------------------------
    def prestart_standby(self, specs: list[NodeSpec]) -> Outcome:
        """Start standby replacements (at deployment time): inactive, or active if hot."""
        specs = [msgspec.structs.replace(s, active=self.replacement.hot(s.name)) for s in specs]
        tx = Transaction(self.clock)
        t0 = self.clock()
        try:
            if specs:
                tx.run("prestart", _names(specs), lambda: self.actuator.start(specs), None)
        except StepFailed as e:
            return Outcome(False, tx.records, str(e), seconds=self.clock() - t0)
        for s in specs:
            self.standby[s.name] = s
        return Outcome(True, tx.records, seconds=self.clock() - t0)

    def normalize(self, plan: r.Plan) -> tuple[r.Plan, list[str]]:
        """The plan as it applies to the nodes this executor knows to run, and what had to
        change: a stop of a node that is not running is dropped, a swap whose old node is not
        running becomes a start, parameters and rewires of a node that is not running are
        dropped (it starts with them). Such a plan comes from a model that moved on without
        the running system; the reconcile loop converges the rest."""
        known = {**self.running, **self.standby}
        steps: list[r.PlanStep] = []
        notes: list[str] = []
        for s in plan.steps:
            name = s.component
            if isinstance(s, r.SwapComponent) and name not in self.running:
                notes.append(f"{name} was not running: {s.replacement} is started instead")
                steps.append(
                    r.StartComponent(
                        component=s.replacement,
                        definition=s.definition,
                        inputs=s.inputs,
                        outputs=s.outputs,
                    )
                )
            elif isinstance(s, r.StartComponent) and name in self.running:
                notes.append(f"{name} was running already")
            elif isinstance(
                s, r.StopComponent | r.SetParameters | r.Rewire | r.SetImplementation
            ) and (name not in known):
                if isinstance(s, r.SetImplementation):
                    steps.append(
                        r.StartComponent(
                            component=name,
                            definition=s.definition,
                            inputs=s.inputs,
                            outputs=s.outputs,
                        )
                    )
                notes.append(f"{name} was not running ({type(s).__name__} adjusted)")
            else:
                steps.append(s)
        return r.Plan(steps=tuple(steps)), notes

    def execute(self, plan: r.Plan) -> Outcome:
        t0 = self.clock()
        plan, notes = self.normalize(plan)
        tx = Transaction(self.clock)
        tx.records.extend(StepRecord("note", "", 0.0, True, n) for n in notes)
        running_before, standby_before = dict(self.running), dict(self.standby)
        self._switched: float | None = None
        try:
            self._apply(plan, tx)
        except StepFailed as e:
            rollback_error = tx.rollback()
            self.running, self.standby = running_before, standby_before
            return Outcome(
                False,
                tx.records,
                str(e),
                rolled_back=not rollback_error,
                rollback_error=rollback_error,
                seconds=self.clock() - t0,
            )
        first = None if self._switched is None else self._switched - t0
        return Outcome(True, tx.records, seconds=self.clock() - t0, first_switch=first)

    # ---- the phases --------------------------------------------------------------------
    def _apply(self, plan: r.Plan, tx: Transaction) -> None:
        steps = plan.steps
        starts = [self._spec(s) for s in steps if isinstance(s, r.StartComponent)]
        if starts:
            self._start(tx, starts)
        swaps = [self._plan_swap(s) for s in steps if isinstance(s, r.SwapComponent)]
        restarts = [s for s in steps if isinstance(s, r.SetImplementation)]
        self._prepare(tx, swaps, restarts)
        cold = [w for w in swaps if w.strategy == "stop-then-start"]
        warm = [w for w in swaps if w.strategy != "stop-then-start"]
        states, cold_states = self._connect(tx, warm, cold, steps)
        hot = [w.new.name for w in warm if self.replacement.hot(w.new.name)]
        if hot:  # the consumers' rewire was the switch: say so in the plan
            self._switched = self.clock()
            tx.records.append(StepRecord("select", ",".join(hot), 0.0, True))
        if cold:
            self._stop(tx, [w.old for w in cold], self.replacement.stop_deadline)
            news = [
                msgspec.structs.replace(w.new, state=st)
                for w, st in zip(cold, cold_states, strict=True)
            ]
            self._start(tx, news)
            self._switched = self.clock()
        self._switch(tx, warm, steps, states)
        retire = [w for w in warm if not self.replacement.pre_started(w.old.name)]
        stops = [self.running[s.component] for s in steps if isinstance(s, r.StopComponent)]
        stops += [self.running[w.old.name] for w in retire]
        for w in warm:  # a swapped-out standby node stays, inactive, for the way back
            if w not in retire:
                self.standby[w.old.name] = self.running.pop(w.old.name)
        if stops:
            self._stop(tx, stops)

    def _spec(self, s: r.StartComponent | r.SwapComponent | r.SetImplementation, **kw: Any):
        return spec_for(
            self.keys,
            s.definition,
            dict(s.inputs),
            dict(s.outputs),
            default_host=self.default_host,
            path=self.path,
            standby=self.standby_inputs.get(s.definition.name),
            **kw,
        )

    def _plan_swap(self, s: r.SwapComponent) -> _Swap:
        strategy = self.replacement.strategy_for(s.replacement)
        if strategy in PRE_STARTED and s.replacement not in self.standby:
            strategy = "start-then-stop"  # nothing pre-started: make before break
        if strategy == "stop-then-start" and self.replacement.pre_started(s.component):
            # The outgoing node stays, inactive, for the way back: it is never stopped, so
            # its replacement starts inactive and takes over in the switch.
            strategy = "start-then-stop"
        new = self.standby.get(s.replacement) if strategy in PRE_STARTED else None
        if new is None:
            new = self._spec(s, active=strategy == "stop-then-start")
        return _Swap(s, self.running[s.component], new, strategy)

    def _prepare(self, tx: Transaction, swaps: list[_Swap], restarts) -> None:
        """Everything before the connect batch: make-before-break replacements started
        (inactive), pre-started ones taken from the standby table, restarts done."""
        mbb = [w.new for w in swaps if w.strategy == "start-then-stop"]
        if mbb:
            self._start(tx, mbb)
        for w in swaps:
            if w.strategy in PRE_STARTED:
                self.running[w.new.name] = self.standby.pop(w.new.name)
        if restarts:
            self._stop(tx, [self.running[s.component] for s in restarts])
            self._start(tx, [self._spec(s) for s in restarts])

    def _wants_state(self, w: _Swap) -> bool:
        return any(
            t.source == w.old.name and t.target == w.new.name
            for t in self.replacement.state_transfer
        )

    def _connect(
        self, tx: Transaction, warm: list[_Swap], cold: list[_Swap], steps
    ) -> tuple[list[Any], list[Any]]:
        """Rewire every subscriber to its new producers and export the state of the old
        nodes of all swaps, in one batch; the exported state of each warm and each cold
        swap (None: not wanted). A cold swap's old node is stopped after this batch, so its
        export costs no round trip of its own, and its consumers, rewired here, hear nothing
        more from it while it stops."""
        batch: list[Ctl] = []
        for w in warm:
            new = self.running[w.new.name]
            batch += self._rewires(
                new, {p: [self.keys.data(t) for t in ts] for p, ts in w.step.inputs.items()}
            )
        for s in steps:
            if isinstance(s, r.Rewire):
                spec = self.running[s.component]
                batch += self._rewires(spec, {s.port: [self.keys.data(t) for t in s.topics]})
        batch = self._merge(batch)
        wanted = [w for w in [*warm, *cold] if self._wants_state(w)]
        exports = [Ctl(w.old, m.ExportState()) for w in wanted]
        if not batch and not exports:
            return [None] * len(warm), [None] * len(cold)
        replies = self._control(tx, "connect", batch + exports)
        states = {
            w.new.name: rep.result  # type: ignore[union-attr]
            for w, rep in zip(wanted, replies[len(batch) :], strict=True)
        }
        return [states.get(w.new.name) for w in warm], [states.get(w.new.name) for w in cold]

    def _switch(self, tx: Transaction, warm: list[_Swap], steps, states: list[Any]) -> None:
        batch: list[Ctl] = []
        for w, state in zip(warm, states, strict=True):
            new = self.running[w.new.name]
            if not new.active:
                batch.append(self._activation(new, True, state))
            elif state is not None:  # a hot standby: it runs already, and takes the state
                batch.append(Ctl(new, m.ImportState(state=state), new, None))
            if self._must_deactivate(w):
                batch.append(self._activation(self.running[w.old.name], False))
        for s in steps:
            if isinstance(s, r.SetParameters):
                spec = self.running[s.component]
                old = {k: spec.params.get(k) for k in s.values}
                after = msgspec.structs.replace(spec, params={**spec.params, **s.values})
                batch.append(
                    Ctl(spec, m.SetParams(params=dict(s.values)), after, m.SetParams(params=old))
                )
        batch = self._merge(batch)
        if not batch:
            return
        self._control(tx, "switch", batch)
        if warm and self._switched is None:
            self._switched = self.clock()

    def _must_deactivate(self, w: _Swap) -> bool:
        """An old node that is stopped after the switch and publishes on other keys than its
        replacement needs no deactivation: the rewire of its subscribers, in the connect
        batch, already cut it off. One that stays (standby) or shares output keys does; one
        that stays hot goes on publishing on its own keys, which its consumers deselected."""
        old_out = {k for p in w.old.ports.values() if p.direction == "publish" for k in p.keys}
        new_out = {k for p in w.new.ports.values() if p.direction == "publish" for k in p.keys}
        shared = bool(old_out & new_out)
        if self.replacement.hot(w.old.name):
            return shared
        return shared or self.replacement.pre_started(w.old.name)

    def _activation(self, spec: NodeSpec, active: bool, state: Any = None) -> Ctl:
        req = m.Activate(state=state) if active else m.Deactivate()
        inv = m.Deactivate() if active else m.Activate()
        return Ctl(spec, req, msgspec.structs.replace(spec, active=active), inv)

    @staticmethod
    def _rewires(spec: NodeSpec, wiring: dict[str, list[str]]) -> list[Ctl]:
        out = []
        for port, keys in wiring.items():
            old = list(spec.ports[port].keys)
            if old == keys:
                continue
            ports = dict(spec.ports)
            ports[port] = msgspec.structs.replace(ports[port], keys=keys)
            after = msgspec.structs.replace(spec, ports=ports)
            out.append(
                Ctl(spec, m.Rewire(port=port, keys=keys), after, m.Rewire(port=port, keys=old))
            )
        return out

    @staticmethod
    def _merge(batch: list[Ctl]) -> list[Ctl]:
        """Several requests to one node: chain their ``after`` specs so the last is complete."""
        latest: dict[str, NodeSpec] = {}
        out = []
        for c in batch:
            base = latest.get(c.spec.name)
            if base is not None and c.after is not None:
                after = _apply_request(base, c.request)
                c = Ctl(base, c.request, after, c.inverse)
            if c.after is not None:
                latest[c.spec.name] = c.after
            out.append(c)
        return out

    # ---- actions with their inverses ---------------------------------------------------
    def _start(self, tx: Transaction, specs: list[NodeSpec]) -> None:
        def undo() -> None:
            self.actuator.stop(specs)

        tx.run("start", _names(specs), lambda: self.actuator.start(specs), undo)
        for s in specs:
            self.running[s.name] = s

    def _stop(
        self, tx: Transaction, specs: list[NodeSpec], deadlines: Mapping[str, float] | None = None
    ) -> None:
        def undo() -> None:
            self.actuator.start(specs)

        tx.run("stop", _names(specs), lambda: self.actuator.stop(specs, deadlines), undo)
        for s in specs:
            self.running.pop(s.name, None)

    def _control(self, tx: Transaction, action: str, batch: list[Ctl]) -> list[m.Reply]:
        t0 = self.clock()
        replies = self.actuator.control(batch)
        seconds = self.clock() - t0
        failed = [(c, rep) for c, rep in zip(batch, replies, strict=True) if isinstance(rep, m.Err)]
        done = [c for c, rep in zip(batch, replies, strict=True) if not isinstance(rep, m.Err)]
        inverses = [Ctl(c.after or c.spec, c.inverse, c.spec) for c in reversed(done) if c.inverse]
        if inverses:

            def undo() -> None:  # the replies' results are of no use to a rollback
                self._ok(inverses)

            tx.undo.append((f"undo {action}", undo))
        for c in done:
            if c.after is not None:
                table = self.running if c.spec.name in self.running else self.standby
                table[c.spec.name] = c.after
        for c in batch:
            bad = next((rep for cc, rep in failed if cc is c), None)
            detail = "" if bad is None else f"{bad.message} ({bad.code})"  # type: ignore[union-attr]
            tx.records.append(StepRecord(c.label, "", seconds, bad is None, detail))
        if failed:
            c, rep = failed[0]
            raise StepFailed(f"{c.label}: {rep.message}")  # type: ignore[union-attr]
        return replies

    def _ok(self, batch: list[Ctl]) -> list[Any]:
        """Send a batch that must succeed whole; the results of its replies."""
        replies = self.actuator.control(batch)
        for c, rep in zip(batch, replies, strict=True):
            if isinstance(rep, m.Err):
                raise StepFailed(f"{c.label}: {rep.message}")
        return [rep.result for rep in replies]  # type: ignore[union-attr]


def _apply_request(spec: NodeSpec, req: m.NodeRequest) -> NodeSpec:
    """The spec after a control request (for the host agent's restarts)."""
    match req:
        case m.Activate():
            return msgspec.structs.replace(spec, active=True)
        case m.Deactivate():
            return msgspec.structs.replace(spec, active=False)
        case m.SetParams(params=params):
            return msgspec.structs.replace(spec, params={**spec.params, **params})
        case m.Rewire(port=port, keys=keys):
            ports = dict(spec.ports)
            ports[port] = msgspec.structs.replace(ports[port], keys=list(keys))
            return msgspec.structs.replace(spec, ports=ports)
    return spec
