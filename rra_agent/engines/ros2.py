"""The engines on the ROS 2 side (a package with ``ros2:`` in its ``rra.yaml``).

- Every engine replica is a ROS 2 node (`EngineRos2`): ``/rra/<replica>`` (e.g.
  ``/rra/monitor``, ``/rra/resolution_2``), with rmw_zenoh's liveliness tokens, so ``ros2
  node list`` on a ROS 2 machine of the domain lists it.
- The Context Monitor reads ROS 2 topics as measurement sources (`TopicSources`): one
  subscription per ``ros2:/topic`` source, as rmw_zenoh has it; each sample is decoded as the
  measurement's ROS 2 type and handed to the monitor as a sample of that source (the
  message as a dict, and the value of each dotted ``field`` a measurement reads under that
  path), stamped with the send time of its attachment. A sample of another type, of another
  definition of the type, or that does not decode, and one whose field is not there (an
  index past the end of a sequence), is refused and counted like a sample of a port
  (``wrong_type``, ``malformed``, ``missing_field``); nothing raises.
- The Run-time Resolution Engine leader puts every event of the system (adaptations,
  node-state changes: what ``rra events`` shows) on the ROS 2 topic of ``ros2: {events}``
  (``/rra/events``), one ``std_msgs/msg/String`` each holding the event's JSON
  (`EventMirror`), so ``ros2 topic echo /rra/events`` follows the adaptations.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import Any

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.counters import Refused, receive
from rra_agent.bus.keys import Keys
from rra_agent.core.samples import Refusal
from rra_agent.deployment import Deployment
from rra_agent.models.measurements import Measurement
from rra_agent.package.ros2 import registry
from rra_agent.ros2.bridge import EVENTS_TYPE
from rra_agent.ros2.endpoint import Received, Ros2Context, Ros2Node, Subscription
from rra_agent.ros2.errors import FieldError

#: The namespace of rra-agent's own ROS 2 nodes.
NAMESPACE = "/rra"
#: A ROS 2 subscription's reasons for a drop -> the Context Monitor's refusal reasons.
_REASONS = {"wrong_type": "wrong_type", "type_hash": "wrong_type", "decode": "malformed"}
_EVT = m.Codec[m.EventMessage](m.EventMessage)
_JSON = msgspec.json.Encoder()


def node_name(replica: str) -> str:
    """A replica's name as a ROS 2 node name (``resolution-2`` -> ``resolution_2``)."""
    out = re.sub(r"[^A-Za-z0-9_]", "_", replica)
    return out if not out[:1].isdigit() else f"_{out}"


class EngineRos2:
    """An engine replica's ROS 2 context and node (close it before the session)."""

    def __init__(self, session: zenoh.Session, dep: Deployment, replica: str) -> None:
        settings = dep.package.manifest.ros2
        assert settings is not None
        self.settings = settings
        self.ctx = Ros2Context(session, registry(dep.package.root, settings), settings.domain)
        self.node: Ros2Node = self.ctx.node(node_name(replica), NAMESPACE)

    def undeclare(self) -> None:
        self.ctx.close()


def engine_ros2(session: zenoh.Session, dep: Deployment, replica: str) -> EngineRos2 | None:
    """The replica's ROS 2 side, if the package has one."""
    if dep.package.manifest.ros2 is None:
        return None
    return EngineRos2(session, dep, replica)


#: ``sink(source, sample, stamp)``: a good sample of a ROS 2 source.
Sink = Callable[[str, Mapping[str, Any], float], None]


class TopicSources:
    """The Context Monitor's ROS 2 sources: ``source`` (``ros2:/topic``) -> its subscription."""

    def __init__(
        self,
        node: Ros2Node,
        measurements: list[Measurement],
        sink: Sink,
        refused: Callable[[Refusal], None],
    ) -> None:
        self.sink = sink
        self.refused = refused
        #: source -> the dotted fields its measurements read (nested ones)
        self.fields: dict[str, set[str]] = {}
        types: dict[str, str] = {}
        for meas in measurements:
            if meas.ros2_topic is None or meas.source is None or meas.ros2_type is None:
                continue
            types.setdefault(meas.source, meas.ros2_type)
            fields = self.fields.setdefault(meas.source, set())
            if meas.field is not None and "." in meas.field:
                fields.add(meas.field)
        self.subs: dict[str, Subscription] = {}
        for source, ros_type in types.items():
            topic = source.split(":", 1)[1].strip()
            self.subs[source] = node.subscription(
                topic, ros_type, self._on_message(source), on_drop=self._on_drop(source)
            )

    @property
    def sources(self) -> list[str]:
        return sorted(self.subs)

    def _on_message(self, source: str) -> Callable[[Received], None]:
        # Imported here, with a ROS 2 topic to read: it imports numpy and rosbags, which an
        # engine of a package without ROS 2 never needs (docs/performance.md, Memory).
        from rra_agent.ros2.types import get_field

        fields = sorted(self.fields.get(source, ()))

        def callback(got: Received) -> None:
            message = got.message
            assert message is not None
            sample: dict[str, Any] = dict(message)
            for path in fields:
                try:
                    sample[path] = get_field(message, path)
                except FieldError as e:
                    self.refused(Refusal(source, "missing_field", str(e)))
                    return
            att = got.attachment
            stamp = att.timestamp_ns / 1e9 if att is not None else got.received_ns / 1e9
            self.sink(source, sample, stamp)

        return callback

    def _on_drop(self, source: str) -> Callable[[str, str], None]:
        def drop(reason: str, detail: str) -> None:
            self.refused(Refusal(source, _REASONS.get(reason, "malformed"), detail))

        return drop

    def undeclare(self) -> None:
        for sub in self.subs.values():
            sub.close()


class EventMirror:
    """The system's events on a ROS 2 topic while ``leading()`` (one replica puts them)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        node: Ros2Node,
        topic: str,
        leading: Callable[[], bool],
    ) -> None:
        self.pub = node.publisher(topic, EVENTS_TYPE)
        self.leading = leading
        self.sent = 0
        self._sub = session.declare_subscriber(keys.events, self._on_event)

    def _on_event(self, sample: zenoh.Sample) -> None:
        if not self.leading():
            return
        event = receive(sample.payload, "events", _EVT)
        if isinstance(event, Refused):
            return  # counted by the engine's own subscription to the events
        self.pub.publish({"data": _JSON.encode(event).decode()})
        self.sent += 1

    def undeclare(self) -> None:
        self._sub.undeclare()
        self.pub.close()

