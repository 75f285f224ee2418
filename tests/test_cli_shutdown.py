"""A normal shutdown of ``rra up`` logs no failure and leaves no process behind (also after an
engine, a fork of the fork server, was killed and started again).

A Ctrl-C in a terminal sends SIGINT to the whole foreground process group: ``rra up`` and,
unless they have a group of their own, every process it started, all at once. The host
agent must stop its nodes itself (they have their own process group), and a process still
starting (importing) is stopped without a KeyboardInterrupt traceback in its log. Checked at
the two moments a user presses Ctrl-C: while the engines start, and once the system runs.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import pytest
from conftest import RELAY, ROOT, pid_alive, wait_until

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, gather
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.engines.events import read_events
from rra_agent.host import procfs
from rra_agent.host.supervisor import State, StopPolicy, Supervisor

#: Every test here starts processes or opens Zenoh sessions (pytest -m 'not system').
pytestmark = pytest.mark.system

#: What a log of a normal shutdown must not contain.
FAILURE = re.compile(r"BACKOFF|FATAL|Traceback|lost")


class Up:
    """``rra up`` of the relay system in a session of its own, as a terminal runs it."""

    def __init__(self, tmp_path: Path) -> None:
        self.run_dir = tmp_path / "run"
        self.out = tmp_path / "up.out"
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        with self.out.open("wb") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "rra_agent", "up", str(RELAY), "--run-dir",
                 str(self.run_dir), "--connect", self.endpoint, "--lease-ms", "500"],
                stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
                env={**os.environ, "PYTHONPATH": str(ROOT), "RERUN_ANALYTICS": "0"},
                start_new_session=True,
            )  # fmt: skip

    def printed(self) -> str:
        return self.out.read_text(errors="replace")

    def pids(self) -> set[int]:
        """Every process it started (its progress lines name them) and its fork server."""
        pids = {int(p) for p in re.findall(r" pid (\d+)", self.printed())}
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit():
                continue
            try:
                cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
            except OSError:
                continue
            if f"rra_agent.host.forkserver {self.proc.pid}" in cmd or str(self.run_dir) in cmd:
                pids.add(int(entry.name))
        return pids

    def ctrl_c(self) -> int:
        """SIGINT to the whole process group, as a Ctrl-C in its terminal does (what each
        file held before is remembered: `check_clean` looks at what the shutdown wrote)."""
        self.before = {p: p.stat().st_size for p in self.run_dir.rglob("*") if p.is_file()}
        self.printed_before = len(self.printed())
        os.killpg(self.proc.pid, signal.SIGINT)
        return self.proc.wait(30)

    def kill(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()


def check_clean(up: Up, pids: set[int], since: float | None = None) -> None:
    """No failure in anything the shutdown wrote to the run folder or printed (a machine
    loaded by other work may have restarted a slow engine before), nor among the events
    from ``since`` (default: the first STOPPING); no process left."""
    files = [p for p in up.run_dir.rglob("*") if p.is_file()]
    assert files
    for path in files:
        with path.open("rb") as f:
            f.seek(up.before.get(path, 0))
            written = f.read().decode(errors="replace")
        for line in written.splitlines():
            assert not FAILURE.search(line), f"{path.relative_to(up.run_dir)}: {line}"
    printed = up.printed()[up.printed_before :]
    assert not FAILURE.search(printed), printed
    log = up.run_dir / "events.jsonl"  # none if stopped before an engine led
    states = [e for e in read_events(log) if isinstance(e, m.NodeState)] if log.exists() else []
    stop = since or min((e.stamp for e in states if e.state == "STOPPING"), default=0.0)
    for ev in states:
        assert ev.stamp < stop or ev.state not in ("BACKOFF", "FATAL", "EXITED"), ev
    wait_until(lambda: not [p for p in pids if pid_alive(p)], 10, "every process gone")


def test_ctrl_c_while_the_engines_start(tmp_path: Path) -> None:
    up = Up(tmp_path)
    try:
        # Every engine spawned (its pid printed), most still importing.
        wait_until(lambda: len(re.findall(r"STARTING pid", up.printed())) >= 6, 60,
                   "the engines spawned", interval=0.002)  # fmt: skip
        pids = up.pids()
        assert up.ctrl_c() == 0, up.printed()
    finally:
        up.kill()
    check_clean(up, pids)


def test_ctrl_c_of_a_running_system(tmp_path: Path) -> None:
    up = Up(tmp_path)
    follower: subprocess.Popen[bytes] | None = None
    bus = BusConfig(connect=[up.endpoint], lease_ms=500)
    try:
        wait_until(lambda: "Ctrl-C to stop" in up.printed(), 60, "rra up listening")
        with BusClient(bus, "relay_system") as client:

            def deployed() -> bool:
                st = gather(client, timeout=1.0)
                eng = st["engine"] or {}
                nodes = {n["node"]: n["state"] for n in st["nodes"]}
                return "sink" in eng.get("running", {}) and all(
                    s == "RUNNING" for s in nodes.values()
                )

            wait_until(deployed, 60, "the system deployed, every process running", 0.1)
        pids = up.pids()
        assert len(pids) >= 9
        followed = tmp_path / "events.out"
        with followed.open("wb") as out:
            follower = subprocess.Popen(
                [sys.executable, "-m", "rra_agent", "events", "--connect", up.endpoint],
                stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
                env={**os.environ, "PYTHONPATH": str(ROOT)},
            )  # fmt: skip
        wait_until(lambda: "following system" in followed.read_text(), 30, "rra events")
        assert up.ctrl_c() == 0, up.printed()
        # `rra events` sees the system go and ends by itself.
        assert follower.wait(30) == 0
    finally:
        up.kill()
        if follower is not None and follower.poll() is None:
            follower.kill()
    check_clean(up, pids)
    assert "rra up: all processes stopped" in up.printed()
    events = followed.read_text()
    assert "Traceback" not in events
    assert events.splitlines()[-1] == "system 'relay_system' stopped: no host agent is left"


def test_the_engines_are_forks_of_the_fork_server_and_restart_as_such(tmp_path: Path) -> None:
    """The engines share the fork server's interpreter (`rra_agent.host.forkserver`): each is
    a fork of it (its command line is the fork server's), a child of ``rra up``, writing its
    own log. Killed with SIGKILL, an engine is started again the same way; Ctrl-C then stops
    everything cleanly."""
    up = Up(tmp_path)
    try:
        wait_until(lambda: "Ctrl-C to stop" in up.printed(), 60, "rra up listening")

        def engine(name: str, old: int = 0) -> int | None:
            pids = re.findall(rf"\b{name}\s+RUNNING pid (\d+)", up.printed())
            return int(pids[-1]) if pids and int(pids[-1]) != old else None

        names = [f"{e}-{r}" for e in ("monitor", "adaptation", "resolution") for r in "ab"]
        pids = {n: wait_until(lambda n=n: engine(n), 60, f"{n} running") for n in names}
        for name, pid in pids.items():
            check_forked(up, name, pid)
        os.kill(pids["monitor-a"], signal.SIGKILL)
        again = wait_until(lambda: engine("monitor-a", pids["monitor-a"]), 60, "its restart")
        check_forked(up, "monitor-a", again)
        everything = up.pids() | {again}
        stopped = time.time()
        assert up.ctrl_c() == 0, up.printed()
    finally:
        up.kill()
    check_clean(up, everything, since=stopped)


def check_forked(up: Up, name: str, pid: int) -> None:
    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    assert b"rra_agent.host.forkserver" in cmd, cmd
    assert procfs.parent(pid) == up.proc.pid
    assert os.readlink(f"/proc/{pid}/fd/1") == str(up.run_dir / "logs" / f"{name}.log")


# ---- the supervisor: how a starting process is stopped ----------------------------------------
class FakeHost:
    name = "h"

    def __init__(self) -> None:
        self.signals: list[tuple[int, int]] = []

    def spawn(self, spec: m.NodeSpec) -> int:
        return 100

    def signal(self, pid: int, sig: int) -> None:
        self.signals.append((pid, sig))

    def probe(self, name: str, pid: int, timeout: float) -> None:
        pass


@pytest.mark.parametrize("ready", [False, True], ids=["starting", "running"])
def test_a_starting_process_is_stopped_with_sigterm(ready: bool) -> None:
    """Still starting, a Python process has no SIGINT handler of its own yet: a SIGINT would
    interrupt its imports with a traceback; SIGTERM ends it silently. A running one gets
    SIGINT (its graceful stop), then SIGTERM, then SIGKILL."""
    host = FakeHost()
    sup = Supervisor(stop=StopPolicy(sigint_timeout=1.0, sigterm_timeout=1.0))
    spec = msgspec.convert({"system": "s", "name": "n", "host": "h", "implementation": "x.Y"},
                           m.NodeSpec)  # fmt: skip
    sup.add(spec, host)
    sup.start("n", 0.0)
    if ready:
        sup.on_ready("n", 0.1)
    sup.stop("n", 0.2)
    assert sup.state("n") == State.STOPPING
    sup.tick(1.3)
    sup.tick(2.4)
    expected = [signal.SIGINT, signal.SIGTERM, signal.SIGKILL] if ready else [
        signal.SIGTERM, signal.SIGKILL]  # fmt: skip
    assert [s for _, s in host.signals] == expected
    sup.on_exit(100, -signal.SIGTERM, 2.5)
    assert sup.state("n") == State.STOPPED
