"""Recovery benchmark: fault -> first Proploss command applied, and altitude lost, per strategy.

Runs the quadcopter motor-failure scenario (hover at 2 m, motor 2 breaks) N times for each
of: ``standby`` (the Proploss controller pre-started inactive: switch = activation + rewire),
``stop-then-start`` (cold: stop the controller, start the Proploss controller), and
``delayed 0.5 s`` (standby, but the resolution engine waits 0.5 s before executing: the
paper's figure, emulated with ``RRA_EMULATED_SWAP_DELAY``). Every run is a real system under
``rra up``; the figures come from what was recorded on the bus (`rra_agent.demo`).

Prints median and p99 per strategy side by side and writes a PNG of altitude over time
around the failure (one run per strategy; needs matplotlib: ``pip install -e '.[bench]'``).
Targets on a 2-core machine: standby <= 10 ms median, <= 25 ms p99, altitude lost < 0.1 m;
stop-then-start <= 150 ms median.

    .venv/bin/python tools/bench_recovery.py [--runs 20] [--plot recovery.png]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
from pathlib import Path

import msgspec

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _benchutil import median, p99, print_table

from rra_agent.demo import FAULT, RECORD, SCENARIO, recovery_report
from rra_agent.models.loader import load_package
from rra_agent.scenario.model import load_scenario
from rra_agent.scenario.runner import run_case

FAULT_AT = 3.0
DURATION = 6.0
STRATEGIES = {
    "standby": ("standby", 0.0),
    "stop-then-start": ("stop-then-start", 0.0),
    "delayed 0.5 s": ("standby", 0.5),
}


def make_case(strategy: str):
    """The adaptive case, shortened (fault at 3 s, 6 s long), with ``strategy``."""
    sf = load_scenario(SCENARIO)
    case = next(c for c in sf.cases if c.case == "adaptive")
    rep = load_package(case.package).runtime.replacement
    rep = msgspec.structs.replace(
        rep, components={**rep.components, "proploss_controller": strategy}
    )
    timeline = tuple(
        dataclasses.replace(t, step=msgspec.structs.replace(t.step, at=FAULT_AT))
        if t.name == FAULT
        else t
        for t in case.timeline
    )
    return dataclasses.replace(
        case, replacement=rep, timeline=timeline, duration=DURATION, record_topics=RECORD
    )


def one_run(case, delay: float, run_dir: Path):
    os.environ["RRA_EMULATED_SWAP_DELAY"] = str(delay)
    try:
        result = run_case(case, run_dir)
    finally:
        os.environ.pop("RRA_EMULATED_SWAP_DELAY", None)
    if result.recording is None:
        raise SystemExit(f"run failed: {result.error}")
    report = recovery_report(result.recording, setpoint=2.0)
    return report, result.recording


def altitude_trace(rec, report) -> tuple[list[float], list[float]]:
    t_f = report.fault_stamp or rec.t0
    pts = [
        (d.stamp - t_f, d.value["position"][2])
        for d in rec.data
        if d.topic == "vehicle_simulator/state" and -0.5 <= d.stamp - t_f <= 2.5
    ]
    return [t for t, _ in pts], [z for _, z in pts]


def plot(traces: dict[str, tuple[list[float], list[float]]], path: Path) -> bool:
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("(no plot: install matplotlib, e.g. pip install -e '.[bench]')")
        return False
    fig, ax = plt.subplots(figsize=(9, 4.5), dpi=110)
    for name, (ts, zs) in traces.items():
        ax.plot(ts, zs, label=name, linewidth=1.6)
    ax.axvline(0.0, color="grey", linestyle="--", linewidth=1)
    ax.axhline(2.0, color="grey", linestyle=":", linewidth=1)
    ax.set_xlabel("time after motor 2 broke (s)")
    ax.set_ylabel("altitude (m)")
    ax.set_title("Quadcopter losing motor 2 at 2 m: altitude by replacement strategy")
    ax.set_ylim(-0.1, 2.4)
    ax.legend(loc="lower left")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    return True


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=20, help="runs per strategy (default 20)")
    ap.add_argument("--plot", default="recovery.png", help="PNG of altitude around the fault")
    ap.add_argument("--only", choices=list(STRATEGIES), action="append", help="these only")
    args = ap.parse_args()
    rows, traces = [], {}
    with tempfile.TemporaryDirectory(prefix="rra-recovery-") as tmp:
        for name in args.only or list(STRATEGIES):
            strategy, delay = STRATEGIES[name]
            case = make_case(strategy)
            latencies, losses, survived = [], [], 0
            for i in range(args.runs):
                report, rec = one_run(case, delay, Path(tmp) / f"{name}-{i}")
                if report.first_proploss_command is not None:
                    latencies.append(report.first_proploss_command)
                if report.altitude_lost is not None:
                    losses.append(report.altitude_lost)
                survived += report.airborne
                if i == 0:
                    traces[name] = altitude_trace(rec, report)
                print(f"  {name:<16} run {i + 1}/{args.runs}: latency "
                      f"{(report.first_proploss_command or float('nan')) * 1e3:6.1f} ms, "
                      f"altitude lost {report.altitude_lost or float('nan'):.3f} m, "
                      f"{'airborne' if report.airborne else 'CRASHED'}", flush=True)  # fmt: skip
            rows.append(
                [
                    name,
                    len(latencies),
                    median(latencies) * 1e3 if latencies else float("nan"),
                    p99(latencies) * 1e3 if latencies else float("nan"),
                    median(losses) if losses else float("nan"),
                    p99(losses) if losses else float("nan"),
                    f"{survived}/{args.runs}",
                ]
            )
    print()
    print_table(
        ["strategy", "runs", "latency median ms", "latency p99 ms", "alt. lost median m",
         "alt. lost p99 m", "airborne"],
        rows,
        digits=3,
    )  # fmt: skip
    print("latency = fault -> first Proploss command applied by the simulator")
    print("targets: standby <= 10 ms median, <= 25 ms p99, altitude lost < 0.1 m; "
          "stop-then-start <= 150 ms median")  # fmt: skip
    if traces and plot(traces, Path(args.plot)):
        print(f"plot: {Path(args.plot).resolve()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
