"""Start, signal and reap node processes on this machine (the host agent's hands).

A node is started as ``python -m rra_agent.node`` (Python implementations) or as its own
command (external implementations), with its spec in ``RRA_NODE_SPEC`` and the bus
configuration in ``RRA_BUS_CONFIG``; stdout and stderr go to ``<log_dir>/<node>.log``.

No orphans: on Linux every child gets ``PR_SET_PDEATHSIG = SIGKILL``, so it dies with the
process that started it even when that one is killed with SIGKILL. Children are spawned from
the thread that owns this object (the death signal is tied to the spawning thread).
"""

from __future__ import annotations

import ctypes
import os
import signal
import subprocess
import sys
from pathlib import Path

import msgspec

from rra_agent.bus.config import ENV_VAR as BUS_ENV
from rra_agent.bus.config import BusConfig
from rra_agent.bus.messages import NodeSpec
from rra_agent.node import SPEC_ENV

_PR_SET_PDEATHSIG = 1


def _die_with_parent() -> None:  # runs in the child between fork and exec
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
    except (OSError, AttributeError):
        pass


def node_command(spec: NodeSpec) -> list[str]:
    if isinstance(spec.implementation, str):
        return [sys.executable, "-m", "rra_agent.node"]
    return list(spec.implementation.command)


class LocalHost:
    """`ProcessHost` for this machine."""

    def __init__(self, name: str, bus: BusConfig, log_dir: str | Path) -> None:
        self.name = name
        self.bus = bus
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.children: dict[int, subprocess.Popen[bytes]] = {}
        self.names: dict[int, str] = {}

    def spawn(self, spec: NodeSpec) -> int:
        env = dict(os.environ)
        env[SPEC_ENV] = msgspec.json.encode(spec).decode()
        env[BUS_ENV] = self.bus.to_env()
        env.setdefault("PYTHONUNBUFFERED", "1")
        cwd = None
        if not isinstance(spec.implementation, str):
            env.update(spec.implementation.env)
            cwd = spec.implementation.cwd
        log = (self.log_dir / f"{spec.name}.log").open("ab")
        try:
            proc = subprocess.Popen(
                node_command(spec),
                env=env,
                cwd=cwd,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                preexec_fn=_die_with_parent if sys.platform == "linux" else None,
            )
        finally:
            log.close()
        self.children[proc.pid] = proc
        self.names[proc.pid] = spec.name
        return proc.pid

    def signal(self, pid: int, sig: int) -> None:
        proc = self.children.get(pid)
        if proc is not None and proc.poll() is None:
            proc.send_signal(sig)

    def poll(self, pid: int) -> int | None:
        proc = self.children.get(pid)
        if proc is None:
            return None
        return proc.poll()

    def forget_exited(self, keep: set[int]) -> None:
        """Drop the handles of exited children nobody asks about any more (``keep``)."""
        for pid, proc in list(self.children.items()):
            if pid not in keep and proc.poll() is not None:
                del self.children[pid]
                self.names.pop(pid, None)

    def running(self) -> dict[int, str]:
        return {pid: self.names[pid] for pid, p in self.children.items() if p.poll() is None}

    def kill_all(self, timeout: float = 2.0) -> None:
        """Last resort at shutdown: SIGTERM everything left, then SIGKILL, and reap."""
        for proc in self.children.values():
            if proc.poll() is None:
                proc.terminate()
        for proc in self.children.values():
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
