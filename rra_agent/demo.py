"""``rra demo``: the paper's evaluation, end to end, with a report.

Runs ``scenarios/quadcopter/motor_failure.scenario.yaml`` (case ``adaptive``, or ``control``
with ``--no-adaptation``) headless under ``rra up --rerun save demo.rrd``: the quadcopter
hovers at 2 m, motor 2 breaks at t = 5 s, RRA swaps the controller, the run stops at
t = 20 s (t = 10 s without adaptation: on the ground by then). Then it prints what
happened, measured from what was recorded on the bus:

- detection: fault -> the Context Monitor's first ``WorkingMotors < 4``;
- decision: that measurement -> the Adaptation Engine's selection with Proploss;
- plan and execution: the Run-time Resolution Engine's own figures for that adaptation;
- latency: fault -> the simulator's first physics step driven by a Proploss command;
- the largest deviation from the hover target after the fault: up (overshoot), down
  (altitude lost) and sideways (horizontal drift from where it hovered before the fault);
- the time to settle: from the fault until the vehicle is back within `SETTLE_Z` (5 cm) of
  the target altitude and `SETTLE_XY` (10 cm) sideways of the hover point, and stays so for
  `SETTLE_FOR` (1 s); and the same for the altitude alone;
- whether the vehicle stayed airborne.

`recovery_report` is pure (a scenario `Recording` in, a `RecoveryReport` out) and is reused
by ``tools/bench_recovery.py``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path

import msgspec

from rra_agent.bus import messages as m
from rra_agent.cli.common import add_wide_argument
from rra_agent.errors import RraError

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = ROOT / "scenarios" / "quadcopter" / "motor_failure.scenario.yaml"
FAULT = "motor_failure"
SIM = "vehicle_simulator"
RECORD = frozenset({f"{SIM}/events", f"{SIM}/state"})
#: Settled: within this of the target altitude (m) ...
SETTLE_Z = 0.05
#: ... and this of the hover point sideways (m) ...
SETTLE_XY = 0.10
#: ... for this long (s).
SETTLE_FOR = 1.0


class RecoveryReport(msgspec.Struct, kw_only=True):
    """Times in seconds after the fault (None: did not happen)."""

    fault_stamp: float | None = None
    detected: float | None = None
    decided: float | None = None
    plan: float | None = None
    #: From the start of the plan's execution until the new controller was switched to.
    switch: float | None = None
    #: The whole plan, including stopping the old controller after the switch.
    execute: float | None = None
    first_proploss_command: float | None = None
    setpoint: float | None = None
    #: The largest deviation below the target altitude (m).
    altitude_lost: float | None = None
    #: The largest deviation above the target altitude (m).
    overshoot: float | None = None
    #: The largest horizontal distance from the hover point before the fault (m).
    drift: float | None = None
    #: From the fault until settled (`SETTLE_Z`, `SETTLE_XY`, `SETTLE_FOR`); None: never
    #: within the recording.
    settled: float | None = None
    #: The same for the altitude alone (within `SETTLE_Z` for `SETTLE_FOR`).
    altitude_settled: float | None = None
    min_altitude: float | None = None
    airborne: bool = False
    crash: str = ""
    strategy: str = ""


def _data(rec, topic: str) -> list:
    return [d for d in rec.data if d.topic == topic]


def recovery_report(rec, *, setpoint: float | None = None) -> RecoveryReport:
    """What happened around the fault, from a scenario recording."""
    out = RecoveryReport()
    sim_events = [d.value for d in _data(rec, f"{SIM}/events")]
    fault = next((e for e in sim_events if e.get("kind") == "fault"), None)
    applied = next((a for a in rec.injections if a.name == FAULT and a.ok), None)
    t_f = fault["wall_time"] if fault else (applied.stamp if applied else None)
    if t_f is None:
        return out
    out.fault_stamp = t_f
    _adaptation(out, rec, t_f)
    switch = next(
        (
            e
            for e in sim_events
            if e.get("kind") == "controller"
            and "proploss" in str(e.get("detail", ""))
            and e["wall_time"] >= t_f
        ),
        None,
    )
    if switch is not None:
        out.first_proploss_command = switch["wall_time"] - t_f
    _flight(out, rec, t_f, setpoint)
    crash = next((e for e in sim_events if e.get("kind") == "crash"), None)
    out.crash = str(crash.get("detail", "crashed")) if crash else ""
    out.airborne = crash is None and out.min_altitude is not None and out.min_altitude > 0.2
    return out


def _adaptation(out: RecoveryReport, rec, t_f: float) -> None:
    """The engines' part after the fault at ``t_f``: detected, decided, planned, switched."""
    detect = next(
        (
            x
            for x in rec.measurements
            if x.name == "WorkingMotors" and x.value < 4 and x.stamp >= t_f
        ),
        None,
    )
    if detect is not None:
        out.detected = detect.stamp - t_f
    chosen = next(
        (
            s
            for s in rec.selections
            if isinstance(s, m.Selection) and "Proploss" in s.features and s.stamp >= t_f
        ),
        None,
    )
    if chosen is not None:
        out.decided = chosen.stamp - (detect.stamp if detect else t_f)
    adaptation = next(
        (
            e
            for e in rec.events
            if isinstance(e, m.AdaptationEvent)
            and e.kind == "adaptation"
            and e.stamp >= t_f
            and any("proploss" in p for p in e.plan)
        ),
        None,
    )
    if adaptation is not None:
        out.plan = adaptation.durations.get("plan")
        out.switch = adaptation.durations.get("switch")
        out.execute = adaptation.durations.get("execute")


def _flight(out: RecoveryReport, rec, t_f: float, setpoint: float | None) -> None:
    """The vehicle after the fault at ``t_f``: its lowest altitude and its deviations from
    ``setpoint`` (by default the altitude it held before the fault)."""
    states = [d for d in _data(rec, f"{SIM}/state") if _xyz(d.value.get("position"))]
    before = [d.value["position"] for d in states if d.stamp < t_f]
    after = [(d.stamp - t_f, d.value["position"]) for d in states if d.stamp >= t_f]
    out.setpoint = setpoint if setpoint is not None else (before[-1][2] if before else None)
    if after:
        out.min_altitude = min(p[2] for _, p in after)
        if out.setpoint is not None:
            _deviations(out, out.setpoint, before[-1][:2] if before else None, after)


def _xyz(p: object) -> bool:
    return isinstance(p, list) and len(p) >= 3


def _deviations(
    out: RecoveryReport, z0: float, xy0: list[float] | None, after: list[tuple[float, list]]
) -> None:
    """The largest deviations from the target (``z0``, ``xy0``: the hover point) after the
    fault, and the time to settle; ``after``: (seconds after the fault, position)."""
    out.altitude_lost = max(0.0, z0 - min(p[2] for _, p in after))
    out.overshoot = max(0.0, max(p[2] for _, p in after) - z0)

    def sideways(p: list) -> float:
        return math.hypot(p[0] - xy0[0], p[1] - xy0[1]) if xy0 is not None else 0.0

    out.drift = max(sideways(p) for _, p in after) if xy0 is not None else None

    def level(p: list) -> bool:
        return abs(p[2] - z0) <= SETTLE_Z

    out.settled = _settled(after, lambda p: level(p) and sideways(p) <= SETTLE_XY)
    out.altitude_settled = _settled(after, level)


def _settled(after: list[tuple[float, list]], calm: Callable[[list], bool]) -> float | None:
    """The first time from which every position is ``calm`` for `SETTLE_FOR` (None: never
    within ``after``)."""
    since: float | None = None
    for t, p in after:
        if not calm(p):
            since = None
        elif since is None:
            since = t
        if since is not None and t - since >= SETTLE_FOR:
            return since
    return None


def _ms(v: float | None) -> str:
    return "-" if v is None else f"{v * 1e3:.1f} ms"


def render_report(r: RecoveryReport) -> str:
    def metres(v: float | None) -> str:
        return "-" if v is None else f"{v:.3f} m"

    def when(v: float | None) -> str:
        if v is not None:
            return f"{v:.2f} s"
        return "never (within the recording)" if r.min_altitude is not None else "-"

    verdict = "STAYED AIRBORNE" if r.airborne else f"CRASHED{': ' + r.crash if r.crash else ''}"
    rows = [
        ("detection (fault -> WorkingMotors < 4)", _ms(r.detected)),
        ("decision (-> Proploss selected)", _ms(r.decided)),
        ("plan", _ms(r.plan)),
        ("execution: switch (activate + rewire)", _ms(r.switch)),
        ("execution: whole plan (+ stop old controller)", _ms(r.execute)),
        ("fault -> first Proploss command applied", _ms(r.first_proploss_command)),
        ("largest deviation up (overshoot)", metres(r.overshoot)),
        ("largest deviation down (altitude lost)", metres(r.altitude_lost)),
        ("largest deviation sideways (drift)", metres(r.drift)),
        (
            f"settled (+-{SETTLE_Z * 100:g} cm up/down, {SETTLE_XY * 100:g} cm sideways, "
            f"{SETTLE_FOR:g} s)",
            when(r.settled),
        ),
        (f"altitude settled (+-{SETTLE_Z * 100:g} cm, {SETTLE_FOR:g} s)", when(r.altitude_settled)),
        ("vehicle", verdict),
    ]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k:<{width}}  {v}" for k, v in rows)


# ---- the command --------------------------------------------------------------------------
def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo.rrd", help="the Rerun recording (default demo.rrd)")
    p.add_argument(
        "--strategy",
        choices=("hot-standby", "standby", "start-then-stop", "stop-then-start"),
        default="hot-standby",
        help="how the Proploss controller replaces the standard one (default hot-standby, "
        "as scenarios/quadcopter has it)",
    )
    p.add_argument("--no-adaptation", action="store_true", help="the control case: no RRA")
    p.add_argument(
        "--duration",
        type=_duration,
        help="stop the run at t = SECONDS (at least 6: the motor breaks at 5 s; default the "
        "scenario's: 20 s, 10 s without adaptation)",
    )
    p.add_argument("--run-dir", help="logs of the run (default: .rra/demo-<time>)")
    add_wide_argument(p, "the report's tables")


def _duration(text: str) -> float:
    """``--duration``: seconds, at least one after the motor failure."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 6.0 <= value <= 600.0:
        raise argparse.ArgumentTypeError(f"{value:g} s: between 6 (the motor breaks at 5 s) "
                                         "and 600")  # fmt: skip
    return value


def prepare_case(strategy: str, adaptation: bool, out: Path, duration: float | None = None):
    """The scenario case to run: the package's replacement model with ``strategy`` for the
    Proploss controller, the simulator's topics recorded, a Rerun recording saved, stopped
    at ``duration`` if given (the expectations' windows are cut by the end of the run)."""
    from rra_agent.package.loader import load_package
    from rra_agent.scenario.model import load_scenario

    sf = load_scenario(SCENARIO)
    case = next(c for c in sf.cases if c.case == ("adaptive" if adaptation else "control"))
    rep = load_package(case.package).runtime.replacement
    rep = msgspec.structs.replace(
        rep, components={**rep.components, "proploss_controller": strategy}
    )
    return dataclasses.replace(
        case,
        replacement=rep,
        record_topics=RECORD,
        up_args=("--rerun", "save", str(out)),
        duration=case.duration if duration is None else duration,
    )


def _progress(case, stop: threading.Event, started: float) -> None:
    """A progress line: redrawn in place on a terminal, every 5 s otherwise."""
    fault = next((s.step.at for s in case.timeline if s.name == FAULT), None)
    tty = sys.stdout.isatty()
    note = f"motor 2 breaks at t = {fault:g} s, " if fault is not None else ""
    while not stop.wait(0.5 if tty else 5.0):
        t = time.monotonic() - started
        line = f"  running: {t:5.1f} s ({note}stops at t = {case.duration:g} s)"
        print(f"\r{line}" if tty else line, end="" if tty else "\n", flush=True)
    if tty:
        print()


def run(args: argparse.Namespace) -> int:
    from rra_agent.scenario.runner import render_rows, run_case

    out = Path(args.out).resolve()
    run_dir = Path(args.run_dir or Path(".rra") / f"demo-{time.strftime('%Y%m%d-%H%M%S')}")
    run_dir = run_dir.resolve()
    case = prepare_case(args.strategy, not args.no_adaptation, out, args.duration)
    how = "no adaptation (control case)" if args.no_adaptation else f"{args.strategy} strategy"
    print(f"rra demo: quadcopter hovering at 2 m, motor 2 breaks at t = 5 s; {how}", flush=True)
    stop = threading.Event()
    ticker = threading.Thread(target=_progress, args=(case, stop, time.monotonic()), daemon=True)
    ticker.start()
    try:
        result = run_case(case, run_dir)
    finally:
        stop.set()
        ticker.join()
    if result.error:
        raise RraError(f"the demo run failed: {result.error}")
    report = recovery_report(result.recording, setpoint=2.0)
    report.strategy = args.strategy if not args.no_adaptation else "none"
    print("\nWhat happened after the fault:")
    print(render_report(report))
    print("\nThe scenario's expectations:")
    print(render_rows([result], wide=args.wide))
    (run_dir / "report.json").write_bytes(msgspec.json.encode(report))
    if out.exists():
        print(f"\nRecording: {out} (verified). Open it with:\n  rra view {out}")
    else:
        print(f"\nNo recording was written (see {run_dir / 'up.log'}).")
    print(f"Logs and events: {run_dir}")
    return 0 if result.passed and out.exists() else 1
