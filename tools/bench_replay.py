"""Benchmark: how fast ``rra replay`` re-runs a recorded run, and what recording costs.

Replay: each shipped package's scenario is recorded once (``rra test SCENARIO -k CASE --out
DIR --keep``; or pass run folders with ``--run``), then its record is opened and replayed
``--runs`` times in this process (`open_run` + `replay`, and `what_if` with the run's own
models). The figure is *x real time*: the recorded run's span divided by the replay's wall
time, and by its CPU time (``x CPU``: what it takes without the other processes of a busy
machine); median and p99 over the runs (the p99 is the slowest run as an x factor, i.e. the
lowest). Each includes opening the record: reading, checking and loading its models. Goal:
>= 100x real time (the median, wall time).

Recording: the hot-path cost of one record (`RecordWriter.write` of an Adaptation Engine
`Tick` with two measurements: msgpack encoding, CRC, one unbuffered ``write(2)``), median
and p99 over ``--writes`` writes.

    .venv/bin/python tools/bench_replay.py [--runs 20] [--writes 20000] [--run DIR ...]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _benchutil import format_table, median, p99

from rra_agent.record import format as f
from rra_agent.record.replay import open_run, replay, what_if

ROOT = Path(__file__).resolve().parents[1]
#: One scenario case per shipped package.
CASES = [
    ("quadcopter/motor_failure.scenario.yaml", "motor_failure::adaptive"),
    ("object_storing/radio.scenario.yaml", "radio::adaptive"),
    ("base_station/link_cut.scenario.yaml", "link_cut::short"),
]
GOAL = 100.0


def record(base: Path, scenario: str, case: str) -> Path:
    out = subprocess.run(
        [sys.executable, "-m", "rra_agent", "test", str(ROOT / "scenarios" / scenario), "-k",
         case, "--out", str(base), "--keep"],
        capture_output=True, text=True, cwd=ROOT, check=False, timeout=600,
    )  # fmt: skip
    folder = base / case.replace("::", "-")
    if not (folder / "record" / "run.json").exists():
        sys.exit(f"bench_replay: recording {case} failed:\n{out.stdout}{out.stderr}")
    return folder


def bench_run(folder: Path, runs: int) -> list[object]:
    """One table row: the replay and the what-if of ``folder``, in x real time."""
    replayed: list[float] = []
    cpu: list[float] = []
    whatif: list[float] = []
    duration = 0.0
    evaluations = 0
    for _ in range(runs):
        t0, c0 = time.perf_counter(), time.process_time()
        run = open_run(folder)
        result = replay(run)
        replayed.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        if result.difference is not None:
            sys.exit(f"bench_replay: {folder}: {result.difference.line()}")
        duration, evaluations = result.duration, result.evaluations
        t0 = time.perf_counter()
        run = open_run(folder)
        what_if(run, run.models(run.info.models))
        whatif.append(time.perf_counter() - t0)
    x = [duration / s for s in replayed]
    xw = [duration / s for s in whatif]
    lowest = duration / p99(replayed)
    return [folder.name, duration, evaluations, median(x), lowest,
            median([duration / c for c in cpu]), duration / p99(cpu), median(xw),
            duration / p99(whatif), "yes" if median(x) >= GOAL else "NO"]  # fmt: skip


def bench_writes(n: int) -> list[object]:
    tick = f.Tick(
        now=1234.5, changed=["Level", "Battery"], selection=["Direct", "Hover"],
        ctx=[f.Ctx(name="Level", value=1.0, stamp=1234.4, at=1234.45),
             f.Ctx(name="Battery", value=0.8, stamp=1234.4, at=1234.45)],
        cv={"Hover.gain": 0.5}, lead=True, seq=42,
    )  # fmt: skip
    samples: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        writer = f.RecordWriter(Path(tmp) / "bench-1.rec")
        for _ in range(n):
            t0 = time.perf_counter()
            writer.write(tick)
            samples.append(time.perf_counter() - t0)
        writer.close(end=time.time())
        size = writer.bytes / writer.records
    return [n, size, median(samples) * 1e6, p99(samples) * 1e6]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=20, help="replays of each record (default 20)")
    ap.add_argument("--writes", type=int, default=20000, help="records written (default 20000)")
    ap.add_argument("--run", action="append", default=[], help="a recorded run folder")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-replay-") as tmp:
        folders = [Path(r) for r in args.run] or [record(Path(tmp), s, c) for s, c in CASES]
        rows = [bench_run(folder, args.runs) for folder in folders]
    print(f"replay: x real time over {args.runs} runs (goal >= {GOAL:.0f}x; p99 = slowest)")
    print(format_table(["run", "run s", "evals", "replay x", "p99", "x CPU", "p99",
                        "what-if x", "p99", "goal"], rows))  # fmt: skip
    print()
    print("recording: one Tick record, RecordWriter.write (encode, CRC, write(2))")
    print(format_table(["writes", "bytes/rec", "median us", "p99 us"], [bench_writes(args.writes)]))


if __name__ == "__main__":
    main()
