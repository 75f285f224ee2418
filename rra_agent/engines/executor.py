"""Execute a reconfiguration `Plan` on the running system: what can be applied is applied.

The Run-time Resolution Engine computes a `Plan` (`rra_agent.core.plan.diff`); this
module carries it out through an `Actuator` (host agents and node control endpoints on the
bus, or a fake in unit tests).

**Units.** A plan's steps form a dependency graph (`plan_units`): the steps that launch,
stop or rewire one component belong together, a rewire to the output of a component started
(or away from one stopped) in the same plan belongs with that start (or stop), and a
component started with inputs from another one started in the same plan belongs with it. A
parameter change of a running component depends on nothing. Each connected part is a
*unit*: it is applied whole or not at all. Every action records its inverse in its unit; when
an action fails (a node that does not start, a refused control request), that unit's
executed actions are undone in reverse order at once and its remaining steps are skipped,
while every other unit goes on. So a speed limit (a parameter) never waits for, or rolls back
with, an unrelated camera that cannot start. The `Outcome` lists each failed unit, its steps
and why; `rra_agent.core.effect` turns that into what is in effect.

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
   inputs, and the plan's `Rewire` steps) and export the state of the old nodes of the
   warm swaps. Every subscriber listens to the new producers *before* they produce: a
   replacement publishes its first command the moment it is activated (or, cold, as soon
   as it runs), and a sample published before its subscriber is declared is lost (one
   producer period late; measured 3-5 ms of a 10 ms standby switch);
4. ``stop-then-start``, while the connect batch is in flight: the old nodes **stop**, then
   their replacements **start** (active, with the old one's state, which their host agent
   exports before the stop: `ReplaceNode` with ``export``); recorded once the connect batch
   is settled (an action of a unit that failed meanwhile is undone at once);
5. **switch**, one batch: activate the new nodes (with the exported state), deactivate the
   old ones (unless they are stopped next and publish on other keys than their
   replacements: then the connect batch already cut them off), set parameters;
6. **stop** the components that go, with the swapped-out nodes (an inactive node publishes
   nothing, so stopping it last costs the switch nothing), unless a swapped-out node's own
   strategy is ``standby``: then it stays, inactive, for the way back.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Protocol

import msgspec

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.bus.messages import NodeSpec, ParamDecl, PortSpec
from rra_agent.core.plan import (
    Plan,
    PlanStep,
    Rewire,
    SetImplementation,
    SetParameters,
    StartComponent,
    StopComponent,
    SwapComponent,
)
from rra_agent.errors import RraError
from rra_agent.models.resolution import PRE_STARTED, Replacement
from rra_agent.models.system import Component


class StepFailed(RraError):
    """An action on the running system failed. ``nodes``: the nodes it failed for and why,
    when only some of a batch failed (None: all of them)."""

    def __init__(self, message: str, nodes: Mapping[str, str] | None = None) -> None:
        super().__init__(message)
        self.nodes = dict(nodes) if nodes is not None else None


class Actuator(Protocol):
    """What the executor needs from the running system."""

    def start(self, specs: list[NodeSpec]) -> None:
        """Start the nodes and return once all are ready; raise StepFailed naming the nodes
        that did not start (``nodes``), after stopping them; the others run."""
        ...

    def stop(self, nodes: list[NodeSpec], deadlines: Mapping[str, float] | None = None) -> None:
        """Stop the nodes and return once all are gone; raise StepFailed otherwise.
        ``deadlines``: seconds by node name after which its host agent kills it (0: at
        once) instead of its grace periods."""
        ...

    def replace(
        self,
        pairs: list[tuple[NodeSpec, NodeSpec]],
        deadlines: Mapping[str, float] | None = None,
        on_stopped: Callable[[], None] | None = None,
        export: Collection[str] = (),
    ) -> None:
        """Stop each pair's old node, as `stop` does, and start its new one once the old
        one is gone, as `start` does, with the state of the old nodes named in ``export``;
        raise StepFailed naming the old nodes that did not stop (or export) and the new ones
        that did not start (a new one whose old one did not stop is not started).
        ``on_stopped`` is called once the old nodes are gone (the last call counts)."""
        ...

    def control(
        self, batch: list[Ctl], meanwhile: Callable[[], None] | None = None
    ) -> list[m.Reply]:
        """Send every request of the batch at once; one reply per request, in order. With
        ``meanwhile``, it is called once the requests are sent, before their replies are
        read.

        A node that does not answer in time yields an `Err`; nothing is raised."""
        ...


@dataclass(frozen=True)
class Ctl:
    """One control request to a node (its spec before it) and the request undoing it."""

    spec: NodeSpec
    request: m.NodeRequest
    inverse: m.NodeRequest | None = None
    #: The unit of the plan it belongs to (-1: none, it must succeed on its own).
    unit: int = -1

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
class UnitFailure:
    """A unit of a plan that could not be applied (and was undone)."""

    #: The unit's steps, as one line each (``start depth_camera``, ``rewire in of sink``).
    steps: list[str]
    #: Components whose launch, stop or wiring failed, and whose parameter change failed.
    structure: frozenset[str]
    parameters: frozenset[str]
    error: str
    #: The nodes that did not start (or stop), and why (their host agent's reason).
    nodes: dict[str, str] = field(default_factory=dict)
    #: The components that were not even tried (unavailable implementations).
    skipped: bool = False
    rollback_error: str = ""


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
    #: The units that failed (each undone on its own); the others were applied.
    failures: list[UnitFailure] = field(default_factory=list)
    #: Steps of the plan applied, and in all.
    applied: int = 0
    steps: int = 0

    @property
    def partial(self) -> bool:
        """Some of the plan was applied, some not."""
        return bool(self.failures) and self.applied > 0

    @property
    def failed_structure(self) -> frozenset[str]:
        return frozenset(c for f in self.failures for c in f.structure)

    @property
    def failed_parameters(self) -> frozenset[str]:
        return frozenset(c for f in self.failures for c in f.parameters)


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


def must_deactivate(replacement: Replacement, old: NodeSpec, new: NodeSpec) -> bool:
    """Whether a swap deactivates the node it swaps out. An old node that is stopped after
    the switch and publishes on other keys than its replacement needs no deactivation: the
    rewire of its subscribers, in the connect batch, already cut it off. One that stays
    (standby) or shares output keys does; one that stays hot goes on publishing on its own
    keys, which its consumers deselected."""
    shared = bool(_outputs(old) & _outputs(new))
    if replacement.hot(old.name):
        return shared
    return shared or replacement.pre_started(old.name)


def _names(specs: Iterable[NodeSpec]) -> str:
    return ",".join(s.name for s in specs)


# ---- the dependency graph of a plan ----------------------------------------------------------
def _outputs(spec: NodeSpec) -> set[str]:
    return {k for p in spec.ports.values() if p.direction == "publish" for k in p.keys}


def plan_units(
    steps: tuple[PlanStep, ...], running: Mapping[str, NodeSpec], data_key: Callable[[str], str]
) -> list[int]:
    """The unit of each step (an index per step; steps of one unit share it).

    Steps are joined when they launch, stop, restart or rewire the same component; when a
    rewire adds the output of a component launched by the plan, or drops the output of one
    it stops; and when a launched component listens to the output of another one launched.
    A parameter change of a running component stays on its own. ``running``: the specs of
    the nodes that run now; ``data_key``: topic -> key.
    """
    parent = list(range(len(steps)))

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def join(i: int, j: int) -> None:
        parent[find(i)] = find(j)

    owner: dict[str, int] = {}  # component -> a structural step of it
    launched: dict[str, int] = {}  # key -> the step launching its producer
    stopped: dict[str, int] = {}  # key -> the step stopping its producer
    wants: list[tuple[int, set[str], set[str]]] = []  # (step, keys added, keys dropped)
    for i, s in enumerate(steps):
        for name in _structural(s):
            if name in owner:
                join(i, owner[name])
            owner[name] = i
        if isinstance(s, StartComponent | SwapComponent | SetImplementation):
            for t in s.outputs.values():
                launched[data_key(t)] = i
            wants.append((i, {data_key(t) for ts in s.inputs.values() for t in ts}, set()))
        if isinstance(s, StopComponent | SwapComponent) and s.component in running:
            for k in _outputs(running[s.component]):
                stopped[k] = i
        if isinstance(s, Rewire):
            new = {data_key(t) for t in s.topics}
            spec = running.get(s.component)
            old = set(spec.ports[s.port].keys) if spec and s.port in spec.ports else set()
            wants.append((i, new - old, old - new))
    for i, added, dropped in wants:
        for k in added:
            if k in launched and launched[k] != i:
                join(i, launched[k])
        for k in dropped:
            if k in stopped:
                join(i, stopped[k])
    roots: dict[int, int] = {}
    return [roots.setdefault(find(i), len(roots)) for i in range(len(steps))]


def _structural(s: PlanStep) -> tuple[str, ...]:
    """The components whose presence or wiring a step changes (none for parameters)."""
    if isinstance(s, SwapComponent):
        return (s.component, s.replacement)
    if isinstance(s, SetParameters):
        return ()
    return (s.component,)


def describe_step(s: PlanStep) -> str:
    match s:
        case SwapComponent(component=old, replacement=new):
            return f"swap {old} -> {new}"
        case StartComponent(component=c):
            return f"start {c}"
        case StopComponent(component=c):
            return f"stop {c}"
        case SetImplementation(component=c):
            return f"restart {c} (implementation)"
        case SetParameters(component=c, values=v):
            return f"set {c} {', '.join(f'{k}={x!r}' for k, x in v.items())}"
        case Rewire(component=c, port=p):
            return f"rewire {c}.{p}"
    return type(s).__name__  # pragma: no cover


class Transaction:
    """Runs actions, remembers per unit how to undo each, and undoes a unit when one of its
    actions fails (the other units go on)."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self.clock = clock
        self.records: list[StepRecord] = []
        self.undo: dict[int, list[tuple[str, Callable[[], None]]]] = {}
        #: unit -> (error, nodes that failed)
        self.failed: dict[int, tuple[str, dict[str, str], str]] = {}

    def ok(self, unit: int) -> bool:
        return unit not in self.failed

    def push(self, unit: int, what: str, undo: Callable[[], None]) -> None:
        """Remember how to undo an action of ``unit`` that was done; if the unit has failed
        meanwhile (an action running beside another that failed it), undo it now."""
        if unit in self.failed:
            try:
                undo()
            except Exception as e:
                error, nodes, first = self.failed[unit]
                self.failed[unit] = (error, nodes, first or f"{what}: {e}")
            return
        self.undo.setdefault(unit, []).append((what, undo))

    def fail(self, unit: int, error: str, nodes: Mapping[str, str] | None = None) -> None:
        """Unit ``unit`` failed: undo what it did, in reverse order, at once."""
        if unit in self.failed:
            return
        first = ""
        for what, fn in reversed(self.undo.pop(unit, [])):
            try:
                fn()
            except Exception as e:  # keep undoing the rest
                first = first or f"{what}: {e}"
        self.failed[unit] = (error, dict(nodes or {}), first)


@dataclass
class _Swap:
    step: SwapComponent
    old: NodeSpec
    new: NodeSpec
    strategy: str
    unit: int


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
        self._switched: float | None = None

    # ---- public ------------------------------------------------------------------------
    def prestart_standby(self, specs: list[NodeSpec]) -> Outcome:
        """Start standby replacements (at deployment time): inactive, or active if hot.
        Those that start are kept even when others do not."""
        specs = [msgspec.structs.replace(s, active=self.replacement.hot(s.name)) for s in specs]
        t0 = self.clock()
        if not specs:
            return Outcome(True)
        try:
            self.actuator.start(specs)
            failed: dict[str, str] = {}
        except StepFailed as e:
            failed = e.nodes if e.nodes is not None else {s.name: str(e) for s in specs}
        seconds = self.clock() - t0
        records = [StepRecord("prestart", s.name, seconds, s.name not in failed,
                              failed.get(s.name, "")) for s in specs]  # fmt: skip
        for s in specs:
            if s.name not in failed:
                self.standby[s.name] = s
        failures = [
            UnitFailure([f"prestart {n}"], frozenset({n}), frozenset(), f"start {n}: {why}",
                        {n: why}) for n, why in failed.items()
        ]  # fmt: skip
        return Outcome(
            not failed,
            records,
            failures[0].error if failures else "",
            rolled_back=bool(failed),
            seconds=seconds,
            failures=failures,
            applied=len(specs) - len(failed),
            steps=len(specs),
        )

    def normalize(self, plan: Plan) -> tuple[Plan, list[str]]:
        """The plan as it applies to the nodes this executor knows to run, and what had to
        change: a stop of a node that is not running is dropped, a swap whose old node is not
        running becomes a start, parameters and rewires of a node that is not running are
        dropped (it starts with them). Such a plan comes from a model that moved on without
        the running system; the reconcile loop converges the rest."""
        known = {**self.running, **self.standby}
        steps: list[PlanStep] = []
        notes: list[str] = []
        for s in plan.steps:
            name = s.component
            if isinstance(s, SwapComponent) and name not in self.running:
                notes.append(f"{name} was not running: {s.replacement} is started instead")
                steps.append(
                    StartComponent(
                        component=s.replacement,
                        definition=s.definition,
                        inputs=s.inputs,
                        outputs=s.outputs,
                    )
                )
            elif isinstance(s, StartComponent) and name in self.running:
                notes.append(f"{name} was running already")
            elif isinstance(
                s, StopComponent | SetParameters | Rewire | SetImplementation
            ) and (name not in known):
                if isinstance(s, SetImplementation):
                    steps.append(
                        StartComponent(
                            component=name,
                            definition=s.definition,
                            inputs=s.inputs,
                            outputs=s.outputs,
                        )
                    )
                notes.append(f"{name} was not running ({type(s).__name__} adjusted)")
            else:
                steps.append(s)
        return Plan(steps=tuple(steps)), notes

    def execute(self, plan: Plan, *, skip: Collection[str] = ()) -> Outcome:
        """Apply ``plan``; the units launching a component named in ``skip`` (implementations
        known to be unavailable) are not tried and count as failed."""
        t0 = self.clock()
        plan, notes = self.normalize(plan)
        units = plan_units(plan.steps, self.running, self.keys.data)
        tx = Transaction(self.clock)
        tx.records.extend(StepRecord("note", "", 0.0, True, n) for n in notes)
        self._switched = None
        for i, s in enumerate(plan.steps):
            name = _launches(s)
            if name is not None and name in skip:
                tx.fail(units[i], f"{name} is unavailable", {name: "unavailable"})
        self._apply(plan, units, tx)
        return self._outcome(plan, units, tx, t0)

    def _outcome(self, plan: Plan, units: list[int], tx: Transaction, t0: float) -> Outcome:
        failures = []
        for u, (error, nodes, rollback_error) in tx.failed.items():
            mine = [s for s, v in zip(plan.steps, units, strict=True) if v == u]
            failures.append(
                UnitFailure(
                    steps=[describe_step(s) for s in mine],
                    structure=frozenset(n for s in mine for n in _structural(s)),
                    parameters=frozenset(
                        s.component for s in mine if isinstance(s, SetParameters)
                    ),
                    error=error,
                    nodes=nodes,
                    skipped=set(nodes.values()) == {"unavailable"},
                    rollback_error=rollback_error,
                )
            )
        applied = sum(1 for u in units if u not in tx.failed)
        first = None if self._switched is None else self._switched - t0
        rollback_error = next((f.rollback_error for f in failures if f.rollback_error), "")
        return Outcome(
            not failures,
            tx.records,
            failures[0].error if failures else "",
            rolled_back=bool(failures) and not rollback_error,
            rollback_error=rollback_error,
            seconds=self.clock() - t0,
            first_switch=first,
            failures=failures,
            applied=applied,
            steps=len(plan.steps),
        )

    # ---- the phases --------------------------------------------------------------------
    def _apply(self, plan: Plan, units: list[int], tx: Transaction) -> None:
        steps = list(zip(plan.steps, units, strict=True))
        steps = self._parameters_first(tx, steps)
        live = [(s, u) for s, u in steps if tx.ok(u)]
        starts = [(self._spec(s), u) for s, u in live if isinstance(s, StartComponent)]
        self._start(tx, starts)
        swaps = [
            self._plan_swap(s, u)
            for s, u in steps
            if isinstance(s, SwapComponent) and tx.ok(u)
        ]
        restarts = [(s, u) for s, u in steps if isinstance(s, SetImplementation) and tx.ok(u)]
        self._prepare(tx, swaps, restarts)
        swaps = [w for w in swaps if tx.ok(w.unit)]
        cold = [w for w in swaps if w.strategy == "stop-then-start"]
        warm = [w for w in swaps if w.strategy != "stop-then-start"]
        replaced: list[Callable[[Transaction], None]] = []
        meanwhile = (lambda: replaced.append(self._replace(cold))) if cold else None
        states = self._connect(tx, warm, steps, meanwhile)
        hot = [w.new.name for w in warm if self.replacement.hot(w.new.name) and tx.ok(w.unit)]
        if hot:  # the consumers' rewire was the switch: say so in the plan
            self._switched = self.clock()
            tx.records.append(StepRecord("select", ",".join(hot), 0.0, True))
        for settle in replaced:
            settle(tx)
            if any(tx.ok(w.unit) for w in cold):
                self._switched = self.clock()
        warm = [w for w in warm if tx.ok(w.unit)]
        self._switch(tx, warm, steps, states)
        self._retire(tx, [w for w in warm if tx.ok(w.unit)], steps)

    def _parameters_first(self, tx: Transaction, steps: list[tuple[PlanStep, int]]):
        """A plan that starts processes sets the parameters that depend on nothing first, in
        one batch, so that they never wait for a start (seconds, or a timeout); the other
        steps are returned. Without starts they go with the switch (one batch less)."""
        launches = any(self._starts_process(s) for s, u in steps if tx.ok(u))
        mixed = {u for s, u in steps if not isinstance(s, SetParameters)}
        alone = [(s, u) for s, u in steps if u not in mixed and tx.ok(u)]
        if not launches or not alone:
            return steps
        self._control(tx, "parameters", self._param_ctls(alone))
        return [(s, u) for s, u in steps if u in mixed]

    def _starts_process(self, s: PlanStep) -> bool:
        """Whether a step starts a process: a swap to a pre-started replacement that is
        running (standby, hot standby) does not."""
        name = _launches(s)
        if name is None:
            return False
        strategy = self.replacement.strategy_for(name)
        return not (isinstance(s, SwapComponent) and strategy in PRE_STARTED
                    and name in self.standby)

    def _param_ctls(self, steps) -> list[Ctl]:
        out = []
        for s, u in steps:
            if isinstance(s, SetParameters):
                spec = self.running[s.component]
                old = {k: spec.params.get(k) for k in s.values}
                request = m.SetParams(params=dict(s.values))
                out.append(Ctl(spec, request, m.SetParams(params=old), u))
        return out

    def _retire(self, tx: Transaction, warm: list[_Swap], steps) -> None:
        """Stop what goes; a swapped-out standby node stays, inactive, for the way back."""
        stops = [
            (self.running[s.component], u)
            for s, u in steps
            if isinstance(s, StopComponent) and tx.ok(u) and s.component in self.running
        ]
        for w in warm:
            if not self.replacement.pre_started(w.old.name):
                stops.append((self.running[w.old.name], w.unit))
            else:
                spec = self.running.pop(w.old.name)
                self.standby[w.old.name] = spec
                tx.push(w.unit, f"keep {w.old.name}", partial(self._unkeep, spec))
        self._stop(tx, stops)

    def _unkeep(self, spec: NodeSpec) -> None:
        self.running[spec.name] = self.standby.pop(spec.name, spec)

    def _spec(self, s: StartComponent | SwapComponent | SetImplementation, **kw: Any):
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

    def _plan_swap(self, s: SwapComponent, unit: int) -> _Swap:
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
        return _Swap(s, self.running[s.component], new, strategy, unit)

    def _prepare(self, tx: Transaction, swaps: list[_Swap], restarts) -> None:
        """Everything before the connect batch: make-before-break replacements started
        (inactive), pre-started ones taken from the standby table, restarts done."""
        self._start(tx, [(w.new, w.unit) for w in swaps if w.strategy == "start-then-stop"])
        for w in swaps:
            if w.strategy in PRE_STARTED and tx.ok(w.unit):
                name = w.new.name
                self.running[name] = self.standby.pop(name)
                tx.push(w.unit, f"take {name}", partial(self._untake, name))
        if restarts:
            self._stop(tx, [(self.running[s.component], u) for s, u in restarts])
            self._start(tx, [(self._spec(s), u) for s, u in restarts if tx.ok(u)])

    def _untake(self, name: str) -> None:
        """Give a pre-started node back to the standby table (its unit failed)."""
        if name in self.running:
            self.standby[name] = self.running.pop(name)

    def _wants_state(self, w: _Swap) -> bool:
        return any(
            t.source == w.old.name and t.target == w.new.name
            for t in self.replacement.state_transfer
        )

    def _connect(
        self,
        tx: Transaction,
        warm: list[_Swap],
        steps,
        meanwhile: Callable[[], None] | None = None,
    ) -> dict[str, Any]:
        """Rewire every subscriber to its new producers and export the state of the old
        nodes of the warm swaps, in one batch; the exported state of each warm swap's new
        node (absent: not wanted). ``meanwhile`` (the cold swaps, whose host agents export
        their old nodes' state themselves) runs while the batch is in flight: a cold swap's
        consumers, rewired here, may hear its old node until it is killed, never its new
        one before they listen to it (its code runs only once the old one is gone)."""
        batch: list[Ctl] = []
        for w in warm:
            new = self.running[w.new.name]
            wiring = {p: [self.keys.data(t) for t in ts] for p, ts in w.step.inputs.items()}
            batch += self._rewires(new, wiring, w.unit)
        for s, u in steps:
            if isinstance(s, Rewire) and tx.ok(u):
                spec = self.running[s.component]
                batch += self._rewires(spec, {s.port: [self.keys.data(t) for t in s.topics]}, u)
        wanted = [w for w in warm if self._wants_state(w)]
        exports = [Ctl(w.old, m.ExportState(), unit=w.unit) for w in wanted]
        if not batch and not exports:
            if meanwhile is not None:
                meanwhile()
            return {}
        replies = self._control(tx, "connect", batch + exports, meanwhile)
        return {
            w.new.name: rep.result
            for w, rep in zip(wanted, replies[len(batch) :], strict=True)
            if isinstance(rep, m.Ok)
        }

    def _switch(self, tx: Transaction, warm: list[_Swap], steps, states: dict[str, Any]) -> None:
        batch: list[Ctl] = []
        for w in warm:
            new = self.running[w.new.name]
            state = states.get(w.new.name)
            if not new.active:
                batch.append(self._activation(new, True, w.unit, state))
            elif state is not None:  # a hot standby: it runs already, and takes the state
                batch.append(Ctl(new, m.ImportState(state=state), None, w.unit))
            if self._must_deactivate(w):
                batch.append(self._activation(self.running[w.old.name], False, w.unit))
        batch += self._param_ctls([(s, u) for s, u in steps if tx.ok(u)])
        if not batch:
            return
        self._control(tx, "switch", batch)
        if any(tx.ok(w.unit) for w in warm) and self._switched is None:
            self._switched = self.clock()

    def _must_deactivate(self, w: _Swap) -> bool:
        return must_deactivate(self.replacement, w.old, w.new)

    @staticmethod
    def _activation(spec: NodeSpec, active: bool, unit: int, state: Any = None) -> Ctl:
        req = m.Activate(state=state) if active else m.Deactivate()
        inv = m.Deactivate() if active else m.Activate()
        return Ctl(spec, req, inv, unit)

    @staticmethod
    def _rewires(spec: NodeSpec, wiring: dict[str, list[str]], unit: int) -> list[Ctl]:
        out = []
        for port, keys in wiring.items():
            old = list(spec.ports[port].keys)
            if old != keys:
                out.append(Ctl(spec, m.Rewire(port=port, keys=keys), m.Rewire(port=port, keys=old),
                               unit))  # fmt: skip
        return out

    # ---- actions with their inverses ---------------------------------------------------
    def _start(self, tx: Transaction, specs: list[tuple[NodeSpec, int]]) -> None:
        """Start the nodes at once; a node that does not start fails its unit."""
        self._batch(tx, "start", specs, self.actuator.start, self._started, self._unstart)

    def _started(self, spec: NodeSpec) -> None:
        self.running[spec.name] = spec

    def _unstart(self, spec: NodeSpec) -> None:
        self.running.pop(spec.name, None)
        self.actuator.stop([spec])

    def _stop(
        self,
        tx: Transaction,
        specs: list[tuple[NodeSpec, int]],
        deadlines: Mapping[str, float] | None = None,
    ) -> None:
        def stop(nodes: list[NodeSpec]) -> None:
            self.actuator.stop(nodes, deadlines)

        self._batch(tx, "stop", specs, stop, self._stopped, self._unstop)

    def _stopped(self, spec: NodeSpec) -> None:
        self.running.pop(spec.name, None)

    def _unstop(self, spec: NodeSpec) -> None:
        self.actuator.start([spec])
        self.running[spec.name] = spec

    def _replace(self, cold: list[_Swap]) -> Callable[[Transaction], None]:
        """Do the ``stop-then-start`` swaps: each old node stopped and its new one started
        once it is gone, with the old one's state where it is wanted (exported by their host
        agent); recorded and undone as a stop then a start (a failed start brings the old
        node back) by the function returned, once the connect batch beside it is settled."""
        pairs = [(w.old, w.new, w.unit) for w in cold]
        exporting = [w.old for w in cold if self._wants_state(w)]
        t0 = self.clock()
        gone: list[float] = []
        failed = _failed_by(
            lambda: self.actuator.replace([(o, n) for o, n, _ in pairs],
                                          self.replacement.stop_deadline,
                                          lambda: gone.append(self.clock()),
                                          {o.name for o in exporting}),
            [s.name for o, n, _ in pairs for s in (o, n)],
        )  # fmt: skip
        t1 = self.clock()
        stopped = gone[-1] if gone else t1  # the start's line: from the old node's end

        def settle(tx: Transaction) -> None:
            # the exports were part of the stops (their host agents asked first): one line
            _record(tx, "export_state", exporting,
                    {o.name: failed[o.name] for o in exporting if o.name in failed},
                    stopped - t0)  # fmt: skip
            self._settle(tx, failed, [
                ("stop", [(o, u) for o, _, u in pairs], self._stopped, self._unstop,
                 stopped - t0),
                ("start", [(n, u) for _, n, u in pairs], self._started, self._unstart,
                 t1 - stopped),
            ])  # fmt: skip

        return settle

    def _batch(
        self,
        tx: Transaction,
        action: str,
        specs: list[tuple[NodeSpec, int]],
        call: Callable[[list[NodeSpec]], None],
        done: Callable[[NodeSpec], None],
        undo: Callable[[NodeSpec], None],
    ) -> None:
        """Start or stop the nodes at once. Each that made it is ``done`` and leaves its
        ``undo`` in its unit first; then each that did not fails its unit (undoing the
        unit's other actions, those of this batch included)."""
        if not specs:
            return
        t0 = self.clock()
        failed = _failed_by(lambda: call([s for s, _ in specs]), [s.name for s, _ in specs])
        self._settle(tx, failed, [(action, specs, done, undo, self.clock() - t0)])

    def _settle(
        self,
        tx: Transaction,
        failed: Mapping[str, str],
        groups: list[tuple[str, list[tuple[NodeSpec, int]], Callable[[NodeSpec], None],
                          Callable[[NodeSpec], None], float]],
    ) -> None:
        """After one call to the actuator: each group's action recorded with its seconds;
        each action that was done is ``done`` and leaves its ``undo`` in its unit first; then
        each unit with an action that failed (named in ``failed``) fails, undoing the unit's
        other actions, those of this call included."""
        for action, specs, _, _, seconds in groups:
            mine = {s.name: failed[s.name] for s, _ in specs if s.name in failed}
            _record(tx, action, [s for s, _ in specs], mine, seconds)
        late: list[tuple[int, str, Callable[[], None]]] = []  # of units failed meanwhile
        for action, specs, done, undo, _ in groups:
            for spec, unit in specs:
                if spec.name not in failed:
                    done(spec)
                    entry: tuple[int, str, Callable[[], None]] = (
                        unit, f"{action} {spec.name}", partial(undo, spec))  # fmt: skip
                    if tx.ok(unit):
                        tx.push(*entry)
                    else:
                        late.append(entry)
        for entry in reversed(late):  # undone at once, the newest action first
            tx.push(*entry)
        for action, specs, _, _, _ in groups:
            for spec, unit in specs:
                if spec.name in failed:
                    why = failed[spec.name]
                    tx.fail(unit, f"{action} {spec.name}: {why}", {spec.name: why})

    def _control(
        self,
        tx: Transaction,
        action: str,
        batch: list[Ctl],
        meanwhile: Callable[[], None] | None = None,
    ) -> list[m.Reply]:
        """Send the batch (``meanwhile`` runs while it is in flight: the batch's lines leave
        its time out, being the send and what was still to wait for after it); each
        successful request updates its node's spec and leaves its inverse in its unit; a
        failed one fails its unit (undoing what the unit did)."""
        beside = [0.0]

        def timed() -> None:
            t = self.clock()
            assert meanwhile is not None
            meanwhile()
            beside[0] = self.clock() - t

        t0 = self.clock()
        replies = self.actuator.control(batch, timed if meanwhile is not None else None)
        seconds = self.clock() - t0 - beside[0]
        for c, rep in zip(batch, replies, strict=True):
            bad = rep if isinstance(rep, m.Err) else None
            detail = "" if bad is None else f"{bad.message} ({bad.code})"
            tx.records.append(StepRecord(c.label, "", seconds, bad is None, detail))
            if bad is None:
                self._update(c.spec.name, c.request)
                if c.inverse is not None:
                    tx.push(c.unit, f"{action} {c.label}", partial(self._undo_control, c))
        for c, rep in zip(batch, replies, strict=True):
            if isinstance(rep, m.Err):
                tx.fail(c.unit, f"{c.label}: {rep.message}")
        return replies

    def _undo_control(self, c: Ctl) -> None:
        assert c.inverse is not None
        table = self.running if c.spec.name in self.running else self.standby
        spec = table.get(c.spec.name, c.spec)
        rep = self.actuator.control([Ctl(spec, c.inverse)])[0]
        if isinstance(rep, m.Err):
            raise StepFailed(f"{c.label}: {rep.message}")
        self._update(c.spec.name, c.inverse)

    def _update(self, name: str, request: m.NodeRequest) -> None:
        table = self.running if name in self.running else self.standby
        if name in table:
            table[name] = apply_request(table[name], request)


def _record(
    tx: Transaction, action: str, specs: list[NodeSpec], failed: Mapping[str, str], seconds: float
) -> None:
    """One plan line for the nodes of a batch that made it, one for each that did not."""
    done = [s for s in specs if s.name not in failed]
    if done:
        tx.records.append(StepRecord(action, _names(done), seconds))
    for name, why in failed.items():
        tx.records.append(StepRecord(action, name, seconds, False, why))


def _failed_by(call: Callable[[], None], names: list[str]) -> dict[str, str]:
    """Run an actuator call; the nodes it names as failed, and why (all of ``names`` if it
    names none)."""
    try:
        call()
    except StepFailed as e:
        return dict(e.nodes) if e.nodes is not None else {n: str(e) for n in names}
    return {}


def _launches(s: PlanStep) -> str | None:
    """The component a step starts a process of (None: it starts nothing)."""
    if isinstance(s, StartComponent | SetImplementation):
        return s.component
    if isinstance(s, SwapComponent):
        return s.replacement
    return None


def apply_request(spec: NodeSpec, req: m.NodeRequest) -> NodeSpec:
    """The spec after a control request (for the host agent's restarts)."""
    match req:
        case m.Activate():
            return msgspec.structs.replace(spec, active=True)
        case m.Deactivate():
            return msgspec.structs.replace(spec, active=False)
        case m.SetParams(params=params, decl=decl):
            return msgspec.structs.replace(
                spec, params={**spec.params, **params}, decl={**spec.decl, **decl}
            )
        case m.Rewire(port=port, keys=keys):
            ports = dict(spec.ports)
            ports[port] = msgspec.structs.replace(ports[port], keys=list(keys))
            return msgspec.structs.replace(spec, ports=ports)
    return spec
