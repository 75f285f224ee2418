"""Node classes of the mini test package (kept in the package folder; they do nothing)."""

from __future__ import annotations

from rra_agent.node import Node


class Driver(Node):
    pass


class Laser(Node):
    pass


class Navigation(Node):
    pass


class Dwa(Navigation):
    pass


class Arm(Node):
    pass


class Radio(Node):
    pass


class RadioSwitch(Node):
    pass
