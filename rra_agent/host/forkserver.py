"""A fork server: start node processes from an interpreter that has already imported them.

Starting ``python -m rra_agent.node`` costs ~70 ms of CPU before the node does anything
(interpreter, msgspec, zenoh, the node's own modules); a hundred nodes on two cores are
several seconds. The host agent instead keeps one *zygote* child that imports all of that
once (importing zenoh starts no thread, so forking is safe; no session is ever opened in the
zygote) and forks a ready interpreter per node.

The nodes are not the zygote's children but the host agent's: the zygote forks an
intermediate process that forks the node and exits at once, so the node is re-parented to
the host agent, which is a *child subreaper* (``PR_SET_CHILD_SUBREAPER``). Only then does
the node ask to die with its parent (``PR_SET_PDEATHSIG``), i.e. with the host agent. The
zygote does this ahead of time: it keeps a *spare* (forked, adopted, waiting on a pipe)
and hands the next request to it, so a start pays neither the forks nor the adoption; then
it forks the next spare. A spare sees the end of file when the zygote goes, and exits. So:

- the host agent reaps every node itself and learns of an exit at once (SIGCHLD);
- the zygote is a helper, nothing more: if it dies (or is killed), the nodes go on, the
  host agent starts a new zygote on the next spawn;
- nothing outlives the host agent (the zygote dies with it too).

External-command nodes are started the same way (the node process ``exec``s the command),
so every node has one parent, one way to be reaped and the same parent-death signal. A
command ``python -m MODULE ARGS`` of this interpreter that the host agent names (``rra up``'s
engines) is not ``exec``ed: the zygote's *branch* (`_Branch`, a fork of the zygote made at
its start) imports MODULE, calls ``MODULE.warm_up(ARGS)`` if there is one (the engines load
and resolve the system package there, once) and forks it on request like a node; the forked
process calls ``MODULE.main(ARGS)`` as ``python -m`` would have (its exit status,
``SystemExit`` and ``atexit`` hooks included). So it shares the zygote's imported modules
and what ``warm_up`` made instead of making them again in a new interpreter (measured with
``tools/bench_memory.py``: 23 MiB private memory per engine exec'd, 18.5 MiB forked,
8.5 MiB forked after the deployment was prepared), and the nodes do not inherit what only
the engines need.

Protocol on the zygote's stdin/stdout, one JSON object per line:

- host -> zygote: ``{"id": n, "spec": <NodeSpec>, "env": {...}, "log": "<path>",
  "argv": [...] | null, "cwd": "<dir>" | null, "main": "<module>" | null, "gate": bool,
  "after": [pid, start time] | null}``
  (``argv`` null: a Python node; ``main`` set: ``argv`` is ``python -m <module> ...``, run
  in the fork; ``gate``: a Python node that prepares, then waits for its gate to open before
  any of its code runs, `rra_agent.host.gate`: as the process ``after`` ends, or without
  it when the host agent sends the gate's signal);
- zygote -> host: ``{"id": n, "started": pid}`` (the pid of the spare it handed it to;
  for a ``main`` request the branch writes it, on the same pipe).

The zygote's arguments are the modules and implementations to preload; an absolute folder
among them is the system package's folder, appended to the import path before them;
``--main JSON`` (repeatable) a command ``[python, "-m", MODULE, ARG...]`` to prepare for;
``--spare-bus JSON`` the bus configuration of every node of the host, when they share one
(no certificates): each spare opens its Zenoh session with it while it waits, and the node
it becomes takes that session (`rra_agent.bus.session.preopen`).

The zygote exits when its stdin closes.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import gc
import importlib
import json
import os
import select
import signal
import subprocess
import sys
import time
import traceback
from collections.abc import Iterable, Sequence
from typing import Any

import msgspec

from rra_agent import trace
from rra_agent.bus.messages import NodeSpec
from rra_agent.host import gate

#: What every Python node needs: imported once, in the zygote. Also what a node imports as
#: it starts (``run_node``) or may import in its hooks (Rerun logging: the module, not
#: rerun): a module first imported in a forked node costs it its own copy of every page the
#: import machinery writes to (measured: 0.5 MiB per node for ``rra_agent.node.process``).
PRELOAD = (
    "zenoh",
    "msgspec",
    "rra_agent.node.runtime",
    "rra_agent.node",
    "rra_agent.node.process",
    "rra_agent.viz.rerun_log",
)
_PR_SET_PDEATHSIG = 1
_PR_SET_CHILD_SUBREAPER = 36
#: How long a node waits to be adopted by the host agent before it gives up.
_ADOPTION_TIMEOUT = 5.0
#: Exit status of a node process that could not be set up (never ran its code; an exception
#: of the node's own code is status 1 with a report, `rra_agent.node.run_node`).
EXIT_SETUP = 71
#: Spare node processes kept forked, adopted and waiting for a request: a start then costs
#: neither a fork nor the wait for the adoption (measured ~7 ms of a 20 ms cold start).
SPARES = int(os.environ.get("RRA_SPARE_NODES", "1"))
#: Seconds after a start before the next spare is forked: forking it, its adoption and its
#: session's opening take CPU (and the router's) exactly while the node just started sets up
#: and a swap's old node is reaped; on two cores that made a ``stop-then-start`` swap ~3 ms
#: slower. A request that finds no spare meanwhile forks one for itself.
SPARE_DELAY = float(os.environ.get("RRA_SPARE_DELAY", "0.25"))
#: Seconds without a request after which the branch (`_Branch`) is retired (0: never). An
#: engine started after that (a killed one replaced) is handed to a spare, like a node, and
#: warms up in its own process `REWARM_DELAY` later (`run_main`). Forking and warming a new
#: branch instead held the host agent's answer for the warm-up (~0.35 s of CPU) exactly
#: when the standby that had taken over asked it for its first plan's nodes: on two cores
#: the standby Resolution Engine's switch after a kill -9 came ~0.6 s late instead of ~0.2 s
#: (scenarios/quadcopter/engine_faults.scenario.yaml, resolution_killed).
BRANCH_IDLE = float(os.environ.get("RRA_BRANCH_IDLE", "5"))
#: Seconds an engine started without the branch waits before it imports and warms up its
#: module: the replacement of a killed engine, whose standby has taken over (claim 6-10 ms,
#: first plan ~0.2 s after the kill). Warming up at once, even at nice 19 or SCHED_IDLE,
#: delayed that plan on two loaded cores (engine_faults::resolution_killed failed 4 of 6
#: and 2 of 6 runs; with the warm-up 2 s later, none of 5: docs/performance.md).
REWARM_DELAY = float(os.environ.get("RRA_REWARM_DELAY", "2"))


def _prctl(option: int, value: int) -> bool:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return libc.prctl(option, value, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def trim_heap() -> None:
    """Give the C heap's free pages back to the system (glibc ``malloc_trim``; nothing
    elsewhere): what loading modules and models freed stays mapped otherwise."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None).malloc_trim(0)


def _pool_vacancies() -> dict[int, int]:
    """Free blocks in the partly used pools of Python's small-object allocator, by block
    size (``sys._debugmallocstats``, which writes to the C stderr)."""
    import tempfile

    with tempfile.TemporaryFile() as out:
        saved = os.dup(2)
        try:
            sys.stderr.flush()
            os.dup2(out.fileno(), 2)
            sys._debugmallocstats()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        out.seek(0)
        text = out.read().decode(errors="replace")
    vacancies: dict[int, int] = {}
    for line in text.splitlines():
        parts = line.split()
        if len(parts) == 5 and all(p.isdigit() for p in parts):
            vacancies[int(parts[1])] = int(parts[4])
    return vacancies


#: What `fill_pools` keeps alive (never freed: the zygote's filled pools stay full).
_FILLERS: list[bytes] = []


def fill_pools() -> None:
    """Fill the free blocks of the partly used pools of Python's allocator before forking:
    else a forked child's first small objects land in them, and every such block copies the
    zygote's page it is on (and its pool's header) into the child. CPython's allocator
    only (``sys._debugmallocstats``); nothing elsewhere."""
    if not hasattr(sys, "_debugmallocstats"):
        return
    for size, free in _pool_vacancies().items():
        if size >= 48:  # a bytes object of n bytes asks for 33 + n
            _FILLERS.extend(bytes(size - 33) for _ in range(free))


def die_with_parent() -> None:
    """Ask for SIGKILL when the parent dies (Linux; call in the child after fork)."""
    _prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)


def become_subreaper() -> bool:
    """Make this process adopt its orphaned descendants (the nodes of its zygote)."""
    return _prctl(_PR_SET_CHILD_SUBREAPER, 1)


class ForkServerError(OSError):
    """The zygote died, or did not answer in time."""


# ---- the zygote side ------------------------------------------------------------------------
#: The preloaded node classes that have a rehearsal (`Node.rehearse`): a spare runs them
#: while it waits for its request (`_wait_for_request`).
_REHEARSING: list[type] = []


def _preload(names: Iterable[str]) -> None:
    """Import modules; for an implementation (``pkg.module.Class``), import it and call its
    `Node.warm_up`. An absolute folder among the names is a system package's folder: it is
    appended to the import path first (`rra_agent.package.imports`), so the package's own
    node classes are imported and warmed up here too, and every node forked inherits it."""
    from rra_agent.node.loading import load_node_class
    from rra_agent.node.runtime import rehearses
    from rra_agent.package.imports import add_package_path

    names = list(names)
    folders = [n for n in names if os.path.isabs(n)]
    add_package_path(folders)
    for name in names:
        if name in folders:
            continue
        with contextlib.suppress(Exception):  # the node's own start reports real problems
            try:
                importlib.import_module(name)
            except ImportError:
                cls = load_node_class(name, folders)
                cls.warm_up()
                if rehearses(cls) and cls not in _REHEARSING:
                    _REHEARSING.append(cls)


def _warm_sdk() -> None:
    """First uses that cost milliseconds in every forked node unless done here once:
    msgspec's type information for the node's spec, bus configuration and control
    messages, the scheduling module (measured: 2 ms each in a cold start)."""
    from rra_agent.bus import messages as m
    from rra_agent.bus.config import BusConfig
    from rra_agent.host import scheduling  # noqa: F401  (imported for the nodes)

    spec = NodeSpec(system="s", name="n", host="h", implementation="a.B")
    msgspec.convert(msgspec.to_builtins(spec), NodeSpec)
    msgspec.json.decode(msgspec.json.encode(spec), type=NodeSpec)
    msgspec.json.decode(BusConfig().to_env(), type=BusConfig)
    BusConfig().to_zenoh()  # a Config is data: no session, no thread
    codec = m.Codec[m.NodeRequest](m.NodeRequest)
    codec.decode(codec.encode(m.Ping()))
    replies = m.Codec[m.Reply](m.Reply)
    replies.decode(replies.encode(m.Ok()))


def _warm_mains(mains: Iterable[list[str]]) -> None:
    """For each command ``python -m MODULE ARGS`` the zygote will fork: import MODULE and
    call its ``warm_up(ARGS)`` if it has one (a failure is the process's own to report)."""
    for argv in mains:
        module = python_module(argv)
        if module is None:
            continue
        with contextlib.suppress(Exception):
            warm_up = getattr(importlib.import_module(module), "warm_up", None)
            if warm_up is not None:
                warm_up(argv[3:])


def serve(
    host_pid: int,
    preload: Iterable[str] = (),
    mains: Sequence[list[str]] = (),
    spare_bus: str | None = None,
) -> int:
    """The zygote's main loop (``python -m rra_agent.host.forkserver HOST_PID [--main JSON]...
    [--spare-bus JSON] [MODULE ...]``). ``spare_bus``: the bus configuration every node of
    this host has (none with per-node identities): each spare opens its session ahead."""
    gate.block()  # every fork starts with the gate's signal blocked (`rra_agent.host.gate`)
    _preload((*PRELOAD, *preload))
    with contextlib.suppress(Exception):
        _warm_sdk()
    trim_heap()
    fill_pools()
    # What the zygote made is never freed: keep the garbage collector of every fork from
    # visiting (and so copying) its pages.
    gc.freeze()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the host agent decides when we stop
    stdin = sys.stdin.buffer.fileno()
    out = sys.stdout.buffer.fileno()
    spares: list[tuple[int, int]] = []
    branch = _Branch(list(mains), out, host_pid, spares) if mains else None
    try:
        return _serve_requests(stdin, out, host_pid, SPARES, spares, branch, spare_bus)
    finally:
        if branch is not None:
            branch.close()


def _serve_requests(
    requests: int,
    out: int,
    host_pid: int,
    wanted: int,
    spares: list[tuple[int, int]],
    branch: _Branch | None,
    preopen: str | None = None,
) -> int:
    """Answer the requests read from ``requests`` until its end of file, keeping ``wanted``
    spares (each opening a session with ``preopen``, if given); a request with ``main``
    goes to ``branch`` if there is one, which is retired once it has idled `BRANCH_IDLE`
    (then to a spare, which warms it up itself, `REWARM_DELAY` later: `run_main`)."""
    held = [branch.pipe] if branch is not None and branch.pipe is not None else []
    buffer = b""
    refill = 0.0  # when the next spare may be forked (`SPARE_DELAY` after a start)
    while True:
        now = time.monotonic()
        with contextlib.suppress(OSError):
            while len(spares) < wanted and now >= refill:
                spares.append(_spare([requests, out], host_pid, spares, held, preopen))
        due = branch.due(now) if branch is not None else None
        if len(spares) < wanted:  # wake for the refill too
            wait = max(0.0, refill - now)
            due = wait if due is None else min(due, wait)
        if not select.select([requests], [], [], due)[0]:
            if branch is not None and branch.tick(time.monotonic()):
                held[:] = []
            continue
        chunk = os.read(requests, 65536)
        if not chunk:
            return 0
        buffer += chunk
        *lines, buffer = buffer.split(b"\n")
        for line in lines:
            if not line.strip():
                continue
            request = json.loads(line)
            if branch is not None and branch.pipe is not None and request.get("main"):
                branch.forward(line)
                held[:] = [branch.pipe] if branch.pipe is not None else []
            else:
                _start(request, line, spares, out, [requests, out], host_pid, held, preopen)
                refill = time.monotonic() + SPARE_DELAY


class _Branch:
    """The zygote's branch for the ``python -m`` commands it runs (``rra up``'s engines): a
    fork of the zygote that imports their modules, calls their ``warm_up`` and forks them on
    request (without spares: they start once and rarely restart), answering the host agent
    on the zygote's stdout itself. The nodes, forked from the zygote, so do not inherit what
    only the engines need: a node's private memory grows with every page of its zygote it
    writes to, and a bigger zygote heap offers it more pages to write to (measured with
    ``tools/bench_memory.py``: 4.3 MiB per node, 5.8 with the engines' modules and
    deployment in the zygote). The branch dies with the zygote (parent-death signal); one
    that died is forked again at the next request.

    Once it has had no request for `BRANCH_IDLE` seconds the zygote *retires* it (closes its
    pipe: it exits; the engines it forked are the host agent's and run on); a later start
    (a crashed engine replaced, whose standby has taken over meanwhile) goes to a spare,
    which warms up in its own process once that standby's first plan is done
    (`REWARM_DELAY`, `run_main`): the zygote answers at once. Every page an engine has
    written is the engine's own copy, so the branch's original is its alone: kept, it costs
    its private memory (~6 MiB of object_storing's, docs/performance.md) for nothing but a
    replacement that shares its warm-up (one started by a spare has ~10 MiB of its own)."""

    def __init__(
        self, mains: list[list[str]], out: int, host_pid: int, spares: list[tuple[int, int]]
    ) -> None:
        self.mains, self.out, self.host_pid, self.spares = mains, out, host_pid, spares
        self.pid: int | None = None
        self.pipe: int | None = None
        self.last = 0.0
        #: Retired branches not reaped yet (each exits once it has read its end of file).
        self.retired: list[int] = []
        self._start()

    def _start(self) -> None:
        self.pid, self.pipe = self._fork()
        self.last = time.monotonic()

    def _fork(self) -> tuple[int, int]:
        """(the branch's pid, the write end of its request pipe)."""
        zygote = os.getpid()
        requests, pipe = os.pipe()
        pid = os.fork()
        if pid == 0:
            code = 1
            try:
                os.close(pipe)
                for _, spare in self.spares:  # a spare must see its end of file
                    os.close(spare)
                _detach([sys.stdin.fileno()])  # the zygote's requests are not the branch's
                die_with_parent()
                if os.getppid() != zygote:
                    os._exit(0)
                _warm_mains(self.mains)
                trim_heap()
                fill_pools()
                gc.freeze()
                code = _serve_requests(requests, self.out, self.host_pid, 0, [], None)
            finally:
                os._exit(code)
        os.close(requests)
        return pid, pipe

    def due(self, now: float) -> float | None:
        """Seconds until `tick` has something to do: retire it, or reap a retired one (a
        tenth of a second, until it has exited); None: nothing."""
        if self.retired:
            return 0.1
        if self.pid is None or BRANCH_IDLE <= 0:
            return None
        return max(0.0, self.last + BRANCH_IDLE - now)

    def tick(self, now: float) -> bool:
        """Reap the retired branches that have exited; retire this one if it has idled
        `BRANCH_IDLE` (True then)."""
        for pid in list(self.retired):
            with contextlib.suppress(ChildProcessError):
                if os.waitpid(pid, os.WNOHANG)[0] == 0:
                    continue
            self.retired.remove(pid)
        if self.pid is None or BRANCH_IDLE <= 0 or now < self.last + BRANCH_IDLE:
            return False
        self.retire()
        return True

    def forward(self, line: bytes) -> None:
        """Pass a request on (to a new branch if this one was retired or died)."""
        if self.pipe is None:
            self._start()
        try:
            os.write(self.pipe, line + b"\n")  # type: ignore[arg-type]
        except OSError:
            self.close()
            with contextlib.suppress(OSError):
                os.kill(self.pid, signal.SIGKILL)  # type: ignore[arg-type]
                os.waitpid(self.pid, 0)  # type: ignore[arg-type]
            self._start()
            os.write(self.pipe, line + b"\n")  # type: ignore[arg-type]
        self.last = time.monotonic()

    def retire(self) -> None:
        """Close its pipe: it exits at the end of file, after the requests it was given (the
        engines it forked are not its children); `tick` reaps it."""
        if self.pid is not None:
            self.retired.append(self.pid)
        self.pid = None
        self.close()

    def close(self) -> None:
        """No more requests: the branch sees the end of its pipe and exits."""
        if self.pipe is not None:
            with contextlib.suppress(OSError):
                os.close(self.pipe)
            self.pipe = None


def _start(
    request: dict[str, Any],
    line: bytes,
    spares: list[tuple[int, int]],
    out: int,
    fds: list[int],
    host_pid: int,
    held: Iterable[int] = (),
    preopen: str | None = None,
) -> None:
    """Hand the request to a spare (a node process already: adopted, warm, waiting); with
    none left (or all dead), fork one for it first. Either way it is one kind of process."""
    while True:
        if not spares:
            spares.append(_spare(fds, host_pid, spares, held, preopen))
        pid, pipe = spares.pop(0)
        try:
            os.write(pipe, line + b"\n")
        except OSError:  # that spare died: take (or make) the next
            continue
        finally:
            os.close(pipe)
        os.write(out, json.dumps({"id": request.get("id"), "started": pid}).encode() + b"\n")
        return


def _spare(
    fds: list[int],
    host_pid: int,
    spares: list[tuple[int, int]],
    held: Iterable[int] = (),
    preopen: str | None = None,
) -> tuple[int, int]:
    """Fork a spare node process (through an intermediate, so the host agent adopts it) that
    waits for its request on a pipe; (its pid, the pipe's write end). It closes the other
    spares' pipes (a spare must see the end of file when the zygote goes) and ``held``
    (the branch's request pipe). With ``preopen`` (a bus configuration) it opens its
    session while it waits."""
    req_r, req_w = os.pipe()
    pid_r, pid_w = os.pipe()
    pid = os.fork()
    if pid == 0:
        status = 0
        try:
            for fd in (req_w, pid_r, *(w for _, w in spares), *held):
                os.close(fd)
            node = os.fork()
            if node == 0:
                os.close(pid_w)
                _detach(fds)
                _wait_for_request(req_r, host_pid, preopen)
            os.write(pid_w, str(node).encode())
        except BaseException:
            status = 1
        finally:
            os._exit(status)
    os.close(req_r)
    os.close(pid_w)
    os.waitpid(pid, 0)
    raw = os.read(pid_r, 64)
    os.close(pid_r)
    if not raw:
        os.close(req_w)
        raise OSError("the spare was not forked")
    return int(raw), req_w


def _detach(fds: list[int]) -> None:
    """A spare must not hold the zygote's pipes to the host agent (the agent learns of the
    zygote's death by their end of file)."""
    null = os.open(os.devnull, os.O_RDWR)
    for fd in fds:
        os.dup2(null, fd)
    os.close(null)


def _rehearse_classes(pipe: int) -> None:
    """In a spare, until its request comes: the rehearsals of the host's node classes that
    have one, so that the node it becomes finds its own done (`Node.rehearse`: the first
    run of the code it needs at once, off a swap's critical path)."""
    if not _REHEARSING:
        return
    from rra_agent.node.runtime import rehearse_ahead

    for cls in _REHEARSING:
        if select.select([pipe], [], [], 0)[0]:
            return  # the request came: the node rehearses its own class if it must
        rehearse_ahead(cls)


def _wait_for_request(pipe: int, host_pid: int, preopen: str | None = None) -> None:
    """In a spare: be adopted, open the session ahead (``preopen``), then wait for the
    request and become its node. Never returns; exits quietly when the zygote goes without
    giving it one."""
    request: dict[str, Any] | None = None
    try:
        if not _adopted(host_pid):
            os._exit(EXIT_SETUP)
        if preopen is not None:
            from rra_agent.bus.config import BusConfig
            from rra_agent.bus.session import preopen as open_ahead
            from rra_agent.node.runtime import rehearse

            bus = msgspec.json.decode(preopen, type=BusConfig)
            session = open_ahead(bus)
            if session is not None and not select.select([pipe], [], [], 0)[0]:
                with contextlib.suppress(Exception):  # no request yet: time to rehearse
                    rehearse(session, str(os.getpid()), bus)
        _rehearse_classes(pipe)
        data = b""
        while not data.endswith(b"\n"):
            chunk = os.read(pipe, 65536)
            if not chunk:
                os._exit(0)  # no request: the zygote stopped (or died)
            data += chunk
        os.close(pipe)
        request = json.loads(data)
    except BaseException:
        os._exit(EXIT_SETUP)
    _node(request)


def _adopted(host_pid: int) -> bool:
    """Wait until the intermediate exits and we are the host agent's; then die with it."""
    deadline = time.monotonic() + _ADOPTION_TIMEOUT
    while os.getppid() != host_pid:  # the intermediate exits: we move to the host agent
        if time.monotonic() > deadline:
            return False
        time.sleep(0.0002)
    die_with_parent()
    return os.getppid() == host_pid  # the host agent died in between: no


def _node(request: dict[str, Any]) -> None:
    """In a spare that got its request: become the node. Never returns."""
    code = EXIT_SETUP
    try:
        trace.mark("node:request", request["spec"]["name"])
        gated = bool(request.get("gate"))
        # The old process's end watched before anything else (`gate.Exit`).
        after = gate.Exit(*request["after"]) if gated and request.get("after") else None
        if not gated:
            gate.unblock()
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        _redirect(request["log"])
        spec = msgspec.convert(request["spec"], NodeSpec)
        argv = request.get("argv")
        main = request.get("main")
        if argv:  # exec'd: the command opens its own session, if it has one
            from rra_agent.bus.session import discard_preopened

            discard_preopened()
        _schedule(spec)
        env = request.get("env", {})
        if request.get("cwd"):
            os.chdir(request["cwd"])
        if argv and not main:
            os.execvpe(argv[0], argv, {**os.environ, **env})
        os.environ.update(env)
        if main and argv:
            code = run_main(main, argv[3:])
        else:
            from rra_agent.node.process import run_node

            code = run_node(spec, gate=(after.wait if after else gate.wait) if gated else None)
    except SystemExit as e:  # sys.exit in the node's code: its status, as Python's own
        code = _status(e.code)
    except BaseException:  # the node must never fall back into the zygote's loop
        with contextlib.suppress(Exception):
            print("rra node (forked): could not be set up:", file=sys.stderr, flush=True)
            traceback.print_exc()
    finally:
        with contextlib.suppress(Exception):
            sys.stdout.flush()
            sys.stderr.flush()
        os._exit(code)


def python_module(argv: list[str]) -> str | None:
    """MODULE of a command ``python -m MODULE ...`` run by this interpreter, else None."""
    if len(argv) >= 3 and argv[0] == sys.executable and argv[1] == "-m":
        return argv[2]
    return None


def run_main(module: str, args: list[str]) -> int:
    """``python -m MODULE ARGS`` in this forked interpreter: ``MODULE.main(ARGS)`` with what a
    new interpreter would have (``sys.argv``, Python's SIGINT handler, no ``atexit`` hook of
    the zygote's); its exit status as the interpreter's would be, after its ``atexit`` hooks.
    A module the process has not imported yet (run by a spare, not by the branch that
    warmed it up: a replaced engine) is imported and warmed up first, `REWARM_DELAY` later.
    An uncaught exception is printed with its traceback (status 1; a KeyboardInterrupt ends
    the process by SIGINT, as Python does)."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    atexit._clear()
    code, interrupted = 1, False
    try:
        if module not in sys.modules:  # not warmed by a branch: warm up here, later
            time.sleep(REWARM_DELAY)
            _warm_mains([[sys.executable, "-m", module, *args]])
        mod = importlib.import_module(module)
        sys.argv = [getattr(mod, "__file__", None) or module, *args]
        code = _status(mod.main(args))
    except SystemExit as e:
        code = _status(e.code)
    except KeyboardInterrupt:
        traceback.print_exc()
        interrupted = True
    except BaseException:
        traceback.print_exc()
    atexit._run_exitfuncs()
    if interrupted:
        sys.stderr.flush()
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
    return code


def _status(value: object) -> int:
    """An exit status as ``sys.exit(value)`` makes it (None 0, a message 1)."""
    if value is None:
        return 0
    if isinstance(value, int):
        return value & 0xFF
    print(value, file=sys.stderr)
    return 1


def _schedule(spec: NodeSpec) -> None:
    """The component's scheduling, before it runs any code, on every thread (those of a
    session opened ahead too); a refusal is logged, not fatal (the host agent also reports
    it as a warning event)."""
    from rra_agent.host import scheduling

    for problem in scheduling.apply_to_process(spec.scheduling):
        print(f"rra node {spec.name}: scheduling: {problem}", file=sys.stderr, flush=True)


def _redirect(log_path: str) -> None:
    """stdout and stderr to the node's log (stdin is /dev/null since `_detach`)."""
    log = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(log, 1)
    os.dup2(log, 2)
    if log > 2:
        os.close(log)
    sys.stdout = os.fdopen(1, "w", buffering=1)
    sys.stderr = os.fdopen(2, "w", buffering=1)


# ---- the host agent side ---------------------------------------------------------------------
def _zygote_setup():
    """The zygote dies with its host agent, in a process group of its own (with its nodes:
    a Ctrl-C in the terminal reaches only the host agent, which stops them), and runs with
    the agent's own scheduling: a
    real-time host agent (``agents`` in rra.yaml) must not wait on a fork server starved by
    the real-time nodes it started. The zygote's children start as normal processes
    (SCHED_RESET_ON_FORK) and take their own scheduling from the model."""
    from rra_agent.host import scheduling

    own = scheduling.observed(os.getpid())
    realtime = own.policy != "other" or own.nice != 0

    def setup() -> None:
        die_with_parent()
        os.setpgid(0, 0)  # it and its nodes: not reached by a Ctrl-C of the host agent's
        if realtime:
            scheduling.apply(msgspec.structs.replace(own, cpus=[]), reset_on_fork=True)

    return setup


class ForkServer:
    """Handle on a zygote, used by `LocalHost` from the host agent's main thread. The host
    agent reaps the zygote (its child) itself and calls `exited` when it ends."""

    def __init__(
        self,
        preload: Iterable[str] = (),
        pass_fds: Iterable[int] = (),
        mains: Iterable[Sequence[str]] = (),
        spare_bus: str | None = None,
    ) -> None:
        warm = [a for argv in mains for a in ("--main", json.dumps(list(argv)))]
        if spare_bus is not None:
            warm += ["--spare-bus", spare_bus]
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rra_agent.host.forkserver", str(os.getpid()), *warm, *preload],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            pass_fds=tuple(pass_fds),
            preexec_fn=_zygote_setup() if sys.platform == "linux" else None,
        )
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self._in = self.proc.stdin
        self._out = self.proc.stdout
        os.set_blocking(self._out.fileno(), False)
        self._buffer = b""
        self._next_id = 0
        self.dead = False

    @property
    def pid(self) -> int:
        return self.proc.pid

    def spawn(
        self,
        spec: NodeSpec,
        env: dict[str, str],
        log: str,
        *,
        argv: list[str] | None = None,
        cwd: str | None = None,
        main: str | None = None,
        gate: bool = False,
        after: tuple[int, int] | None = None,
        timeout: float = 5.0,
    ) -> int:
        """Start a node; its pid. ``main``: ``argv`` is ``python -m main ...``, run in the
        fork rather than ``exec``ed (the zygote must have imported ``main``). ``gate``: a
        Python node that waits before its code runs until the process ``after`` (pid, start
        time) has ended, or without ``after`` for `rra_agent.host.gate.open_gate`. Raises
        `ForkServerError` if the zygote is gone or does not answer within ``timeout`` (then
        it is killed: a new one starts next time)."""
        if self.dead:
            raise ForkServerError("the fork server exited")
        self._next_id += 1
        request = {
            "id": self._next_id,
            "spec": msgspec.to_builtins(spec),
            "env": env,
            "log": log,
            "argv": argv,
            "cwd": cwd,
            "main": main,
            "gate": gate,
            "after": after,
        }
        try:
            self._in.write(json.dumps(request).encode() + b"\n")
            self._in.flush()
        except (BrokenPipeError, ValueError) as e:
            self.dead = True
            raise ForkServerError(f"the fork server exited ({e})") from None
        deadline = time.monotonic() + timeout
        while True:
            for msg in self._read(deadline):
                if msg.get("id") == self._next_id and "started" in msg:
                    return int(msg["started"])

    def _read(self, deadline: float) -> list[dict[str, Any]]:
        """The complete lines available, waiting until ``deadline`` for at least one."""
        fd = self._out.fileno()
        while b"\n" not in self._buffer:
            left = deadline - time.monotonic()
            if left <= 0:
                self.kill()
                raise ForkServerError("the fork server did not answer in time (killed)")
            select.select([fd], [], [], left)
            try:
                chunk = os.read(fd, 65536)
            except BlockingIOError:
                continue
            if not chunk:
                self.dead = True
                raise ForkServerError("the fork server exited")
            self._buffer += chunk
        *lines, self._buffer = self._buffer.split(b"\n")
        return [json.loads(line) for line in lines if line.strip()]

    def exited(self, status: int) -> None:
        """The host agent reaped the zygote."""
        self.dead = True
        self.proc.returncode = status

    def kill(self) -> None:
        self.dead = True
        with contextlib.suppress(ProcessLookupError):
            self.proc.kill()

    def close(self, timeout: float = 5.0) -> None:
        """Close its stdin (it exits) and reap it if the host agent has not."""
        with contextlib.suppress(OSError, ValueError):
            self._in.close()
        with contextlib.suppress(OSError, ValueError):
            self._out.close()
        if self.proc.returncode is not None:
            return
        try:
            self.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        except ChildProcessError:
            pass


def _cli(argv: list[str]) -> int:
    mains, names, args = [], [], iter(argv[1:])
    spare_bus = None
    for arg in args:
        if arg == "--main":
            mains.append(json.loads(next(args)))
        elif arg == "--spare-bus":
            spare_bus = next(args)
        else:
            names.append(arg)
    return serve(int(argv[0]), names, mains, spare_bus)


if __name__ == "__main__":
    sys.exit(_cli(sys.argv[1:]))
