"""Recovery benchmark: fault -> first Proploss command, and altitude lost, per strategy.

Runs the quadcopter motor-failure scenario (hover at 2 m, motor 2 breaks) N times for each
of: ``standby`` (the Proploss controller pre-started inactive: switch = activation + rewire),
``hot-standby`` (pre-started active, publishing on its own key, which the simulator listens
to without delivering: switch = one rewire of the simulator, which applies the newest held
command at once), ``stop-then-start`` (cold: stop the controller, start the Proploss
controller), and ``delayed 0.5 s`` (standby, but the resolution engine waits 0.5 s before
executing: the paper's figure, emulated with ``RRA_EMULATED_SWAP_DELAY``). Every run is a
real system under ``rra up``. The latency and the crash come from the simulator's own trace
marks (fault, first physics step driven by a Proploss command, crash); the altitude lost from
the recording (`rra_agent.demo`).

Each strategy runs once per scheduling variant of its critical path (the simulator,
estimator and both controllers in system.yaml, ``engines`` and ``agents`` in rra.yaml), in a
copy of scenarios/quadcopter: ``fifo`` (SCHED_FIFO 50), ``nice`` (nice -10: more weight for
the normal scheduler, no real-time budget to exhaust) and ``none`` (no scheduling anywhere);
``--scheduling`` picks them (default fifo and none). ``--load`` runs a busy loop on every
core (``tools/cpuhog.py``) during all runs. Where the kernel refuses a scheduling, the runs
say so and its rows are the same as the others. ``--layout co-located`` runs the simulator
and the Proploss controller in one component container (beside the usual process per
component with ``--layout processes``). ``--cpu-latency 0`` has the host agent keep the CPUs
out of idle halts while the system runs (``agents: cpu_latency_us``, Linux PM QoS);
``--cpu-latency off`` runs without it whatever the package says (default: as it ships, not
held for the quadcopter).

Prints median and p99 per strategy beside the goals, for the first Proploss command received
by the simulator (the switch done) and for the first physics step it drives (the simulator
applies a command at its next 2 ms step, which quantizes that figure), then where the time
goes: the phases of one adaptation, from a cross-process trace (`rra_agent.trace`,
``RRA_TRACE``): fault -> Context Monitor's measurement -> Adaptation Engine's selection ->
Run-time Resolution Engine's plan -> (cold: stop the old node, fork, session open,
declarations, ready seen) -> connect (rewire + state export) -> activation -> the
simulator's first Proploss command received -> first physics step driven by it. Writes a
PNG of altitude over time around the failure (needs matplotlib: ``pip install -e '.[bench]'``).

    .venv/bin/python tools/bench_recovery.py [--runs 20] [--load] [--plot recovery.png]
        [--layout processes --layout co-located] [--cpu-latency off|US]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import msgspec
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _benchutil import median, p99, print_table

from rra_agent import trace
from rra_agent.demo import FAULT, RECORD, SCENARIO, recovery_report
from rra_agent.package.loader import load_package
from rra_agent.scenario.model import load_scenario
from rra_agent.scenario.runner import run_case

FAULT_AT = 3.0
DURATION = 6.0
#: name -> (replacement strategy, emulated swap delay s, reflexes on).
STRATEGIES = {
    "standby": ("standby", 0.0, True),
    "hot-standby": ("hot-standby", 0.0, True),
    "standby, engines": ("standby", 0.0, False),
    "hot-standby, engines": ("hot-standby", 0.0, False),
    "stop-then-start": ("stop-then-start", 0.0, True),
    "delayed 0.5 s": ("standby", 0.5, False),
}
#: (median ms, p99 ms) goals: quiet machine, and under --load.
GOALS = {
    ("standby", False): (5.0, 8.0),
    ("standby", True): (8.0, 15.0),
    ("hot-standby", False): (2.0, 4.0),
    ("hot-standby", True): (4.0, 8.0),
    ("hot-standby, engines", False): (5.0, 8.0),
    ("hot-standby, engines", True): (8.0, 15.0),
    ("stop-then-start", False): (20.0, 30.0),
    ("stop-then-start", True): (20.0, 30.0),
}
_ENGINES = [
    ("detect (fault -> measurement)", "monitor:measurement"),
    ("decide (-> selection)", "adaptation:selection"),
    ("deliver (-> resolution engine)", "resolution:selection"),
    ("plan", "resolution:planned"),
]
_SIM = [
    ("first command received by the sim", "sim:command_from"),
    ("first physics step with it", "sim:commanded_by"),
]
#: The phases of each strategy: (label, the trace mark that ends it), in order.
_REFLEX = [
    ("reflex fired in the consumer", "node:reflex"),
    *_SIM,
]
#: Beside the reflex: the control loop's two hops (the fault's telemetry to the Proploss
#: controller, its command back), which bound the first command whatever switches.
_LOOP = [
    ("(loop) fault -> the Proploss controller sees it", "sim:fault", "node:failure_known"),
    ("(loop) -> its command received by the sim", "node:failure_known", "sim:command_from"),
]
PHASES = {
    "standby": _REFLEX,
    "hot-standby": _REFLEX,
    "standby, engines": [
        *_ENGINES,
        ("connect (rewire, export state)", "engine:replied"),
        ("activate (-> first command sent)", "node:activated_publish"),
        *_SIM,
    ],
    "hot-standby, engines": [
        *_ENGINES,
        ("select (consumer rewired, held command delivered)", "sim:command_from"),
        ("first physics step with it", "sim:commanded_by"),
    ],
    "stop-then-start": [
        *_ENGINES,
        ("replace request sent (the rewire in flight)", "engine:replace"),
        ("its host agent asks for the old node's state", "agent:export"),
        ("state exported", "agent:exported"),
        ("old node killed", "agent:STOPPING"),
        ("its end seen by the new node (its gate)", "node:gate"),
        ("import_state, on_start, token", "node:token"),
        *_SIM,
    ],
}
#: Phases that run beside those above: (label, the mark that starts it, the one that ends it).
MEANWHILE = {
    "standby": _LOOP,
    "hot-standby": _LOOP,
    "stop-then-start": [
        ("(meanwhile) the spare prepares: session, ports", "node:request", "node:prepared"),
        ("(meanwhile) the old node's exit reaped by its agent", "agent:STOPPING", "agent:STOPPED"),
        ("(meanwhile) ready seen by the engine", "node:token", "engine:started"),
        ("(meanwhile) the consumers' rewire answered", "engine:control", "engine:replied"),
    ],
}


#: Scheduling variants of the critical path (the nodes below, the engines, the host agents):
#: ``fifo`` real time, ``nice`` a higher weight for the normal scheduler, ``none`` nothing.
VARIANTS: dict[str, dict | None] = {
    "fifo": {"policy": "fifo", "priority": 50},
    "nice": {"nice": -10},
    "none": None,
}
CRITICAL = ("estimator", "controller", "proploss_controller", "vehicle_simulator")
#: Layouts of the control loop: a process per component (as shipped), or the simulator and
#: the controllers named in ``COLOCATED`` in one component container (as ros2_control runs
#: its controllers in the hardware interface's process).
LAYOUTS = ("processes", "co-located")
COLOCATED = ("vehicle_simulator", "proploss_controller")


def scheduled(
    package: Path,
    into: Path,
    scheduling: dict | None,
    layout: str = "processes",
    cpu_latency: int | None = None,
) -> Path:
    """A copy of ``package`` with its critical path (nodes, engines, agents) scheduled with
    ``scheduling``, and nothing else scheduled (``None``: no scheduling anywhere); with
    ``layout`` ``co-located``, the components of `COLOCATED` in one container; with
    ``cpu_latency``, the host agent holding the CPUs' wake-up latency (``agents:
    cpu_latency_us``; None: not held)."""
    shutil.copytree(package, into)
    system = yaml.safe_load((into / "system.yaml").read_text())
    for c in system.get("components", []):
        c.pop("scheduling", None)
        if scheduling is not None and c["name"] in CRITICAL:
            c["scheduling"] = dict(scheduling)
        if layout == "co-located" and c["name"] in COLOCATED:
            c["container"] = "flight"
    (into / "system.yaml").write_text(yaml.safe_dump(system, sort_keys=False))
    manifest = yaml.safe_load((into / "rra.yaml").read_text())
    for key in ("engines", "agents"):
        manifest.pop(key, None)
        if scheduling is not None:
            manifest[key] = {"scheduling": dict(scheduling)}
    if cpu_latency is not None:
        manifest.setdefault("agents", {})["cpu_latency_us"] = cpu_latency
    (into / "rra.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return into


def _latency(value: str) -> int | str | None:
    """``--cpu-latency``'s value: microseconds, ``off`` (not held) or ``shipped`` (as the
    package says)."""
    if value in ("off", "shipped"):
        return None if value == "off" else value
    if not value.isdigit():
        raise argparse.ArgumentTypeError(f"{value!r}: microseconds, off or shipped")
    return int(value)


def _shipped_latency() -> int | None:
    """The CPU latency the package's host agents hold (``agents: cpu_latency_us``), if any."""
    manifest = yaml.safe_load((SCENARIO.parent / "rra.yaml").read_text())
    return (manifest.get("agents") or {}).get("cpu_latency_us")


def phases(path: Path, strategy: str) -> dict[str, float]:
    """Seconds per phase of the adaptation after the fault, from one run's trace (each
    phase ends at the first occurrence of its mark after the previous phase's end)."""
    lines = trace.read(path)
    i = next((k for k, x in enumerate(lines) if x["what"] == "sim:fault"), None)
    if i is None:
        return {}
    out: dict[str, float] = {}
    t = float(lines[i]["t"])
    for label, mark in PHASES.get(strategy, []):
        j = next(
            (
                k
                for k in range(i + 1, len(lines))
                if lines[k]["what"] == mark
                and (mark != "sim:command_from" or "proploss" in str(lines[k]["node"]))
            ),
            None,
        )
        if j is None:
            break
        out[label] = float(lines[j]["t"]) - t
        t, i = float(lines[j]["t"]), j
    start = next(k for k, x in enumerate(lines) if x["what"] == "sim:fault")
    for label, first, last in MEANWHILE.get(strategy, []):
        a = next((x for x in lines[start:] if x["what"] == first), None)
        b = next((x for x in lines[start:] if x["what"] == last), None)
        if a is not None and b is not None:
            out[label] = float(b["t"]) - float(a["t"])
    return out


class Marks(msgspec.Struct):
    """What the simulator marked after the fault (seconds after it)."""

    #: its first Proploss command received (the switch done, not yet applied)
    received: float | None = None
    #: the first physics step driven by a Proploss command (the 2 ms step quantizes it)
    applied: float | None = None
    crashed: bool = False


def _first_proploss(after: list[dict], what: str, t_fault: float) -> float | None:
    return next(
        (
            float(x["t"]) - t_fault
            for x in after
            if x["what"] == what and "proploss" in str(x["node"])
        ),
        None,
    )


def from_trace(path: Path) -> Marks:
    """Fault -> first Proploss command received by the simulator and first physics step
    driven by one, and whether the vehicle crashed, as the simulator itself marked them
    (``sim:fault``, ``sim:command_from``, ``sim:commanded_by``, ``sim:crash``). The
    simulator's own marks, not the scenario's recording: under load a normal-priority
    recorder beside real-time processes can fall behind the window, and its samples'
    arrival says nothing of the switch."""
    if not path.exists():
        return Marks()
    lines = trace.read(path)
    t_fault = next((float(x["t"]) for x in lines if x["what"] == "sim:fault"), None)
    if t_fault is None:
        return Marks()
    after = [x for x in lines if float(x["t"]) >= t_fault]
    return Marks(
        received=_first_proploss(after, "sim:command_from", t_fault),
        applied=_first_proploss(after, "sim:commanded_by", t_fault),
        crashed=any(x["what"] == "sim:crash" for x in after),
    )


def make_case(strategy: str, package: Path | None = None):
    """The adaptive case, shortened (fault at 3 s, 6 s long), with ``strategy``."""
    sf = load_scenario(SCENARIO)
    case = next(c for c in sf.cases if c.case == "adaptive")
    if package is not None:
        case = dataclasses.replace(case, package=package)
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


class RunFailed(Exception):
    """A run that produced no recording (e.g. no deployment came); its folder is kept."""


def keep(run_dir: Path, into: Path | None, why: str) -> None:
    """Copy a failing run's folder (trace, logs, events, recording) to ``into`` for study."""
    if into is None:
        return
    dest = into / run_dir.name
    shutil.rmtree(dest, ignore_errors=True)
    shutil.copytree(run_dir, dest, dirs_exist_ok=True)
    (dest / "WHY").write_text(why + "\n")
    print(f"    kept {dest} ({why})", flush=True)


def one_run(case, delay: float, run_dir: Path, name: str):
    """One run: its report, its recording and its phases (seconds)."""
    run_dir.mkdir(parents=True)
    trace_file = run_dir / "trace.jsonl"
    os.environ["RRA_EMULATED_SWAP_DELAY"] = str(delay)
    os.environ[trace.ENV] = str(trace_file)
    try:
        result = run_case(case, run_dir)
    finally:
        os.environ.pop("RRA_EMULATED_SWAP_DELAY", None)
        os.environ.pop(trace.ENV, None)
    if result.recording is None:
        raise RunFailed(str(result.error))
    report = recovery_report(result.recording, setpoint=2.0)
    marks = from_trace(trace_file)
    if marks.applied is not None:
        report.first_proploss_command = marks.applied
    if marks.crashed:
        report.airborne = False
    ph = phases(trace_file, name) if trace_file.exists() else {}
    return report, result.recording, ph, marks.received, confirmations(result.recording)


def confirmations(rec) -> list[float]:
    """Seconds from each reflex's fire to the engines' confirmation (its events)."""
    return [
        float(e.durations.get("confirm", 0.0))
        for e in rec.events
        if getattr(e, "kind", "") == "reflex" and e.outcome == "ok"
    ]


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


def _variant(scheduling: str, layout: str) -> str:
    """The label of a scheduling variant in a layout (the table's scheduling column)."""
    return scheduling if layout == "processes" else f"{scheduling}, {layout}"


def _goal(strategy: str, load: bool) -> str:
    goal = GOALS.get((strategy, load))
    if goal is None:
        return ""
    med, p = goal
    return f"<= {med:g}" + (f" / <= {p:g}" if p is not None else "")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=20, help="runs per strategy (default 20)")
    ap.add_argument("--plot", default="recovery.png", help="PNG of altitude around the fault")
    ap.add_argument("--only", choices=list(STRATEGIES), action="append", help="these only")
    ap.add_argument("--load", action="store_true", help="a busy loop on every core meanwhile")
    ap.add_argument(
        "--scheduling",
        choices=list(VARIANTS),
        action="append",
        help="scheduling of the critical path: fifo (SCHED_FIFO 50), nice (-10), none "
        "(repeatable; default: fifo and none)",
    )
    ap.add_argument(
        "--layout",
        choices=LAYOUTS,
        action="append",
        help="processes (a process per component, as shipped) or co-located (the simulator "
        "and the Proploss controller in one component container); repeatable, default "
        "processes",
    )
    ap.add_argument(
        "--cpu-latency",
        type=_latency,
        default="shipped",
        metavar="US|off",
        help="the host agent holds its CPUs' wake-up latency at US microseconds while the "
        "system runs, or not at all with off (agents: cpu_latency_us in rra.yaml; Linux PM "
        "QoS, root); default: as the package ships",
    )
    ap.add_argument(
        "--keep",
        default="recovery-failures",
        help="folder where the run folders of failed or crashed runs are copied "
        "(trace, logs, events; default recovery-failures/, '' to keep none)",
    )
    args = ap.parse_args()
    hog = None
    if args.load:
        hog = subprocess.Popen([sys.executable, str(Path(__file__).parent / "cpuhog.py")])
        print(f"load: tools/cpuhog.py, {os.cpu_count()} busy loops")
    scheds = args.scheduling or ["fifo", "none"]
    layouts = args.layout or ["processes"]
    chosen = [_variant(v, lay) for v in scheds for lay in layouts]
    names = args.only or list(STRATEGIES)
    shipped = args.cpu_latency == "shipped"
    held = _shipped_latency() if shipped else args.cpu_latency
    accs = {(n, v): Acc(n, v) for n in names for v in chosen}
    try:
        with tempfile.TemporaryDirectory(prefix="rra-recovery-") as tmp:
            variants = {
                _variant(v, lay): scheduled(
                    SCENARIO.parent, Path(tmp) / _variant(v, lay).replace(", ", "-"),
                    VARIANTS[v], lay, held,
                )
                for v in scheds
                for lay in layouts
            }  # fmt: skip
            # Interleaved (A, B, A, B, ...): what the machine's other load does meanwhile
            # falls on every strategy alike.
            for i in range(args.runs):
                for (_, variant), acc in accs.items():
                    acc.run(i, variants[variant], args, Path(tmp))
    finally:
        if hog is not None:
            hog.kill()
            hog.wait()
    print()
    load = "under a busy loop on every core" if args.load else "quiet machine"
    print(
        f"fault -> first Proploss command received by the simulator / applied at its next "
        f"2 ms physics step ({load}; runs interleaved)"
    )
    print(
        "scheduling of the critical path: "
        + ", ".join(f"{v} = {VARIANTS[v] or 'none'}" for v in scheds)
    )
    said = ("not held" if held is None else f"held at {held} us") + (", as shipped" * shipped)
    print(f"CPU wake-up latency: {said} (agents: cpu_latency_us)")
    if "co-located" in layouts:
        print(f"co-located: {', '.join(COLOCATED)} in one component container")
    print_table(
        ["strategy", "scheduling", "runs", "received ms (median / p99)",
         "applied ms (median / p99)", "goal ms (median / p99)",
         "alt. lost median m", "alt. lost p99 m", "airborne", "confirmed ms (median / p99)"],
        [acc.row(args) for acc in accs.values()],
        digits=3,
    )  # fmt: skip
    print_phases({f"{n}, {v}": acc.per_phase for (n, v), acc in accs.items()})
    traces = {n: acc.trace_xy for (n, _), acc in accs.items() if acc.trace_xy is not None}
    if traces and plot(traces, Path(args.plot)):
        print(f"plot: {Path(args.plot).resolve()}")
    return 0


class Acc:
    """One strategy under one scheduling variant: its runs so far."""

    def __init__(self, name: str, variant: str) -> None:
        self.name, self.variant = name, variant
        self.latencies: list[float] = []
        self.received: list[float] = []
        self.losses: list[float] = []
        self.confirmed: list[float] = []
        self.survived = 0
        self.per_phase: dict[str, list[float]] = {}
        self.trace_xy: tuple[list[float], list[float]] | None = None

    def run(self, i: int, package: Path, args, tmp: Path) -> None:
        name, variant = self.name, self.variant
        strategy, delay, reflexes = STRATEGIES[name]
        case = make_case(strategy, reflex_variant(package, reflexes))
        kept = Path(args.keep) if args.keep else None
        label = f"{name}-{variant}".replace(", ", "-").replace(" ", "_")
        run_dir = tmp / f"{label}-{i}"
        try:
            report, rec, ph, got, conf = one_run(case, delay, run_dir, name)
        except RunFailed as e:
            print(f"  {name:<20} {variant:<5} run {i + 1}/{args.runs}: FAILED: {e}", flush=True)
            keep(run_dir, kept, f"failed: {e}")
            return
        if not report.airborne or report.first_proploss_command is None:
            keep(run_dir, kept, "crashed" if not report.airborne else "no Proploss command")
        if report.first_proploss_command is not None:
            self.latencies.append(report.first_proploss_command)
        if got is not None:
            self.received.append(got)
        if report.altitude_lost is not None:
            self.losses.append(report.altitude_lost)
        self.confirmed += conf
        self.survived += report.airborne
        for k, v in ph.items():
            self.per_phase.setdefault(k, []).append(v)
        if self.trace_xy is None:
            self.trace_xy = altitude_trace(rec, report)
        print(f"  {name:<20} {variant:<5} run {i + 1}/{args.runs}: received "
              f"{(got or float('nan')) * 1e3:6.1f} ms, applied "
              f"{(report.first_proploss_command or float('nan')) * 1e3:6.1f} ms, "
              f"altitude lost {report.altitude_lost or float('nan'):.3f} m, "
              f"{'airborne' if report.airborne else 'CRASHED'}"
              + (f", confirmed {conf[0] * 1e3:.1f} ms" if conf else ""), flush=True)  # fmt: skip

    def row(self, args) -> list:
        delay = STRATEGIES[self.name][1]
        return [
            self.name,
            self.variant,
            len(self.latencies),
            _ms(self.received),
            _ms(self.latencies),
            _goal(self.name if delay == 0 else "", args.load),
            median(self.losses) if self.losses else float("nan"),
            p99(self.losses) if self.losses else float("nan"),
            f"{self.survived}/{args.runs}",
            _ms(self.confirmed),
        ]


def reflex_variant(package: Path, reflexes: bool) -> Path:
    """``package`` itself (reflexes on, as shipped) or a sibling copy with them off."""
    if reflexes:
        return package
    off = package.with_name(package.name + "-engines")
    if not off.exists():
        shutil.copytree(package, off)
        manifest = yaml.safe_load((off / "rra.yaml").read_text())
        manifest["reflexes"] = {"enabled": False}
        (off / "rra.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return off


def _ms(xs: list[float]) -> str:
    """``median / p99`` in ms."""
    return f"{median(xs) * 1e3:.1f} / {p99(xs) * 1e3:.1f}" if xs else "-"


def print_phases(breakdown: dict[str, dict[str, list[float]]]) -> None:
    """Median ms per phase (rows) for each strategy and scheduling (columns)."""
    names = [n for n in breakdown if breakdown[n]]
    if not names:
        return
    print()
    print("where the time goes: median ms per phase (cross-process trace, RRA_TRACE)")
    rows = []
    middle = [label for ph in PHASES.values() for label, _ in ph if (label, _) not in _SIM]
    beside = [label for ph in MEANWHILE.values() for label, _, _ in ph]
    labels = list(dict.fromkeys([*middle, *(label for label, _ in _SIM), *beside]))
    for label in labels:
        if any(label in breakdown[n] for n in names):
            rows.append([label] + [
                median(breakdown[n][label]) * 1e3 if label in breakdown[n] else float("nan")
                for n in names
            ])  # fmt: skip
    print_table(["phase", *names], rows, digits=2)


if __name__ == "__main__":
    sys.exit(main())
