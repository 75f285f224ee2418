"""Generic nodes: building blocks for tests, benchmarks and quick prototypes.

- `Relay`: forwards each input sample from port ``in`` to port ``out``, adding the ``offset``
  parameter to the field ``value`` if present; keeps a count it can hand over as state. A
  standby relay follows its input while inactive (the SDK drops what it publishes) and
  publishes its latest output the moment it is activated, as a standby controller hands
  on its latest command: its consumer does not wait for the next input.
- `Echo`: publishes each input sample of port ``in`` unchanged on port ``out`` (benchmarks:
  the least a node can do, so a round trip through it measures the SDK alone).
- `Ticker`: publishes ``{"seq": n, "value": param value}`` on ``out`` at ``rate_hz``.
"""

from __future__ import annotations

from typing import Any

from rra_agent.node.api import Node


class Relay(Node):
    def on_start(self) -> None:
        self.count = 0
        self.last: dict[str, Any] | None = None

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        self.count += 1
        out = dict(data)
        offset = self.ctx.param("offset", 0.0)
        if isinstance(out.get("value"), int | float) and not isinstance(out.get("value"), bool):
            out["value"] = out["value"] + offset
        out["relay"] = self.ctx.name
        out["count"] = self.count
        self.last = out
        self.ctx.publish("out", out)

    def on_active(self, active: bool) -> None:
        if active and self.last is not None:
            self.ctx.publish("out", self.last)

    def export_state(self) -> Any:
        return {"count": self.count}

    def import_state(self, state: Any) -> None:
        if isinstance(state, dict) and isinstance(state.get("count"), int):
            self.count = state["count"]


class Echo(Node):
    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        self.ctx.publish("out", data)


class Ticker(Node):
    rate_hz = 10.0

    def on_start(self) -> None:
        self.seq = 0

    def step(self, now: float) -> None:
        self.seq += 1
        self.ctx.publish("out", {"seq": self.seq, "value": self.ctx.param("value", 0.0)})
