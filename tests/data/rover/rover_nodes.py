"""Node classes of the rover package, kept in the package folder (not in rra_agent)."""

from __future__ import annotations

from rra_agent.node import Node


class GnssReceiver(Node):
    """Publishes a fix at ``rate_hz``: its parameters are what the receiver sees."""

    rate_hz = 20.0

    def on_start(self) -> None:
        self.seq = 0

    def step(self, now: float) -> None:
        self.seq += 1
        self.ctx.publish(
            "fix",
            {
                "seq": self.seq,
                "satellites": int(self.ctx.param("satellites", 0)),
                "indoor": bool(self.ctx.param("indoor", False)),
                "speed": float(self.ctx.param("speed", 0.0)),
            },
        )
