"""The plant of the reflex test package: a Ticker that is also commanded."""

from __future__ import annotations

from typing import Any

from rra_agent.nodes.generic import Ticker


class Plant(Ticker):
    """Publishes ``{seq, value}`` on ``out`` at ``rate_hz`` (``value``: a parameter) and
    takes commands on ``cmd``: ``commanded_by`` (a parameter the tests read with Describe is
    not touched; the count per sender is kept in ``by``)."""

    rate_hz = 50.0

    def on_start(self) -> None:
        super().on_start()
        self.by: dict[str, int] = {}

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        if port == "cmd":
            sender = str(data.get("relay", ""))
            self.by[sender] = self.by.get(sender, 0) + 1

    def export_state(self) -> Any:
        return {"by": dict(self.by)}
