"""A module that cannot be imported: its driver is not installed."""

from __future__ import annotations

import camera_driver_sdk  # noqa: F401  (not installed anywhere)

from rra_agent.node import Node


class Grabber(Node):
    pass
