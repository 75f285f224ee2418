"""What a host agent may run: the components its system model places on its host.

A host agent never runs what a request describes; it runs what the model declares. A
``StartNode`` or ``UpdateSpec`` from the bus names a component and one of its declared
implementations; `Catalog.admit` checks the request against the host's own copy of the
Deployment-time Configured System Model (every run-time variant is in it) and returns the
spec the host runs, whose command line, environment, working directory, import path,
parameter declarations and supervision all come from the model on this host:

- the system and the host are this agent's; the node name is a declared component (valid
  as a file name and a key chunk: no path separators, no ``..``) placed on this host;
- the implementation is one of the component's declared implementations, compared whole:
  an external command with another argument, environment variable or working directory is
  not the declared one;
- every parameter is declared and within its declared type and bounds;
- every port is one the component declares, of the type it declares; the data types of its
  inputs (and the types they nest) go with the spec, for the node to check its samples.

Processes the host agent starts itself (``rra up``'s engines) are registered as built-ins;
a request from the bus may not start or respecify them.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec

from rra_agent.bus import messages as m
from rra_agent.bus.keys import check_chunk
from rra_agent.core.samples import nested
from rra_agent.host.forkserver import python_module
from rra_agent.models.manifest import Ros2Settings
from rra_agent.models.measurements import DataType
from rra_agent.models.system import (
    CONTAINER,
    Component,
    Implementation,
    SystemModel,
    coerce_parameter,
    is_ros2_implementation,
)
from rra_agent.package.ros2 import interfaces_folder, node_name

if TYPE_CHECKING:
    from rra_agent.deployment import Deployment


class Refused(Exception):
    """A request the model does not allow (the message says which rule)."""


def check_name(name: str, what: str = "node name") -> str:
    """A name used as a key chunk and as a file name (logs, heartbeats)."""
    try:
        check_chunk(name, what)
    except ValueError as e:
        raise Refused(str(e)) from None
    if name.startswith("."):
        raise Refused(f"{what} {name!r} may not start with '.'")
    return name


class Catalog:
    """The components a host may run, from its own copy of the system model."""

    def __init__(
        self,
        model: SystemModel,
        host: str,
        *,
        package_root: str | Path,
        default_host: bool = False,
        ros2: Ros2Settings | None = None,
        data_types: Iterable[DataType] = (),
    ) -> None:
        self.system = model.system
        self.data_types = list(data_types)
        self.host = host
        self.default_host = default_host
        self.path = [str(Path(package_root).resolve())]
        #: The package's ``ros2:`` section, and its interface files on this host.
        self.ros2 = ros2
        self.interfaces = interfaces_folder(package_root, ros2)
        #: Components placed on this host (those without a host run on the first host).
        self.components: dict[str, Component] = {
            c.name: c
            for c in model.components
            if c.host == host or (c.host is None and default_host)
        }
        self.builtins: dict[str, m.NodeSpec] = {}

    @classmethod
    def of(cls, dep: Deployment, host: str, *, default_host: bool = False) -> Catalog:
        """The catalog of ``host`` in a deployment: its configured system model, its package
        folder, its ``ros2:`` settings and its data types."""
        return cls(
            dep.configured, host, package_root=dep.package.root, default_host=default_host,
            ros2=dep.package.manifest.ros2, data_types=dep.package.measurements.data_types,
        )  # fmt: skip

    def types_of(self, c: Component) -> list[DataType]:
        """The data types the inputs of ``c`` carry, with the types they nest."""
        inputs = (p.type for p in c.ports if p.direction == "subscribe")
        return nested(self.data_types, inputs)

    def add_builtins(self, specs: Iterable[m.NodeSpec]) -> None:
        """Processes this host agent starts on its own (never from a request)."""
        self.builtins.update((s.name, s) for s in specs)

    @property
    def forked(self) -> list[list[str]]:
        """The built-ins' commands that are ``python -m MODULE ...`` of this interpreter
        (``rra up``'s engines): the fork server imports MODULE, lets it prepare (its
        ``warm_up``) and runs each in a fork of itself instead of a new interpreter
        (`rra_agent.host.forkserver`)."""
        out: list[list[str]] = []
        for spec in self.builtins.values():
            impl = spec.implementation
            command = [] if isinstance(impl, str) else list(impl.command)
            if python_module(command) is not None and command not in out:
                out.append(command)
        return out

    def container_of(self, name: str) -> str | None:
        """The container a component of this host runs in (None: a process of its own)."""
        c = self.components.get(name)
        return c.container if c is not None else None

    @property
    def containers(self) -> frozenset[str]:
        return frozenset(c.container for c in self.components.values() if c.container)

    def container_spec(self, container: str) -> m.NodeSpec:
        """The spec of a container process: what it may load (its members' declared
        implementations and parameters), made here, never taken from the bus."""
        members = [c for c in self.components.values() if c.container == container]
        scheduling = next((c.scheduling for c in members if not c.scheduling.is_default), None)
        spec = m.NodeSpec(
            system=self.system,
            name=container,
            host=self.host,
            implementation=CONTAINER,
            params={
                "members": {
                    c.name: {
                        "implementations": [c.implementation, *c.implementations.values()],
                        "decl": {
                            k: msgspec.to_builtins(m.ParamDecl(type=p.type, min=p.min, max=p.max))
                            for k, p in c.parameters.items()
                        },
                        "ports": {p.name: p.type for p in c.ports},
                        "types": msgspec.to_builtins(self.types_of(c)),
                    }
                    for c in members
                }
            },
            path=list(self.path),
        )
        if scheduling is not None:  # else NodeSpec's own default instance, which encoding omits
            spec.scheduling = scheduling
        return spec

    @property
    def implementations(self) -> frozenset[str]:
        """Python implementations this host may run (the fork server pre-imports them)."""
        return frozenset(
            impl
            for c in self.components.values()
            for impl in (c.implementation, *c.implementations.values())
            if isinstance(impl, str) and not is_ros2_implementation(impl)
        )

    @property
    def preload(self) -> list[str]:
        """What the fork server imports ahead of the nodes: the package folder (appended to
        the import path) and every Python implementation of this host."""
        return [*self.path, *sorted(i for i in self.implementations if "." in i)]

    def admit(self, spec: m.NodeSpec) -> m.NodeSpec:
        """The spec to run for this request, derived from the model; `Refused` if the model
        does not allow it."""
        name = check_name(spec.name)
        if spec.system != self.system:
            raise Refused(f"node {name}: system {spec.system!r} is not {self.system!r}")
        if spec.host != self.host:
            raise Refused(f"node {name}: host {spec.host!r} is not this host ({self.host})")
        if name in self.builtins:
            raise Refused(f"{name} is started by this host agent only")
        c = self.components.get(name)
        if c is None:
            raise Refused(f"no component {name!r} is placed on host {self.host} by the model")
        declared = (c.implementation, *c.implementations.values())
        if spec.implementation not in declared:
            raise Refused(
                f"node {name}: implementation {m.implementation_id(spec.implementation)} is "
                "not one the model declares for it"
            )
        impl = declared[declared.index(spec.implementation)]
        try:
            ports = m.typed_ports(name, spec.ports, {p.name: p.type for p in c.ports})
        except ValueError as e:
            raise Refused(str(e)) from None
        decl = {k: m.ParamDecl(type=p.type, min=p.min, max=p.max) for k, p in c.parameters.items()}
        for key, value in spec.params.items():
            d = decl.get(key)
            if d is None:
                raise Refused(f"node {name}: parameter {key!r} is not declared")
            if value is None:
                continue  # not set: the node starts without it
            try:
                coerce_parameter(d.type, value, d.min, d.max)
            except ValueError as e:
                raise Refused(f"node {name}: parameter {key}: {e}") from None
        return msgspec.structs.replace(
            spec,
            implementation=impl,
            decl=decl,
            supervision=c.supervision,
            scheduling=c.scheduling,
            path=list(self.path) if isinstance(impl, str) else [],
            ros2=self.ros2_spec(c, impl),
            ports=ports,
            types=self.types_of(c),
        )

    def ros2_spec(self, c: Component, impl: Implementation) -> m.Ros2Spec | None:
        """The ROS 2 side of component ``c`` run as ``impl``, from the model (None: it has
        none)."""
        if self.ros2 is None or not c.speaks_ros2():
            return None
        node = c.ros2
        return m.Ros2Spec(
            domain=self.ros2.domain,
            distro=self.ros2.distro,
            interfaces=self.interfaces,
            folder=self.path[0],
            node=node_name(c),
            namespace=node.namespace if node else "/",
            executable=is_ros2_implementation(impl, c),
            lifecycle=bool(node and node.lifecycle),
            rewire=node.rewire if node else "relay",
            timeout=node.timeout if node else 1.0,
            ports={p.name: p.ros2_type for p in c.ports if p.ros2_type},
        )
