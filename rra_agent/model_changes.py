"""What a reload changes, and what of it cannot change while the system runs (``rra reload``).

`compare` takes the running deployment, the edited one and what runs now (`Running`), and
returns the changes in words (rules, measurements, the Run-time Resolution Model, parameter
bounds, components, implementations, connections, features) and the *refusals*: what
cannot change live, each an error at its place in the edited files (``file:line:col``):

- the system's name, the deployment-time selection (the Deployment-time Configured System
  Model is what the host agents were started with), the engines' or agents' scheduling;
- a running component removed, its running implementation no longer declared, its host or
  container changed, its ports or parameters added, removed or retyped (a running node's
  ports and parameters are fixed when it starts);
- a port's type, of any component (samples of the old type are on the bus);
- a parameter bound that the value a node runs with does not fit;
- a run-time selection (the current one) that the edited feature model does not allow.

Pure: it reads no file and asks no process.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import msgspec

from rra_agent.core.features import check_selection
from rra_agent.deployment import Deployment
from rra_agent.errors import Location, ModelError, RraError
from rra_agent.models.system import Component, Implementation, coerce_parameter


@dataclass(frozen=True)
class Running:
    """What runs, as the Run-time Resolution Engine leader holds it: each node (running or
    on standby) with its implementation, host and the parameter values it runs with, and the
    run-time selection decided."""

    implementations: Mapping[str, Implementation] = field(default_factory=dict)
    hosts: Mapping[str, str] = field(default_factory=dict)
    params: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    selection: frozenset[str] = frozenset()


@dataclass
class Comparison:
    changes: list[str] = field(default_factory=list)
    refusals: list[RraError] = field(default_factory=list)

    @property
    def allowed(self) -> bool:
        return not self.refusals


def compare(old: Deployment, new: Deployment, running: Running) -> Comparison:
    out = Comparison()
    _system(old, new, out)
    _features(old, new, running, out)
    _components(old, new, running, out)
    _connections(old, new, out)
    _named("rule", _rules(old), _rules(new), out)
    _named("measurement", _measurements(old), _measurements(new), out)
    _named("data type", _data_types(old), _data_types(new), out)
    _runtime(old, new, out)
    return out


# ---- whole-system settings ---------------------------------------------------------------------
def _system(old: Deployment, new: Deployment, out: Comparison) -> None:
    doc = new.package.doc("system")
    if new.system != old.system:
        out.refusals.append(doc.error(
            f"the system's name cannot change while it runs ({old.system} -> {new.system})",
            doc.loc("system"),
        ))  # fmt: skip
    manifest = new.package.doc("manifest")
    for what in ("engines", "agents"):
        if getattr(old.package.manifest, what) != getattr(new.package.manifest, what):
            out.refusals.append(manifest.error(
                f"the {what}' scheduling cannot change while they run (it applies when "
                "`rra up` starts them)", manifest.loc(what),
            ))  # fmt: skip
    if new.selection != old.selection:
        gained = ", ".join(sorted(new.selection - old.selection)) or "nothing"
        lost = ", ".join(sorted(old.selection - new.selection)) or "nothing"
        out.refusals.append(_at(
            _feature_span(new, sorted(new.selection ^ old.selection)),
            f"the deployment-time selection would change (+{gained}, -{lost}): it cannot "
            "change while the system runs (restart it with `rra up`)",
        ))  # fmt: skip


def _features(old: Deployment, new: Deployment, running: Running, out: Comparison) -> None:
    fm_old, fm_new = old.package.features, new.package.features
    for name in sorted(fm_new.features.keys() - fm_old.features.keys()):
        out.changes.append(f"feature {name}: added")
    for name in sorted(fm_old.features.keys() - fm_new.features.keys()):
        out.changes.append(f"feature {name}: removed")
    for name in sorted(fm_old.features.keys() & fm_new.features.keys()):
        if plain(fm_old.features[name].attributes) != plain(fm_new.features[name].attributes):
            out.changes.append(f"feature {name}: attributes changed")
    if plain(fm_old.constraints) != plain(fm_new.constraints):
        out.changes.append("feature model: constraints changed")
    runtime = set(fm_new.runtime_features())
    lost = sorted(running.selection - runtime)
    if lost:
        out.refusals.append(_at(
            _feature_span(new, []), f"run-time feature(s) {', '.join(lost)} are selected now "
            "and no longer run-time features of the edited model",
        ))  # fmt: skip
        return
    problems = check_selection(fm_new, new.selection | running.selection)
    if problems:
        out.refusals.append(_at(
            _feature_span(new, []), "the edited feature model does not allow the current "
            f"selection ({', '.join(sorted(running.selection))}): "
            f"{'; '.join(p.message for p in problems)}",
        ))  # fmt: skip


# ---- components ---------------------------------------------------------------------------------
def _components(old: Deployment, new: Deployment, running: Running, out: Comparison) -> None:
    before = {c.name: c for c in old.configured.components}
    after = {c.name: c for c in new.configured.components}
    index = {c.name: i for i, c in enumerate(new.package.system.components)}
    doc = new.package.doc("system")

    def loc(name: str, *path: str | int) -> Location:
        return doc.loc("components", index[name], *path) if name in index else doc.loc(
            "components")  # fmt: skip

    for name in sorted(after.keys() - before.keys()):
        out.changes.append(f"component {name}: added")
    for name in sorted(before.keys() - after.keys()):
        if name in running.implementations:
            host = running.hosts.get(name, "")
            out.refusals.append(doc.error(
                f"component {name} runs{f' on host {host}' if host else ''}: it cannot be "
                "removed while the system runs (select a configuration without it first)",
                doc.key_loc("components"),
            ))  # fmt: skip
        else:
            out.changes.append(f"component {name}: removed")
    for name in sorted(before.keys() & after.keys()):
        _component(before[name], after[name], running, lambda *p, n=name: loc(n, *p), doc, out)


def _component(
    old: Component,
    new: Component,
    running: Running,
    loc: Callable[..., Location],
    doc: Any,
    out: Comparison,
) -> None:
    name, runs = new.name, new.name in running.implementations

    def refuse(message: str, *path: str | int) -> None:
        out.refusals.append(doc.error(f"component {name}: {message}", loc(*path)))

    _ports(old, new, runs, refuse)
    impls_old = {"": old.implementation, **old.implementations}
    impls_new = {"": new.implementation, **new.implementations}
    added = [k or "(its own)" for k, v in impls_new.items() if v not in impls_old.values()]
    removed = [k or "(its own)" for k, v in impls_old.items() if v not in impls_new.values()]
    if added:
        out.changes.append(f"component {name}: implementation(s) added: {', '.join(added)}")
    if removed:
        out.changes.append(f"component {name}: implementation(s) removed: {', '.join(removed)}")
    if runs and running.implementations[name] not in impls_new.values():
        refuse("the implementation it runs with is no longer declared", "implementation")
    if runs and (old.host or "") != (new.host or ""):
        refuse(f"its host cannot change while it runs ({old.host} -> {new.host})", "host")
    if runs and old.container != new.container:
        refuse("its container cannot change while it runs", "container")
    if old.supervision != new.supervision or old.scheduling != new.scheduling:
        out.changes.append(f"component {name}: supervision or scheduling changed (from its "
                           "next start)")  # fmt: skip
    _parameters(old, new, runs, running.params.get(name, {}), refuse, out)


def _ports(old: Component, new: Component, runs: bool, refuse: Callable[..., None]) -> None:
    ports_old = {p.name: p for p in old.ports}
    for j, p in enumerate(new.ports):
        was = ports_old.get(p.name)
        if was is not None and was.type != p.type:
            refuse(f"port {p.name}: its type cannot change while the system runs "
                   f"({was.type} -> {p.type}): samples of the old type are on the bus",
                   "ports", j, "type")  # fmt: skip
        elif was is not None and was.direction != p.direction:
            refuse(f"port {p.name}: its direction cannot change", "ports", j, "direction")
        elif was is None and runs:
            refuse(f"port {p.name}: a running node's ports are fixed when it starts", "ports", j)
    gone = sorted(ports_old.keys() - {p.name for p in new.ports})
    if gone and runs:
        refuse(f"port(s) {', '.join(gone)} removed: a running node's ports are fixed when it "
               "starts", "ports")  # fmt: skip


def _parameters(
    old: Component,
    new: Component,
    runs: bool,
    values: Mapping[str, Any],
    refuse: Callable[..., None],
    out: Comparison,
) -> None:
    for pname, p in new.parameters.items():
        was = old.parameters.get(pname)
        if was is None:
            if runs:
                refuse(f"parameter {pname}: a running node's parameters are fixed when it "
                       "starts", "parameters", pname)  # fmt: skip
            continue
        if was.type != p.type and runs:
            refuse(f"parameter {pname}: its type cannot change while the node runs",
                   "parameters", pname, "type")  # fmt: skip
            continue
        if (was.min, was.max) != (p.min, p.max):
            bounds = f"{_bounds(was.min, was.max)} -> {_bounds(p.min, p.max)}"
            out.changes.append(f"component {new.name}: parameter {pname} bounds {bounds}")
            value = values.get(pname, p.value)
            if runs and value is not None:
                try:
                    coerce_parameter(p.type, value, p.min, p.max)
                except ValueError as e:
                    where = "min" if p.min is not None and _below(value, p.min) else "max"
                    refuse(f"parameter {pname}: the value it runs with ({value!r}) does not "
                           f"fit the new bounds: {e}", "parameters", pname, where)  # fmt: skip
        elif was.value != p.value:
            out.changes.append(f"component {new.name}: parameter {pname} value "
                               f"{was.value!r} -> {p.value!r}")  # fmt: skip
    for pname in sorted(old.parameters.keys() - new.parameters.keys()):
        if runs:
            refuse(f"parameter {pname} removed: a running node's parameters are fixed when it "
                   "starts", "parameters")  # fmt: skip


def _connections(old: Deployment, new: Deployment, out: Comparison) -> None:
    a = {(c.source, c.target) for c in old.configured.connections}
    b = {(c.source, c.target) for c in new.configured.connections}
    for s, t in sorted(b - a):
        out.changes.append(f"connection {s} -> {t}: added")
    for s, t in sorted(a - b):
        out.changes.append(f"connection {s} -> {t}: removed")


# ---- rules, measurements, run-time resolution -------------------------------------------------
def _rules(dep: Deployment) -> dict[str, Any]:
    model = dep.package.adaptation
    if model is None:
        return {}
    out: dict[str, Any] = {}
    for item in model.items:
        out[item.name] = plain(item)
    return out


def _measurements(dep: Deployment) -> dict[str, Any]:
    return {m.name: plain(m) for m in dep.package.measurements.measurements}


def _data_types(dep: Deployment) -> dict[str, Any]:
    return {t.name: plain(t) for t in dep.package.measurements.data_types}


def _runtime(old: Deployment, new: Deployment, out: Comparison) -> None:
    a, b = old.package.runtime, new.package.runtime
    if plain(a.replacement) != plain(b.replacement):
        out.changes.append("run-time resolution model: replacement strategies changed")
    if plain(msgspec.structs.replace(a, replacement=b.replacement)) != plain(b):
        out.changes.append("run-time resolution model: transformations changed")


def _named(kind: str, before: dict[str, Any], after: dict[str, Any], out: Comparison) -> None:
    for name in sorted(after.keys() - before.keys()):
        out.changes.append(f"{kind} {name}: added")
    for name in sorted(before.keys() - after.keys()):
        out.changes.append(f"{kind} {name}: removed")
    for name in sorted(before.keys() & after.keys()):
        if before[name] != after[name]:
            out.changes.append(f"{kind} {name}: changed")


# ---- helpers -------------------------------------------------------------------------------------
def plain(obj: Any) -> Any:
    """``obj`` as builtins without its source positions (``span``, descriptions): two
    models that differ only in where they are written or in comments compare equal."""
    return _strip(msgspec.to_builtins(obj))


def _strip(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _strip(v) for k, v in value.items() if k not in ("span", "description")}
    if isinstance(value, list | tuple):
        return [_strip(v) for v in value]
    return value


def _feature_span(dep: Deployment, names: Iterable[str]) -> Location:
    """Where the first of these features is written in the edited feature model (else the
    file's first line)."""
    fm = dep.package.features
    file = str(dep.package.file("features"))
    for name in names:
        feature = fm.features.get(name)
        span = feature.span if feature is not None else None
        if span is not None:
            return Location(span.file or file, span.line, span.col)
    return Location(file, 1, 1)


def _at(location: Location, message: str) -> ModelError:
    return ModelError(message, location)


def _bounds(low: float | None, high: float | None) -> str:
    return f"[{'-inf' if low is None else f'{low:g}'}, {'inf' if high is None else f'{high:g}'}]"


def _below(value: Any, low: float) -> bool:
    try:
        return float(value) < low
    except (TypeError, ValueError):
        return False
