"""A Python node's ROS 2 side: its ROS 2 node, and its ROS 2 ports also on ROS 2.

A node with a ``ros2:`` side (its component speaks ROS 2, `rra_agent.bus.messages.Ros2Spec`)
is also a ROS 2 node (its component's name, or its ``ros2.node``), and every sample of a
publisher port with a ROS 2 type also goes, as CDR with rmw_zenoh's attachment, on the ROS 2
topic ``/<topic>`` (`Ros2Mirror`): a ROS 2 machine's ``ros2 topic echo`` sees it. The
sample's fields that the ROS 2 type has are sent (the others left out, missing ones their
zero value); a sample that does not fit the type is counted (``ros2_unencodable``) and
logged, never raised in the node's code. The ROS 2 executables' runtime
(`rra_agent.node.ros2`) uses `Ros2Side` too.
"""

from __future__ import annotations

import re
import sys
from typing import Any

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.counters import RateLimitedLog
from rra_agent.bus.data import DATA_DECODER
from rra_agent.node.api import NodeError
from rra_agent.ros2.endpoint import Publisher, Ros2Context
from rra_agent.ros2.errors import Ros2Error
from rra_agent.ros2.types import TypeRegistry

_registries: dict[tuple[str, str | None], TypeRegistry] = {}


def registry(spec: m.Ros2Spec) -> TypeRegistry:
    """The message types of a node's ROS 2 side (once per process)."""
    key = (spec.distro, spec.interfaces)
    types = _registries.get(key)
    if types is None:
        types = TypeRegistry(spec.distro)
        if spec.interfaces is not None:
            types.register_folder(spec.interfaces)
        _registries[key] = types
    return types


def ros2_topic(key: str) -> str:
    """The ROS 2 topic of a data key: ``rra/<system>/data/a/b`` -> ``/a/b``."""
    parts = key.split("/", 3)
    if len(parts) != 4 or parts[0] != "rra" or parts[2] != "data":
        raise NodeError(f"{key!r} is not a data key")
    return "/" + parts[3]


def ros2_token(name: str) -> str:
    out = re.sub(r"[^A-Za-z0-9_]", "_", name)
    return out if not out[:1].isdigit() else f"_{out}"


class Ros2Side:
    """A process's ROS 2 context and node, on its own session."""

    def __init__(self, session: zenoh.Session, spec: m.Ros2Spec, name: str, namespace: str):
        self.types = registry(spec)
        self.ctx = Ros2Context(session, self.types, spec.domain)
        self.node = self.ctx.node(name, namespace)

    def close(self) -> None:
        self.ctx.close()


# ---- a Python node's ROS 2 ports ----------------------------------------------------------
class Ros2Mirror:
    """A node's transport (`ZenohTransport`) whose ROS 2 publisher ports also publish on
    their ROS 2 topic."""

    def __init__(self, inner: Any, spec: m.NodeSpec) -> None:  # inner: a ZenohTransport
        assert spec.ros2 is not None
        self.inner = inner
        self.ros = spec.ros2
        self.side = Ros2Side(inner.session, spec.ros2, spec.ros2.node, spec.ros2.namespace)
        self.publishers: dict[str, Publisher] = {}
        self.fields = {
            port: frozenset(self.side.types.field_names(t)) for port, t in self.ros.ports.items()
        }
        self.unencodable = 0
        self._log = RateLimitedLog(lambda s: print(f"[{spec.name}] {s}", file=sys.stderr,
                                                   flush=True))

    @property
    def core(self) -> Any:
        return self.inner.core

    @core.setter
    def core(self, core: Any) -> None:
        self.inner.core = core

    def start_delivery(self, core: Any) -> None:
        self.inner.start_delivery(core)

    @property
    def session(self) -> zenoh.Session:
        return self.inner.session

    def publish(self, port: str, payload: bytes, stamp: float) -> None:
        self.inner.publish(port, payload, stamp)
        pub = self.publishers.get(port)
        if pub is None:
            return
        try:
            data = DATA_DECODER.decode(payload)
            fields = self.fields[port]
            pub.publish({k: v for k, v in data.items() if k in fields})
        except (Ros2Error, msgspec.DecodeError, AttributeError) as e:
            self.unencodable += 1
            core = self.inner.core
            if core is not None:
                core.counters.bump("ros2_unencodable")
            self._log(f"not sent on ROS 2 topic {pub.key.name}", f"{port}: {e}")

    def rebind(
        self, port: str, direction: str, keys: list[str], standby: list[str] | None = None
    ) -> None:
        self.inner.rebind(port, direction, keys, standby)
        if direction != "publish" or port not in self.ros.ports:
            return
        topic = ros2_topic(keys[0])
        old = self.publishers.get(port)
        if old is None or old.key.name != topic:
            self.publishers[port] = self.side.node.publisher(topic, self.ros.ports[port])
            if old is not None:
                old.close()

    def subscribe(self, key_expr: str, callback: Any) -> None:
        self.inner.subscribe(key_expr, callback)

    def close(self) -> None:
        self.side.close()


