"""Shared fixtures: free loopback ports, a hub session, real processes that never outlive a test."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from rra_agent.bus.config import free_port

ROOT = Path(__file__).resolve().parents[1]


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


def pid_alive(pid: int) -> bool:
    """True if ``pid`` exists and is not a zombie."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return False


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
    """A BusConfig connecting to this test's hub endpoint on loopback, multicast off."""
    from rra_agent.bus.config import BusConfig

    return BusConfig(connect=[f"tcp/127.0.0.1:{hub_port}"], multicast=False, lease_ms=500)
