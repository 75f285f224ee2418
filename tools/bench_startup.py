"""Benchmark of the CLI's start: wall time of ``rra validate`` and ``rra resolve`` of the
example packages (scenarios/object_storing, quadcopter, base_station), each run as a fresh
process, against the 0.3 s goal.

Two cases per command and package:

- **cold**: an empty parser cache (``RRA_CACHE_DIR`` pointed at a new folder before every
  run), so the UVL and rules parsers are built from their grammars (strict mode included), as
  on the first run after an install or a grammar change;
- **warm**: the parser cache filled by an earlier run, the usual case.

Each line gives the median and p99 wall time and the median CPU time (user + system) of the
process: on a loaded machine the wall time includes waiting for a core, the CPU time does not.

Python's compiled bytecode is kept in a private folder (``PYTHONPYCACHEPREFIX``) that the
first run fills, so both cases measure an installed package, not the compilation of its
sources (``--no-bytecode`` measures with ``PYTHONDONTWRITEBYTECODE=1`` instead, i.e. every
module compiled at every start).

Run: ``.venv/bin/python tools/bench_startup.py [--runs N] [--no-bytecode]``.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _benchutil import median, p99  # noqa: E402

PACKAGES = ("object_storing", "quadcopter", "base_station")
COMMANDS = ("validate", "resolve")
GOAL_S = 0.3


def _run(command: str, package: str, env: dict[str, str]) -> tuple[float, float]:
    """One ``rra COMMAND PACKAGE`` process: (wall time, CPU time user+system) in seconds."""
    argv = [sys.executable, "-m", "rra_agent", command, str(ROOT / "scenarios" / package)]
    start = time.perf_counter()
    proc = subprocess.Popen(
        argv, env=env, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE
    )
    _, status, usage = os.wait4(proc.pid, 0)
    elapsed = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    assert proc.stderr is not None
    if proc.returncode != 0:
        raise SystemExit(f"rra {command} {package} failed:\n{proc.stderr.read().decode()}")
    proc.stderr.close()
    return elapsed, usage.ru_utime + usage.ru_stime


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=10, help="runs per command, package and case")
    ap.add_argument(
        "--no-bytecode", action="store_true", help="compile every module at every start"
    )
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(prefix="rra-bench-startup-") as tmp:
        base = {**os.environ, "PYTHONPATH": str(ROOT)}
        if args.no_bytecode:
            base["PYTHONDONTWRITEBYTECODE"] = "1"
        else:
            base.pop("PYTHONDONTWRITEBYTECODE", None)
            base["PYTHONPYCACHEPREFIX"] = str(Path(tmp) / "pyc")
            _run("validate", PACKAGES[0], {**base, "RRA_CACHE_DIR": str(Path(tmp) / "warmup")})
        warm_env = {**base, "RRA_CACHE_DIR": str(Path(tmp) / "warm")}
        _run("validate", PACKAGES[0], warm_env)  # fills the warm cache

        print(f"load average: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
        print(
            f"{'command':<9} {'package':<15} {'case':<5} {'median':>8} {'p99':>8} {'cpu':>7}  goal"
        )
        worst = 0.0
        for command in COMMANDS:
            for package in PACKAGES:
                for case in ("cold", "warm"):
                    samples, cpu = [], []
                    for i in range(args.runs):
                        env = warm_env
                        if case == "cold":
                            cold = Path(tmp) / f"cold-{command}-{package}-{i}"
                            env = {**base, "RRA_CACHE_DIR": str(cold)}
                        wall, used = _run(command, package, env)
                        samples.append(wall)
                        cpu.append(used)
                    med, top = median(samples), p99(samples)
                    if case == "warm":
                        worst = max(worst, med)
                    verdict = "ok" if med < GOAL_S else "OVER"
                    times = f"{med:>7.3f}s {top:>7.3f}s {median(cpu):>6.3f}s"
                    note = verdict if case == "warm" else "(first run)"
                    print(f"{command:<9} {package:<15} {case:<5} {times}  {GOAL_S:.1f}s {note}")
        print(f"slowest warm median: {worst:.3f} s (goal {GOAL_S} s)")


if __name__ == "__main__":
    main()
