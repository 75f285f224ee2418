"""The Template System Model (paper Sec. II): components, ports, parameters, connections, hosts.

The same Structs describe the Deployment-time and Run-time Configured System Models: those are
system models with their deployment-time (resp. all) variation points resolved.

Variation points of the template (paper Sec. II): (a) optional components, (b) alternative
implementations, (c) optional connections, (d) configurable parameters. A component or
connection with ``optional: true`` is absent unless a resolution transformation includes it;
its ``binding`` says which resolution model may do so. Run-time-bound optional parts stay in
the Deployment-time Configured System Model as run-time variation points.
"""

from __future__ import annotations

from typing import Literal

import msgspec

from rra_agent.models.base import FrozenModel
from rra_agent.ros2.errors import BadName
from rra_agent.ros2.names import check_namespace, check_node_name, check_type_name

Binding = Literal["deployment", "runtime"]
ParamType = Literal["float", "int", "bool", "str", "list"]
ParamValue = bool | int | float | str | list
Direction = Literal["publish", "subscribe"]


class Command(FrozenModel, frozen=True):
    """An external program run as a node (any language speaking the wire protocol)."""

    command: list[str]
    env: dict[str, str] = {}
    cwd: str | None = None


#: A dotted Python path of a Node class (``pkg.module.ClassName``) or an external command.
Implementation = str | Command


class Parameter(FrozenModel, frozen=True):
    """A typed, run-time settable component parameter."""

    type: ParamType
    value: ParamValue
    unit: str | None = None
    description: str | None = None
    #: Bounds, in the parameter's type: an int parameter's are ints (``min: 0``, never
    #: ``0.0`` in what `rra resolve` prints), a float parameter's floats.
    min: float | None = None
    max: float | None = None

    def __post_init__(self) -> None:
        if not value_has_type(self.value, self.type):
            raise ValueError(f"value {self.value!r} is not of type {self.type}")
        for bound in ("min", "max"):
            typed = _bound_in_type(getattr(self, bound), self.type)
            msgspec.structs.force_setattr(self, bound, typed)
        if self.min is not None and self.max is not None and self.min > self.max:
            raise ValueError(f"min {self.min} is greater than max {self.max}")


def _bound_in_type(bound: float | None, type_: ParamType) -> float | None:
    """A bound as the parameter's type has it: an integral bound of an int parameter an int,
    a bound of a float parameter a float (others as written)."""
    if bound is None or isinstance(bound, bool):
        return bound
    if type_ == "int" and float(bound).is_integer():
        return int(bound)
    if type_ == "float":
        return float(bound)
    return bound


def value_has_type(value: object, type_: ParamType) -> bool:
    """Whether a parameter value fits a declared type (ints are accepted as floats)."""
    match type_:
        case "bool":
            return isinstance(value, bool)
        case "int":
            return isinstance(value, int) and not isinstance(value, bool)
        case "float":
            return isinstance(value, int | float) and not isinstance(value, bool)
        case "str":
            return isinstance(value, str)
        case "list":
            return isinstance(value, list)
    return False


def coerce_parameter(
    type_: ParamType, value: object, lo: float | None = None, hi: float | None = None
) -> ParamValue:
    """``value`` as a parameter of the declared type and bounds, or ValueError saying why.

    An int is accepted for a float (and becomes a float: a float parameter stays a float);
    a float with an integral value for an int; NaN and values outside [lo, hi] never.
    """
    if type_ == "float" and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    elif type_ == "int" and isinstance(value, float) and value.is_integer():
        value = int(value)
    if not value_has_type(value, type_):
        raise ValueError(f"expected {type_}, got {type(value).__name__} {value!r}")
    if type_ in ("int", "float"):
        number = float(value)  # type: ignore[arg-type]
        if number != number:
            raise ValueError("NaN is not a value")
        if lo is not None and number < lo:
            raise ValueError(f"{value!r} is below its minimum {lo:g}")
        if hi is not None and number > hi:
            raise ValueError(f"{value!r} is above its maximum {hi:g}")
    return value  # type: ignore[return-value]


class Port(FrozenModel, frozen=True):
    """A data port. A publisher's samples go to ``rra/<system>/data/<topic>``; ``topic``
    defaults to ``<component>/<port>``. A subscriber listens on the topics of the publishers
    connected to it."""

    name: str
    direction: Direction
    type: str
    topic: str | None = None
    #: A publisher: the largest sample it may send, in bytes (default 1 MiB,
    #: `rra_agent.bus.counters.MAX_PAYLOAD`); larger ones are dropped by the routers.
    max_bytes: int | None = None
    #: A ROS 2 port: its samples are also (a ROS 2 component's: only) this ROS 2 message
    #: type, on the ROS 2 topic ``/<topic>`` (docs/ros2.md), e.g. ``sensor_msgs/msg/Imu``.
    ros2_type: str | None = None

    def __post_init__(self) -> None:
        if self.ros2_type is not None:
            try:
                check_type_name(self.ros2_type, "msg")
            except BadName as e:
                raise ValueError(str(e)) from None
        if self.max_bytes is not None:
            if self.direction != "publish":
                raise ValueError("'max_bytes' is a publisher's: its subscribers take what it sends")
            if self.max_bytes <= 0:
                raise ValueError(f"'max_bytes' must be positive, got {self.max_bytes}")


class Supervision(FrozenModel, frozen=True):
    """How a component's process is supervised by its host agent (docs/architecture.md,
    failure model). Times in seconds.

    A process's exit is known from the OS at once. A *frozen* process is one whose heartbeat
    is older than ``heartbeat_timeout`` and that then does not answer a direct probe within
    ``probe_timeout``; only then is it killed. More than ``max_restarts`` restarts within
    ``restart_window`` make it FATAL; a FATAL node is tried again after ``cooldown``.
    """

    #: Restart after: ``on-failure`` a non-zero exit or a freeze; ``always`` also exit 0.
    restart: Literal["always", "on-failure", "never"] = "on-failure"
    #: Heartbeat deadline (the node beats ~4 times per deadline); 0 = no freeze detection.
    heartbeat_timeout: float = 4.0
    probe_timeout: float = 1.0
    #: From spawn to ready (the liveliness token declared after ports and ``on_start``).
    start_timeout: float = 10.0
    max_restarts: int = 5
    restart_window: float = 60.0
    cooldown: float = 30.0
    backoff_initial: float = 0.1
    backoff_max: float = 5.0

    def __post_init__(self) -> None:
        for name in self.__struct_fields__:
            value = getattr(self, name)
            if isinstance(value, int | float) and not isinstance(value, bool) and value < 0:
                raise ValueError(f"{name} must not be negative, got {value}")
        if 0 < self.heartbeat_timeout < 0.2:
            raise ValueError("heartbeat_timeout below 0.2 s makes busy nodes look frozen")
        if self.max_restarts < 1:
            raise ValueError("max_restarts must be at least 1")


class Scheduling(FrozenModel, frozen=True):
    """How the kernel schedules a component's process, applied by its host agent at start
    (before the node runs any of its code; every thread it starts inherits it).

    ``policy``: ``fifo`` / ``rr`` are real-time (SCHED_FIFO / SCHED_RR) with ``priority``
    1..99 (a real-time process runs before every normal one: give it to the few processes
    on the critical path, and keep their callbacks short); ``other`` (the default), ``batch``
    and ``idle`` are the normal policies, ordered among themselves by ``nice`` (-20..19,
    lower runs first). ``cpus``: the CPUs the process may run on (empty: all). Where the
    kernel refuses (no CAP_SYS_NICE, RLIMIT_RTPRIO 0, a CPU that does not exist), the node
    runs without it and its host agent says so in a warning event.
    """

    policy: Literal["other", "batch", "idle", "fifo", "rr"] = "other"
    priority: int = 0
    nice: int = 0
    cpus: list[int] = []

    def __post_init__(self) -> None:
        realtime = self.policy in ("fifo", "rr")
        if realtime and not 1 <= self.priority <= 99:
            raise ValueError(f"a {self.policy} policy needs a priority 1..99, got {self.priority}")
        if not realtime and self.priority != 0:
            raise ValueError(f"priority is for the fifo and rr policies, not {self.policy!r}")
        if not -20 <= self.nice <= 19:
            raise ValueError(f"nice must be -20..19, got {self.nice}")
        if any(c < 0 for c in self.cpus) or len(set(self.cpus)) != len(self.cpus):
            raise ValueError(f"cpus must be distinct CPU numbers, got {self.cpus}")

    @property
    def is_default(self) -> bool:
        return self == Scheduling()


class Ros2Node(FrozenModel, frozen=True):
    """A component that is a ROS 2 node (docs/ros2.md): its external commands (and its
    ``ros2: PACKAGE EXECUTABLE`` implementations) are ROS 2 executables, started with
    ``--ros-args`` and driven through the node's ROS 2 services.

    ``node``/``namespace``: its ROS 2 name (default: the component's name, in ``/``);
    ``lifecycle``: a managed node (activated and deactivated with ``change_state``: what
    the ``standby`` and ``hot-standby`` strategies need); ``rewire``: how a subscriber port
    is rewired at run time, ``relay`` (a relay in front of it is switched: no restart) or
    ``restart`` (the executable is restarted with the new ``-r`` remapping);
    ``timeout``: the deadline of each ROS 2 service call (parameters, lifecycle), seconds."""

    node: str | None = None
    namespace: str = "/"
    lifecycle: bool = False
    rewire: Literal["relay", "restart"] = "relay"
    timeout: float = 1.0

    def __post_init__(self) -> None:
        try:
            if self.node is not None:
                check_node_name(self.node)
            check_namespace(self.namespace)
        except BadName as e:
            raise ValueError(str(e)) from None
        if not 0 < self.timeout <= 1.5:
            raise ValueError(
                f"timeout must be in (0, 1.5] s (an engine waits 2 s for the reply), got "
                f"{self.timeout}"
            )


ROS2_PREFIX = "ros2:"


def is_ros2_implementation(impl: Implementation, component: Component | None = None) -> bool:
    """Whether an implementation is a ROS 2 executable: ``ros2: PACKAGE EXECUTABLE``, or an
    external command of a component with a ``ros2`` section."""
    if isinstance(impl, str):
        return impl.startswith(ROS2_PREFIX)
    return component is not None and component.ros2 is not None


#: The implementation of a component container's process (`rra_agent.node.container`; its
#: spec is made by the host agent, never taken from the bus). Here, not in the node's
#: modules: the host agent names it without importing the Node SDK.
CONTAINER = "rra_agent.node.container"


class Component(FrozenModel, frozen=True):
    name: str
    implementation: Implementation
    #: Named alternative implementations, selectable by a ``set_implementation`` transformation.
    implementations: dict[str, Implementation] = {}
    parameters: dict[str, Parameter] = {}
    ports: list[Port] = []
    optional: bool = False
    binding: Binding = "deployment"
    host: str | None = None
    description: str | None = None
    supervision: Supervision = Supervision()
    scheduling: Scheduling = Scheduling()
    #: Run in this component container of the host (with the other components naming it)
    #: instead of a process of its own; Python implementations only.
    container: str | None = None
    #: The component is a ROS 2 node (docs/ros2.md).
    ros2: Ros2Node | None = None

    @property
    def implementations_all(self) -> tuple[Implementation, ...]:
        return (self.implementation, *self.implementations.values())

    def speaks_ros2(self) -> bool:
        """Whether its process is on the ROS 2 side: a ROS 2 node, or a node with a ROS 2
        port (rra-agent's own ROS 2 node of it publishes there)."""
        return (
            self.ros2 is not None
            or any(p.ros2_type for p in self.ports)
            or any(is_ros2_implementation(i, self) for i in self.implementations_all)
        )

    def __post_init__(self) -> None:
        names = [p.name for p in self.ports]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicate port name(s) {', '.join(dup)}")
        if self.binding == "runtime" and not self.optional:
            raise ValueError("a run-time-bound component must be optional")
        if self.container is not None:
            impls = (self.implementation, *self.implementations.values())
            if not all(isinstance(i, str) and not is_ros2_implementation(i) for i in impls):
                raise ValueError("a component in a container needs Python implementations")

    def port(self, name: str) -> Port | None:
        return next((p for p in self.ports if p.name == name), None)


class Endpoint(FrozenModel, frozen=True):
    """``component.port`` parsed."""

    component: str
    port: str

    def __str__(self) -> str:
        return f"{self.component}.{self.port}"


def parse_endpoint(text: str) -> Endpoint:
    comp, sep, port = text.partition(".")
    if not sep or not comp or not port:
        raise ValueError(f"expected 'component.port', got {text!r}")
    return Endpoint(component=comp, port=port)


class Connection(FrozenModel, frozen=True):
    """A publisher port feeding a subscriber port (``from``/``to`` as ``component.port``)."""

    source: str = msgspec.field(name="from")
    target: str = msgspec.field(name="to")
    optional: bool = False
    binding: Binding = "deployment"

    def __post_init__(self) -> None:
        parse_endpoint(self.source)
        parse_endpoint(self.target)
        if self.binding == "runtime" and not self.optional:
            raise ValueError("a run-time-bound connection must be optional")

    @property
    def key(self) -> tuple[str, str]:
        return (self.source, self.target)


class Host(FrozenModel, frozen=True):
    name: str
    #: Zenoh endpoint of the host agent, e.g. ``tcp/127.0.0.1:7448``; None = this machine.
    endpoint: str | None = None
    description: str | None = None


class SystemModel(FrozenModel, frozen=True):
    """A Template (or Configured) System Model."""

    system: str
    components: list[Component] = []
    connections: list[Connection] = []
    hosts: list[Host] = []
    description: str | None = None

    def __post_init__(self) -> None:
        names = [c.name for c in self.components]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicate component name(s) {', '.join(dup)}")
        hosts: dict[str, str | None] = {}
        for c in self.components:
            if c.container is None:
                continue
            if c.container in names:
                raise ValueError(f"container {c.container!r} has a component's name")
            if hosts.setdefault(c.container, c.host) != c.host:
                raise ValueError(f"the components of container {c.container!r} are on two hosts")

    def component(self, name: str) -> Component | None:
        return next((c for c in self.components if c.name == name), None)


#: The paper's Configured System Models are system models with variation points resolved:
#: the Deployment-time one (`rra_agent.core.resolution.resolve_deployment`) has only its
#: run-time variation points left; the Run-time one (`resolve_runtime`: what runs for a
#: run-time selection and its CV values; `rra_agent.core.effect.effective_model`: what runs
#: after a plan applied in part) has none. The names say which one a function takes or gives.
DeploymentConfiguredSystemModel = SystemModel
RuntimeConfiguredSystemModel = SystemModel
