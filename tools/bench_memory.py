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
engines' standbys cost. ``--bytecode`` compiles rra_agent first and runs it from that
bytecode, as a wheel install does, when the environment says ``PYTHONDONTWRITEBYTECODE``
(then every process compiles the modules it imports from source: `bytecode_env`).

``--flood``: what oversized samples cost. Once the system runs, the PSS of all its processes
before, after three 10 MB samples on each of four keys (two data topics that the Context
Monitor and components read, a measurement, the selection) and after one 11 MB well-formed
``LaserScan`` (1.2 million ranges) on the laser's topic, each after ``--settle`` seconds.
Measured twice: with the routers' limits (Zenoh's low-pass filter and largest reassembled
message, `rra_agent.bus.counters.router_limits`) and with them switched off through
``--bus-config`` (every process then receives the samples and only its own Python-side check
drops them).

    .venv/bin/python tools/bench_memory.py [scenarios/object_storing] [--compare] [--env N=V]
    .venv/bin/python tools/bench_memory.py --flood
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
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _benchutil import interrupt, print_table

from rra_agent.bus.client import BusClient, gather, wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.host import procfs
from rra_agent.package.loader import load_package

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
    return procfs.parent(pid) or 0


def pss_kib(pid: int) -> int:
    """The PSS of one process in KiB (``/proc/<pid>/smaps_rollup``), 0 if it is gone."""
    try:
        with open(f"/proc/{pid}/smaps_rollup") as f:
            return next((int(line.split()[1]) for line in f if line.startswith("Pss:")), 0)
    except OSError:
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


@contextlib.contextmanager
def running(
    package: Path, env: dict[str, str], replicas: int = 2, extra: tuple[str, ...] = ()
) -> Iterator[tuple[subprocess.Popen, BusClient, dict]]:
    """``rra up package`` deployed: (its process, a client of its bus, its status)."""
    system = load_package(package).system.system
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with tempfile.TemporaryDirectory(prefix="rra-memory-") as run_dir:
        up = subprocess.Popen(
            [sys.executable, "-m", "rra_agent", "up", str(package), "--run-dir", run_dir,
             "-q", "--connect", endpoint, "--no-multicast", "--replicas", str(replicas),
             *extra],
            env={**os.environ, "RERUN_ANALYTICS": "0", **env},
        )  # fmt: skip
        client = None
        try:
            wait_until(lambda: up.poll() is not None or _listening(port), 60, "rra up listening")
            client = BusClient(BusConfig(connect=[endpoint], multicast=False), system)
            st = wait_until(lambda: _deployed(client), 120, "the deployment", interval=0.5)
            yield up, client, st
        finally:
            if client is not None:
                client.close()
            interrupt(up)


def measure(
    package: Path, settle: float, env: dict[str, str], replicas: int = 2
) -> tuple[list[Process], int]:
    """(every process, components running) of ``rra up package``."""
    with running(package, env, replicas) as (up, _client, st):
        time.sleep(settle)
        return snapshot(up.pid), len(st["engine"]["running"])


def flood_keys(client: BusClient, package: Path) -> tuple[list[str], str]:
    """Four keys with readers (a battery-like and a laser-like topic, a measurement, the
    selection) and the laser's topic, of an object-storing-like package."""
    k = client.keys
    names = [meas.name for meas in load_package(package).measurements.measurements]
    laser = k.data("laser_scanner/scan")
    return [k.data("robot_driver/battery"), laser, k.ctx(names[0]), k.selection], laser


def laser_scan(size: int) -> bytes:
    """A well-formed LaserScan of about ``size`` bytes (msgpack floats are 9 bytes)."""
    from rra_agent.bus.data import encode_data

    n = size // 9
    return encode_data({"frame_id": "base_laser", "angle_min": -2.0, "angle_max": 2.0,
                        "angle_increment": 4.0 / n, "range_min": 0.05, "range_max": 10.0,
                        "ranges": [1.5] * n})  # fmt: skip


#: What a flood phase sends: three 10 MB samples on each of four keys, or one 11 MB scan.
PHASES = {"4x3x10MB": "three 10 MB samples on each of four keys", "11MB": "an 11 MB LaserScan",
          "none": "nothing (the drift)"}  # fmt: skip


def measure_flood(
    package: Path, settle: float, env: dict[str, str], *, router_limits: bool, phase: str
) -> tuple[float, float]:
    """PSS (MiB) of the system before and ``settle`` s after a phase of `PHASES`."""
    import zenoh

    from rra_agent.bus.counters import MAX_MESSAGE_SIZE

    extra: tuple[str, ...] = ()
    with tempfile.TemporaryDirectory(prefix="rra-memory-bus-") as tmp:
        if not router_limits:  # the routers' limits off: only the processes' own checks
            off = {"zenoh": {"low_pass_filter": [], MAX_MESSAGE_SIZE: 1 << 30}}
            (Path(tmp) / "bus.yaml").write_text(yaml.safe_dump(off))
            extra = ("--bus-config", str(Path(tmp) / "bus.yaml"))
        with running(package, env, extra=extra) as (up, client, _st):
            keys, laser = flood_keys(client, package)
            block = zenoh.CongestionControl.BLOCK
            scan = laser_scan(11_000_000)
            time.sleep(settle)
            before = total_pss(up.pid)
            if phase == "4x3x10MB":
                big = b"\x00" * 10_000_000
                for _ in range(3):
                    for key in keys:
                        client.session.put(key, big, congestion_control=block)
            elif phase == "11MB":
                client.session.put(laser, scan, congestion_control=block)
            time.sleep(settle)
            return before, total_pss(up.pid)


def total_pss(root_pid: int) -> float:
    """The PSS of ``rra up`` and every process under it, MiB."""
    return sum(pss_kib(pid) for pid in descendants(root_pid)) / 1024


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


def bytecode_env(prefix: Path) -> dict[str, str]:
    """Variables under which ``rra up`` imports rra_agent from bytecode compiled here first
    (into ``prefix``), as a wheel installs it: with ``PYTHONDONTWRITEBYTECODE`` set and no
    ``__pycache__`` (an editable checkout), every process that imports a module compiles it
    from source, and the compiler's freed memory stays in the heap of the zygote, the
    engines' branch and ``rra up``, where the forked processes' allocations land and copy it."""
    env = {"PYTHONDONTWRITEBYTECODE": "", "PYTHONPYCACHEPREFIX": str(prefix)}
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(ROOT / "rra_agent")],
                   env={**os.environ, **env}, check=True, stdout=subprocess.DEVNULL)  # fmt: skip
    return env


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
    ap.add_argument("--flood", action="store_true",
                    help="PSS before and after floods of oversized samples")  # fmt: skip
    ap.add_argument("--bytecode", action="store_true",
                    help="rra_agent's modules from compiled bytecode, as installed (see below)")
    args = ap.parse_args()
    env = dict(e.split("=", 1) for e in args.env)
    package = Path(args.package).resolve()
    if args.flood:
        return flood_report(package, args.settle, env)
    rows = []
    with tempfile.TemporaryDirectory(prefix="rra-memory-pkg-") as tmp:
        if args.bytecode:
            env.update(bytecode_env(Path(tmp) / "pycache"))
        layouts = ["processes", "one container"] if args.compare else (
            ["one container"] if args.containers else ["processes"])  # fmt: skip
        for layout in layouts:
            pkg = package if layout == "processes" else contained(package, Path(tmp) / "c")
            procs, running = measure(pkg, args.settle, env, args.replicas)
            rss, pss = (sum(p.mib(k) for p in procs) for k in ("Rss", "Pss"))
            rows.append([layout, running, len(procs), rss, pss, f"<= {GOAL_PSS_MIB:g}"])
            print_breakdown(layout, procs)
    print()
    extra = " ".join([*args.env, *([f"--replicas {args.replicas}"] if args.replicas != 2 else []),
                      *(["--bytecode"] if args.bytecode else [])])  # fmt: skip
    extra = f" ({extra})" if extra else ""
    print(f"memory of {package.name} under rra up (every process: agent, engines, nodes){extra}")
    print_table(["layout", "components", "processes", "RSS MiB", "PSS MiB", "goal PSS MiB"],
                rows)  # fmt: skip
    return 0


def flood_report(package: Path, settle: float, env: dict[str, str]) -> int:
    rows = []
    for name, on in (("routers' limits (Zenoh)", True), ("Python-side checks only", False)):
        for phase in PHASES if on else ("4x3x10MB", "11MB"):
            before, after = measure_flood(package, settle, env, router_limits=on, phase=phase)
            rows.append([name, PHASES[phase], before, after, after - before])
    print(f"\nPSS of {package.name} under rra up (MiB), a fresh system per row:")
    print_table(["limits", "sent", "before", "after", "grew"], rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
