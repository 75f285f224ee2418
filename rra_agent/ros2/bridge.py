"""ROS 2 topics as context, adaptation events as a ROS 2 topic.

`parse_source` / `check_measurement` validate a measurement that reads a ROS 2 topic
(``source: ros2:/battery``, ``ros2_type: sensor_msgs/msg/BatteryState``, ``field:
percentage``) without any bus; `TopicField` then delivers that field's value of every
sample (a sample whose field cannot be read is a counted drop). `EventTopic` publishes
rra-agent's adaptation events on a ROS 2 topic (default ``/rra/events``) as
``std_msgs/msg/String`` holding the event's JSON.
"""

from __future__ import annotations

import json
from collections import Counter
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any

from rra_agent.ros2.endpoint import Received, Ros2Node, Subscription
from rra_agent.ros2.errors import FieldError
from rra_agent.ros2.names import qualify

if TYPE_CHECKING:  # imported where used: it imports numpy and rosbags, which an engine of a
    from rra_agent.ros2.types import TypeRegistry  # package without ROS 2 never needs

PREFIX = "ros2:"
EVENTS_TOPIC = "/rra/events"
EVENTS_TYPE = "std_msgs/msg/String"
#: Leaf types a measurement can take its value from.
VALUE_TYPES = {"bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32",
               "int64", "uint64", "float32", "float64", "string"}


def parse_source(source: str) -> str | None:
    """``ros2:/battery`` -> ``/battery``; None for a source that is not a ROS 2 topic;
    `BadName` for a ROS 2 source whose topic name is not valid."""
    if not source.startswith(PREFIX):
        return None
    return qualify(source[len(PREFIX):].strip())


def check_measurement(types: TypeRegistry, topic: str, ros_type: str, field: str) -> str:
    """Check a ROS 2 measurement; the ROS type of its field (e.g. ``float32``). Raises a
    one-line `Ros2Error` (the model loader adds the file position)."""
    qualify(topic)
    leaf = types.field_type(ros_type, field)
    base = leaf.split("<=")[0]
    if base not in VALUE_TYPES:
        raise FieldError(
            f"{ros_type} field {field!r} is {leaf}, not a number, bool or string a "
            "measurement can take (name a field inside it, e.g. with a dotted path)"
        )
    return leaf


class TopicField:
    """Calls ``on_value(value, received)`` with ``field`` of every sample of ``topic``."""

    def __init__(
        self,
        node: Ros2Node,
        topic: str,
        ros_type: str,
        field: str,
        on_value: Callable[[Any, Received], None],
        on_drop: Callable[[str, str], None] | None = None,
    ) -> None:
        from rra_agent.ros2.types import get_field

        check_measurement(node.ctx.types, topic, ros_type, field)
        self.get_field = get_field
        self.field = field
        self.on_value = on_value
        self.on_drop = on_drop
        self.dropped: Counter[str] = Counter()
        self.sub: Subscription = node.subscription(
            topic, ros_type, self._on_sample, on_drop=self._drop
        )

    def _on_sample(self, got: Received) -> None:
        assert got.message is not None
        try:
            value = self.get_field(got.message, self.field)
        except FieldError as e:  # an index past the end of a sequence
            self._drop("field", f"{self.sub.key.name}: {e}")
            return
        self.on_value(value, got)

    def _drop(self, reason: str, detail: str) -> None:
        self.dropped[reason] += 1
        if self.on_drop is not None:
            self.on_drop(reason, detail)

    @property
    def received(self) -> int:
        return self.sub.received

    def close(self) -> None:
        self.sub.close()


class EventTopic:
    """Adaptation events on a ROS 2 topic, one ``std_msgs/msg/String`` of JSON each."""

    def __init__(self, node: Ros2Node, topic: str = EVENTS_TOPIC) -> None:
        self.pub = node.publisher(topic, EVENTS_TYPE)

    def publish(self, event: Mapping[str, Any]) -> None:
        self.pub.publish({"data": json.dumps(event, default=str, separators=(",", ":"))})

    def close(self) -> None:
        self.pub.close()
