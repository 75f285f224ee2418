"""A relay in front of a ROS 2 subscriber: rewiring without restarting it.

The node subscribes to the relay's output topic once; the relay republishes, bytes as they
come (no decoding), whatever source topic it is switched to. `switch` declares the new
source before dropping the old one (make before break), so no sample window is lost for
want of a subscription. The price: one more hop per sample.
"""

from __future__ import annotations

import threading
import time

from rra_agent.ros2.endpoint import Received, Ros2Node, Subscription


class Relay:
    def __init__(self, node: Ros2Node, output: str, ros_type: str, source: str) -> None:
        self.node = node
        self.ros_type = ros_type
        self.pub = node.publisher(output, ros_type)
        self.forwarded = 0
        self.switched_ns: int | None = None
        self.first_after_switch_ns: int | None = None
        self._lock = threading.Lock()
        self.source = source
        self._sub = self._subscribe(source)

    def _subscribe(self, source: str) -> Subscription:
        return self.node.subscription(
            source, self.ros_type, lambda got: self._forward(source, got), decode=False
        )

    def _forward(self, source: str, got: Received) -> None:
        with self._lock:
            if source != self.source:
                return  # the old source, between the new subscription and the undeclare
            if self.switched_ns is not None and self.first_after_switch_ns is None:
                self.first_after_switch_ns = time.monotonic_ns()
        self.pub.publish(got.payload)
        self.forwarded += 1

    def switch(self, source: str) -> None:
        """Forward ``source`` from now on instead of the current one."""
        new = self._subscribe(source)
        with self._lock:
            old, self._sub, self.source = self._sub, new, source
            self.switched_ns, self.first_after_switch_ns = time.monotonic_ns(), None
        old.close()

    def close(self) -> None:
        self._sub.close()
        self.pub.close()
