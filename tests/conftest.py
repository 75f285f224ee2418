"""Shared fixtures: free loopback ports, a hub session, real processes that never outlive a test.

The adversity options (``--cpu-hog``, ``--hostile``) are the rootdir's conftest.py's: every
path the suite runs has them."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, gather, set_params, wait_until
from rra_agent.bus.config import free_port
from rra_agent.bus.keys import Keys
from rra_agent.engines.events import read_events
from rra_agent.host import procfs

ROOT = Path(__file__).resolve().parents[1]


#: A test using one of these fixtures starts processes (or opens Zenoh sessions): `system`.
SYSTEM_FIXTURES = frozenset({"procs", "system", "bus", "hub_port", "hog", "pytester"})


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark `system` every test that starts processes: by its fixtures, and every scenario
    case (``pytest -m "not system"`` runs the in-process suite)."""
    for item in items:
        fixtures = set(getattr(item, "fixturenames", ()))
        if fixtures & SYSTEM_FIXTURES or item.path.name.endswith(".scenario.yaml"):
            item.add_marker(pytest.mark.system)


@pytest.fixture(autouse=True)
def in_process_only(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> None:
    """A test not marked `system` may not start a process of this project (``rra``, an
    ``rra_agent`` module, a tool) or open a Zenoh session: the in-process suite stays fast,
    and a test that forgets its mark says so. (Libraries may still probe with a process of
    their own: glfw does when mujoco is imported.)"""
    if request.node.get_closest_marker("system") is not None:
        return
    import zenoh

    def refuse() -> AssertionError:
        return AssertionError(
            f"{request.node.nodeid} starts a process or opens a Zenoh session: "
            "mark it @pytest.mark.system"
        )

    popen = subprocess.Popen

    class Guarded(popen):  # type: ignore[misc, valid-type]
        def __init__(self, args: object, *rest: object, **kw: object) -> None:
            text = " ".join(map(str, args)) if isinstance(args, list | tuple) else str(args)
            if "rra_agent" in text or f"{os.sep}tools{os.sep}" in text or text.startswith("rra"):
                raise refuse()
            super().__init__(args, *rest, **kw)

    def no_session(*args: object, **kwargs: object) -> None:
        raise refuse()

    monkeypatch.setattr(subprocess, "Popen", Guarded)
    monkeypatch.setattr(zenoh, "open", no_session)


def stop_process(proc: subprocess.Popen) -> None:
    """SIGINT, then SIGKILL if it has not exited within 10 s."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@pytest.fixture
def hog() -> Iterator[subprocess.Popen]:
    """A busy loop on both cores for the length of the test."""
    proc = subprocess.Popen([sys.executable, str(ROOT / "tools" / "cpuhog.py"), "2"])
    yield proc
    stop_process(proc)


MINI = Path(__file__).parent / "data" / "mini"


def copy_mini(tmp_path: Path) -> Path:
    """A private copy of the small complete package tests/data/mini, to corrupt."""
    root = tmp_path / "mini"
    shutil.copytree(MINI, root, ignore=shutil.ignore_patterns("__pycache__"))
    return root


def plant(root: Path, file: str, old: str, new: str) -> str:
    """Replace the single occurrence of ``old`` in ``file`` by ``new``; the new text."""
    path = root / file
    text = path.read_text()
    assert text.count(old) == 1, f"{old!r} occurs {text.count(old)} times in {file}"
    text = text.replace(old, new)
    path.write_text(text)
    return text


def position(text: str, token: str, nth: int = 1) -> tuple[int, int]:
    """1-based (line, col) of the ``nth`` occurrence of ``token`` in ``text``."""
    idx = -1
    for _ in range(nth):
        idx = text.index(token, idx + 1)
    line = text.count("\n", 0, idx) + 1
    col = idx - (text.rfind("\n", 0, idx) + 1) + 1
    return line, col


def ok(reply: m.Reply) -> object:
    """The result of a request that must have succeeded."""
    assert isinstance(reply, m.Ok), reply
    return reply.result


def pid_alive(pid: int) -> bool:
    """True if ``pid`` exists and is not a zombie."""
    return procfs.state(pid) not in ("", "Z")


class Procs:
    """Processes a test starts; all are killed at teardown, and none may survive it."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.started: list[subprocess.Popen[bytes]] = []
        self.watched: set[int] = set()

    def spawn(self, args: list[str], env: dict[str, str] | None = None, name: str = "proc"):
        log = (self.tmp / f"{name}.log").open("ab")
        proc = subprocess.Popen(
            args,
            env={**os.environ, "RERUN_ANALYTICS": "0", **(env or {})},
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
        )
        log.close()
        self.started.append(proc)
        return proc

    def python(self, module: str, *args: str, name: str = "proc", env=None):
        return self.spawn([sys.executable, "-m", module, *args], env=env, name=name)

    def watch(self, pid: int | None) -> None:
        """Also check at teardown that this (grand)child ``pid`` is gone."""
        if pid:
            self.watched.add(pid)

    def log(self, name: str) -> str:
        p = self.tmp / f"{name}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def teardown(self) -> list[int]:
        for p in self.started:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in self.started:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        return [pid for pid in self.watched if pid_alive(pid)]


@pytest.fixture
def procs(tmp_path: Path) -> Iterator[Procs]:
    p = Procs(tmp_path)
    yield p
    survivors = p.teardown()
    assert not survivors, f"processes outlived the test: {survivors}"


@pytest.fixture
def hub_port() -> int:
    return free_port()


@pytest.fixture
def bus(hub_port: int):
    """A BusConfig connecting to this test's hub endpoint on loopback, multicast off. The
    test's own session keeps a 500 ms lease (the systems it starts run with the shipped
    one): with the 2 s lease, test_host_agent's 17 MiB sample was lost before the node
    counted it in half the runs under --cpu-hog (its publisher drops under congestion)."""
    from rra_agent.bus.config import BusConfig

    return BusConfig(connect=[f"tcp/127.0.0.1:{hub_port}"], multicast=False, lease_ms=500)


# ---- a whole system: `rra up` of tests/data/relay_system ---------------------------------------
#: A Ticker ``source`` whose value is the measurement Level; Level above 5 selects Filtered
#: (swap ``direct`` -> ``filtered``, rewire ``sink``), and the CV Gain follows Level into
#: ``sink.offset``.
RELAY = Path(__file__).parent / "data" / "relay_system"
RELAY_KEYS = Keys("relay_system")


def listening(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


def run_rra(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """``python -m rra_agent ARGS`` of this checkout, to completion (60 s at most)."""
    return subprocess.run(
        [sys.executable, "-m", "rra_agent", *args],
        capture_output=True,
        text=True,
        timeout=60,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        cwd=cwd,
        check=False,
    )


def tcp_peers(pid: int, netns: str | None = None) -> set[int]:
    """Remote TCP ports of the established connections of process ``pid`` (from ``ss``)."""
    cmd = ["ss", "-Htnp", "state", "established"]
    if netns:
        cmd = ["ip", "netns", "exec", netns, *cmd]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    return {
        int(line.split()[3].rsplit(":", 1)[1]) for line in out.splitlines() if f"pid={pid}," in line
    }


class System:
    def __init__(
        self, procs, bus, run_dir: Path, package: Path, *extra: str, hostile: bool = False,
        name: str = "relay_system", ready: str = "sink",
    ) -> None:  # fmt: skip
        self.procs = procs
        self.run_dir = run_dir
        self.proc = procs.python(
            "rra_agent", "up", str(package), "--run-dir", str(run_dir), "-q",
            "--connect", bus.connect[0], "--no-multicast", *extra,
            name="up",
        )  # fmt: skip
        # A loaded machine can take many seconds to start `rra up`: connect once it listens.
        port = int(bus.connect[0].rsplit(":", 1)[1])
        wait_until(lambda: self.proc.poll() is not None or listening(port), 60,
                   "rra up listening", interval=0.02)  # fmt: skip
        self.client = BusClient(bus, name)
        if hostile:
            procs.spawn([sys.executable, str(ROOT / "tools" / "hostile.py"), bus.connect[0],
                         name], name="hostile")  # fmt: skip
        self.status = self.wait(lambda s: s["engine"] and not s["engine"]["failed"]
                                and ready in s["engine"]["running"], "deployment")  # fmt: skip

    def gather(self) -> dict:
        st = gather(self.client, timeout=1.0)
        for n in st["nodes"]:
            self.procs.watch(n.get("pid"))
        return st

    def wait(self, pred, what: str, timeout: float = 30.0) -> dict:
        def check():
            st = self.gather()
            return st if pred(st) else None

        try:
            return wait_until(check, timeout, what, interval=0.05)
        except TimeoutError:
            raise AssertionError(f"{what}: not reached; up log:\n{self.procs.log('up')}") from None

    def node(self, st: dict, name: str) -> dict:
        """A node as the host agents report it (state ABSENT when no host agent does)."""
        absent = {"node": name, "state": "ABSENT", "pid": None, "host": None, "restarts": 0}
        return next((n for n in st["nodes"] if n["node"] == name), absent)

    def ctl(self, node: str, req: m.NodeRequest) -> m.Reply:
        wait_until(lambda: node in {n for _, n in self.client.alive()}, 10, f"{node}'s token")
        return self.client.node(node, req)

    def set_level(self, value: float) -> None:
        """As an operator does (``rra param``): through the Run-time Resolution Engine."""
        set_params(self.client, "source", {"value": value})

    def leader(self, st: dict, role: str = "resolution") -> str:
        if role == "resolution":
            leader = (st.get("engine") or {}).get("leader") or ["", ""]
            return leader[1]
        reply = self.client.request(RELAY_KEYS.engine_ctl(role), m.Status(), 2.0)
        assert isinstance(reply, m.Ok), reply
        return reply.result["leader"][1]

    def events(self) -> list:
        return read_events(self.run_dir / "events.jsonl")

    def stop(self) -> int:
        self.client.close()
        self.proc.send_signal(signal.SIGINT)
        return self.proc.wait(30)


@pytest.fixture
def system(procs, bus, tmp_path, request):
    """Start ``rra up`` of a package (default: tests/data/relay_system) in real processes
    (with a hostile client on its bus under ``--hostile``)."""
    started: list[System] = []
    hostile = request.config.getoption("--hostile")

    def start(package: Path = RELAY, *extra: str, **kw: str) -> System:
        s = System(procs, bus, tmp_path / "run", package, *extra, hostile=hostile, **kw)
        started.append(s)
        return s

    yield start
    for s in started:
        if s.proc.poll() is None:
            assert s.stop() == 0


def package_copy(tmp_path: Path) -> Path:
    pkg = tmp_path / "pkg"
    shutil.copytree(RELAY, pkg)
    return pkg


def edit_text(pkg: Path, file: str, old: str, new: str) -> str:
    """Replace the one occurrence of ``old`` in ``pkg/file`` (a model edited by hand)."""
    text = (pkg / file).read_text()
    assert text.count(old) == 1, old
    text = text.replace(old, new)
    (pkg / file).write_text(text)
    return text


def edit_yaml(path: Path, fn) -> None:
    data = yaml.safe_load(path.read_text())
    fn(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
