"""Node classes that fail, as a new user's might (kept in the package folder)."""

from __future__ import annotations

import sys
from typing import Any

from rra_agent.node import Node


def open_camera(device: str) -> None:
    raise RuntimeError(f"camera {device} not found")


class Camera(Node):
    """Its camera is not plugged in: raises in on_start (in a helper it calls)."""

    def on_start(self) -> None:
        open_camera(self.ctx.param("device", "/dev/video0"))


class BadInit(Node):
    """Raises in its constructor."""

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.gain = {}["gain"]


class Drifting(Node):
    """Steps a few times, then raises in every step (the node goes on, broken)."""

    rate_hz = 50.0

    def on_start(self) -> None:
        self.ticks = 0

    def step(self, now: float) -> None:
        self.ticks += 1
        if self.ticks > 3:
            raise ValueError(f"lost sync after {self.ticks - 1} ticks")


class Quitter(Node):
    """Calls sys.exit(3) in on_start: in a container, that must not end its neighbours."""

    def on_start(self) -> None:
        sys.exit(3)


class BadStop(Node):
    """Raises in on_stop."""

    def on_stop(self) -> None:
        raise OSError("could not park the arm")
