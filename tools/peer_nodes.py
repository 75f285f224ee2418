"""rra-agent nodes of the side-by-side benchmarks (`tools/bench_peer.py`,
``tools/bench_roundtrip.py --node-to-node``): copied into the system packages those tools
write, as the package's own module ``peer_nodes``. Their dora-rs counterparts are in
``tools/peer_dora.py``; both sides send the same 93-byte payload (`payload`).

- `Pinger`: publishes a ping on ``ping``, times until its echo comes back on ``pong``
  (``time.perf_counter`` just before the publish to the start of ``on_message``), sends the
  next at once; after ``warm`` unmeasured and ``n`` measured round trips writes the round
  trips (µs, one per line) to the file ``out``. Its ``step`` (10 Hz) starts the exchange
  and sends again when an echo was lost (the echo node not subscribed yet).
- `Source`: at ``rate_hz`` publishes ``{"pid": its process id, "seq": n}`` on ``out``.
- `Echo`: every sample on ``in`` published as is on ``out``.
- `Recorder`: appends ``<wall time> <pid>`` (the sample's ``pid``, else -1) of every sample on
  ``in`` to the file ``out``, one line each, written at once.
"""

from __future__ import annotations

import os
import time
from typing import Any, ClassVar

from rra_agent.node.api import Node

#: The payload's fields (``seq`` below 128: its msgpack encoding is 93 bytes for every seq).
_FIELDS = {"frame": "base_link", "position": [0.125, -1.5, 2.75], "value": 41.5, "ok": True}


def payload(seq: int) -> dict[str, Any]:
    """The benchmarks' sample: 93 bytes of msgpack (``seq`` is kept below 128)."""
    seq %= 100
    return {"seq": seq, "stamp": 1.7e9 + seq * 1e-3, **_FIELDS}


class Pinger(Node):
    rate_hz: ClassVar[float] = 10.0

    def on_start(self) -> None:
        self.n = int(self.ctx.param("n", 1000))
        self.warm = int(self.ctx.param("warm", 200))
        self.out = str(self.ctx.param("out", ""))
        self.samples: list[float] = []
        self.seq = 0
        self.sent: float | None = None
        self.done = False

    def _ping(self) -> None:
        self.seq += 1
        data = payload(self.seq)
        self.sent = time.perf_counter()
        self.ctx.publish("ping", data)

    def step(self, now: float) -> None:
        if not self.done and (self.sent is None or time.perf_counter() - self.sent > 1.0):
            self._ping()  # the first, or one whose echo was lost

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        arrived = time.perf_counter()
        if self.done or self.sent is None or data.get("seq") != self.seq % 100:
            return
        if self.seq > self.warm:
            self.samples.append((arrived - self.sent) * 1e6)
        if len(self.samples) >= self.n:
            self.done = True
            self._write()
            return
        self._ping()

    def _write(self) -> None:
        if self.out:
            tmp = f"{self.out}.tmp"
            with open(tmp, "w") as f:
                f.write("".join(f"{s:.1f}\n" for s in self.samples))
            os.replace(tmp, self.out)  # whole or absent for the reader


class Source(Node):
    rate_hz: ClassVar[float] = 100.0

    def on_start(self) -> None:
        self.seq = 0
        self.pid = os.getpid()

    def step(self, now: float) -> None:
        self.seq += 1
        self.ctx.publish("out", {"pid": self.pid, "seq": self.seq})


class Recorder(Node):
    def on_start(self) -> None:
        self.file = open(str(self.ctx.param("out", os.devnull)), "a", buffering=1)  # noqa: SIM115

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        self.file.write(f"{time.time():.6f} {data.get('pid', -1)}\n")

    def on_stop(self) -> None:
        self.file.close()


class Echo(Node):
    """Publishes every sample on ``in`` as is on ``out`` (the round trip's echo, the chain's
    relays)."""

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        self.ctx.publish("out", data)
