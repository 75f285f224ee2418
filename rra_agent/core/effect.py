"""What is in effect: the model the running system realises after a plan applied in part.

The Adaptation Engine *decides* a selection and CV values; the Run-time Resolution Engine
computes the target model and applies the plan from the current model to it, unit by unit
(`rra_agent.engines.executor`). When some units fail (a node that cannot start), what runs is
neither the old model nor the target. This module says what it is:

- `effective_model`: the current model with every change of the target that was applied:
  a component whose launch, stop or wiring failed keeps its current form (present or absent,
  its implementation and the connections into it), and its parameters unless only their
  change was applied; a component whose parameter change failed keeps its current values.
- `in_effect`: which features and CV values the effective model shows. A decided feature is
  in effect when every one of its run-time transformations holds in the effective model; a
  feature that was in effect and is no longer decided stays in effect while its
  transformations still hold (its removal failed); a feature without transformations is in
  effect when decided. A CV value is in effect when every parameter set from it shows the
  decided value; otherwise the one in effect before stays.

Pure: models in, models out.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import msgspec

from rra_agent.models.features import FeatureModel
from rra_agent.models.resolution import ResolutionModel, Transformation
from rra_agent.models.system import (
    Component,
    Connection,
    RuntimeConfiguredSystemModel,
    SystemModel,
    parse_endpoint,
)


def effective_model(
    current: RuntimeConfiguredSystemModel,
    target: RuntimeConfiguredSystemModel,
    structure_failed: Collection[str],
    parameters_failed: Collection[str] = (),
) -> RuntimeConfiguredSystemModel:
    """The model that runs after applying ``current`` -> ``target`` where the changes of the
    components in ``structure_failed`` (launch, stop, restart, wiring) and the parameter
    changes of those in ``parameters_failed`` failed and were undone."""
    if not structure_failed and not parameters_failed:
        return target
    failed = set(structure_failed)
    params_failed = set(parameters_failed)
    cur = {c.name: c for c in current.components}
    tgt = {c.name: c for c in target.components}
    components: list[Component] = []
    for name in [*tgt, *(n for n in cur if n not in tgt)]:
        c = _component(name, cur.get(name), tgt.get(name), name in failed, name in params_failed)
        if c is not None:
            components.append(c)
    present = {c.name for c in components}
    connections = [
        *_into(target.connections, present, lambda n: n not in failed),
        *_into(current.connections, present, lambda n: n in failed),
    ]
    return msgspec.structs.replace(target, components=components, connections=connections)


def _component(
    name: str, cur: Component | None, tgt: Component | None, failed: bool, params_failed: bool
) -> Component | None:
    if not failed:
        if tgt is not None and cur is not None and params_failed:
            return msgspec.structs.replace(tgt, parameters=cur.parameters)
        return tgt
    if cur is None or tgt is None or params_failed:
        return cur
    if cur.implementation != tgt.implementation or cur.parameters.keys() != tgt.parameters.keys():
        return cur  # a restart that failed: it runs as it was
    return msgspec.structs.replace(cur, parameters=tgt.parameters)


def _into(
    connections: list[Connection], present: set[str], keep: object
) -> list[Connection]:
    out = []
    for conn in connections:
        src, dst = parse_endpoint(conn.source), parse_endpoint(conn.target)
        if src.component in present and dst.component in present and keep(dst.component):  # type: ignore[operator]
            out.append(conn)
    return out


def in_effect(
    fm: FeatureModel,
    runtime: ResolutionModel,
    decided: Collection[str],
    before: Collection[str],
    effective: SystemModel,
    target: SystemModel,
    cv: Mapping[str, float],
    cv_before: Mapping[str, float],
) -> tuple[frozenset[str], dict[str, float]]:
    """The run-time selection and CV values ``effective`` shows (see the module doc).
    ``decided``/``cv``: what was decided, and ``target`` the model it resolves to (operators'
    parameters included); ``before``/``cv_before``: what was in effect before the plan."""
    by_feature = {fm.resolve_name(k) or k: v for k, v in runtime.features.items()}
    selection = set()
    for f in {*decided, *before}:
        steps = by_feature.get(f, [])
        if not steps:
            if f in decided:
                selection.add(f)
            continue
        wanted = cv if f in decided else cv_before
        if all(_holds(t, effective, wanted, target if f in decided else None) for t in steps):
            selection.add(f)
    values = dict(cv_before)
    for key, value in cv.items():
        targets = [
            (t.set_parameter.component, t.set_parameter.parameter)
            for f in decided
            for t in by_feature.get(f, [])
            if t.set_parameter is not None and t.set_parameter.from_attribute == key
        ]
        if all(_param(effective, c, p) == _param(target, c, p) for c, p in targets):
            values[key] = value
    return frozenset(selection), values


def _param(model: SystemModel, component: str, name: str) -> object:
    c = model.component(component)
    p = c.parameters.get(name) if c is not None else None
    return None if p is None else p.value


def _holds(
    t: Transformation, model: SystemModel, cv: Mapping[str, float], target: SystemModel | None
) -> bool:
    """Whether a run-time transformation shows in ``model``: a parameter has the value of
    ``target`` (when given: the operators' values included), else the transformation's."""
    conns = {c.key for c in model.connections}
    match t.op:
        case "include_component":
            return model.component(t.include_component or "") is not None
        case "remove_component":
            return model.component(t.remove_component or "") is None
        case "set_implementation":
            si = t.set_implementation
            assert si is not None
            c = model.component(si.component)
            return c is not None and c.implementation == c.implementations.get(si.implementation)
        case "set_parameter":
            sp = t.set_parameter
            assert sp is not None
            if target is not None:
                want = _param(target, sp.component, sp.parameter)
            else:
                want = cv.get(sp.from_attribute) if sp.from_attribute else sp.value
            return _param(model, sp.component, sp.parameter) == want
        case "add_connection":
            return t.add_connection is not None and t.add_connection.key in conns
        case "remove_connection":
            return t.remove_connection is not None and t.remove_connection.key not in conns
    return False  # pragma: no cover
