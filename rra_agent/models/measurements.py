"""Data Types and Context Dependent Measurements Model (paper Sec. III-C, Fig. 4, Table I).

Data types describe what component ports carry (msgpack maps on the bus) and the functions
defined on them. A measurement names its source interface(s) (``component.port``), the type it
produces, and an optional function turning the source data into the measurement. A function
is a key of the source type's ``functions`` (the paper: functions belong to data types) or a
dotted Python path ``pkg.module.func``.

Multi-input measurements (the paper's first future-work item) list several ``sources`` and a
synchronisation policy: ``latest`` (recompute on every input from the latest value of each)
or ``window`` (recompute only when every input has a sample within ``window_ms`` of the newest).
The function then receives one argument per source, in order.

Data the monitor can trust: every sample of a measured source is decoded against its port's
declared data type (a missing field or a value of the wrong type refuses the sample; a field
listed in ``optional`` may be absent). A measurement refuses NaN and infinities in the values
it reads and in the value it computes unless it says ``finite: false`` (a distance that is
``inf`` when nothing is in sight), and a value outside its ``plausible`` bounds. Refused
samples never reach the rules; the Context Monitor counts them per source and reason.

Nodes trust their inputs the same way: a subscriber port whose type is a declared data type
delivers to the node only samples of that type, with finite numbers except in the fields the
type lists in ``non_finite`` (`rra_agent.node.core.NodeCore.deliver`).

A measurement may instead be a host's reachability (``reachable: base_station``, type
``bool``): true while that host's agent is reachable from the engines, false from the moment
its link is lost (within the bus lease). The Context Monitor publishes it like any other, so
rules can react to a partition (e.g. select an on-board planner when the base station is
gone).

Or a ROS 2 topic (``source: ros2:/battery``, ``ros2_type: sensor_msgs/msg/BatteryState``,
``field: percentage``; the package's ``rra.yaml`` has a ``ros2:`` section): the Context
Monitor subscribes to the topic as rmw_zenoh does and takes ``field`` (a dotted path,
``header.stamp.sec``, ``cell_voltage.2``) of every sample; a ``function`` gets the whole
message as a dict. A sample of another type, of another definition of the type or that is
not CDR of it is refused and counted, like a sample of a port.

Or a component's availability (``available: camera``, type ``bool``): false while an
implementation of that component is unavailable (it could not start, or kept crashing; the
Run-time Resolution Engine says so), true otherwise. Failure is context: rules may read it
like any measurement.
"""

from __future__ import annotations

from typing import Literal

from rra_agent.models.base import FrozenModel
from rra_agent.models.system import ROS2_PREFIX, parse_endpoint
from rra_agent.ros2.errors import BadName
from rra_agent.ros2.names import check_type_name, qualify

PRIMITIVE_TYPES = frozenset({"float", "int", "bool", "str", "bytes"})
MeasurementType = Literal["float", "int", "bool", "str"]


class DataType(FrozenModel, frozen=True):
    """A composite data type: named fields of primitive, ``list[T]`` or other composite types."""

    name: str
    fields: dict[str, str] = {}
    #: Fields a sample may leave out (every other field is required).
    optional: list[str] = []
    #: Fields whose numbers may be NaN or infinite (a scan's ``ranges``: ``inf`` where
    #: nothing returned). A node's typed input refuses a sample with a non-finite number in
    #: any other field.
    non_finite: list[str] = []
    #: Function name -> dotted Python path of a callable taking one value of this type.
    functions: dict[str, str] = {}
    description: str | None = None


class Sync(FrozenModel, frozen=True):
    policy: Literal["latest", "window"] = "latest"
    window_ms: float | None = None

    def __post_init__(self) -> None:
        if self.policy == "window" and (self.window_ms is None or self.window_ms <= 0):
            raise ValueError("the 'window' policy needs a positive window_ms")
        if self.policy == "latest" and self.window_ms is not None:
            raise ValueError("window_ms only applies to the 'window' policy")


class Plausible(FrozenModel, frozen=True):
    """The bounds a plausible value lies within (inclusive; either may be left out)."""

    min: float | None = None
    max: float | None = None

    def __post_init__(self) -> None:
        if self.min is None and self.max is None:
            raise ValueError("'plausible' needs 'min', 'max' or both")
        if self.min is not None and self.max is not None and self.min > self.max:
            raise ValueError(f"'plausible' min {self.min} is above max {self.max}")

    def admits(self, value: float) -> bool:
        """Whether ``value`` lies within the bounds (NaN never does)."""
        return (self.min is None or value >= self.min) and (self.max is None or value <= self.max)


class Measurement(FrozenModel, frozen=True):
    name: str
    type: MeasurementType
    #: One source interface ``component.port`` ...
    source: str | None = None
    #: ... or several, for a multi-input measurement.
    sources: list[str] = []
    #: ... or a host of the system model: true while it is reachable (type bool).
    reachable: str | None = None
    #: ... or a component of the system model: false while it is unavailable (type bool).
    available: str | None = None
    #: The message type of a ROS 2 ``source`` (``ros2:/topic``), e.g. ``std_msgs/msg/Float32``.
    ros2_type: str | None = None
    #: Field of the source sample to take when there is no function (e.g. ``level``).
    field: str | None = None
    function: str | None = None
    sync: Sync = Sync()
    #: A measurement older than this is stale (rule conditions reading it are undefined).
    max_age_ms: float | None = None
    #: Refuse NaN and infinities in the values it reads and the value it computes (false:
    #: they are legitimate, e.g. ``inf`` for "nothing in sight").
    finite: bool = True
    #: Values outside these bounds are refused (a numeric measurement only).
    plausible: Plausible | None = None
    unit: str | None = None
    description: str | None = None

    def __post_init__(self) -> None:
        given = (
            (self.source is not None)
            + bool(self.sources)
            + (self.reachable is not None)
            + (self.available is not None)
        )
        if given != 1:
            raise ValueError(
                "a measurement needs exactly one of 'source', 'sources', 'reachable' and "
                "'available'"
            )
        derived = "reachable" if self.reachable is not None else "available"
        if self.reachable is not None or self.available is not None:
            if self.type != "bool":
                raise ValueError(f"a '{derived}' measurement is of type bool")
            if self.field is not None or self.function is not None:
                raise ValueError(f"a '{derived}' measurement has no field or function")
        self._check_ros2()
        for s in self.inputs:
            if not is_ros2_source(s):
                parse_endpoint(s)
        if len(self.inputs) > 1 and self.function is None:
            raise ValueError("a multi-input measurement needs a function")
        if self.field is not None and self.function is not None:
            raise ValueError("'field' and 'function' are exclusive")
        if self.plausible is not None and self.type not in ("float", "int"):
            raise ValueError(f"'plausible' bounds need a numeric measurement, not {self.type}")

    def _check_ros2(self) -> None:
        if any(is_ros2_source(s) for s in self.sources):
            raise ValueError("a ROS 2 topic is a measurement's one 'source', not one of 'sources'")
        if self.source is None or not is_ros2_source(self.source):
            if self.ros2_type is not None:
                raise ValueError("'ros2_type' is for a ROS 2 source ('source: ros2:/topic')")
            return
        if self.ros2_type is None:
            raise ValueError("a ROS 2 source needs 'ros2_type' (e.g. std_msgs/msg/Float32)")
        if self.field is None and self.function is None:
            raise ValueError("a ROS 2 source needs a 'field' of its message (or a 'function')")
        try:
            qualify(self.source[len(ROS2_PREFIX):].strip())
            check_type_name(self.ros2_type, "msg")
        except BadName as e:
            raise ValueError(str(e)) from None

    @property
    def ros2_topic(self) -> str | None:
        """The ROS 2 topic of a ROS 2 source (``/battery``), else None."""
        if self.source is None or not is_ros2_source(self.source):
            return None
        return qualify(self.source[len(ROS2_PREFIX):].strip())

    @property
    def inputs(self) -> list[str]:
        """The ``component.port`` interfaces it is computed from (none for reachability)."""
        return [self.source] if self.source is not None else list(self.sources)


def is_ros2_source(source: str) -> bool:
    """Whether a measurement source is a ROS 2 topic (``ros2:/battery``)."""
    return source.startswith(ROS2_PREFIX)


class MeasurementsModel(FrozenModel, frozen=True):
    data_types: list[DataType] = []
    measurements: list[Measurement] = []

    def __post_init__(self) -> None:
        for what, names in (
            ("data type", [t.name for t in self.data_types]),
            ("measurement", [m.name for m in self.measurements]),
        ):
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ValueError(f"duplicate {what} name(s) {', '.join(dup)}")

    def data_type(self, name: str) -> DataType | None:
        return next((t for t in self.data_types if t.name == name), None)
