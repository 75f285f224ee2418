"""Cross-reference validation of a loaded system package.

Each model file is well-formed on its own once loaded; this module checks what ties them
together (a connection's ports exist and agree, a resolution model names real features,
components and parameters, a measurement's source publishes a known data type, ...). Every
problem is a `ModelError` located at the offending reference, saying what was expected.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import re
import shutil
import sys
from collections.abc import Hashable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import TypeVar

from rra_agent.errors import Location, ModelError
from rra_agent.models.measurements import PRIMITIVE_TYPES, DataType, Measurement
from rra_agent.models.resolution import ConnectionRef, ResolutionModel, Transformation
from rra_agent.models.system import (
    ROS2_PREFIX,
    Command,
    Component,
    Connection,
    Implementation,
    Parameter,
    Port,
    parse_endpoint,
    value_has_type,
)
from rra_agent.package.contents import SystemPackage
from rra_agent.package.imports import add_package_path, shadowed_problem
from rra_agent.package.yamlload import PathItem, unknown_name

H = TypeVar("H", bound=Hashable)
_LIST_RE = re.compile(r"^list\[(.+)\]$")
_BINDING_WORD = {"deployment": "deployment time", "runtime": "run time"}


def validate_package(pkg: SystemPackage, *, implementations: bool = True) -> list[ModelError]:
    """Every cross-reference problem of ``pkg``, in file order (empty when it is consistent).

    ``implementations``: also resolve every component implementation (import each node
    class, look up each external command), as ``rra validate`` does. Loading a package to
    run it does not: a host imports only the implementations it runs (another host's may
    need libraries this one does not have), when it starts them."""
    return _Checker(pkg, implementations=implementations).run()


class _Checker:
    """Walks the models of one package, collecting located errors."""

    def __init__(self, pkg: SystemPackage, *, implementations: bool = True) -> None:
        self.pkg = pkg
        self.implementations = implementations
        self.fm = pkg.features
        self.components = {c.name: c for c in pkg.system.components}
        self.types = {t.name: t for t in pkg.measurements.data_types}
        self.errors: list[ModelError] = []
        self._callables: dict[str, str | None] = {}
        self._classes: dict[str, str | None] = {}

    def run(self) -> list[ModelError]:
        self.check_manifest()
        self.check_system()
        for kind in ("deployment", "runtime"):
            self.check_resolution(kind)
        self.check_replacement()
        with _on_sys_path(self.pkg.root):
            if self.implementations:
                self.check_implementations()
            self.check_measurements()
        self.check_ros2()
        return _in_file_order(self.errors)

    # ---- helpers ------------------------------------------------------------------------
    def error(
        self, model: str, path: tuple[PathItem, ...], message: str, key: bool = False
    ) -> None:
        doc = self.pkg.doc(model)
        loc = doc.key_loc(*path) if key else doc.loc(*path)
        self.errors.append(doc.error(message, loc))

    def component(self, model: str, path: tuple[PathItem, ...], name: str) -> Component | None:
        comp = self.components.get(name)
        if comp is None:
            self.error(model, path, unknown_name("component", name, self.components))
        return comp

    def endpoint(
        self, model: str, path: tuple[PathItem, ...], text: str, direction: str | None = None
    ) -> Port | None:
        """The port named by ``component.port`` (checking its direction), or None."""
        ep = parse_endpoint(text)
        comp = self.component(model, path, ep.component)
        if comp is None:
            return None
        port = comp.port(ep.port)
        if port is None:
            known = [p.name for p in comp.ports]
            self.error(model, path, unknown_name("port", ep.port, known, f" of '{comp.name}'"))
        elif direction is not None and port.direction != direction:
            self.error(
                model,
                path,
                f"'{text}' is a {port.direction} port; expected a {direction} port here",
            )
            return None
        return port

    def type_known(self, expr: str) -> bool:
        m = _LIST_RE.match(expr.strip())
        if m:
            return self.type_known(m[1])
        return expr.strip() in PRIMITIVE_TYPES or expr.strip() in self.types

    def unknown_type(self, expr: str) -> str:
        known = [*PRIMITIVE_TYPES, *self.types]
        return unknown_name("type", expr, known) + "; expected a primitive, list[T] or a data type"

    # ---- manifest -----------------------------------------------------------------------
    def check_manifest(self) -> None:
        if "manifest" not in self.pkg.docs:
            return
        for i, name in enumerate(self.pkg.manifest.default_selection):
            self.feature_ref("manifest", ("default_selection", i), name, "deployment")

    def feature_ref(
        self, model: str, path: tuple[PathItem, ...], name: str, binding: str, key: bool = False
    ) -> str | None:
        """The feature named ``name`` (or alias) if it exists and has ``binding``."""
        resolved = self.fm.resolve_name(name)
        if resolved is None:
            known = list(self.fm.features) + list(self.fm.aliases)
            self.error(model, path, unknown_name("feature", name, known), key)
            return None
        actual = self.fm.binding[resolved]
        if actual != binding:
            word = _BINDING_WORD[actual]
            if model == "manifest":
                msg = f"feature '{name}' is bound at {word}; a deployment selection names"
                msg += " deployment-time features only"
            else:
                msg = f"feature '{name}' is bound at {word}; its transformations belong in"
                msg += f" {getattr(self.pkg.manifest, actual)}"
            self.error(model, path, msg, key)
        return resolved

    # ---- system.yaml --------------------------------------------------------------------
    def check_system(self) -> None:
        system = self.pkg.system
        hosts = [h.name for h in system.hosts]
        for i, name in _duplicates(hosts):
            self.error("system", ("hosts", i, "name"), f"duplicate host name '{name}'")
        for i, comp in enumerate(system.components):
            self.check_component(i, comp, set(hosts))
        keys = [c.key for c in system.connections]
        for i, key in _duplicates(keys):
            self.error("system", ("connections", i), f"duplicate connection {key[0]} -> {key[1]}")
        for i, conn in enumerate(system.connections):
            self.check_connection(i, conn)

    def check_component(self, i: int, comp: Component, hosts: set[str]) -> None:
        path: tuple[PathItem, ...] = ("components", i)
        if hosts and comp.host is not None and comp.host not in hosts:
            self.error("system", (*path, "host"), unknown_name("host", comp.host, hosts))
        for j, port in enumerate(comp.ports):
            if port.ros2_type is not None and port.type == port.ros2_type:
                continue  # a ROS 2 message type (check_ros2 looks it up)
            if port.ros2_type is not None and "/" in port.type:
                self.error("system", (*path, "ports", j, "type"),
                           f"type {port.type} is not the port's ros2_type {port.ros2_type}: a "
                           "ROS 2 port's type is its ROS 2 type, or a data type")
                continue
            if not self.type_known(port.type):
                self.error("system", (*path, "ports", j, "type"), self.unknown_type(port.type))
        for name, param in comp.parameters.items():
            problem = _out_of_range(param, param.value)
            if problem:
                self.error("system", (*path, "parameters", name, "value"), problem)

    def check_connection(self, i: int, conn: Connection) -> None:
        src = self.endpoint("system", ("connections", i, "from"), conn.source, "publish")
        dst = self.endpoint("system", ("connections", i, "to"), conn.target, "subscribe")
        if src is not None and dst is not None and src.type != dst.type:
            self.error(
                "system",
                ("connections", i, "to"),
                f"message type mismatch: '{conn.source}' publishes {src.type} but"
                f" '{conn.target}' expects {dst.type}",
            )

    def check_implementations(self) -> None:
        """Every implementation resolves, without starting anything: a dotted path imports
        (with the package folder on the import path, as a node process has it) to a
        `rra_agent.node.Node` subclass; an external command exists and is executable."""
        for i, comp in enumerate(self.pkg.system.components):
            path: tuple[PathItem, ...] = ("components", i)
            # a ROS 2 node's command runs in the package folder
            root = self.pkg.root if comp.ros2 is not None else None
            self.check_implementation((*path, "implementation"), comp.implementation, root)
            for name, impl in comp.implementations.items():
                self.check_implementation((*path, "implementations", name), impl, root)

    def check_implementation(
        self, path: tuple[PathItem, ...], impl: Implementation, root: Path | None = None
    ) -> None:
        if isinstance(impl, str) and impl.startswith(ROS2_PREFIX):
            return  # a ROS 2 executable: parsed by check_ros2 (`ros2 run` needs ROS 2 here)
        if isinstance(impl, str):
            if impl not in self._classes:
                self._classes[impl] = _node_class_problem(impl, self.pkg.root)
            problem = self._classes[impl]
            if problem:
                self.error("system", path, problem)
            return
        if not impl.command:
            self.error("system", (*path, "command"), "an external command needs a program")
            return
        problem = _command_problem(impl, root)
        if problem:
            self.error("system", (*path, "command", 0), problem)

    # ---- deployment.yaml / runtime.yaml -------------------------------------------------
    def check_resolution(self, kind: str) -> None:
        model: ResolutionModel = getattr(self.pkg, kind)
        seen: dict[str, str] = {}
        for fname, transformations in model.features.items():
            resolved = self.feature_ref(kind, ("features", fname), fname, kind, key=True)
            if resolved is not None and resolved in seen:
                msg = f"feature '{fname}' already has transformations (as '{seen[resolved]}')"
                self.error(kind, ("features", fname), msg, key=True)
            if resolved is not None:
                seen.setdefault(resolved, fname)
            for j, t in enumerate(transformations):
                self.check_transformation(kind, ("features", fname, j, t.op), t)

    def check_transformation(
        self, kind: str, path: tuple[PathItem, ...], t: Transformation
    ) -> None:
        match t.op:
            case "include_component":
                self.check_include(kind, path, t.include_component or "")
            case "remove_component":
                self.component(kind, path, t.remove_component or "")
            case "set_implementation":
                self.check_set_implementation(kind, path, t)
            case "set_parameter":
                self.check_set_parameter(kind, path, t)
            case "add_connection" | "remove_connection":
                ref = t.add_connection or t.remove_connection
                assert ref is not None
                self.check_connection_ref(kind, path, ref, adding=t.op == "add_connection")

    def check_include(self, kind: str, path: tuple[PathItem, ...], name: str) -> None:
        comp = self.component(kind, path, name)
        if comp is None:
            return
        if not comp.optional:
            self.error(
                kind,
                path,
                f"component '{name}' is not optional (only optional ones can be included)",
            )
        elif comp.binding != kind:
            self.error(
                kind,
                path,
                f"component '{name}' is bound at {_BINDING_WORD[comp.binding]}; include it from"
                f" {getattr(self.pkg.manifest, comp.binding)}",
            )

    def check_set_implementation(
        self, kind: str, path: tuple[PathItem, ...], t: Transformation
    ) -> None:
        ref = t.set_implementation
        assert ref is not None
        comp = self.component(kind, (*path, "component"), ref.component)
        if comp is not None and ref.implementation not in comp.implementations:
            where = f" of '{comp.name}'"
            msg = unknown_name("implementation", ref.implementation, comp.implementations, where)
            self.error(kind, (*path, "implementation"), msg)

    def check_set_parameter(self, kind: str, path: tuple[PathItem, ...], t: Transformation) -> None:
        ref = t.set_parameter
        assert ref is not None
        comp = self.component(kind, (*path, "component"), ref.component)
        if comp is None:
            return
        param = comp.parameters.get(ref.parameter)
        if param is None:
            msg = unknown_name("parameter", ref.parameter, comp.parameters, f" of '{comp.name}'")
            self.error(kind, (*path, "parameter"), msg)
            return
        if ref.value is not None:
            self.check_parameter_value(
                kind, (*path, "value"), f"{comp.name}.{ref.parameter}", param, ref.value
            )
        if ref.from_attribute is not None:
            self.check_from_attribute(kind, (*path, "from_attribute"), ref.from_attribute, param)

    def check_parameter_value(
        self, kind: str, path: tuple[PathItem, ...], name: str, param: Parameter, value: object
    ) -> None:
        if not value_has_type(value, param.type):
            self.error(
                kind,
                path,
                f"value {value!r} is not of type {param.type} (the type of parameter {name})",
            )
            return
        problem = _out_of_range(param, value)
        if problem:
            self.error(kind, path, f"{problem} (parameter {name})")

    def check_from_attribute(
        self, kind: str, path: tuple[PathItem, ...], name: str, param: Parameter
    ) -> None:
        if kind != "runtime":
            self.error(
                kind,
                path,
                "from_attribute is only allowed in the run-time resolution"
                f" model ({self.pkg.manifest.runtime}); CV values are set at run time",
            )
            return
        owner_attr = self.fm.attributes.get(name)
        cvs = [a for a, (_, attr) in self.fm.attributes.items() if attr.kind == "cv"]
        if owner_attr is None:
            self.error(kind, path, unknown_name("CV attribute", name, cvs))
        elif owner_attr[1].kind != "cv":
            self.error(
                kind,
                path,
                f"attribute '{name}' of '{owner_attr[0]}' is a"
                f" {owner_attr[1].kind} attribute; expected a cv one (known: "
                f"{', '.join(sorted(cvs)) or 'none'})",
            )
        elif param.type not in ("float", "int"):
            self.error(kind, path, f"a CV attribute sets a numeric parameter, not a {param.type}")

    def check_connection_ref(
        self, kind: str, path: tuple[PathItem, ...], ref: ConnectionRef, adding: bool
    ) -> None:
        src = self.endpoint(kind, (*path, "from"), ref.source)
        dst = self.endpoint(kind, (*path, "to"), ref.target)
        if src is None or dst is None:
            return
        conn = next((c for c in self.pkg.system.connections if c.key == ref.key), None)
        arrow = f"{ref.source} -> {ref.target}"
        if conn is None:
            need = " with optional: true" if adding else ""
            self.error(
                kind,
                path,
                f"no connection {arrow} in the template system model (declare"
                f" it in {self.pkg.manifest.system}{need})",
            )
        elif adding and not conn.optional:
            self.error(
                kind, path, f"connection {arrow} is not optional (only optional ones can be added)"
            )
        elif adding and conn.binding != kind:
            self.error(
                kind,
                path,
                f"connection {arrow} is bound at {_BINDING_WORD[conn.binding]};"
                f" add it from {getattr(self.pkg.manifest, conn.binding)}",
            )

    def check_replacement(self) -> None:
        rep = self.pkg.runtime.replacement
        for name in rep.components:
            if name not in self.components:
                msg = unknown_name("component", name, self.components)
                self.error("runtime", ("replacement", "components", name), msg, key=True)
        for name in rep.stop_deadline:
            if name not in self.components:
                msg = unknown_name("component", name, self.components)
                self.error("runtime", ("replacement", "stop_deadline", name), msg, key=True)
        targets = [st.target for st in rep.state_transfer]
        for i, st in enumerate(rep.state_transfer):
            path: tuple[PathItem, ...] = ("replacement", "state_transfer", i)
            self.component("runtime", (*path, "from"), st.source)
            self.component("runtime", (*path, "to"), st.target)
        for i, name in _duplicates(targets):
            self.error(
                "runtime",
                ("replacement", "state_transfer", i, "to"),
                f"duplicate state transfer into '{name}'",
            )

    # ---- ROS 2 ---------------------------------------------------------------------------
    def check_ros2(self) -> None:
        """Types, fields, topics and links of the package's ROS 2 parts
        (`rra_agent.package.ros2`), each at its place."""
        from rra_agent.package import ros2

        if self.pkg.manifest.ros2 is None and not ros2.uses_ros2(self.pkg):
            return
        for p in ros2.problems(self.pkg):
            self.error(p.model, p.path, p.message, p.key)

    # ---- measurements.yaml --------------------------------------------------------------
    def check_measurements(self) -> None:
        for i, dt in enumerate(self.pkg.measurements.data_types):
            self.check_data_type(i, dt)
        for i, m in enumerate(self.pkg.measurements.measurements):
            self.check_measurement(i, m)

    def check_data_type(self, i: int, dt: DataType) -> None:
        path: tuple[PathItem, ...] = ("data_types", i)
        if dt.name in PRIMITIVE_TYPES:
            self.error(
                "measurements", (*path, "name"), f"data type '{dt.name}' shadows a primitive type"
            )
        for name, expr in dt.fields.items():
            if not self.type_known(expr):
                self.error("measurements", (*path, "fields", name), self.unknown_type(expr))
        for j, name in enumerate(dt.optional):
            if name not in dt.fields:
                msg = unknown_name("field", name, dt.fields, f" of {dt.name}")
                self.error("measurements", (*path, "optional", j), msg)
        for j, name in enumerate(dt.non_finite):
            if name not in dt.fields:
                msg = unknown_name("field", name, dt.fields, f" of {dt.name}")
                self.error("measurements", (*path, "non_finite", j), msg)
        for name, dotted in dt.functions.items():
            problem = self.callable_problem(dotted)
            if problem:
                self.error("measurements", (*path, "functions", name), problem)

    def check_measurement(self, i: int, m: Measurement) -> None:
        path: tuple[PathItem, ...] = ("measurements", i)
        if m.ros2_topic is not None:  # a ROS 2 topic: its type and field in check_ros2
            if m.function is not None:
                self.check_function(path, m, [])
            return
        if m.reachable is not None:
            hosts = {h.name for h in self.pkg.system.hosts}
            if m.reachable not in hosts:
                msg = unknown_name("host", m.reachable, hosts)
                self.error("measurements", (*path, "reachable"), msg)
            return
        if m.available is not None:
            names = {c.name for c in self.pkg.system.components}
            if m.available not in names:
                msg = unknown_name("component", m.available, names)
                self.error("measurements", (*path, "available"), msg)
            return
        ports: list[Port | None] = []
        for j, src in enumerate(m.inputs):
            where = (*path, "source") if m.source is not None else (*path, "sources", j)
            ports.append(self.endpoint("measurements", where, src, "publish"))
        if any(p is None for p in ports):
            return
        in_types = [self.types.get(p.type) for p in ports if p is not None]
        if m.field is not None:
            self.check_field(path, m, ports[0], in_types[0])
        if m.function is not None:
            self.check_function(path, m, in_types)

    def check_field(
        self, path: tuple[PathItem, ...], m: Measurement, port: Port | None, dt: DataType | None
    ) -> None:
        assert m.field is not None and port is not None
        if dt is None:
            self.error(
                "measurements",
                (*path, "field"),
                f"'{m.source}' carries {port.type},"
                f" which has no fields (a field needs a data type)",
            )
        elif m.field not in dt.fields:
            msg = unknown_name("field", m.field, dt.fields, f" of {dt.name}")
            self.error("measurements", (*path, "field"), msg)
        elif not _measurable(dt.fields[m.field], m.type):
            self.error(
                "measurements",
                (*path, "field"),
                f"field '{m.field}' of {dt.name} is"
                f" {dt.fields[m.field]}, but measurement '{m.name}' is {m.type}",
            )

    def check_function(
        self, path: tuple[PathItem, ...], m: Measurement, in_types: list[DataType | None]
    ) -> None:
        assert m.function is not None
        named = {k for dt in in_types if dt is not None for k in dt.functions}
        if m.function in named:
            return
        if "." not in m.function:
            msg = unknown_name("function", m.function, named)
            msg += "; expected a function of the source data type or a dotted Python path"
            self.error("measurements", (*path, "function"), msg)
            return
        problem = self.callable_problem(m.function)
        if problem:
            self.error("measurements", (*path, "function"), problem)

    def callable_problem(self, dotted: str) -> str | None:
        if dotted not in self._callables:
            self._callables[dotted] = _callable_problem(dotted, self.pkg.root)
        return self._callables[dotted]


# ---- warnings -----------------------------------------------------------------------------
@dataclass(frozen=True)
class ModelWarning:
    """Something legal in a model that weakens a guarantee (printed by ``rra validate``)."""

    message: str
    location: Location | None

    def __str__(self) -> str:
        where = f"{self.location}: " if self.location is not None else ""
        return f"{where}warning: {self.message}"


def measurement_warnings(pkg: SystemPackage) -> list[ModelWarning]:
    """A measured port whose type is not a declared data type: the Context Monitor can only
    check that its samples are maps (no field, no type), so it says so, at the source."""
    types = {t.name for t in pkg.measurements.data_types}
    doc = pkg.doc("measurements")
    out = []
    for i, m in enumerate(pkg.measurements.measurements):
        for j, src in enumerate(m.inputs):
            if m.ros2_topic is not None:
                continue  # a ROS 2 topic: every sample is decoded as its ROS 2 type
            ep = parse_endpoint(src)
            comp = pkg.system.component(ep.component)
            port = comp.port(ep.port) if comp is not None else None
            if port is None or port.type in types:
                continue
            where = ("measurements", i, "source") if m.source else ("measurements", i, "sources", j)
            out.append(
                ModelWarning(
                    f"'{src}' carries {port.type}, not a data type of data_types: the Context "
                    "Monitor can only check that its samples are maps (give the port a data "
                    "type to have every sample checked field by field)",
                    doc.loc(*where),
                )
            )
    return out


# ---- plain helpers -----------------------------------------------------------------------
def _in_file_order(errors: list[ModelError]) -> list[ModelError]:
    """Errors by file (in order of first appearance), then by line and column."""
    files: dict[str, int] = {}
    for e in errors:
        files.setdefault(e.location.file if e.location else "", len(files))

    def key(e: ModelError) -> tuple[int, int, int]:
        loc = e.location
        return (files[loc.file], loc.line, loc.col) if loc else (files[""], 0, 0)

    return sorted(errors, key=key)


def _duplicates(items: Iterable[H]) -> Iterator[tuple[int, H]]:
    """(index, item) of every repeated occurrence after the first."""
    seen: set[H] = set()
    for i, item in enumerate(items):
        if item in seen:
            yield i, item
        seen.add(item)


def _out_of_range(param: Parameter, value: object) -> str | None:
    if not isinstance(value, int | float) or isinstance(value, bool):
        return None
    if param.min is not None and value < param.min:
        return f"value {value} is below the minimum {param.min}"
    if param.max is not None and value > param.max:
        return f"value {value} is above the maximum {param.max}"
    return None


def _measurable(field_type: str, measurement_type: str) -> bool:
    return field_type == measurement_type or (field_type, measurement_type) == ("int", "float")


def _callable_problem(dotted: str, root: Path) -> str | None:
    """Why ``dotted`` does not import to a callable (None when it does)."""
    parts = dotted.split(".")
    if len(parts) < 2 or not all(p.isidentifier() for p in parts):
        return f"'{dotted}' is not a dotted Python path (expected module.function)"
    for i in range(len(parts) - 1, 0, -1):
        modname = ".".join(parts[:i])
        module, problem = _import(modname, root)
        if module is None and problem is None:  # no such module: a shorter prefix may be
            continue
        if module is None:
            return problem
        return _attribute_problem(module, modname, parts[i:], dotted)
    return f"cannot import '{dotted}': no module named '{parts[0]}'"


def _import(modname: str, root: Path) -> tuple[ModuleType | None, str | None]:
    """The module ``modname`` (its module-level code runs), or why not: ``(None, None)``
    when no module of that name exists, ``(None, reason)`` when importing it failed or a
    module of another origin hides the package's."""
    try:
        module = importlib.import_module(modname)
    except ModuleNotFoundError as e:
        if e.name is not None and (modname == e.name or modname.startswith(e.name + ".")):
            return None, None
        return None, f"importing '{modname}' failed: {e}"
    except (Exception, SystemExit) as e:
        return None, f"importing '{modname}' failed: {type(e).__name__}: {e}"
    hidden = shadowed_problem(module, [root])
    return (None, hidden) if hidden is not None else (module, None)


def _node_class_problem(dotted: str, root: Path) -> str | None:
    """Why the implementation ``pkg.module.Class`` (or ``pkg.module:Class``) does not import
    to a `rra_agent.node.Node` subclass (None when it does). Imports the module (its
    module-level code runs) and instantiates nothing."""
    modname, sep, clsname = dotted.replace(":", ".").rpartition(".")
    if not sep or not all(p.isidentifier() for p in [*modname.split("."), clsname]):
        return f"implementation '{dotted}' is not a dotted Python path (expected module.Class)"
    module, problem = _import(modname, root)
    if module is None:
        return problem or (
            f"cannot import '{modname}' for implementation '{dotted}': no module named"
            f" '{modname}' (neither installed nor in the package folder)"
        )
    cls = getattr(module, clsname, None)
    if cls is None:
        known = [
            n
            for n, v in vars(module).items()
            if _is_node_class(v) and not n.startswith("_")
        ]
        return unknown_name("node class", clsname, known, f" in '{modname}'")
    if not _is_node_class(cls):
        return f"'{dotted}' is not a subclass of rra_agent.node.Node"
    return None


#: The SDK's base class, by name: a package's models are checked below the Node SDK (which
#: this floor does not import), so a class is recognised by its ancestry's names.
_NODE_BASE = "rra_agent.node.api.Node"


def _is_node_class(obj: object) -> bool:
    """Whether ``obj`` is a subclass of the Node SDK's `Node` (by its ancestry's names)."""
    return isinstance(obj, type) and any(
        f"{c.__module__}.{c.__qualname__}" == _NODE_BASE for c in obj.__mro__
    )


def _command_problem(impl: Command, root: Path | None = None) -> str | None:
    """Why an external command's program cannot be run (None when it can): a name is looked
    up on PATH (the implementation's own ``env`` PATH if it sets one); a path is taken
    relative to its ``cwd`` (itself relative to the current folder, as the host agent runs
    it; to ``root``, the package folder, for a ROS 2 node's) and must be an executable file."""
    program = impl.command[0]
    if "/" not in program:
        search = impl.env.get("PATH", os.environ.get("PATH", os.defpath))
        if shutil.which(program, path=search) is None:
            return f"program '{program}' of the external command is not on PATH"
        return None
    file = Path(root or ".") / (impl.cwd or ".") / program
    if not file.exists():
        return f"program '{program}' of the external command does not exist ({file})"
    if not file.is_file() or not os.access(file, os.X_OK):
        return f"program '{program}' of the external command is not an executable file"
    return None


def _attribute_problem(obj: object, owner: str, attrs: list[str], dotted: str) -> str | None:
    for attr in attrs:
        if not hasattr(obj, attr):
            known = [n for n in dir(obj) if not n.startswith("_")]
            return unknown_name("name", attr, known, f" in '{owner}'")
        obj, owner = getattr(obj, attr), f"{owner}.{attr}"
    return None if callable(obj) else f"'{dotted}' is not callable"


@contextlib.contextmanager
def _on_sys_path(root: Path) -> Iterator[None]:
    """Put the package folder on sys.path as a node process has it (last: see
    `rra_agent.package.imports`); forget it and the modules imported from it after."""
    folder = str(root.resolve())
    before = set(sys.modules)
    present = folder in sys.path
    add_package_path([folder])
    try:
        yield
    finally:
        if not present:
            with contextlib.suppress(ValueError):
                sys.path.remove(folder)
        for name in set(sys.modules) - before:
            file = getattr(sys.modules[name], "__file__", None) or ""
            if file.startswith(folder + "/") or file.startswith(folder + "\\"):
                del sys.modules[name]
