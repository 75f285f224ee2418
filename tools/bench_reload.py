"""Benchmark: ``rra reload`` time, from the command to the new rules in effect.

A running system (``rra up`` of tests/data/relay_system, or ``--package``, on a loopback
endpoint from `free_port`) gets ``--runs`` reloads in turn of two edits of one rule's
threshold (``--old`` -> ``--new`` and back, so each reload is a real change). Each
``rra reload`` prints when the Run-time Resolution Engine leader switched (every replica
prepared, the new state published) and when the Adaptation Engine leader first published a
selection decided under the new models (the new rules in effect); both are measured from
the command's start inside the command (its own process start and bus join excluded; the
``cli`` column is the whole command's wall time). Median and p99 over the runs.

    .venv/bin/python tools/bench_reload.py [--runs 10] [--package DIR --file F --old S --new S]
"""

from __future__ import annotations

import argparse
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _benchutil import interrupt, median, p99, print_table

from rra_agent.bus.client import BusClient, gather, wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.errors import RraError
from rra_agent.package.loader import load_package

ROOT = Path(__file__).resolve().parents[1]
RELAY = ROOT / "tests" / "data" / "relay_system"
SWITCHED = re.compile(r"switched in ([0-9.]+) s")
DECIDES = re.compile(r"decides under them ([0-9.]+) s after")
GOAL_S = 1.0


def rra(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rra_agent", *args], capture_output=True,
                          text=True, cwd=ROOT, check=False, timeout=timeout)  # fmt: skip


def edited(src: Path, tmp: Path, name: str, file: str, old: str, new: str) -> Path:
    pkg = tmp / name
    shutil.copytree(src, pkg, ignore=shutil.ignore_patterns("__pycache__", "*.scenario.yaml"))
    text = (pkg / file).read_text()
    if text.count(old) != 1:
        sys.exit(f"bench_reload: {file}: {old!r} is not there once")
    (pkg / file).write_text(text.replace(old, new))
    return pkg


def listening(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def wait_up(endpoint: str, system: str, up: subprocess.Popen[bytes]) -> None:
    """Until the Resolution Engine reports the system deployed."""

    def deployed() -> bool:
        if up.poll() is not None:
            sys.exit("bench_reload: rra up exited")
        try:
            st = gather(client, timeout=1.0)
        except RraError:
            return False
        return bool((st.get("engine") or {}).get("deployed"))

    port = int(endpoint.rsplit(":", 1)[1])
    wait_until(lambda: up.poll() is not None or listening(port), 120, "rra up listening")
    client = BusClient(BusConfig(connect=[endpoint], multicast=False), system)
    with client:
        wait_until(deployed, 120, "the system deployed")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10, help="reloads (default 10)")
    ap.add_argument("--package", type=Path, default=RELAY, help="the system package")
    ap.add_argument("--file", default="adaptation.rra", help="the edited file")
    ap.add_argument("--old", default="cdm.Level > 5", help="the text edited")
    ap.add_argument("--new", default="cdm.Level > 6", help="what it becomes")
    args = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with tempfile.TemporaryDirectory(prefix="bench-reload-") as name:
        tmp = Path(name)
        a = edited(args.package, tmp, "a", args.file, args.old, args.new)
        b = edited(args.package, tmp, "b", args.file, args.old, args.old)
        up = subprocess.Popen(
            [sys.executable, "-m", "rra_agent", "up", str(args.package), "-q", "--run-dir",
             str(tmp / "run"), "--connect", endpoint, "--no-multicast"],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        try:
            wait_up(endpoint, load_package(args.package).system.system, up)
            rows = measure(endpoint, [a, b], args.runs)
        finally:
            interrupt(up)
    switched, decides, cli = rows
    print(f"rra reload of {args.package.name} ({args.old!r} <-> {args.new!r}), {len(cli)} reloads")
    print(f"goal: new rules in effect <= {GOAL_S:.1f} s after the command")
    print_table(
        ["measure", "median s", "p99 s"],
        [["switched (every replica prepared, leader's state)", median(switched), p99(switched)],
         ["new rules in effect (first selection under them)", median(decides), p99(decides)],
         ["cli wall time (process start to exit)", median(cli), p99(cli)]],
        digits=3,
    )  # fmt: skip


def measure(endpoint: str, pkgs: list[Path], runs: int) -> tuple[list[float], ...]:
    switched: list[float] = []
    decides: list[float] = []
    cli: list[float] = []
    for i in range(runs):
        t0 = time.perf_counter()
        out = rra("reload", str(pkgs[i % 2]), "--connect", endpoint, "--no-multicast")
        cli.append(time.perf_counter() - t0)
        if out.returncode != 0:
            sys.exit(f"bench_reload: rra reload failed:\n{out.stdout}{out.stderr}")
        s, d = SWITCHED.search(out.stdout), DECIDES.search(out.stdout)
        if s is None or d is None:
            sys.exit(f"bench_reload: unexpected output:\n{out.stdout}")
        switched.append(float(s.group(1)))
        decides.append(float(d.group(1)))
    return switched, decides, cli


if __name__ == "__main__":
    main()
