"""Node classes of the hosttest package that misbehave (kept in the package folder)."""

from __future__ import annotations

from typing import Any

from rra_agent.node import Node


class Faulty(Node):
    """Raises in every sample callback."""

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        raise ValueError("faulty on purpose")


class BadStart(Node):
    """Raises in on_start: it never runs."""

    def on_start(self) -> None:
        raise RuntimeError("cannot start on purpose")
