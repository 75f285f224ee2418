"""A relay in front of a ROS 2 subscriber: rewiring without restarting it.

The node subscribes to the relay's output topic once; the relay republishes, bytes as they
come (no decoding), whatever source topics it is switched to (none: it forwards nothing; a
subscriber fed by several publishers: all of them). `switch` declares the new sources
before dropping the old ones (make before break), so no sample window is lost for want of
a subscription. The price: one more hop per sample.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterable

from rra_agent.ros2.endpoint import Received, Ros2Node, Subscription


class Relay:
    def __init__(
        self, node: Ros2Node, output: str, ros_type: str, source: str | Iterable[str] = ()
    ) -> None:
        self.node = node
        self.ros_type = ros_type
        self.pub = node.publisher(output, ros_type)
        self.forwarded = 0
        self.switched_ns: int | None = None
        self.first_after_switch_ns: int | None = None
        self._lock = threading.Lock()
        self.sources: tuple[str, ...] = _sources(source)
        self._subs = {s: self._subscribe(s) for s in self.sources}

    @property
    def source(self) -> str | None:
        """The one source (None: none, or several)."""
        return self.sources[0] if len(self.sources) == 1 else None

    def _subscribe(self, source: str) -> Subscription:
        return self.node.subscription(
            source, self.ros_type, lambda got: self._forward(source, got), decode=False
        )

    def _forward(self, source: str, got: Received) -> None:
        with self._lock:
            if source not in self.sources:
                return  # an old source, between the new subscription and the undeclare
            if self.switched_ns is not None and self.first_after_switch_ns is None:
                self.first_after_switch_ns = time.monotonic_ns()
        self.pub.publish(got.payload)
        self.forwarded += 1

    def switch(self, source: str | Iterable[str]) -> None:
        """Forward ``source`` (a topic, or several) from now on instead of the current."""
        wanted = _sources(source)
        new = {s: self._subs.get(s) or self._subscribe(s) for s in wanted}
        with self._lock:
            old = {s: sub for s, sub in self._subs.items() if s not in new}
            self._subs, self.sources = new, wanted
            self.switched_ns, self.first_after_switch_ns = time.monotonic_ns(), None
        for sub in old.values():
            sub.close()

    def close(self) -> None:
        for sub in self._subs.values():
            sub.close()
        self._subs.clear()
        self.pub.close()


def _sources(source: str | Iterable[str]) -> tuple[str, ...]:
    return (source,) if isinstance(source, str) else tuple(dict.fromkeys(source))
