"""What a node's typed input costs per sample (`NodeCore.deliver`, no bus).

A node that does nothing with what it gets; a quadcopter ``MotorTelemetry`` sample (a time
and three lists of four floats, 160 bytes) delivered on an input of an undeclared type (any
msgpack map) and on one of the declared type (decoded against it, every number checked
finite). Prints median and p99 of ``--repeats`` timings of ``--n`` deliveries each, in µs per
sample, and the goal: a typed input costs at most 0.5 µs more than an untyped one.

    .venv/bin/python tools/bench_deliver.py [--n 100000] [--repeats 30]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))
sys.path.insert(0, str(ROOT))

from _benchutil import median, p99, print_table  # noqa: E402

from rra_agent.bus.data import encode_data  # noqa: E402
from rra_agent.node import Node, NodeHarness  # noqa: E402

#: The extra cost per sample a typed input may have over an untyped one (µs).
GOAL_US = 0.5
SAMPLE = {"time": 1.0, "desired_speed": [1.0] * 4, "measured_speed": [2.0] * 4,
          "current": [0.5] * 4}  # fmt: skip


class Idle(Node):
    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        pass


def per_sample_us(typed: bool, n: int, repeats: int) -> list[float]:
    types = ROOT / "scenarios" / "quadcopter" if typed else ()
    h = NodeHarness(Idle, ports={"in": ("subscribe", "MotorTelemetry")}, types=types)
    deliver, payload, key = h.core.deliver, encode_data(SAMPLE), h.core.ports["in"].keys[0]
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            deliver("in", payload, None, key)
        out.append((time.perf_counter() - t0) / n * 1e6)
    assert h.core.counters.received == n * repeats, "every sample delivered"
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=100_000, help="deliveries per timing (100000)")
    ap.add_argument("--repeats", type=int, default=30, help="timings per input kind (30)")
    args = ap.parse_args()
    untyped = per_sample_us(False, args.n, args.repeats)
    typed = per_sample_us(True, args.n, args.repeats)
    extra = median(typed) - median(untyped)
    print_table(
        ["input", "µs per sample (median)", "p99", "goal"],
        [
            ["untyped (any map)", round(median(untyped), 3), round(p99(untyped), 3), ""],
            ["typed (MotorTelemetry)", round(median(typed), 3), round(p99(typed), 3),
             f"<= +{GOAL_US} µs: {extra:+.3f} {'PASS' if extra <= GOAL_US else 'FAIL'}"],
        ],
        digits=3,
    )  # fmt: skip
    return 0 if extra <= GOAL_US else 1


if __name__ == "__main__":
    sys.exit(main())
