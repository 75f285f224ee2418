"""A fork server: start node processes from an interpreter that has already imported them.

Starting ``python -m rra_agent.node`` costs ~70 ms of CPU before the node does anything
(interpreter, msgspec, zenoh, the node's own modules); a hundred nodes on two cores are
several seconds. The host agent instead keeps one *zygote* child that imports all of that
once (importing zenoh starts no thread, so forking is safe; no session is ever opened in
the zygote) and forks a ready interpreter per node: the child redirects its output to the
node's log, takes its environment, and runs `rra_agent.node.run_node`.

Protocol on the zygote's stdin/stdout, one JSON object per line:

- host -> zygote: ``{"spec": <NodeSpec>, "env": {...}, "log": "<path>"}``;
- zygote -> host: ``{"started": pid}`` in answer, and ``{"exit": pid, "status": s}`` whenever
  a child ends (``s`` as `subprocess.Popen.returncode`: negative = killed by signal -s).

The zygote is the nodes' parent: it reaps them and reports their exit. Each child gets
``PR_SET_PDEATHSIG = SIGKILL`` (it dies with the zygote), and the zygote gets it too (it dies
with the host agent), so nothing outlives the host agent. The zygote exits when its stdin
closes.
"""

from __future__ import annotations

import contextlib
import importlib
import json
import os
import select
import signal
import subprocess
import sys
from collections.abc import Iterable
from typing import IO, Any

import msgspec

from rra_agent.bus.messages import NodeSpec
from rra_agent.host.processes import die_with_parent

#: What every Python node needs: imported once, in the zygote.
PRELOAD = ("zenoh", "msgspec", "rra_agent.bus.runtime", "rra_agent.node")


# ---- the zygote side ------------------------------------------------------------------------
def _preload(modules: Iterable[str]) -> None:
    for name in modules:
        with contextlib.suppress(Exception):  # the node's own start reports real problems
            importlib.import_module(name)


def _child(request: dict[str, Any], fds: list[int]) -> None:
    """In the forked child: become the node. Never returns."""
    code = 70
    try:
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        signal.set_wakeup_fd(-1)
        die_with_parent()
        log = os.open(request["log"], os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        null = os.open(os.devnull, os.O_RDONLY)
        os.dup2(null, 0)
        os.dup2(log, 1)
        os.dup2(log, 2)
        for fd in {*fds, log, null} - {0, 1, 2}:  # the zygote's pipes, not our new stdio
            with contextlib.suppress(OSError):
                os.close(fd)
        os.environ.update(request.get("env", {}))
        sys.stdout = os.fdopen(1, "w", buffering=1)
        sys.stderr = os.fdopen(2, "w", buffering=1)
        from rra_agent.node import run_node

        code = run_node(msgspec.convert(request["spec"], NodeSpec))
    except BaseException as e:  # the child must never fall back into the zygote's loop
        with contextlib.suppress(Exception):
            print(f"rra node (forked): {type(e).__name__}: {e}", file=sys.stderr, flush=True)
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def _status(raw: int) -> int:
    return -os.WTERMSIG(raw) if os.WIFSIGNALED(raw) else os.WEXITSTATUS(raw)


def serve(preload: Iterable[str] = ()) -> int:
    """The zygote's main loop (``python -m rra_agent.host.forkserver [MODULE ...]``)."""
    _preload((*PRELOAD, *preload))
    rsig, wsig = os.pipe()
    os.set_blocking(wsig, False)
    signal.set_wakeup_fd(wsig)
    signal.signal(signal.SIGCHLD, lambda *_: None)  # wake the select below
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the host agent decides when we stop
    stdin, out = sys.stdin.buffer, sys.stdout
    buffer = b""
    while True:
        ready, _, _ = select.select([stdin, rsig], [], [])
        if rsig in ready:
            os.read(rsig, 512)
        _reap(out)
        if stdin in ready:
            chunk = os.read(stdin.fileno(), 65536)
            if not chunk:
                return 0
            buffer += chunk
            *lines, buffer = buffer.split(b"\n")
            for line in lines:
                if line.strip():
                    _fork(json.loads(line), out, [stdin.fileno(), out.fileno(), rsig, wsig])


def _fork(request: dict[str, Any], out: IO[str], fds: list[int]) -> None:
    pid = os.fork()
    if pid == 0:
        _child(request, fds)
    out.write(json.dumps({"started": pid}) + "\n")
    out.flush()


def _reap(out: IO[str]) -> None:
    while True:
        try:
            pid, raw = os.waitpid(-1, os.WNOHANG)
        except ChildProcessError:
            return
        if pid == 0:
            return
        out.write(json.dumps({"exit": pid, "status": _status(raw)}) + "\n")
        out.flush()


# ---- the host agent side ---------------------------------------------------------------------
class ForkServer:
    """Handle on a zygote, used by `LocalHost` from the host agent's main thread."""

    def __init__(self, preload: Iterable[str] = ()) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rra_agent.host.forkserver", *preload],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            preexec_fn=die_with_parent if sys.platform == "linux" else None,
        )
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self._in = self.proc.stdin
        self._out = self.proc.stdout
        os.set_blocking(self._out.fileno(), False)
        self._buffer = b""
        #: pid -> exit status (None while running) of every node forked.
        self.children: dict[int, int | None] = {}

    def spawn(self, spec: NodeSpec, env: dict[str, str], log: str) -> int:
        request = {"spec": msgspec.to_builtins(spec), "env": env, "log": log}
        self._in.write(json.dumps(request).encode() + b"\n")
        self._in.flush()
        while True:
            for msg in self._read(block=True):
                if "started" in msg:
                    pid = int(msg["started"])
                    self.children.setdefault(pid, None)
                    return pid

    def poll(self, pid: int) -> int | None:
        for _ in self._read(block=False):
            pass
        return self.children.get(pid)

    def _read(self, *, block: bool) -> list[dict[str, Any]]:
        """Messages available now (with ``block``: wait for at least one line)."""
        fd = self._out.fileno()
        while True:
            try:
                chunk = os.read(fd, 65536)
            except BlockingIOError:
                chunk = None
            if chunk == b"":
                raise OSError("the fork server exited")
            if chunk:
                self._buffer += chunk
            if b"\n" in self._buffer or not block:
                break
            select.select([fd], [], [], 5.0)
        *lines, self._buffer = self._buffer.split(b"\n")
        msgs = [json.loads(line) for line in lines if line.strip()]
        for msg in msgs:
            if "exit" in msg:
                self.children[int(msg["exit"])] = int(msg["status"])
        return msgs

    def close(self, timeout: float = 5.0) -> None:
        with contextlib.suppress(OSError):
            self._in.close()
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


if __name__ == "__main__":
    sys.exit(serve(sys.argv[1:]))
