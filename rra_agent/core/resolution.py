"""Variability resolution (paper Sec. II and III-E): one engine for both binding times.

The paper's Deployment-time and Run-time Resolution Engines are "based on the same software
library"; this module is that library. Both apply the transformations of the selected features
to a system model; they differ only in their input model and in which optional parts are
variation points:

- `resolve_deployment`: Template System Model -> Deployment-time Configured System Model. An
  optional *deployment-bound* component or connection is present only if a selected feature's
  transformation includes it (``include_component`` / ``add_connection``); once included it is
  no longer optional. Optional *run-time-bound* parts are kept untouched, still marked
  optional: they are the run-time variation points. ``from_attribute`` is not allowed here.
- `resolve_runtime`: Deployment-time Configured System Model -> the target Run-time Configured
  System Model for one run-time selection and its Continuous Variability values. The run-time
  variation points start absent; the selected features' transformations launch them (or
  remove, re-implement, re-parameterise, rewire anything else). The result holds only what
  runs; included run-time parts keep ``optional``/``binding`` as provenance.

Rules common to both (a transformation list is the resolution model's entries for the
selected features, in the feature model's order, each feature's list in order):

- A connection is present only if both of its components are: removing (or not including) a
  component removes its connections. A non-optional connection to a run-time optional
  component therefore appears whenever that component is launched.
- ``include_component`` / ``add_connection`` name an optional part the input model declares
  with this phase's binding (a non-optional part is always there). ``remove_component`` may
  remove any component, including a non-optional one (at run time too: e.g. a stable
  controller replaced by a run-time variant).
- Conflicts are errors naming both features and both transformations: one parameter set to
  two different values (or once from a CV attribute and once literally), two implementations
  for one component, include and remove of one component, add and remove of one connection.
  Two features doing the same thing are not in conflict. As every conflict is an error, the
  result does not depend on the order of application.
- Referencing something absent is an error: an unknown feature, component, port, parameter or
  implementation name, or a change to a component the selection removes or does not include.
  Parameter values are type-checked against the declaration; nothing is clamped.
- Output is deterministic: components and connections in the input model's order.

`diff` compares two configured models and produces the `Plan` that turns the running system of
one into the other's; `topic_of` and `subscriptions` define how connections map onto topics.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from typing import Literal, TypeVar

import msgspec

from rra_agent.errors import ResolutionError, SelectionError
from rra_agent.models.features import FeatureModel
from rra_agent.models.resolution import ConnectionRef, ResolutionModel, Transformation
from rra_agent.models.system import (
    Component,
    Connection,
    Implementation,
    Parameter,
    ParamValue,
    SystemModel,
    coerce_parameter,
    parse_endpoint,
    value_has_type,
)

Phase = Literal["deployment", "runtime"]
_WORD = {"deployment": "deployment", "runtime": "run"}
_Part = TypeVar("_Part", Component, Connection)
ConnKey = tuple[str, str]

__all__ = [
    "Plan",
    "PlanStep",
    "Rewire",
    "SetImplementation",
    "SetParameters",
    "StartComponent",
    "Step",
    "StopComponent",
    "SwapComponent",
    "diff",
    "peers_of",
    "resolve_deployment",
    "resolve_runtime",
    "standby_subscriptions",
    "subscriptions",
    "topic_of",
    "wiring",
]


# ---------------------------------------------------------------------------------------------
# Public entry points
# ---------------------------------------------------------------------------------------------
def resolve_deployment(
    template: SystemModel,
    model: ResolutionModel,
    fm: FeatureModel,
    selection: Collection[str],
) -> SystemModel:
    """The Deployment-time Configured System Model for a deployment-time selection.

    ``selection`` holds feature names or aliases; features of ``model`` not selected are
    ignored. Checking the selection against the feature model's constraints is the caller's
    job (the feature-model core). Raises `ResolutionError` (`SelectionError` for an unknown
    selected feature).
    """
    steps = _selected_transformations(model, fm, selection, "deployment")
    return _Resolver("deployment", template, steps, {}).run()


def resolve_runtime(
    configured: SystemModel,
    model: ResolutionModel,
    fm: FeatureModel,
    selection: Collection[str],
    cv: Mapping[str, float],
) -> SystemModel:
    """The target Run-time Configured System Model for a run-time selection.

    ``configured`` is a Deployment-time Configured System Model (no deployment-time variation
    point left); ``selection`` the selected features (names or aliases; features without
    run-time transformations, deployment-time ones included, change nothing); ``cv`` maps
    Continuous Variability attribute names to their current values, read by ``set_parameter``
    with ``from_attribute``.
    """
    steps = _selected_transformations(model, fm, selection, "runtime")
    _check_attributes(steps, fm)
    return _Resolver("runtime", configured, steps, cv).run()


# ---------------------------------------------------------------------------------------------
# Selecting the transformations
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class _Step:
    """One transformation of one selected feature."""

    feature: str
    t: Transformation

    def __str__(self) -> str:
        return f"feature {self.feature!r} ({_describe(self.t)})"


def _selected_transformations(
    model: ResolutionModel, fm: FeatureModel, selection: Collection[str], phase: Phase
) -> list[_Step]:
    """The transformations of the selected features, in the feature model's order."""
    by_feature = _normalise_model(model, fm, phase)
    selected: set[str] = set()
    unknown = []
    for name in selection:
        canonical = fm.resolve_name(name)
        if canonical is None:
            unknown.append(name)
        else:
            selected.add(canonical)
    if unknown:
        raise SelectionError(
            "unknown feature(s) in the selection", [f"no feature {n!r}" for n in sorted(unknown)]
        )
    return [_Step(f, t) for f in fm.features if f in selected for t in by_feature.get(f, ())]


def _normalise_model(
    model: ResolutionModel, fm: FeatureModel, phase: Phase
) -> dict[str, list[Transformation]]:
    """The model's entries keyed by canonical feature name (keys may be aliases)."""
    out: dict[str, list[Transformation]] = {}
    problems = []
    for key, transformations in model.features.items():
        name = fm.resolve_name(key)
        if name is None:
            problems.append(
                f"the {_WORD[phase]}-time resolution model maps unknown feature {key!r}"
            )
        elif name in out:
            problems.append(f"the {_WORD[phase]}-time resolution model maps feature {name!r} twice")
        elif fm.binding[name] != phase:
            problems.append(
                f"the {_WORD[phase]}-time resolution model maps feature {name!r}, "
                f"which is bound at {_WORD[fm.binding[name]]} time"
            )
        else:
            out[name] = list(transformations)
    _raise(phase, problems)
    return out


def _check_attributes(steps: list[_Step], fm: FeatureModel) -> None:
    problems = []
    for s in steps:
        sp = s.t.set_parameter
        if sp is None or sp.from_attribute is None:
            continue
        found = fm.attributes.get(sp.from_attribute)
        if found is None or found[1].kind != "cv":
            problems.append(f"{s}: {sp.from_attribute!r} is not a Continuous Variability attribute")
    _raise("runtime", problems)


def _describe(t: Transformation) -> str:
    """A one-line rendering of a transformation, as used in error messages."""
    match t.op:
        case "include_component" | "remove_component":
            return f"{t.op} {getattr(t, t.op)}"
        case "set_implementation":
            si = t.set_implementation
            assert si is not None
            return f"set_implementation {si.component} -> {si.implementation}"
        case "set_parameter":
            sp = t.set_parameter
            assert sp is not None
            what = f"from {sp.from_attribute}" if sp.from_attribute else f"= {sp.value!r}"
            return f"set_parameter {sp.component}.{sp.parameter} {what}"
        case _:
            ref: ConnectionRef = getattr(t, t.op)
            return f"{t.op} {ref.source} -> {ref.target}"


def _raise(phase: Phase, problems: list[str]) -> None:
    if len(problems) == 1:
        raise ResolutionError(f"{_WORD[phase]}-time resolution: {problems[0]}")
    if problems:
        lines = "\n".join(f"  - {p}" for p in problems)
        raise ResolutionError(f"{_WORD[phase]}-time resolution: {len(problems)} problems\n{lines}")


# ---------------------------------------------------------------------------------------------
# Applying them
# ---------------------------------------------------------------------------------------------
@dataclass
class _Resolver:
    """Collects the transformations (checking conflicts), then builds the result."""

    phase: Phase
    source: SystemModel
    steps: list[_Step]
    cv: Mapping[str, float]
    problems: list[str] = field(default_factory=list)
    include: dict[str, _Step] = field(default_factory=dict)
    remove: dict[str, _Step] = field(default_factory=dict)
    implementation: dict[str, _Step] = field(default_factory=dict)
    parameter: dict[tuple[str, str], _Step] = field(default_factory=dict)
    add: dict[ConnKey, _Step] = field(default_factory=dict)
    drop: dict[ConnKey, _Step] = field(default_factory=dict)
    components: dict[str, Component] = field(init=False)
    declared: dict[ConnKey, Connection] = field(init=False)

    def __post_init__(self) -> None:
        self.components = {c.name: c for c in self.source.components}
        self.declared = {c.key: c for c in self.source.connections}

    def run(self) -> SystemModel:
        if self.phase == "runtime":
            self._check_configured()
        for step in self.steps:
            self._collect(step)
        kept = self._kept_components()
        self._check_targets(kept)
        connections = self._connections(kept)
        components = [self._configure(c) for c in kept.values()]
        _raise(self.phase, self.problems)
        return msgspec.structs.replace(self.source, components=components, connections=connections)

    # ---- phase 1: collect, detecting conflicts ----------------------------------------------
    def _collect(self, step: _Step) -> None:
        t = step.t
        match t.op:
            case "include_component":
                self._include(step, t.include_component)  # type: ignore[arg-type]
            case "remove_component":
                self._component_exists(step, t.remove_component)  # type: ignore[arg-type]
                self._record(self.remove, t.remove_component, step, self.include)
            case "set_implementation":
                si = t.set_implementation
                assert si is not None
                self._record(self.implementation, si.component, step)
            case "set_parameter":
                sp = t.set_parameter
                assert sp is not None
                if sp.from_attribute is not None and self.phase == "deployment":
                    self.problems.append(f"{step}: from_attribute is only allowed at run time")
                self._record(self.parameter, (sp.component, sp.parameter), step)
            case "add_connection":
                self._add_connection(step, t.add_connection)  # type: ignore[arg-type]
            case "remove_connection":
                ref: ConnectionRef = t.remove_connection  # type: ignore[assignment]
                if ref.key not in self.declared:
                    self.problems.append(f"{step}: no such connection")
                self._record(self.drop, ref.key, step, self.add)

    def _record(self, table: dict, key: object, step: _Step, opposite: dict | None = None) -> None:
        """Record ``step`` under ``key``; a different earlier entry (or an opposite) conflicts."""
        if opposite is not None and key in opposite:
            self._conflict(opposite[key], step)
        earlier = table.get(key)
        if earlier is None:
            table[key] = step
        elif not _same_effect(earlier.t, step.t):
            self._conflict(earlier, step)

    def _conflict(self, a: _Step, b: _Step) -> None:
        self.problems.append(f"conflict between {a} and {b}")

    def _component_exists(self, step: _Step, name: str) -> bool:
        if name in self.components:
            return True
        self.problems.append(f"{step}: no component {name!r} in system {self.source.system!r}")
        return False

    def _include(self, step: _Step, name: str) -> None:
        if self._component_exists(step, name):
            problem = self._variation_point_problem(self.components[name])
            if problem:
                self.problems.append(f"{step}: component {name!r} {problem}")
        self._record(self.include, name, step, self.remove)

    def _add_connection(self, step: _Step, ref: ConnectionRef) -> None:
        conn = self.declared.get(ref.key)
        problem = "is not declared" if conn is None else self._variation_point_problem(conn)
        if problem:
            self.problems.append(f"{step}: connection {problem}")
        self._record(self.add, ref.key, step, self.drop)

    def _variation_point_problem(self, part: Component | Connection) -> str | None:
        """Why ``part`` cannot be included in this phase (None if it can)."""
        if not part.optional:
            return "is not optional"
        if part.binding != self.phase:
            return f"is bound at {_WORD[part.binding]} time"
        return None

    def _check_configured(self) -> None:
        """A run-time input must have no deployment-time variation point left."""
        parts: list[Component | Connection] = [*self.source.components, *self.source.connections]
        for part in parts:
            if part.optional and part.binding == "deployment":
                what = part.name if isinstance(part, Component) else "->".join(part.key)
                self.problems.append(
                    f"{what!r} is a deployment-time variation point: resolve deployment first"
                )

    # ---- phase 2: build ---------------------------------------------------------------------
    def _kept_components(self) -> dict[str, Component]:
        kept = {}
        for c in self.source.components:
            if c.name in self.remove:
                continue
            if not c.optional or c.name in self.include:
                kept[c.name] = _fixed(c) if c.binding == "deployment" else c
            elif self.phase == "deployment" and c.binding == "runtime":
                kept[c.name] = c  # a run-time variation point
        return kept

    def _connections(self, kept: dict[str, Component]) -> list[Connection]:
        out: list[Connection] = []
        for conn in self.source.connections:
            if conn.key in self.drop:
                continue
            wanted = not conn.optional or conn.key in self.add or self._is_variation_point(conn)
            if wanted and self._endpoints_present(conn.key, kept, self.add.get(conn.key)):
                out.append(_fixed(conn) if conn.binding == "deployment" else conn)
        return out

    def _is_variation_point(self, conn: Connection) -> bool:
        return self.phase == "deployment" and conn.binding == "runtime"

    def _endpoints_present(
        self, key: ConnKey, kept: dict[str, Component], step: _Step | None
    ) -> bool:
        """Whether both components of a connection are present; an absent one is an error for
        an explicitly added connection."""
        for end in key:
            comp = parse_endpoint(end).component
            if comp not in kept:
                if step is not None:
                    self.problems.append(f"{step}: {self._absence(comp)}")
                return False
        return True

    def _check_targets(self, kept: dict[str, Component]) -> None:
        """set_implementation / set_parameter must target a component present in the result."""
        targets = [*self.implementation.items(), *self.parameter.items()]
        for key, step in targets:
            name = key if isinstance(key, str) else key[0]
            if name not in kept:
                self.problems.append(f"{step}: {self._absence(name)}")

    def _absence(self, name: str) -> str:
        """Why a component is absent from the result."""
        if name in self.remove:
            return f"component {name!r} is removed by {self.remove[name]}"
        if name in self.components:
            return f"component {name!r} is not included by any selected feature"
        if self.phase == "runtime":
            return f"component {name!r} is not in the deployment-time configured system"
        return f"no component {name!r} in system {self.source.system!r}"

    def _configure(self, c: Component) -> Component:
        """Apply set_implementation / set_parameter to a kept component."""
        changes: dict[str, object] = {}
        step = self.implementation.get(c.name)
        if step is not None:
            name = step.t.set_implementation.implementation  # type: ignore[union-attr]
            if name in c.implementations:
                changes["implementation"] = c.implementations[name]
            else:
                known = ", ".join(sorted(c.implementations)) or "none"
                self.problems.append(f"{step}: no implementation {name!r} (known: {known})")
        params = self._parameters(c)
        if params != c.parameters:
            changes["parameters"] = params
        return msgspec.structs.replace(c, **changes) if changes else c

    def _parameters(self, c: Component) -> dict[str, Parameter]:
        params = dict(c.parameters)
        for (comp, pname), step in self.parameter.items():
            if comp != c.name:
                continue
            decl = params.get(pname)
            if decl is None:
                self.problems.append(f"{step}: component {comp!r} has no parameter {pname!r}")
                continue
            value = self._value(step, decl)
            if value is not None:
                params[pname] = msgspec.structs.replace(decl, value=value)
        return params

    def _value(self, step: _Step, decl: Parameter) -> ParamValue | None:
        sp = step.t.set_parameter
        assert sp is not None
        value: object = sp.value
        if sp.from_attribute is not None:
            if self.phase == "deployment":
                return None  # reported when collected
            if sp.from_attribute not in self.cv:
                self.problems.append(f"{step}: no current value for {sp.from_attribute!r}")
                return None
            value = self.cv[sp.from_attribute]
            if decl.type == "int" and isinstance(value, float) and value.is_integer():
                value = int(value)
        if not value_has_type(value, decl.type):
            self.problems.append(f"{step}: {value!r} is not of type {decl.type}")
            return None
        if decl.type == "float":
            value = float(value)  # type: ignore[arg-type]
        return value  # type: ignore[return-value]


def _fixed(part: _Part) -> _Part:
    """A deployment-bound part once present: no longer a variation point."""
    return msgspec.structs.replace(part, optional=False) if part.optional else part


def _same_effect(a: Transformation, b: Transformation) -> bool:
    """Whether two transformations on one target do the same thing (no conflict)."""
    if a.op != b.op:
        return False
    x, y = getattr(a, a.op), getattr(b, b.op)
    if a.op == "set_parameter":
        return x.from_attribute == y.from_attribute and _same_value(x.value, y.value)
    return x == y


def _same_value(a: object, b: object) -> bool:
    """Value equality that tells booleans from numbers (``True != 1`` here)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same_value(x, y) for x, y in zip(a, b, strict=True))
    return a == b


# ---------------------------------------------------------------------------------------------
# Topics: how connections map onto the bus
# ---------------------------------------------------------------------------------------------
def topic_of(system: SystemModel, component: str, port: str) -> str:
    """The topic a publisher port writes: ``Port.topic``, else ``<component>/<port>``."""
    comp = system.component(component)
    if comp is None:
        raise ResolutionError(f"no component {component!r} in system {system.system!r}")
    p = comp.port(port)
    if p is None:
        raise ResolutionError(f"component {component!r} has no port {port!r}")
    if p.direction != "publish":
        raise ResolutionError(f"port '{component}.{port}' does not publish")
    return p.topic or f"{component}/{port}"


def subscriptions(system: SystemModel) -> dict[tuple[str, str], tuple[str, ...]]:
    """(component, subscriber port) -> the sorted topics it listens on, from the connections.

    Every subscriber port of every component is a key (an unconnected one maps to ``()``), in
    model order. A connection whose endpoints are not a present publisher and subscriber port
    raises `ResolutionError`.
    """
    topics: dict[tuple[str, str], set[str]] = {
        (c.name, p.name): set()
        for c in system.components
        for p in c.ports
        if p.direction == "subscribe"
    }
    for conn in system.connections:
        src, dst = parse_endpoint(conn.source), parse_endpoint(conn.target)
        key = (dst.component, dst.port)
        if key not in topics:
            raise ResolutionError(
                f"connection {conn.source} -> {conn.target}: {conn.target!r} is not a "
                f"subscriber port of a component of {system.system!r}"
            )
        topics[key].add(topic_of(system, src.component, src.port))
    return {k: tuple(sorted(v)) for k, v in topics.items()}


def standby_subscriptions(
    system: SystemModel, hot: Iterable[str]
) -> dict[str, dict[str, tuple[str, ...]]]:
    """component -> subscriber port -> the sorted topics of the ``hot`` components connected
    to it in ``system`` (the deployment-time configured model, optional connections included):
    what each consumer listens to in advance, without delivering, so that switching it to a
    hot standby is a selection, not a new subscription."""
    hot = set(hot)
    out: dict[str, dict[str, set[str]]] = {}
    for conn in system.connections:
        src, dst = parse_endpoint(conn.source), parse_endpoint(conn.target)
        if src.component in hot and dst.component not in hot:
            topics = out.setdefault(dst.component, {}).setdefault(dst.port, set())
            topics.add(topic_of(system, src.component, src.port))
    return {c: {p: tuple(sorted(t)) for p, t in ports.items()} for c, ports in out.items()}


# ---------------------------------------------------------------------------------------------
# The plan: steps turning one running system into another
# ---------------------------------------------------------------------------------------------
class Step(msgspec.Struct, frozen=True, kw_only=True, tag_field="op"):
    """Base of the plan steps; ``component`` names the component acted on."""

    component: str


class StartComponent(Step, frozen=True, tag="start_component"):
    """Launch ``component`` from ``definition``; ``inputs`` maps each subscriber port to its
    topics, ``outputs`` each publisher port to its topic."""

    definition: Component
    inputs: dict[str, tuple[str, ...]] = {}
    outputs: dict[str, str] = {}


class StopComponent(Step, frozen=True, tag="stop_component"):
    """Shut ``component`` down."""


class SwapComponent(Step, frozen=True, tag="swap_component"):
    """Replace ``component`` (stopped) by ``replacement`` (started from ``definition``), which
    is connected to the same peers: the executor applies the replacement strategy (and state
    transfer) of the Run-time Resolution Model for ``replacement``."""

    replacement: str
    definition: Component
    inputs: dict[str, tuple[str, ...]] = {}
    outputs: dict[str, str] = {}


class SetImplementation(Step, frozen=True, tag="set_implementation"):
    """Restart ``component`` from its new ``definition``: emitted when its implementation (or
    its host, ports or parameter declarations) changed."""

    implementation: Implementation
    previous: Implementation
    definition: Component
    inputs: dict[str, tuple[str, ...]] = {}
    outputs: dict[str, str] = {}


class SetParameters(Step, frozen=True, tag="set_parameters"):
    """Set the changed parameter ``values`` of a running component."""

    values: dict[str, ParamValue]


class Rewire(Step, frozen=True, tag="rewire"):
    """Make subscriber ``port`` of a running component listen on exactly ``topics``."""

    port: str
    topics: tuple[str, ...]


PlanStep = (
    StartComponent | StopComponent | SwapComponent | SetImplementation | SetParameters | Rewire
)


class Plan(msgspec.Struct, frozen=True, kw_only=True):
    """Ordered steps; see `diff` for the order."""

    steps: tuple[PlanStep, ...] = ()

    @property
    def empty(self) -> bool:
        return not self.steps

    @property
    def started(self) -> tuple[str, ...]:
        """Components launched (started, or swapped in)."""
        return tuple(_launched(self.steps))

    @property
    def stopped(self) -> tuple[str, ...]:
        """Components shut down (stopped, or swapped out)."""
        return tuple(
            s.component for s in self.steps if isinstance(s, StopComponent | SwapComponent)
        )


def _launched(steps: tuple[PlanStep, ...]) -> Iterator[str]:
    for s in steps:
        if isinstance(s, StartComponent):
            yield s.component
        elif isinstance(s, SwapComponent):
            yield s.replacement


def diff(current: SystemModel, target: SystemModel) -> Plan:
    """The plan turning the running system of ``current`` into that of ``target``.

    What runs is compared: for each component its implementation, host, ports, parameter
    declarations and values, and the topics each subscriber port listens on (descriptions,
    alternative ``implementations``, ``optional``/``binding`` flags and model order are
    metadata). The plan is empty iff the two running systems are equal; both models must be
    of the same system with the same hosts.

    Steps, in this canonical order (each group in target model order unless said otherwise):

    1. `StartComponent` for each component only in ``target`` (not part of a swap);
    2. `SwapComponent` for each swap pair, in ``current`` order. A component ``old`` only in
       ``current`` and ``new`` only in ``target`` form a pair when the peer endpoints ``old``
       is connected to in ``current`` equal (non-empty) those ``new`` is connected to in
       ``target``, as sets of (direction, ``peer.port``). Candidates are paired greedily,
       ``old`` in ``current`` order, each taking the first unpaired ``new`` in ``target`` order.
    3. `SetImplementation` (a restart) for each component in both whose implementation, host,
       ports or parameter declarations (names, types) changed;
    4. `SetParameters` with the changed values, for each other component in both;
    5. `Rewire` of each subscriber port, of a component in both and not restarted, whose topics
       changed (a started, swapped-in or restarted component gets its ``inputs`` with its step);
    6. `StopComponent` for each component only in ``current`` (not part of a swap), in
       ``current`` order.

    Starts come before rewires and stops so that a make-before-break executor can follow the
    order as is; a stop-then-start executor reorders.
    """
    _check_comparable(current, target)
    cur = {c.name: c for c in current.components}
    tgt = {c.name: c for c in target.components}
    cur_subs, tgt_subs = subscriptions(current), subscriptions(target)
    gone = [n for n in cur if n not in tgt]
    new = [n for n in tgt if n not in cur]
    swaps = _pair_swaps(current, target, gone, new)
    swapped_in, swapped_out = {n for _, n in swaps}, {o for o, _ in swaps}
    both = [n for n in tgt if n in cur]
    restarted = [n for n in both if _shape(cur[n]) != _shape(tgt[n])]
    running = [n for n in both if n not in restarted]

    steps: list[PlanStep] = [
        StartComponent(component=n, definition=tgt[n], **wiring(tgt[n], tgt_subs))
        for n in new
        if n not in swapped_in
    ]
    steps += [
        SwapComponent(component=o, replacement=n, definition=tgt[n], **wiring(tgt[n], tgt_subs))
        for o, n in swaps
    ]
    steps += [
        SetImplementation(
            component=n,
            implementation=tgt[n].implementation,
            previous=cur[n].implementation,
            definition=tgt[n],
            **wiring(tgt[n], tgt_subs),
        )
        for n in restarted
    ]
    for n in running:
        values = _changed_parameters(cur[n], tgt[n])
        if values:
            steps.append(SetParameters(component=n, values=values))
    steps += [
        Rewire(component=n, port=p.name, topics=tgt_subs[(n, p.name)])
        for n in running
        for p in tgt[n].ports
        if p.direction == "subscribe" and cur_subs[(n, p.name)] != tgt_subs[(n, p.name)]
    ]
    steps += [StopComponent(component=n) for n in gone if n not in swapped_out]
    return Plan(steps=tuple(steps))


def _check_comparable(current: SystemModel, target: SystemModel) -> None:
    if current.system != target.system:
        raise ResolutionError(
            f"cannot diff system {current.system!r} against system {target.system!r}"
        )
    if current.hosts != target.hosts:
        raise ResolutionError(f"the hosts of system {current.system!r} differ between models")


def _shape(c: Component) -> tuple[object, ...]:
    """What a running component cannot change without a restart."""
    decls = {k: p.type for k, p in c.parameters.items()}
    return (c.implementation, c.host, tuple(c.ports), decls)


def _changed_parameters(cur: Component, tgt: Component) -> dict[str, ParamValue]:
    return {
        k: p.value
        for k, p in tgt.parameters.items()
        if not _same_value(cur.parameters[k].value, p.value)
    }


def wiring(c: Component, subs: Mapping[tuple[str, str], tuple[str, ...]]) -> dict[str, dict]:
    """A component's ``inputs`` (subscriber port -> topics) and ``outputs`` (publisher port ->
    topic), as plan steps carry them; ``subs`` from `subscriptions`."""
    return {
        "inputs": {p.name: subs[(c.name, p.name)] for p in c.ports if p.direction == "subscribe"},
        "outputs": {
            p.name: p.topic or f"{c.name}/{p.name}" for p in c.ports if p.direction == "publish"
        },
    }


def check_parameters(
    model: SystemModel, component: str, values: Mapping[str, object]
) -> dict[str, ParamValue]:
    """Parameter values for ``component`` of ``model``, coerced to their declared types, or
    `ResolutionError` naming every value that is unknown, of the wrong type or out of its
    declared bounds (nothing is half-accepted)."""
    c = next((x for x in model.components if x.name == component), None)
    if c is None:
        known = ", ".join(sorted(x.name for x in model.components)) or "none"
        raise ResolutionError(
            f"no component {component!r} in the running system (running: {known})"
        )
    out: dict[str, ParamValue] = {}
    problems = []
    for name, value in values.items():
        decl = c.parameters.get(name)
        if decl is None:
            known = ", ".join(sorted(c.parameters)) or "none"
            problems.append(f"{component} has no parameter {name!r} (known: {known})")
            continue
        try:
            out[name] = coerce_parameter(decl.type, value, decl.min, decl.max)
        except ValueError as e:
            problems.append(f"{component}.{name}: {e}")
    if problems:
        raise ResolutionError("; ".join(problems))
    return out


def with_parameters(
    model: SystemModel, values: Mapping[str, Mapping[str, ParamValue]]
) -> SystemModel:
    """``model`` with these parameter values (component -> name -> value) set over the
    model's own (operators' values, checked with `check_parameters`)."""
    if not values:
        return model
    components = []
    for c in model.components:
        given = values.get(c.name)
        if given:
            params = {
                k: msgspec.structs.replace(p, value=given[k]) if k in given else p
                for k, p in c.parameters.items()
            }
            c = msgspec.structs.replace(c, parameters=params)
        components.append(c)
    return msgspec.structs.replace(model, components=components)


def peers_of(system: SystemModel, name: str) -> frozenset[tuple[str, str]]:
    """The endpoints a component is connected to: ("in", publisher) / ("out", subscriber)."""
    out = set()
    for conn in system.connections:
        src, dst = parse_endpoint(conn.source), parse_endpoint(conn.target)
        if src.component == name and dst.component != name:
            out.add(("out", conn.target))
        elif dst.component == name and src.component != name:
            out.add(("in", conn.source))
    return frozenset(out)


def _pair_swaps(
    current: SystemModel, target: SystemModel, gone: list[str], new: list[str]
) -> list[tuple[str, str]]:
    new_peers = {n: peers_of(target, n) for n in new}
    pairs: list[tuple[str, str]] = []
    taken: set[str] = set()
    for old in gone:
        peers = peers_of(current, old)
        match = next((n for n in new if n not in taken and peers and new_peers[n] == peers), None)
        if match is not None:
            taken.add(match)
            pairs.append((old, match))
    return pairs
