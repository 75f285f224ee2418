"""Node classes of the AGV package (kept in the package folder)."""

from __future__ import annotations

import os
import time
from typing import Any

from rra_agent.node import Node


class ZoneSensor(Node):
    """Publishes the zone the robot is in (its ``zone`` parameter) at ``rate_hz``."""

    rate_hz = 20.0

    def on_start(self) -> None:
        self.seq = 0

    def step(self, now: float) -> None:
        self.seq += 1
        self.ctx.publish("zone", {"seq": self.seq, "zone": str(self.ctx.param("zone"))})


class DepthCamera(Node):
    """A camera that starts only when its ``device`` is plugged in (the file exists)."""

    rate_hz = 20.0

    def on_start(self) -> None:
        device = str(self.ctx.param("device"))
        if not os.path.exists(device):
            raise RuntimeError(f"camera {device} not found")
        with open(device) as f:
            if f.read().strip() == "hang":  # a driver that never comes back
                time.sleep(3600)
        self.seq = 0

    def step(self, now: float) -> None:
        self.seq += 1
        self.ctx.publish("out", {"seq": self.seq, "value": 1.0})


class Motion(Node):
    """Drives at ``max_speed``: one command per obstacle update."""

    def on_start(self) -> None:
        self.seq = 0

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        self.seq += 1
        self.ctx.publish("cmd", {"seq": self.seq, "speed": float(self.ctx.param("max_speed"))})
