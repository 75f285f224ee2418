"""Memory of a running system: RSS and PSS of every process under ``rra up``.

Starts ``rra up PKG`` (loopback, a free port, Rerun off), waits until the Run-time
Resolution Engine reports the deployment applied, lets it run ``--settle`` seconds, sums
RSS and PSS (``/proc/<pid>/smaps_rollup``: PSS shares a page among the processes that map
it, so it is what the system as a whole costs) over ``rra up`` and all its descendants,
then stops it with SIGINT. ``--containers`` runs the same package with every Python
component of the first host in one component container (``container: all``), to show what
containers save; both are printed side by side with ``--compare``.

    .venv/bin/python tools/bench_memory.py [scenarios/object_storing] [--compare]
"""

from __future__ import annotations

import argparse
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _benchutil import interrupt, print_table
from bench_reconfig import memory

from rra_agent.bus.client import BusClient, wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.cli.status import gather
from rra_agent.models.loader import load_package

ROOT = Path(__file__).resolve().parents[1]
GOAL_PSS_MIB = 150.0


def contained(package: Path, into: Path) -> Path:
    """A copy of ``package`` with its Python components (first host) in container "all"."""
    shutil.copytree(package, into)
    system = yaml.safe_load((into / "system.yaml").read_text())
    for c in system.get("components", []):
        impls = [c.get("implementation"), *(c.get("implementations") or {}).values()]
        if all(isinstance(i, str) for i in impls) and not c.get("host"):
            c["container"] = "all"
    (into / "system.yaml").write_text(yaml.safe_dump(system, sort_keys=False))
    return into


def measure(package: Path, settle: float) -> tuple[int, float, float, int]:
    """(processes, RSS MiB, PSS MiB, components running) of ``rra up package``."""
    system = load_package(package).system.system
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="rra-memory-") as run_dir:
        up = subprocess.Popen(
            [sys.executable, "-m", "rra_agent", "up", str(package), "--run-dir", run_dir,
             "-q", "--connect", endpoint, "--no-multicast"],
            env={**os.environ, "RERUN_ANALYTICS": "0"},
        )  # fmt: skip
        client = None
        try:
            wait_until(lambda: up.poll() is not None or _listening(port), 60, "rra up listening")
            client = BusClient(BusConfig(connect=[endpoint], multicast=False), system)
            st = wait_until(lambda: _deployed(client), 120, "the deployment", interval=0.5)
            time.sleep(settle)
            procs, rss, pss = memory(up.pid)
            return procs, rss, pss, len(st["engine"]["running"])
        finally:
            if client is not None:
                client.close()
            interrupt(up)


def _listening(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


def _deployed(client: BusClient) -> dict | None:
    st = gather(client, timeout=1.0)
    eng = st.get("engine") or {}
    return st if eng.get("running") and not eng.get("failed") else None


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("package", nargs="?", default=str(ROOT / "scenarios" / "object_storing"))
    ap.add_argument("--settle", type=float, default=3.0, help="seconds to run before measuring")
    ap.add_argument("--containers", action="store_true", help="components in one container")
    ap.add_argument("--compare", action="store_true", help="both: processes and containers")
    args = ap.parse_args()
    package = Path(args.package).resolve()
    rows = []
    with tempfile.TemporaryDirectory(prefix="rra-memory-pkg-") as tmp:
        layouts = ["processes", "one container"] if args.compare else (
            ["one container"] if args.containers else ["processes"])  # fmt: skip
        for layout in layouts:
            pkg = package if layout == "processes" else contained(package, Path(tmp) / "c")
            procs, rss, pss, running = measure(pkg, args.settle)
            rows.append([layout, running, procs, rss, pss, f"<= {GOAL_PSS_MIB:g}"])
            print(f"  {layout}: {procs} processes, PSS {pss:.0f} MiB", flush=True)
    print()
    print(f"memory of {package.name} under rra up (every process: agent, engines, nodes)")
    print_table(["layout", "components", "processes", "RSS MiB", "PSS MiB", "goal PSS MiB"],
                rows)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
