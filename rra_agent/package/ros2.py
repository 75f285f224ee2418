"""A package's ROS 2 side: its message types, and the checks of everything ROS 2 it names.

`registry` builds the `TypeRegistry` of a package once per process (the distribution's
messages and the package's own interface files, ``rra.yaml``'s ``ros2: {distro,
interfaces}``). `problems` lists what is wrong with the ROS 2 parts of the models, each at
the place of the model that says it, for `rra_agent.package.validate`: a ROS 2 measurement
whose type or field does not exist or cannot be a measurement of its type, a port whose ROS
2 type does not exist or whose topic is no ROS 2 name, a ``ros2: PACKAGE EXECUTABLE`` that
does not parse, a ROS 2 node's port without a ROS 2 type, a connection between a ROS 2 node
and a node that cannot hear it, a standby strategy for a node that is not managed.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from rra_agent.models.manifest import Ros2Settings
from rra_agent.models.measurements import Measurement
from rra_agent.models.system import (
    Component,
    Port,
    is_ros2_implementation,
    parse_endpoint,
)
from rra_agent.package.contents import SystemPackage
from rra_agent.package.yamlload import PathItem
from rra_agent.ros2.errors import Ros2Error
from rra_agent.ros2.launch import parse_implementation
from rra_agent.ros2.names import check_node_name, qualify

if TYPE_CHECKING:  # imported where a registry is built: it imports numpy and rosbags (8 MiB)
    from rra_agent.ros2.types import TypeRegistry

#: Measurement type -> the ROS 2 field types it can take its value from.
_MEASURABLE = {
    "float": {"float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
              "int64", "uint64", "byte", "char"},
    "int": {"int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64", "byte",
            "char"},
    "bool": {"bool"},
    "str": {"string"},
}
#: Strategies that start a node inactive (a ROS 2 node then needs a lifecycle).
_INACTIVE_START = ("standby", "start-then-stop")

_registries: dict[tuple[str, str | None], TypeRegistry] = {}


def registry(root: str | Path, settings: Ros2Settings) -> TypeRegistry:
    """The package's types (built once per process and package); `Ros2Error` when its
    interface files do not load."""
    folder = None
    if settings.interfaces is not None:
        folder = str((Path(root) / settings.interfaces).resolve())
    key = (settings.distro, folder)
    types = _registries.get(key)
    if types is None:
        from rra_agent.ros2.types import TypeRegistry

        types = TypeRegistry(settings.distro)
        if folder is not None:
            types.register_folder(folder)
        _registries[key] = types
    return types


def interfaces_folder(root: str | Path, settings: Ros2Settings | None) -> str | None:
    """The absolute folder of the package's interface files, if it has one."""
    if settings is None or settings.interfaces is None:
        return None
    return str((Path(root) / settings.interfaces).resolve())


def ros2_topic(component: Component, port: Port) -> str:
    """The ROS 2 topic of a port: ``/`` and its topic (``/<component>/<port>`` by default)."""
    return "/" + (port.topic or f"{component.name}/{port.name}")


def node_name(component: Component) -> str:
    """A component's ROS 2 node name: its ``ros2.node``, else its name."""
    if component.ros2 is not None and component.ros2.node is not None:
        return component.ros2.node
    return component.name


@dataclass(frozen=True)
class Problem:
    model: str
    path: tuple[PathItem, ...]
    message: str
    key: bool = False


def uses_ros2(pkg: SystemPackage) -> bool:
    """Whether any model of the package names something of ROS 2."""
    return any(c.speaks_ros2() for c in pkg.system.components) or any(
        m.ros2_topic is not None for m in pkg.measurements.measurements
    )


def problems(pkg: SystemPackage) -> list[Problem]:
    """What is wrong with the package's ROS 2 parts (empty: nothing, or no ROS 2 parts)."""
    settings = pkg.manifest.ros2
    if settings is None:
        return list(_without_settings(pkg))
    try:
        types = registry(pkg.root, settings)
    except Ros2Error as e:
        return [Problem("manifest", ("ros2", "interfaces"), str(e))]
    return [*_components(pkg, types), *_connections(pkg), *_strategies(pkg),
            *_measurements(pkg, types)]


def _without_settings(pkg: SystemPackage) -> Iterator[Problem]:
    need = "needs a `ros2:` section in rra.yaml (its domain and distribution)"
    for i, c in enumerate(pkg.system.components):
        if c.speaks_ros2():
            yield Problem("system", ("components", i, "name"), f"ROS 2 component {c.name} {need}")
    for i, m in enumerate(pkg.measurements.measurements):
        if m.ros2_topic is not None:
            yield Problem("measurements", ("measurements", i, "source"),
                          f"ROS 2 measurement {m.name} {need}")


def _components(pkg: SystemPackage, types: TypeRegistry) -> Iterator[Problem]:
    for i, c in enumerate(pkg.system.components):
        path: tuple[PathItem, ...] = ("components", i)
        is_node = any(is_ros2_implementation(impl, c) for impl in c.implementations_all)
        for j, port in enumerate(c.ports):
            yield from _port(c, port, (*path, "ports", j), types, is_node)
        if c.container is not None and c.speaks_ros2():
            yield Problem("system", (*path, "container"),
                          f"component {c.name} speaks ROS 2: it needs a process of its own, "
                          "not a container")
        impls: list[tuple[tuple[PathItem, ...], object]] = [
            ((*path, "implementation"), c.implementation),
            *(((*path, "implementations", n), i) for n, i in c.implementations.items()),
        ]
        for at, impl in impls:
            if isinstance(impl, str) and is_ros2_implementation(impl):
                try:
                    parse_implementation(impl)
                except Ros2Error as e:
                    yield Problem("system", at, str(e))


def _port(
    c: Component, port: Port, path: tuple[PathItem, ...], types: TypeRegistry, is_node: bool
) -> Iterator[Problem]:
    if is_node:
        try:
            check_node_name(port.name)  # the name it remaps: a ROS 2 name's token
        except Ros2Error:
            yield Problem("system", (*path, "name"),
                          f"port {port.name!r} of ROS 2 node {c.name} is not a ROS 2 name (its "
                          "executable's name for the topic: letters, digits and '_')")
    if port.ros2_type is None:
        if is_node:
            yield Problem("system", (*path, "name"),
                          f"port {c.name}.{port.name} of ROS 2 node {c.name} needs a "
                          "`ros2_type` (its samples are ROS 2 messages)")
        return
    try:
        types.require(port.ros2_type)
    except Ros2Error as e:
        yield Problem("system", (*path, "ros2_type"), str(e))
    try:
        qualify(ros2_topic(c, port))
    except Ros2Error as e:
        where = "topic" if port.topic else "name"
        yield Problem("system", (*path, where),
                      f"{c.name}.{port.name} is on ROS 2 topic {ros2_topic(c, port)!r}: {e}")


def _connections(pkg: SystemPackage) -> Iterator[Problem]:
    """A ROS 2 node hears and speaks ROS 2 only; both ends of a ROS 2 link agree on its type."""
    system = pkg.system
    for i, conn in enumerate(system.connections):
        ends = []
        for text in (conn.source, conn.target):
            ep = parse_endpoint(text)
            comp = system.component(ep.component)
            port = comp.port(ep.port) if comp is not None else None
            ends.append((comp, port))
        (sc, sp), (tc, tp) = ends
        if sc is None or sp is None or tc is None or tp is None:
            continue  # validate.py reports the unknown names
        s_node, t_node = _is_ros2_node(sc), _is_ros2_node(tc)
        if (s_node or t_node) and (sp.ros2_type is None or tp.ros2_type is None):
            bare = conn.source if sp.ros2_type is None else conn.target
            yield Problem("system", ("connections", i, "from" if bare == conn.source else "to"),
                          f"{conn.source} -> {conn.target} links a ROS 2 node: '{bare}' needs "
                          "a `ros2_type` (a ROS 2 node sends and receives ROS 2 messages only)")
        elif s_node and not t_node:
            yield Problem("system", ("connections", i, "to"),
                          f"{conn.source} -> {conn.target}: '{conn.target}' is a node of "
                          "rra-agent, which receives rra-agent's samples only, not ROS 2 "
                          "messages of ROS 2 node " + sc.name)
        elif sp.ros2_type and tp.ros2_type and sp.ros2_type != tp.ros2_type and sp.type == tp.type:
            yield Problem("system", ("connections", i, "to"),
                          f"ROS 2 type mismatch: '{conn.source}' publishes {sp.ros2_type} but "
                          f"'{conn.target}' expects {tp.ros2_type}")


def _is_ros2_node(c: Component) -> bool:
    return any(is_ros2_implementation(i, c) for i in c.implementations_all)


def _strategies(pkg: SystemPackage) -> Iterator[Problem]:
    rep = pkg.runtime.replacement
    for c in pkg.system.components:
        if not _is_ros2_node(c) or (c.ros2 is not None and c.ros2.lifecycle):
            continue
        strategy = rep.strategy_for(c.name)
        if strategy in _INACTIVE_START:
            where: tuple[PathItem, ...] = (
                ("replacement", "components", c.name) if c.name in rep.components
                else ("replacement", "default")
            )
            yield Problem("runtime", where,
                          f"strategy {strategy} starts {c.name} inactive, but ROS 2 node "
                          f"{c.name} is not managed: give it `ros2: {{lifecycle: true}}` "
                          "(a lifecycle node) or use stop-then-start or hot-standby")


def _measurements(pkg: SystemPackage, types: TypeRegistry) -> Iterator[Problem]:
    for i, m in enumerate(pkg.measurements.measurements):
        if m.ros2_topic is not None:
            yield from _measurement(m, ("measurements", i), types)


def _measurement(m: Measurement, path: tuple[PathItem, ...], types: TypeRegistry
                 ) -> Iterator[Problem]:
    assert m.ros2_type is not None
    try:
        types.require(m.ros2_type)
    except Ros2Error as e:
        yield Problem("measurements", (*path, "ros2_type"), str(e))
        return
    if m.field is None:
        return
    from rra_agent.ros2.bridge import check_measurement

    try:
        leaf = check_measurement(types, m.ros2_topic or "/", m.ros2_type, m.field)
    except Ros2Error as e:
        yield Problem("measurements", (*path, "field"), str(e))
        return
    base = leaf.split("<=")[0]
    if base not in _MEASURABLE[m.type]:
        yield Problem("measurements", (*path, "field"),
                      f"field '{m.field}' of {m.ros2_type} is {leaf}, but measurement "
                      f"'{m.name}' is {m.type}")
