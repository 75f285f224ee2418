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

from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from typing import Literal, TypeVar

import msgspec

from rra_agent import _compat
from rra_agent.core.plan import same_value
from rra_agent.errors import ResolutionError, SelectionError
from rra_agent.models.features import FeatureModel
from rra_agent.models.resolution import ConnectionRef, ResolutionModel, Transformation
from rra_agent.models.system import (
    Component,
    Connection,
    DeploymentConfiguredSystemModel,
    Parameter,
    ParamValue,
    RuntimeConfiguredSystemModel,
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
    "resolve_deployment",
    "resolve_runtime",
]


# ---------------------------------------------------------------------------------------------
# Public entry points
# ---------------------------------------------------------------------------------------------
def resolve_deployment(
    template: SystemModel,
    model: ResolutionModel,
    fm: FeatureModel,
    selection: Collection[str],
) -> DeploymentConfiguredSystemModel:
    """The Deployment-time Configured System Model for a deployment-time selection.

    ``selection`` holds feature names or aliases; features of ``model`` not selected are
    ignored. Checking the selection against the feature model's constraints is the caller's
    job (the feature-model core). Raises `ResolutionError` (`SelectionError` for an unknown
    selected feature).
    """
    steps = _selected_transformations(model, fm, selection, "deployment")
    return _Resolver("deployment", template, steps, {}).run()


def resolve_runtime(
    configured: DeploymentConfiguredSystemModel,
    model: ResolutionModel,
    fm: FeatureModel,
    selection: Collection[str],
    cv: Mapping[str, float],
) -> RuntimeConfiguredSystemModel:
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
        return x.from_attribute == y.from_attribute and same_value(x.value, y.value)
    return x == y


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




__getattr__ = _compat.renamed(__name__)  # old names, for one release (docs/api.md)
