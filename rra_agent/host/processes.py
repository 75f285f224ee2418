"""Start, signal and reap node processes on this machine (the host agent's hands).

A node is started as ``python -m rra_agent.node`` (Python implementations) or as its own
command (external implementations), with its spec in ``RRA_NODE_SPEC`` and the bus
configuration in ``RRA_BUS_CONFIG``; stdout and stderr go to ``<log_dir>/<node>.log``.

Python nodes are forked from a pre-imported interpreter (`rra_agent.host.forkserver`),
which saves each node ~70 ms of CPU at start.

No orphans: on Linux every child gets ``PR_SET_PDEATHSIG = SIGKILL``, so it dies with the
process that started it even when that one is killed with SIGKILL. Children are spawned from
the thread that owns this object (the death signal is tied to the spawning thread).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec

from rra_agent.bus.config import ENV_VAR as BUS_ENV
from rra_agent.bus.config import BusConfig
from rra_agent.bus.messages import NodeSpec
from rra_agent.node import SPEC_ENV

if TYPE_CHECKING:
    from rra_agent.host.forkserver import ForkServer

_PR_SET_PDEATHSIG = 1


def die_with_parent() -> None:
    """Ask for SIGKILL when the parent dies (Linux; call in the child after fork)."""
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
    """`ProcessHost` for this machine.

    Python nodes are forked from a pre-imported interpreter (`ForkServer`) unless
    ``fork_server`` is False (or ``RRA_FORK_SERVER=0``); external commands are started with
    ``Popen``. Both kinds are polled, signalled and reaped the same way.
    """

    def __init__(
        self,
        name: str,
        bus: BusConfig,
        log_dir: str | Path,
        *,
        fork_server: bool | None = None,
        preload: Iterable[str] = (),
    ) -> None:
        self.name = name
        self.bus = bus
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.children: dict[int, subprocess.Popen[bytes]] = {}
        self.names: dict[int, str] = {}
        if fork_server is None:
            fork_server = os.environ.get("RRA_FORK_SERVER", "1") != "0"
        self._fork_server_wanted = fork_server
        self._preload = tuple(preload)
        self.zygote: ForkServer | None = None

    def _env(self, spec: NodeSpec) -> dict[str, str]:
        env = {SPEC_ENV: msgspec.json.encode(spec).decode(), BUS_ENV: self.bus.to_env()}
        env.setdefault("PYTHONUNBUFFERED", "1")
        if not isinstance(spec.implementation, str):
            env.update(spec.implementation.env)
        return env

    def spawn(self, spec: NodeSpec) -> int:
        log_path = self.log_dir / f"{spec.name}.log"
        if isinstance(spec.implementation, str) and self._fork_server_wanted:
            if self.zygote is None:
                from rra_agent.host.forkserver import ForkServer

                self.zygote = ForkServer(self._preload)
            pid = self.zygote.spawn(spec, self._env(spec), str(log_path))
        else:
            pid = self._popen(spec, log_path)
        self.names[pid] = spec.name
        return pid

    def _popen(self, spec: NodeSpec, log_path: Path) -> int:
        env = {**os.environ, **self._env(spec)}
        cwd = None if isinstance(spec.implementation, str) else spec.implementation.cwd
        log = log_path.open("ab")
        try:
            proc = subprocess.Popen(
                node_command(spec),
                env=env,
                cwd=cwd,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                preexec_fn=die_with_parent if sys.platform == "linux" else None,
            )
        finally:
            log.close()
        self.children[proc.pid] = proc
        return proc.pid

    def signal(self, pid: int, sig: int) -> None:
        if self.poll(pid) is None and pid in self.names:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)

    def poll(self, pid: int) -> int | None:
        proc = self.children.get(pid)
        if proc is not None:
            return proc.poll()
        if self.zygote is not None and pid in self.zygote.children:
            return self.zygote.poll(pid)
        return None

    def forget_exited(self, keep: set[int]) -> None:
        """Drop the handles of exited children nobody asks about any more (``keep``)."""
        for pid in list(self.names):
            if pid not in keep and self.poll(pid) is not None:
                self.children.pop(pid, None)
                if self.zygote is not None:
                    self.zygote.children.pop(pid, None)
                del self.names[pid]

    def running(self) -> dict[int, str]:
        return {pid: n for pid, n in self.names.items() if self.poll(pid) is None}

    def kill_all(self, timeout: float = 2.0) -> None:
        """Last resort at shutdown: SIGTERM everything left, then SIGKILL, and reap."""
        alive = list(self.running())
        for pid in alive:
            self.signal(pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and any(self.poll(p) is None for p in alive):
            time.sleep(0.01)
        for pid in alive:
            self.signal(pid, signal.SIGKILL)
        for proc in self.children.values():
            proc.wait()
        if self.zygote is not None:
            self.zygote.close()
