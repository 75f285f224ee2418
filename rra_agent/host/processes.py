"""The host agent's process table: start, signal, reap and read the heartbeats of nodes.

A node is started from the fork server (`rra_agent.host.forkserver`): a Python node runs
`rra_agent.node.run_node` in a pre-imported interpreter, an external command is ``exec``ed.
Either way the node becomes a direct child of this process (a child subreaper), so its exit
is *reaped here*: `reap` returns every exit since the last call, and the host agent calls it
whenever SIGCHLD wakes its loop, so a death is known at once, never from a lease. Each node
gets its spec in ``RRA_NODE_SPEC``, the bus configuration in ``RRA_BUS_CONFIG``, a heartbeat
slot in ``RRA_HEARTBEAT`` (`rra_agent.bus.heartbeat`), its output in ``<log_dir>/<node>.log``
and the file for its failure report in ``RRA_FAILURE_REPORT`` (``<log_dir>/<node>.failure``,
`rra_agent.bus.failure`), read when it is reaped (``failures``; for an external command that
failed, the last lines of its output instead).

A command among ``forked`` (the host agent's own ``python -m MODULE ...`` processes: ``rra
up``'s engines) is run in the forked process, not ``exec``ed
(`rra_agent.host.forkserver.run_main`): it shares the zygote's imported modules and what
MODULE prepared there.

If the fork server dies, the nodes go on: `reap` reports it (``zygote_exits``) and the next
spawn starts a new one. ``RRA_FORK_SERVER=0`` starts every node as its own command instead
(``python -m rra_agent.node``), also a direct child.

No orphans: every node asks for SIGKILL when this process dies (``PR_SET_PDEATHSIG``).
Children are spawned from the thread that owns this object (the death signal is tied to the
spawning thread): the host agent's main thread.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import msgspec

from rra_agent import trace
from rra_agent.bus import failure
from rra_agent.bus import heartbeat as hb
from rra_agent.bus.config import ENV_VAR as BUS_ENV
from rra_agent.bus.config import BusConfig
from rra_agent.bus.keys import check_chunk
from rra_agent.bus.messages import SPEC_ENV, Failure, NodeSpec
from rra_agent.host import gate, scheduling
from rra_agent.host.forkserver import (
    ForkServer,
    ForkServerError,
    become_subreaper,
    die_with_parent,
    python_module,
)
from rra_agent.host.procfs import state as process_state
from rra_agent.models.system import CONTAINER

#: ``probe(name, pid, timeout)``: a direct probe of a node (answered through the supervisor).
Prober = Callable[[str, int, float], None]
#: Ends of a process that say nothing about its code (stopped, or killed, by someone):
#: no output is read for them.
_QUIET_SIGNALS = frozenset({-signal.SIGKILL, -signal.SIGTERM, -signal.SIGINT})


def _preexec(spec: NodeSpec) -> Callable[[], None]:
    """In the exec'd child, before the exec: die with the host agent, a process group of
    its own (a Ctrl-C in the terminal reaches the host agent only, which stops its nodes in
    order; not every node at once, behind its back), take the component's scheduling (a
    refusal goes to the node's log, which is already its stderr)."""

    def setup() -> None:
        die_with_parent()
        os.setpgid(0, 0)
        for problem in scheduling.apply(spec.scheduling):
            os.write(2, f"rra node {spec.name}: scheduling: {problem}\n".encode())

    return setup


def is_external(spec: NodeSpec) -> bool:
    """Whether a node is an external command run as it is (``exec``ed): a program of the
    wire protocol. A ROS 2 executable is run by a node of ours that speaks for it
    (`rra_agent.node.ros2`), like a Python node."""
    if isinstance(spec.implementation, str):
        return False
    return spec.ros2 is None or not spec.ros2.executable


def node_command(spec: NodeSpec) -> list[str]:
    if not is_external(spec):
        return [sys.executable, "-m", "rra_agent.node"]
    return list(spec.implementation.command)  # type: ignore[union-attr]


def _status(raw: int) -> int:
    """A wait status as `subprocess.Popen.returncode` (negative: killed by that signal)."""
    return -os.WTERMSIG(raw) if os.WIFSIGNALED(raw) else os.WEXITSTATUS(raw)


class LocalHost:
    """`ProcessHost` for this machine."""

    def __init__(
        self,
        name: str,
        bus: BusConfig,
        log_dir: str | Path,
        *,
        fork_server: bool | None = None,
        preload: Iterable[str] = (),
        forked: Iterable[Sequence[str]] = (),
        reap_orphans: bool = False,
        prober: Prober | None = None,
    ) -> None:
        self.name = name
        self.bus = bus
        #: Variables every child gets on top of its own (e.g. the run's Rerun configuration).
        self.extra_env: dict[str, str] = {}
        #: The bus configuration of each child (its identity: engine or node, its Zenoh id).
        self.bus_for: Callable[[NodeSpec], BusConfig] = lambda spec: self.bus
        #: Variables of one child's own (e.g. the Zenoh session configuration file of a ROS 2
        #: executable on a bus with certificates), made when it is spawned.
        self.env_for: Callable[[NodeSpec], dict[str, str]] = lambda spec: {}
        #: The one bus configuration of every node of this host, if they have one (no
        #: per-node identity): the fork server's spares open their sessions with it ahead
        #: (``RRA_SPARE_SESSION=0``: not).
        self.spare_bus: BusConfig | None = None
        #: How a node is to start gated (`rra_agent.host.gate`), None if it is not: the host
        #: agent says so for the replacement of a node still stopping.
        self.gate_for: Callable[[NodeSpec], gate.Gated | None] = lambda spec: None
        #: Gated nodes whose gate `open_gate` is to open: pid -> node name.
        self.gated: dict[int, str] = {}
        self.log_dir = Path(log_dir)
        self.log_dir.mkdir(parents=True, exist_ok=True)
        #: Live node processes: pid -> node name.
        self.names: dict[int, str] = {}
        #: Why each process reaped since the host agent last looked failed, by pid: its
        #: report, or for an external command the end of its output (`failure`).
        self.failures: dict[int, Failure] = {}
        #: Live external commands: pid -> where their output began in their log.
        self._commands: dict[int, int] = {}
        self._popen: dict[int, subprocess.Popen[bytes]] = {}
        if fork_server is None:
            fork_server = os.environ.get("RRA_FORK_SERVER", "1") != "0"
        self._fork_server_wanted = fork_server
        #: Commands ``python -m MODULE ...`` run in a fork of the zygote (which imports
        #: MODULE and calls its ``warm_up``), not in a new interpreter.
        self.forked = [list(c) for c in forked if python_module(list(c)) is not None]
        self._preload = tuple(preload)
        self.zygote: ForkServer | None = None
        #: Exit statuses of fork servers reaped since the host agent last looked.
        self.zygote_exits: list[int] = []
        self.zygote_starts = 0
        #: Reap every child, not only ours (the host agent process: orphans of node
        #: subprocesses are re-parented here and must not stay zombies).
        self.reap_orphans = reap_orphans
        self.heartbeats = hb.HeartbeatTable()
        self.prober = prober
        if fork_server and not become_subreaper():
            self._fork_server_wanted = False  # nodes would not be our children: exec them

    # ---- ProcessHost -------------------------------------------------------------------
    def spawn(self, spec: NodeSpec) -> int:
        check_chunk(spec.name, "node name")  # also a file name: no '/', no '..'
        log_path = self.log_path(spec.name)
        with contextlib.suppress(OSError):  # a report left by an earlier run is not this one's
            os.unlink(self.report_path(spec.name))
        env = self._env(spec)
        external = is_external(spec)
        offset = log_path.stat().st_size if log_path.exists() else 0
        if self._fork_server_wanted:
            argv = node_command(spec) if external else None
            cwd = spec.implementation.cwd if external else None  # type: ignore[union-attr]
            main = python_module(argv) if argv in self.forked else None
            gated = self.gate_for(spec) if self.can_gate(spec) else None
            after = gated.after if gated is not None else None
            pid = self._zygote().spawn(
                spec, env, str(log_path), argv=argv, cwd=cwd, main=main,
                gate=gated is not None, after=after,
            )  # fmt: skip
            if gated is not None and after is None:
                self.gated[pid] = spec.name
        else:
            pid = self._exec(spec, env, log_path)
        self.names[pid] = spec.name
        if external:
            self._commands[pid] = offset
        return pid

    def can_gate(self, spec: NodeSpec) -> bool:
        """Whether ``spec`` can start gated: a Python node of the Node SDK forked by the fork
        server (not a command, a container or a ROS 2 executable, which run on their own)."""
        return (
            self._fork_server_wanted
            and isinstance(spec.implementation, str)
            and spec.implementation != CONTAINER
            and not (spec.ros2 is not None and spec.ros2.executable)
        )

    def open_gate(self, name: str) -> None:
        """The node ``name`` replaces is gone: let the gated node ``name`` run its code
        (nothing if it is not waiting, or if it watches that node's end itself)."""
        trace.mark("agent:gate", name)
        for pid in [p for p, n in self.gated.items() if n == name]:
            del self.gated[pid]
            gate.open_gate(pid)

    def log_path(self, name: str) -> Path:
        """Where a node's output goes (its traceback, if it fails)."""
        return self.log_dir / f"{name}.log"

    def report_path(self, name: str) -> Path:
        """Where a node leaves its failure report (``RRA_FAILURE_REPORT``)."""
        return self.log_dir / f"{name}.failure"

    def signal(self, pid: int, sig: int) -> None:
        if pid in self.names:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)

    def probe(self, name: str, pid: int, timeout: float) -> None:
        if self.prober is not None:
            self.prober(name, pid, timeout)

    # ---- the rest of the host agent's needs ---------------------------------------------
    def reap(self) -> list[tuple[int, int]]:
        """(pid, status) of every node that ended since the last call (SIGCHLD or tick)."""
        out: list[tuple[int, int]] = []
        if self.reap_orphans:
            while True:
                try:
                    pid, raw = os.waitpid(-1, os.WNOHANG)
                except ChildProcessError:
                    break
                if pid == 0:
                    break
                self._exited(pid, _status(raw), out)
        else:
            for pid in [*self.names, *([self.zygote.pid] if self.zygote else [])]:
                try:
                    done, raw = os.waitpid(pid, os.WNOHANG)
                except ChildProcessError:
                    continue
                if done:
                    self._exited(pid, _status(raw), out)
        return out

    def _exited(self, pid: int, status: int, out: list[tuple[int, int]]) -> None:
        if self.zygote is not None and pid == self.zygote.pid:
            self.zygote.exited(status)
            self.zygote_exits.append(status)
            self.zygote = None
            return
        name = self.names.pop(pid, None)
        self.gated.pop(pid, None)
        proc = self._popen.pop(pid, None)
        if proc is not None:
            proc.returncode = status
        start = self._commands.pop(pid, None)
        if name is not None:
            found = self._failure(name, status, start)
            if found is not None:
                self.failures[pid] = found
            out.append((pid, status))

    def _failure(self, name: str, status: int, output_start: int | None) -> Failure | None:
        """The report a node left, or for an external command that failed (not stopped or
        killed by someone) the last lines of its output; with the log that holds it all."""
        log = str(self.log_path(name).resolve())
        report = failure.take_report(self.report_path(name))
        if report is not None:
            return msgspec.structs.replace(report, log=report.log or log)
        if output_start is None or status == 0 or status in _QUIET_SIGNALS:
            return None
        text = failure.tail(log, output_start)
        return Failure(message=text, stamp=time.time(), log=log) if text else None

    def beats(self) -> dict[str, hb.Beat]:
        return self.heartbeats.read_all()

    def forget(self, name: str) -> None:
        """A node no longer supervised: free its heartbeat slot."""
        self.heartbeats.release(name)

    def running(self) -> dict[int, str]:
        return dict(self.names)

    def kill_all(self, timeout: float = 2.0) -> None:
        """Last resort at shutdown: SIGTERM everything left, then SIGKILL, and reap."""
        alive = list(self.names)
        for pid in alive:
            self.signal(pid, signal.SIGTERM)
        deadline = time.monotonic() + timeout
        while self.names and time.monotonic() < deadline:
            self.reap()
            time.sleep(0.01)
        for pid in list(self.names):
            self.signal(pid, signal.SIGKILL)
        while self.names and time.monotonic() < deadline + 2.0:
            self.reap()
            time.sleep(0.01)
        if self.zygote is not None:
            self.zygote.close()
            self.zygote = None
        self.heartbeats.close()

    # ---- internals ---------------------------------------------------------------------
    def _zygote(self) -> ForkServer:
        if self.zygote is None or self.zygote.dead:
            ahead = os.environ.get("RRA_SPARE_SESSION", "1") != "0"
            self.zygote = ForkServer(
                self._preload,
                pass_fds=[self.heartbeats.fd],
                mains=self.forked,
                spare_bus=self.spare_bus.to_env() if self.spare_bus and ahead else None,
            )
            self.zygote_starts += 1
        return self.zygote

    def _env(self, spec: NodeSpec) -> dict[str, str]:
        env = {
            SPEC_ENV: msgspec.json.encode(spec).decode(),
            BUS_ENV: self.bus_for(spec).to_env(),
            hb.ENV: self.heartbeats.allocate(spec.name),
            failure.REPORT_ENV: str(self.report_path(spec.name).resolve()),
            "PYTHONUNBUFFERED": "1",
            **self.extra_env,
            **self.env_for(spec),
        }
        if not isinstance(spec.implementation, str):
            env.update(spec.implementation.env)
        return env

    def _exec(self, spec: NodeSpec, env: dict[str, str], log_path: Path) -> int:
        cwd = spec.implementation.cwd if is_external(spec) else None  # type: ignore[union-attr]
        with log_path.open("ab") as log:
            proc = subprocess.Popen(
                node_command(spec),
                env={**os.environ, **env},
                cwd=cwd,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                pass_fds=[self.heartbeats.fd],
                preexec_fn=_preexec(spec) if sys.platform == "linux" else None,
            )
        self._popen[proc.pid] = proc
        return proc.pid


__all__ = ["ForkServerError", "LocalHost", "die_with_parent", "node_command", "process_state"]
