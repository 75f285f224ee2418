"""Altitude lost vs. controller switch delay after a motor failure, in pure simulation.

The quadcopter hovers (or flies a circle); motor 2 breaks at ``--fail-at``; ``delay`` later
the standard controller hands over to the Proploss controller (which ran in standby). Each
cell is the altitude lost (m) below the setpoint after the failure, or ``crash +T`` (the
crash ``T`` seconds after the failure). Runs in-process, as fast as the CPU allows
(`rra_agent.sim.control.simulate`); prints a Markdown table (docs/quadcopter.md has one).

    python tools/sweep_switch_delay.py
    python tools/sweep_switch_delay.py --altitudes 2 --delays 0 50 100 --mode circle
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence

from rra_agent.sim.control import Run, Trajectory, simulate

DELAYS_MS = (0, 10, 25, 50, 75, 100, 150, 250, 500)
ALTITUDES = (1.0, 2.0, 5.0)


def cell(run: Run, altitude: float, fail_at: float) -> str:
    if run.crashed_at is not None:
        return f"crash +{run.crashed_at - fail_at:.2f} s"
    after = run.time >= fail_at
    lost = altitude - float(run.position[after, 2].min())
    drift = float(abs(run.position[after, :2] - run.setpoint[after, :2]).max())
    return f"{max(lost, 0.0):.2f} m (xy {drift:.1f})"


def sweep(
    delays_ms: Sequence[float],
    altitudes: Sequence[float],
    *,
    mode: str,
    fail_at: float,
    after: float,
) -> list[list[str]]:
    rows = []
    for d in delays_ms:
        row = [f"{d:g} ms"]
        for alt in altitudes:
            run = simulate(
                fail_at + after,
                trajectory=Trajectory(mode, altitude=alt),
                fail_at=fail_at,
                switch_delay=d / 1000.0,
                record_every=2,
            )
            row.append(cell(run, alt, fail_at))
        rows.append(row)
    never = ["never"]
    for alt in altitudes:
        run = simulate(
            fail_at + after,
            trajectory=Trajectory(mode, altitude=alt),
            fail_at=fail_at,
            switch_delay=None,
            record_every=2,
        )
        never.append(cell(run, alt, fail_at))
    rows.append(never)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--delays", type=float, nargs="+", default=DELAYS_MS, help="ms")
    ap.add_argument("--altitudes", type=float, nargs="+", default=ALTITUDES, help="m")
    ap.add_argument("--mode", default="hover", choices=("hover", "circle", "waypoints"))
    ap.add_argument("--fail-at", type=float, default=3.0, help="s of sim time")
    ap.add_argument("--after", type=float, default=6.0, help="s simulated after the failure")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = sweep(
        args.delays, args.altitudes, mode=args.mode, fail_at=args.fail_at, after=args.after
    )
    print("| switch delay | " + " | ".join(f"from {a:g} m" for a in args.altitudes) + " |")
    print("|---" * (len(args.altitudes) + 1) + "|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    print(
        f"\n{args.mode}, motor 2 broken at t={args.fail_at:g} s; altitude lost (m) below the "
        f"setpoint (xy: largest horizontal error, m), or the crash time after the failure. "
        f"{time.perf_counter() - t0:.1f} s wall.",
        file=sys.stderr,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
