"""Memory of a running system: RSS and PSS of every process under ``rra up``.

Starts ``rra up PKG`` (loopback, a free port, Rerun off), waits until the Run-time
Resolution Engine reports the deployment applied, lets it run ``--settle`` seconds, sums
RSS and PSS (``/proc/<pid>/smaps_rollup``: PSS shares a page among the processes that map
it, so it is what the system as a whole costs) over ``rra up`` and all its descendants,
then stops it with SIGINT. ``--containers`` runs the same package with every Python
component of the first host in one component container (``container: all``), to show what
containers save; both are printed side by side with ``--compare``.

Where the memory goes: a table per layout with every process (its node or engine name, read
from the log file its stdout goes to), its threads, RSS, PSS split into anonymous memory
(Python and Rust heaps, stacks), file-backed pages (libraries) and shared memory (Zenoh's
``/dev/shm`` segments), and its private dirty pages (what it alone costs); then the PSS of
all processes by kind of mapping. ``--env NAME=VALUE`` (repeatable) runs ``rra up`` with a
variable set (e.g. ``MALLOC_ARENA_MAX=2``), for experiments. ``--replicas N`` runs ``rra up
--replicas N`` (default 2: a leader and a hot standby of each engine), to show what the
engines' standbys cost.

    .venv/bin/python tools/bench_memory.py [scenarios/object_storing] [--compare] [--env N=V]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _benchutil import interrupt, print_table

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


@dataclass
class Process:
    """One process's memory (MiB, from ``/proc/<pid>/smaps``)."""

    pid: int
    role: str
    threads: int
    kb: dict[str, int]
    #: PSS (kB) by kind of mapping (`mapping_kind`).
    by_kind: dict[str, int] = field(default_factory=dict)

    def mib(self, key: str) -> float:
        return self.kb.get(key, 0) / 1024


def descendants(root_pid: int) -> list[int]:
    """``root_pid`` and all its descendants (parents before children)."""
    children: dict[int, list[int]] = defaultdict(list)
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            children[_parent(int(entry))].append(int(entry))
    out, todo = [], [root_pid]
    while todo:
        pid = todo.pop(0)
        out.append(pid)
        todo += sorted(children.get(pid, []))
    return out


def role(pid: int, root_pid: int) -> str:
    """What a process is: the node or engine whose log its stdout is, else by command."""
    with contextlib.suppress(OSError):
        out = os.readlink(f"/proc/{pid}/fd/1")
        if out.endswith(".log"):
            return Path(out).stem
    if pid == root_pid:
        return "rra up (host agent, router)"
    argv = _cmdline(pid)
    if not argv:
        return "?"
    if "rra_agent.host.forkserver" in argv:
        if "/dev/null" in _stdout(pid):
            return "spare (idle fork)"
        if "rra_agent.host.forkserver" in _cmdline(_parent(pid)):
            return "fork server branch (engines)"
        return "fork server (zygote)"
    return " ".join(argv[:3])


def _stdout(pid: int) -> str:
    try:
        return os.readlink(f"/proc/{pid}/fd/1")
    except OSError:
        return ""


def _cmdline(pid: int) -> list[str]:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().decode(errors="replace").split("\0")
    except OSError:
        return []


def _parent(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return int(f.read().rsplit(")", 1)[1].split()[1])
    except (OSError, IndexError, ValueError):
        return 0


def mapping_kind(name: str) -> str:
    """A mapping of ``/proc/<pid>/smaps`` by what it holds."""
    if name.startswith("/dev/shm/") and name.endswith(".zenoh"):
        return "Zenoh shared memory (/dev/shm)"
    if name in ("", "[heap]"):
        return "heap and anonymous (Python, Rust)"
    if name.startswith("[stack"):
        return "main thread stack"
    if "zenoh" in name and name.endswith(".so"):
        return "zenoh library (zenoh.abi3.so)"
    if "libpython" in name:
        return "libpython"
    if name.startswith("["):
        return "other (" + name + ")"
    return "other files (libraries, extensions)"


def process_memory(pid: int, root_pid: int) -> Process | None:
    """The memory of one process, None if it is gone."""
    kb: dict[str, int] = defaultdict(int)
    by_kind: dict[str, int] = defaultdict(int)
    try:
        kind = ""
        with open(f"/proc/{pid}/smaps") as f:
            for line in f:
                parts = line.split()
                if "-" in parts[0] and not parts[0].endswith(":"):  # a mapping's header
                    kind = mapping_kind(parts[5] if len(parts) > 5 else "")
                elif len(parts) == 3 and parts[2] == "kB":
                    kb[parts[0][:-1]] += int(parts[1])
                    if parts[0] == "Pss:":
                        by_kind[kind] += int(parts[1])
        with open(f"/proc/{pid}/smaps_rollup") as f:  # the kernel's own split of PSS
            for line in f:
                parts = line.split()
                if parts[0] in ("Pss_Anon:", "Pss_File:", "Pss_Shmem:"):
                    kb[parts[0][:-1]] = int(parts[1])
        threads = len(os.listdir(f"/proc/{pid}/task"))
    except OSError:
        return None
    return Process(pid, role(pid, root_pid), threads, dict(kb), dict(by_kind))


def snapshot(root_pid: int) -> list[Process]:
    """Every process of the tree under ``root_pid`` (``rra up``)."""
    return [p for pid in descendants(root_pid) if (p := process_memory(pid, root_pid))]


def measure(
    package: Path, settle: float, env: dict[str, str], replicas: int = 2
) -> tuple[list[Process], int]:
    """(every process, components running) of ``rra up package``."""
    system = load_package(package).system.system
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="rra-memory-") as run_dir:
        up = subprocess.Popen(
            [sys.executable, "-m", "rra_agent", "up", str(package), "--run-dir", run_dir,
             "-q", "--connect", endpoint, "--no-multicast", "--replicas", str(replicas)],
            env={**os.environ, "RERUN_ANALYTICS": "0", **env},
        )  # fmt: skip
        client = None
        try:
            wait_until(lambda: up.poll() is not None or _listening(port), 60, "rra up listening")
            client = BusClient(BusConfig(connect=[endpoint], multicast=False), system)
            st = wait_until(lambda: _deployed(client), 120, "the deployment", interval=0.5)
            time.sleep(settle)
            return snapshot(up.pid), len(st["engine"]["running"])
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


def print_breakdown(layout: str, procs: list[Process]) -> None:
    """Per process, then the PSS of all of them by kind of mapping."""
    print(f"\n{layout}: per process (MiB)")
    keys = ("Rss", "Pss", "Pss_Anon", "Pss_File", "Pss_Shmem", "Private_Dirty")
    rows: list[list[object]] = [[p.role, p.pid, p.threads, *map(p.mib, keys)] for p in procs]
    total = [sum(p.mib(k) for p in procs) for k in keys]
    rows.append(["total", "", sum(p.threads for p in procs), *total])
    print_table(["process", "pid", "threads", "RSS", "PSS", "PSS anon", "PSS file",
                 "PSS shmem", "private dirty"], rows)  # fmt: skip
    kinds: dict[str, int] = defaultdict(int)
    for p in procs:
        for kind, kb in p.by_kind.items():
            kinds[kind] += kb
    print(f"\n{layout}: PSS of all processes by mapping (MiB)")
    ordered = sorted(((kb, kind) for kind, kb in kinds.items() if kb >= 512), reverse=True)
    print_table(["mapping", "PSS"], [[kind, kb / 1024] for kb, kind in ordered])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("package", nargs="?", default=str(ROOT / "scenarios" / "object_storing"))
    ap.add_argument("--settle", type=float, default=3.0, help="seconds to run before measuring")
    ap.add_argument("--containers", action="store_true", help="components in one container")
    ap.add_argument("--compare", action="store_true", help="both: processes and containers")
    ap.add_argument("--env", action="append", default=[], metavar="NAME=VALUE",
                    help="a variable for rra up and its processes (repeatable)")  # fmt: skip
    ap.add_argument("--replicas", type=int, default=2,
                    help="replicas of each engine (rra up --replicas; default 2)")  # fmt: skip
    args = ap.parse_args()
    env = dict(e.split("=", 1) for e in args.env)
    package = Path(args.package).resolve()
    rows = []
    with tempfile.TemporaryDirectory(prefix="rra-memory-pkg-") as tmp:
        layouts = ["processes", "one container"] if args.compare else (
            ["one container"] if args.containers else ["processes"])  # fmt: skip
        for layout in layouts:
            pkg = package if layout == "processes" else contained(package, Path(tmp) / "c")
            procs, running = measure(pkg, args.settle, env, args.replicas)
            rss, pss = (sum(p.mib(k) for p in procs) for k in ("Rss", "Pss"))
            rows.append([layout, running, len(procs), rss, pss, f"<= {GOAL_PSS_MIB:g}"])
            print_breakdown(layout, procs)
    print()
    extra = " ".join([*args.env, *([f"--replicas {args.replicas}"] if args.replicas != 2 else [])])
    extra = f" ({extra})" if extra else ""
    print(f"memory of {package.name} under rra up (every process: agent, engines, nodes){extra}")
    print_table(["layout", "components", "processes", "RSS MiB", "PSS MiB", "goal PSS MiB"],
                rows)  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
