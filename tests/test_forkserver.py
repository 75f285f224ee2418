"""The fork server and the host's process table: nodes forked from a pre-imported
interpreter become children of the host agent's process (a subreaper), which reaps them; the
fork server's death leaves them running; every node beats into its heartbeat slot. The host
agent's own ``python -m MODULE`` processes (the engines) run forked, after MODULE's
``warm_up``, as ``python -m`` would run them."""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from pathlib import Path

import msgspec
import pytest
from conftest import pid_alive

from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.bus.messages import NodeSpec, PortSpec
from rra_agent.bus.session import open_session
from rra_agent.host import procfs
from rra_agent.host.processes import LocalHost
from rra_agent.models.system import Command, Scheduling, Supervision

#: Every test here starts processes or opens Zenoh sessions (pytest -m 'not system').
pytestmark = pytest.mark.system


def spec(name: str, impl: str | Command = "rra_agent.nodes.generic.Relay") -> NodeSpec:
    return NodeSpec(
        system="fork", name=name, host="h", implementation=impl,
        ports={"in": PortSpec(direction="subscribe", type="X", keys=["rra/fork/data/a"]),
               "out": PortSpec(direction="publish", type="X", keys=["rra/fork/data/b"])},
        supervision=Supervision(heartbeat_timeout=0.4),
    )  # fmt: skip


@pytest.fixture
def host(tmp_path: Path):
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"])
    hub = open_session(bus.host_router(hub=True))
    h = LocalHost("h", bus, tmp_path)
    try:
        yield h
    finally:
        h.kill_all()
        hub.close()
    assert not h.names


def exits(host: LocalHost, pid: int) -> int:
    seen: dict[int, int] = {}

    def reaped() -> bool:
        seen.update(host.reap())
        return pid in seen

    wait_until(reaped, 10, f"the exit of {pid}")
    return seen[pid]


def test_forked_node_is_our_child_and_its_exit_is_reaped_here(host: LocalHost, tmp_path):
    pid = host.spawn(spec("n1"))
    assert pid_alive(pid)
    # adopted once the zygote's intermediate process has exited
    wait_until(lambda: procfs.parent(pid) == os.getpid(), 5, "the adoption")
    assert host.zygote is not None and pid != host.zygote.pid
    os.kill(pid, signal.SIGKILL)
    assert exits(host, pid) == -signal.SIGKILL  # as subprocess.Popen.returncode would say
    bad = host.spawn(spec("n2", "no.such.Node"))
    assert exits(host, bad) == 2  # unusable implementation: the supervisor's FATAL status
    assert "no.such" in (tmp_path / "n2.log").read_text()


def test_nodes_outlive_their_fork_server_and_a_new_one_starts(host: LocalHost):
    pid = host.spawn(spec("n3"))
    zygote = host.zygote
    assert zygote is not None
    os.kill(zygote.pid, signal.SIGKILL)
    wait_until(lambda: host.reap() or host.zygote_exits, 10, "the fork server's exit")
    assert host.zygote_exits == [-signal.SIGKILL] and host.zygote is None
    assert pid_alive(pid)  # the node goes on
    again = host.spawn(spec("n4"))
    assert host.zygote is not None and host.zygote.pid != zygote.pid
    assert pid_alive(again) and host.zygote_starts == 2


def test_a_node_beats_and_says_when_it_is_ready(host: LocalHost):
    host.spawn(spec("n5"))
    beat = wait_until(lambda: host.beats().get("n5"), 15, "a heartbeat")
    assert beat.at > 0
    wait_until(lambda: host.beats()["n5"].ready, 15, "the ready flag")


def test_external_command_is_execed_with_its_env_and_stops_on_sigint(host: LocalHost, tmp_path):
    script = tmp_path / "ext.py"
    script.write_text(
        "import os, signal, sys, time\n"
        "print('got', os.environ['EXTRA'], 'hb' if os.environ.get('RRA_HEARTBEAT') else '-',"
        " flush=True)\n"
        "signal.sigwait({signal.SIGINT})\n"
        "sys.exit(0)\n"
    )
    cmd = Command(command=[sys.executable, str(script)], env={"EXTRA": "yes"}, cwd=str(tmp_path))
    pid = host.spawn(spec("ext", cmd))
    log = tmp_path / "ext.log"
    wait_until(lambda: log.exists() and "got yes hb" in log.read_text(), 10, "its output")
    assert procfs.parent(pid) == os.getpid()
    os.kill(pid, signal.SIGINT)  # not ignored, although the zygote ignores SIGINT
    assert exits(host, pid) == 0


def test_node_names_cannot_leave_the_log_folder(host: LocalHost):
    with pytest.raises(ValueError):
        host.spawn(spec("../../tmp/x"))


WARM_MODULE = """
import os, sys
from rra_agent.node import Node

WARMED_IN = None


class Warm(Node):
    @classmethod
    def warm_up(cls):
        global WARMED_IN
        WARMED_IN = os.getpid()

    def on_start(self):
        print(f"warmed in {WARMED_IN}, running in {os.getpid()}", file=sys.stderr, flush=True)


class Broken(Node):
    @classmethod
    def warm_up(cls):
        raise RuntimeError("warm-up failed")
"""


def test_warm_up_runs_once_in_the_fork_server_and_nodes_inherit_it(tmp_path, monkeypatch):
    """`Node.warm_up` of every preloaded implementation runs in the zygote; a forked node
    finds its result without computing it (a cold start pays a fork, not the set-up). A
    warm-up that raises costs nothing but its own cache."""
    (tmp_path / "warmmod.py").write_text(WARM_MODULE)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"])
    hub = open_session(bus.host_router(hub=True))
    logs = tmp_path / "logs"
    h = LocalHost("h", bus, logs, preload=["warmmod.Broken", "warmmod.Warm"])
    try:
        pids = [h.spawn(spec(f"w{i}", "warmmod.Warm")) for i in range(2)]
        assert h.zygote is not None
        zygote = h.zygote.pid
        for i, pid in enumerate(pids):
            log = logs / f"w{i}.log"
            wait_until(lambda log=log: log.exists() and "warmed in" in log.read_text(), 10,
                       f"w{i} on_start")  # fmt: skip
            assert f"warmed in {zygote}, running in {pid}" in log.read_text()
    finally:
        h.kill_all()
        hub.close()


def _our_children() -> set[int]:
    """Live (not zombie) children of this process forked from a fork server."""
    from rra_agent.host.processes import process_state

    me = os.getpid()
    out = set()
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                pid = int(entry)
                with open(f"/proc/{pid}/cmdline", "rb") as f:
                    forked = b"forkserver" in f.read()
                if forked and procfs.parent(pid) == me and process_state(pid) not in ("Z", ""):
                    out.add(pid)
            except (OSError, IndexError, ValueError):
                pass
    return out


def test_a_start_takes_the_waiting_spare_and_a_new_spare_is_forked(host: LocalHost):
    """The fork server keeps a spare node process forked, adopted and waiting: a start hands
    it the request (no fork, no adoption wait on the start's path) and forks the next."""
    before = _our_children()  # what earlier tests' processes may still be
    first = host.spawn(spec("s1"))
    assert host.zygote is not None
    known = {first, host.zygote.pid, *before}
    spare = wait_until(lambda: next(iter(_our_children() - known), None), 10, "a spare")
    second = host.spawn(spec("s2"))
    assert second == spare
    known.add(second)
    wait_until(lambda: _our_children() - known, 10, "the next spare")
    # a spare is not a node: the host reaps nothing for it and knows only its nodes
    assert set(host.running()) == {first, second}


def _router_links(pid: int, port: int) -> set[int]:
    """Socket inodes of ``pid`` connected to 127.0.0.1:``port`` (its Zenoh session's link)."""
    inodes = set()
    with contextlib.suppress(OSError):
        for fd in os.listdir(f"/proc/{pid}/fd"):
            with contextlib.suppress(OSError):
                target = os.readlink(f"/proc/{pid}/fd/{fd}")
                if target.startswith("socket:["):
                    inodes.add(int(target[8:-1]))
    with open("/proc/net/tcp") as f:
        rows = [line.split() for line in f.readlines()[1:]]
    return {int(r[9]) for r in rows if int(r[2].split(":")[1], 16) == port and int(r[9]) in inodes}


@pytest.fixture
def ahead(tmp_path: Path):
    """A host whose nodes share one bus configuration (no certificates): spares open
    their sessions ahead. (the host, the router's port)"""
    port = free_port()
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{port}"])
    hub = open_session(bus.host_router(hub=True))
    h = LocalHost("h", bus, tmp_path)
    h.spare_bus = bus
    try:
        yield h, port
    finally:
        h.kill_all()
        hub.close()


def test_a_spare_opens_its_session_ahead_and_its_node_takes_it(ahead):
    """The spare waiting for a request is already linked to the router; the node it
    becomes runs on that very link (no second session opened on the start's path)."""
    host, port = ahead
    before = _our_children()
    first = host.spawn(spec("p1"))
    assert host.zygote is not None
    known = {first, host.zygote.pid, *before}
    spare = wait_until(lambda: next(iter(_our_children() - known), None), 10, "a spare")
    link = wait_until(lambda: _router_links(spare, port), 10, "the spare's session")
    assert host.spawn(spec("p2")) == spare
    wait_until(lambda: host.beats().get("p2") and host.beats()["p2"].ready, 15, "p2 ready")
    assert _router_links(spare, port) == link


def test_a_node_with_scheduling_opens_its_own_session(ahead):
    """Zenoh's threads must inherit a node's scheduling: a node with ``nice: 5`` does not
    take the pre-opened session (its threads started before it knew its scheduling)."""
    host, port = ahead
    nice = msgspec.structs.replace(spec("p3"), scheduling=Scheduling(nice=5))
    first = host.spawn(spec("p0"))  # the spare after it was forked with the host's bus
    assert host.zygote is not None
    before = {first, host.zygote.pid}
    wait_until(lambda: any(_router_links(p, port) for p in _our_children() - before), 10,
               "a spare's session")  # fmt: skip
    pid = host.spawn(nice)
    wait_until(lambda: host.beats().get("p3") and host.beats()["p3"].ready, 15, "p3 ready")
    threads = os.listdir(f"/proc/{pid}/task")
    assert len(threads) > 3  # Zenoh's among them
    for tid in threads:
        assert os.getpriority(os.PRIO_PROCESS, int(tid)) == 5, tid


def test_spares_end_with_their_fork_server(tmp_path, monkeypatch):
    """With three spares, each must close the others' request pipes: killed with the fork
    server, every spare sees the end of its pipe and exits (none waits forever)."""
    monkeypatch.setenv("RRA_SPARE_NODES", "3")
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"])
    hub = open_session(bus.host_router(hub=True))
    h = LocalHost("h", bus, tmp_path)
    try:
        before = _our_children()
        first = h.spawn(spec("t1"))
        assert h.zygote is not None
        known = {first, h.zygote.pid, *before}
        spares = wait_until(lambda: (s := _our_children() - known) and len(s) >= 3 and s, 10,
                            "three spares")  # fmt: skip
        os.kill(h.zygote.pid, signal.SIGKILL)
        wait_until(lambda: not (set(spares) & _our_children()), 10, "the spares' exit")
        assert pid_alive(first)  # the node it started goes on
    finally:
        h.kill_all()
        hub.close()


MAIN_MODULE = """
import atexit, os, sys

WARMED = []


def warm_up(args):
    WARMED.append((os.getpid(), args))


def main(args):
    atexit.register(lambda: print("atexit ran", flush=True))
    mine = [pid for pid, warmed in WARMED if warmed == args]
    print(f"warmed {mine}, main in {os.getpid()} with {args}, argv {sys.argv[1:]}", flush=True)
    if args[0] == "exit":
        sys.exit(int(args[1]))
    if args[0] == "raise":
        raise RuntimeError("main failed")
    return int(args[1])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
"""


PROBE_MODULE = """
import sys
from rra_agent.node import Node


class Probe(Node):
    def on_start(self):
        print(f"mainmod imported: {'mainmod' in sys.modules}", flush=True)
"""


def test_the_host_agents_python_modules_run_forked_after_their_warm_up(tmp_path, monkeypatch):
    """A command the host agent names (``forked``) is not exec'd: the fork server's branch
    (a fork of the fork server) imported its module and ran ``warm_up(ARGS)`` before forking
    it, and the fork calls ``main(ARGS)`` with a new interpreter's exit status (returned,
    ``sys.exit``, an uncaught exception) and ``atexit`` hooks. Any other ``python -m``
    command is exec'd. Nodes, forked by the fork server itself, do not have the module."""
    (tmp_path / "mainmod.py").write_text(MAIN_MODULE)
    (tmp_path / "probe.py").write_text(PROBE_MODULE)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"])
    hub = open_session(bus.host_router(hub=True))
    logs = tmp_path / "logs"
    commands = {
        name: [sys.executable, "-m", "mainmod", *args]
        for name, args in [("ret", ["ret", "3"]), ("exit", ["exit", "4"]),
                           ("raise", ["raise", "0"]), ("other", ["ret", "5"])]
    }  # fmt: skip
    forked = [commands[n] for n in ("ret", "exit", "raise")]
    h = LocalHost("h", bus, logs, preload=["probe.Probe"], forked=forked)
    try:
        pids = {name: h.spawn(spec(name, Command(command=cmd))) for name, cmd in commands.items()}
        assert h.zygote is not None
        zygote = h.zygote.pid
        seen: dict[int, int] = {}
        wait_until(lambda: seen.update(h.reap()) or set(pids.values()) <= set(seen), 10,
                   "every exit")  # fmt: skip
        statuses = {name: seen[pid] for name, pid in pids.items()}
        assert statuses == {"ret": 3, "exit": 4, "raise": 1, "other": 5}
        log = {name: (logs / f"{name}.log").read_text() for name in commands}
        branch = int(log["ret"].split("warmed [", 1)[1].split("]", 1)[0])
        assert branch != zygote and procfs.parent(branch) == zygote
        for name in ("ret", "exit", "raise"):
            args = commands[name][3:]
            assert (
                f"warmed [{branch}], main in {pids[name]} with {args}, argv {args}" in log[name]
            ), log[name]
            assert "atexit ran" in log[name]
        assert "RuntimeError: main failed" in log["raise"] and "Traceback" in log["raise"]
        assert "warmed []" in log["other"]  # exec'd: a new interpreter, no warm-up
        h.spawn(spec("probe", "probe.Probe"))
        probe = logs / "probe.log"
        wait_until(lambda: probe.exists() and "mainmod imported" in probe.read_text(), 10,
                   "the probe's start")  # fmt: skip
        assert "mainmod imported: False" in probe.read_text()
    finally:
        h.kill_all()
        hub.close()


def test_a_dead_branch_is_forked_again(tmp_path, monkeypatch):
    """The branch that forks the host agent's own processes may die (killed): the next such
    start forks a new branch from the fork server, and it warms up again."""
    (tmp_path / "mainmod.py").write_text(MAIN_MODULE)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"])
    hub = open_session(bus.host_router(hub=True))
    logs = tmp_path / "logs"
    command = [sys.executable, "-m", "mainmod", "ret", "0"]
    h = LocalHost("h", bus, logs, forked=[command])
    try:
        branches = []
        for i in range(2):
            pid = h.spawn(spec(f"m{i}", Command(command=command)))
            assert exits(h, pid) == 0
            text = (logs / f"m{i}.log").read_text()
            branches.append(int(text.split("warmed [", 1)[1].split("]", 1)[0]))
            if i == 0:
                os.kill(branches[0], signal.SIGKILL)
                wait_until(lambda: not pid_alive(branches[0]), 10, "the branch's death")
        assert branches[0] != branches[1]
        assert h.zygote is not None and procfs.parent(branches[1]) == h.zygote.pid
    finally:
        h.kill_all()
        hub.close()


def test_an_idle_branch_is_retired_and_a_later_start_warms_up_in_its_own_process(
    tmp_path, monkeypatch
):
    """The branch exits once it has had no request for ``RRA_BRANCH_IDLE`` seconds (every
    page its engines wrote is theirs: kept, it costs its private memory for nothing) and is
    reaped by the fork server; a later start of such a command goes to a spare, like a
    node's (the fork server answers at once: no branch to fork and warm up first), which
    imports the module and warms it up itself, and a process the old branch forked runs on
    meanwhile."""
    (tmp_path / "mainmod.py").write_text(MAIN_MODULE)
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    monkeypatch.setenv("RRA_BRANCH_IDLE", "0.5")
    monkeypatch.setenv("RRA_REWARM_DELAY", "0")  # no failover to let settle here
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"])
    hub = open_session(bus.host_router(hub=True))
    logs = tmp_path / "logs"
    command = [sys.executable, "-m", "mainmod", "ret", "0"]
    h = LocalHost("h", bus, logs, forked=[command])
    try:
        pid = h.spawn(spec("m0", Command(command=command)))
        assert exits(h, pid) == 0
        first = int((logs / "m0.log").read_text().split("warmed [", 1)[1].split("]", 1)[0])
        assert first != pid
        # It exits, and the fork server reaps it (no zombie is left).
        wait_until(lambda: not os.path.exists(f"/proc/{first}"), 10, "the idle branch reaped")
        pid = h.spawn(spec("m1", Command(command=command)))
        assert exits(h, pid) == 0
        text = (logs / "m1.log").read_text()
        assert f"warmed [{pid}], main in {pid} with ['ret', '0']" in text, text
        assert h.zygote is not None and first not in _our_children()
    finally:
        h.kill_all()
        hub.close()
