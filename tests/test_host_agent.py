"""The host agent and node processes on a real Zenoh bus (loopback, free port, no multicast)."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import pytest
import zenoh
from conftest import ok, pid_alive

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply, wait_until
from rra_agent.bus.counters import MAX_PAYLOAD
from rra_agent.bus.data import decode_data, encode_data
from rra_agent.bus.keys import Keys
from rra_agent.host.processes import process_state
from rra_agent.models.system import Command, Scheduling, Supervision

SYSTEM = "hosttest"
PACKAGE = Path(__file__).parent / "data" / "hosttest"
K = Keys(SYSTEM)


class Watch:
    """Collects NodeState events, other events and data samples seen by the test's session."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.states: list[m.NodeState] = []
        self.events: list[m.AdaptationEvent] = []
        self.data: list[dict] = []
        codec = m.Codec[m.EventMessage](m.EventMessage)

        def on_event(sample: zenoh.Sample) -> None:
            msg = codec.decode(sample.payload.to_bytes())
            with self.lock:
                if isinstance(msg, m.NodeState):
                    self.states.append(msg)
                else:
                    self.events.append(msg)

        def on_data(sample: zenoh.Sample) -> None:
            with self.lock:
                self.data.append(decode_data(sample.payload.to_bytes()))

        session.declare_subscriber(K.events, on_event)
        session.declare_subscriber(K.data("relay/out"), on_data)

    def state(self, node: str, state: str, after: int = 0) -> m.NodeState | None:
        with self.lock:
            return next(
                (s for s in self.states[after:] if s.node == node and s.state == state), None
            )


def relay_spec(name: str = "relay", **kw) -> m.NodeSpec:
    kw.setdefault("implementation", "rra_agent.nodes.generic.Relay")
    kw.setdefault("params", {"offset": 1.0})
    kw.setdefault("supervision", Supervision(heartbeat_timeout=1.0, probe_timeout=0.5))
    return m.NodeSpec(
        system=SYSTEM,
        name=name,
        host="h1",
        decl={"offset": m.ParamDecl(type="float", min=-10.0, max=10.0)},
        ports={
            "in": m.PortSpec(direction="subscribe", type="X", keys=[K.data("src")]),
            "out": m.PortSpec(direction="publish", type="X", keys=[K.data(f"{name}/out")]),
        },
        **kw,
    )


def spawn_agent(
    procs, bus, tmp_path: Path, package: Path = PACKAGE, env: dict[str, str] | None = None,
    prefix: tuple[str, ...] = (),
) -> tuple[subprocess.Popen, BusClient]:
    """A host agent of host h1 for ``package`` (``prefix``: a command it runs under, e.g.
    ``chrt``), and a client that has seen its token."""
    proc = procs.spawn(
        [*prefix, sys.executable, "-m", "rra_agent.host.agent", "--package", str(package),
         "--host", "h1", "--hub", "--log-dir", str(tmp_path / "nodes"),
         "--connect", bus.connect[0], "--no-multicast", "--lease-ms", "500"],
        env=env, name="agent",
    )  # fmt: skip
    client = BusClient(bus, SYSTEM)
    try:
        wait_until(lambda: list(client.session.liveliness().get(K.host_alive("h1"), timeout=0.5)),
                   15, "the host agent's token")  # fmt: skip
    except BaseException:
        client.close()
        raise
    return proc, client


@pytest.fixture(params=["fork-server"])
def agent(procs, bus, tmp_path, request):
    """A host agent of host h1; ``exec`` (indirect parametrisation): without the fork server,
    each node its own ``python -m rra_agent.node``."""
    env = {"HOSTTEST_WITNESS": str(tmp_path / "witness")}  # device.Holder's rehearsals
    if request.param == "exec":
        env["RRA_FORK_SERVER"] = "0"
    proc, client = spawn_agent(procs, bus, tmp_path, env=env)
    watch = Watch(client.session)
    yield proc, client, watch
    client.close()


def start(client: BusClient, watch: Watch, procs, spec: m.NodeSpec | None = None) -> m.NodeState:
    spec = spec or relay_spec()
    n = len(watch.states)
    reply = client.host("h1", m.StartNode(spec=spec))
    assert isinstance(reply, m.Ok), reply
    running = wait_until(lambda: watch.state(spec.name, "RUNNING", n), 15, f"{spec.name} RUNNING")
    procs.watch(running.pid)
    return running


@pytest.mark.parametrize("agent", ["fork-server", "exec"], indirect=True)
def test_start_run_data_and_stop(agent, procs):
    _proc, client, watch = agent
    start(client, watch, procs)
    pub = client.session.declare_publisher(K.data("src"))
    wait_until(lambda: pub.matching_status.matching, 5, "the relay's subscriber")
    pub.put(encode_data({"seq": 1, "value": 41.0}))
    wait_until(lambda: watch.data, 5, "relayed sample")
    assert watch.data[0]["value"] == 42.0

    ok(client.host("h1", m.StopNode(node="relay")))
    stopped = wait_until(lambda: watch.state("relay", "STOPPED"), 10, "relay STOPPED")
    assert "exit status 0" in stopped.reason  # SIGINT was enough: a clean shutdown
    listed = ok(client.host("h1", m.ListNodes()))
    assert [n["state"] for n in listed] == ["STOPPED"]  # type: ignore[union-attr]


def test_a_stop_with_deadline_0_kills_at_once_and_is_a_stop(agent, procs):
    """``StopNode(deadline=0)`` (a stop-then-start swap whose runtime.yaml gives the old
    node no grace period): SIGKILL at once, reported STOPPED, never restarted."""
    _, client, watch = agent
    first = start(client, watch, procs)
    n = len(watch.states)
    ok(client.host("h1", m.StopNode(node="relay", deadline=0.0)))
    stopped = wait_until(lambda: watch.state("relay", "STOPPED", n), 10, "relay STOPPED")
    assert stopped.pid == first.pid and "status -9" in stopped.reason
    assert not pid_alive(first.pid)
    assert not any(s.state in ("BACKOFF", "STARTING") for s in watch.states[n:])


def test_a_stop_deadline_cuts_the_grace_period_of_a_node_that_does_not_stop(agent, procs):
    """A node that cannot handle SIGINT (stopped by SIGSTOP) is killed when the stop's
    deadline (0.2 s) passes, not after the host agent's grace periods (SIGINT 2 s, SIGTERM
    2 s)."""
    _, client, watch = agent
    first = start(client, watch, procs)
    os.kill(first.pid, signal.SIGSTOP)
    n = len(watch.states)
    t0 = time.monotonic()
    ok(client.host("h1", m.StopNode(node="relay", deadline=0.2)))
    stopped = wait_until(lambda: watch.state("relay", "STOPPED", n), 10, "relay STOPPED")
    assert "status -9" in stopped.reason
    assert time.monotonic() - t0 < 2.0, "killed only after the SIGINT grace period"


def test_kill9_is_known_from_the_os_within_20_ms(agent, procs):
    _, client, watch = agent
    first = start(client, watch, procs)
    n = len(watch.states)
    t_kill = time.time()
    os.kill(first.pid, signal.SIGKILL)
    backoff = wait_until(lambda: watch.state("relay", "BACKOFF", n), 10, "BACKOFF after kill")
    assert "status -9" in backoff.reason
    assert backoff.stamp - t_kill < 0.020, f"detected after {backoff.stamp - t_kill:.3f} s"
    again = wait_until(lambda: watch.state("relay", "RUNNING", n), 15, "relay RUNNING again")
    procs.watch(again.pid)
    assert again.pid != first.pid and again.restarts == 1


def test_a_first_crash_restarts_at_once_a_second_waits_its_backoff(agent, procs):
    """kill -9 of a running node: its first crash in the restart window is restarted at
    once, not after ``backoff_initial`` (here 30 s, so the old rule cannot pass); the second
    crash waits the backoff (the node stays in BACKOFF)."""
    _, client, watch = agent
    slow = Supervision(heartbeat_timeout=1.0, probe_timeout=0.5, backoff_initial=30.0,
                       backoff_max=60.0)  # fmt: skip
    first = start(client, watch, procs, relay_spec(supervision=slow))
    n = len(watch.states)
    os.kill(first.pid, signal.SIGKILL)
    restarted = wait_until(lambda: watch.state("relay", "STARTING", n), 10, "relay STARTING")
    assert "at once" in restarted.reason, restarted.reason
    again = wait_until(lambda: watch.state("relay", "RUNNING", n), 15, "relay RUNNING again")
    procs.watch(again.pid)
    assert again.pid != first.pid and again.restarts == 1
    n = len(watch.states)
    os.kill(again.pid, signal.SIGKILL)
    wait_until(lambda: watch.state("relay", "BACKOFF", n), 10, "relay BACKOFF")
    assert watch.state("relay", "STARTING", n) is None  # waits its 30 s


def test_frozen_node_is_probed_then_killed_and_replaced(agent, procs):
    _, client, watch = agent
    first = start(client, watch, procs)
    n = len(watch.states)
    t0 = time.time()
    os.kill(first.pid, signal.SIGSTOP)
    suspect = wait_until(lambda: watch.state("relay", "UNRESPONSIVE", n), 10, "a probe")
    lost = wait_until(lambda: watch.state("relay", "BACKOFF", n), 10, "frozen node detected")
    assert "frozen" in lost.reason and "heartbeat" in lost.reason
    # Not before its 1 s heartbeat deadline; and at once after the failed probe.
    assert 0.9 < suspect.stamp - t0 < 2.5
    assert lost.stamp - suspect.stamp < 0.6
    again = wait_until(lambda: watch.state("relay", "RUNNING", n), 15, "replacement RUNNING")
    procs.watch(again.pid)
    assert again.pid != first.pid


def test_a_pause_shorter_than_the_deadline_changes_nothing(agent, procs):
    _, client, watch = agent
    first = start(client, watch, procs)
    n = len(watch.states)
    os.kill(first.pid, signal.SIGSTOP)
    stopped = time.monotonic()
    wait_until(lambda: time.monotonic() - stopped > 0.7, 2, "0.7 s (deadline: 1 s)")
    os.kill(first.pid, signal.SIGCONT)
    wait_until(lambda: time.monotonic() - stopped > 2.5, 4, "2.5 s")
    assert watch.state("relay", "UNRESPONSIVE", n) is None
    assert watch.state("relay", "BACKOFF", n) is None


def test_unusable_implementation_goes_fatal_and_is_retried_later(agent):
    _, client, watch = agent
    spec = m.NodeSpec(system=SYSTEM, name="bad", host="h1", implementation="no.such.Node")
    client.host("h1", m.StartNode(spec=spec))
    fatal = wait_until(lambda: watch.state("bad", "FATAL"), 15, "bad node FATAL")
    assert fatal.restarts == 0
    assert "retrying in 30 s" in fatal.reason


def test_malformed_requests_and_samples_crash_nothing_and_are_counted(agent, procs):
    proc, client, watch = agent
    start(client, watch, procs)
    # Too large (an empty map padded to 17 MiB): the agent's router drops it, the node never
    # sees it. Just over the node's own limit (within the 64 bytes the router leaves for an
    # attachment): the node drops it. Then a good sample: relayed.
    pub = client.session.declare_publisher(
        K.data("src"), congestion_control=zenoh.CongestionControl.BLOCK
    )
    wait_until(lambda: pub.matching_status.matching, 5, "the relay's subscriber")
    pub.put(b"\x80" * (17 * 1024 * 1024))
    pub.put(b"\x80" * (MAX_PAYLOAD["data"] + 16))
    pub.put(encode_data({"seq": 1, "value": 1.0}))
    wait_until(lambda: watch.data, 10, "the good sample relayed")
    assert ok(client.node("relay", m.Stats()))["dropped"] == 1  # type: ignore[index]
    junk = [b"", b"\xc1", b"\x81\xa1t\xa3zzz", bytes(range(256))]
    for key in (K.host_ctl("h1"), K.node_ctl("relay")):
        for payload in junk:
            replies = list(client.session.get(key, payload=payload, timeout=2))
            reply = m.Codec[m.Reply](m.Reply).decode(replies[0].ok.payload.to_bytes())
            assert isinstance(reply, m.Err) and reply.code == "malformed"
    for key in (K.data("src"), K.events, K.selection, K.ctx("x"), K.inject("motor")):
        for payload in junk:
            client.session.put(key, payload)
    info = ok(client.node("relay", m.Describe()))
    assert info["dropped"] >= len(junk)  # type: ignore[index]
    host_stats = ok(client.host("h1", m.Stats()))
    assert host_stats["dropped"] >= len(junk) and host_stats["role"] == "host"  # type: ignore[index]
    assert proc.poll() is None
    assert watch.state("relay", "BACKOFF") is None
    log = (procs.tmp / "nodes" / "relay.log").read_text()
    assert log.count("dropped sample on in") <= 2  # rate-limited, not one line per sample


def test_killed_host_agent_takes_its_nodes_along(agent, procs):
    proc, client, watch = agent
    running = start(client, watch, procs)
    proc.kill()  # SIGKILL: no chance to stop anything
    proc.wait()
    wait_until(lambda: not pid_alive(running.pid), 10, "the orphaned node to die")


def test_fork_server_death_is_reported_nodes_survive_and_ctrl_c_works(agent, procs):
    proc, client, watch = agent
    running = start(client, watch, procs)
    zygotes = [zygote_of(proc.pid)]
    assert running.pid not in zygotes
    spares = [p for p in children(proc.pid) if "forkserver" in cmdline(p)
              and p not in zygotes and p != running.pid]  # fmt: skip
    os.kill(zygotes[0], signal.SIGKILL)
    ev = wait_until(
        lambda: next((e for e in watch.events if e.kind == "fork_server"), None), 10, "the report"
    )
    assert "exited" in ev.message and ev.level == "warning"
    assert pid_alive(running.pid)
    for spare in spares:  # without its zygote, a spare has nothing to wait for
        wait_until(lambda spare=spare: not pid_alive(spare), 10, "the spare's exit")
    second = start(client, watch, procs, relay_spec("relay2"))  # through a new fork server
    assert ok(client.host("h1", m.Stats()))["counters"]["fork_server_restarts"] == 1  # type: ignore[index]
    proc.send_signal(signal.SIGINT)
    assert proc.wait(15) == 0
    assert not pid_alive(running.pid) and not pid_alive(second.pid)


def test_start_and_stop_are_idempotent_and_names_are_checked(agent, procs):
    _, client, watch = agent
    first = start(client, watch, procs)
    again = ok(client.host("h1", m.StartNode(spec=relay_spec())))
    assert again["already"] is True and again["same"] is True and again["pid"] == first.pid  # type: ignore[index]
    assert ok(client.host("h1", m.StopNode(node="nobody")))["already"] is True  # type: ignore[index]
    bad = client.host("h1", m.StartNode(spec=relay_spec("../../../../tmp/x")))
    assert isinstance(bad, m.Err) and bad.code == "denied"


def test_older_leaders_are_fenced_off_at_the_agent_and_its_nodes(agent, procs):
    _, client, watch = agent
    new, old = m.Fence(epoch=5, leader="b", instance="1f"), m.Fence(epoch=4, leader="a")
    # The same replica name and epoch in another process (a second system, the other side
    # of a partition): another term, refused once ``new`` is accepted.
    twin = m.Fence(epoch=5, leader="b", instance="7a")
    claimed = ok(client.host("h1", m.Claim(fence=new)))
    assert claimed == {"accepted": True, "fence": [5, "b", "1f"]}
    stale = client.host("h1", m.StartNode(spec=relay_spec(), fence=old))
    assert isinstance(stale, m.Err) and stale.code == "stale_fence"
    twin_start = client.host("h1", m.StartNode(spec=relay_spec(), fence=twin))
    assert isinstance(twin_start, m.Err) and twin_start.code == "stale_fence"
    start(client, watch, procs, relay_spec())  # unfenced: an operator's tool
    refused = client.node("relay", m.SetParams(params={"offset": 2.0}, fence=old))
    assert isinstance(refused, m.Err) and refused.code == "stale_fence"
    ok(client.node("relay", m.SetParams(params={"offset": 2.0}, fence=new)))
    twin_set = client.node("relay", m.SetParams(params={"offset": 3.0}, fence=twin))
    assert isinstance(twin_set, m.Err) and twin_set.code == "stale_fence"
    assert ok(client.host("h1", m.Stats()))["rejected"] == 2  # type: ignore[index]
    assert ok(client.node("relay", m.Stats()))["rejected"] == 2  # type: ignore[index]


def test_parameters_are_checked_against_their_declaration(agent, procs):
    _, client, watch = agent
    start(client, watch, procs)
    for bad in (1e6, -11, "x", True, float("nan")):
        reply = client.node("relay", m.SetParams(params={"offset": bad}))
        assert isinstance(reply, m.Err) and reply.code == "refused", bad
    ok(client.node("relay", m.SetParams(params={"offset": 9})))
    assert ok(client.node("relay", m.Describe()))["params"]["offset"] == 9.0  # type: ignore[index]
    ok(client.node("relay", m.SetParams(params={"offset": 4.5})))  # a float stays a float
    assert ok(client.node("relay", m.Describe()))["params"]["offset"] == 4.5  # type: ignore[index]


def children(pid: int) -> list[int]:
    with open(f"/proc/{pid}/task/{pid}/children") as f:
        return [int(x) for x in f.read().split()]


def cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def zygote_of(agent_pid: int) -> int:
    """The fork server of the host agent ``agent_pid``. The nodes and the spare node
    processes are forked from it too (same command line): it is the one whose stdin is
    still the host agent's pipe."""
    zygotes = [p for p in children(agent_pid) if "forkserver" in cmdline(p)
               and os.readlink(f"/proc/{p}/fd/0").startswith("pipe:")]  # fmt: skip
    assert len(zygotes) == 1, zygotes
    return zygotes[0]


TOOL = Command(
    command=["python3", "-c", "import time; time.sleep(60)"], env={"TOOL_MODE": "safe"}, cwd="/tmp"
)


def test_only_what_the_model_declares_runs(agent, procs):
    """Every attack on the host agent's start path is refused, counted and logged, and
    starts nothing: an undeclared command, a declared one with an injected environment or
    working directory, an undeclared or misplaced name, a path traversal, a parameter out
    of its bounds, and a spec update smuggling a command in for the next restart."""
    proc, client, watch = agent
    start(client, watch, procs)
    evil = Command(command=["id"])
    attacks = [
        m.StartNode(spec=relay_spec("relay", implementation=evil)),
        m.StartNode(spec=relay_spec("tool", implementation=msgspec.structs.replace(
            TOOL, env={**TOOL.env, "PYTHONWARNINGS": "ignore::0:os.system('id'):0"}))),
        m.StartNode(spec=relay_spec("tool", implementation=msgspec.structs.replace(TOOL, cwd="/"))),
        m.StartNode(spec=relay_spec("tool", implementation=msgspec.structs.replace(
            TOOL, command=[*TOOL.command, "x"]))),
        m.StartNode(spec=relay_spec("intruder")),
        m.StartNode(spec=relay_spec("elsewhere")),
        m.StartNode(spec=msgspec.structs.replace(relay_spec("relay2"), host="h2")),
        m.StartNode(spec=msgspec.structs.replace(relay_spec("relay2"), system="other")),
        m.StartNode(spec=relay_spec("..")),
        m.StartNode(spec=relay_spec("../../../../tmp/x")),
        m.StartNode(spec=relay_spec("relay2", params={"offset": 1e6})),
        m.StartNode(spec=relay_spec("relay2", params={"undeclared": 1})),
        m.UpdateSpec(specs=[relay_spec("relay", implementation=evil)]),
        m.StopNode(node="../relay"),
    ]  # fmt: skip
    before = ok(client.host("h1", m.Stats())).get("rejected", 0)  # type: ignore[union-attr]
    for attack in attacks:
        reply = client.host("h1", attack)
        assert isinstance(reply, m.Err) and reply.code == "denied", (attack, reply)
    assert ok(client.host("h1", m.Stats()))["rejected"] == before + len(attacks)  # type: ignore[index]
    listed = ok(client.host("h1", m.ListNodes()))
    assert [n["node"] for n in listed] == ["relay"]  # type: ignore[union-attr]
    assert proc.poll() is None
    # The smuggled spec did not stick: a restart runs the declared implementation.
    n = len(watch.states)
    os.kill(listed[0]["pid"], signal.SIGKILL)  # type: ignore[index]
    again = wait_until(lambda: watch.state("relay", "RUNNING", n), 15, "relay restarted")
    procs.watch(again.pid)
    assert again.implementation == "rra_agent.nodes.generic.Relay"
    assert ok(client.node("relay", m.Describe()))["params"]["offset"] == 1.0  # type: ignore[index]


def test_a_declared_command_runs_as_declared_and_is_not_disclosed(agent, procs):
    _, client, watch = agent
    spec = relay_spec("tool", implementation=TOOL, params={})
    # A plain program never declares a liveliness token: it stays STARTING, which is enough.
    pid = ok(client.host("h1", m.StartNode(spec=msgspec.structs.replace(spec, ports={}))))["pid"]  # type: ignore[index]
    procs.watch(pid)
    running = wait_until(lambda: watch.state("tool", "STARTING"), 10, "tool started")
    assert running.pid == pid

    def exec_done() -> list[bytes] | None:  # the fork server forks, then execs the command
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            if b"time.sleep(60)" not in f.read():
                return None
        with open(f"/proc/{pid}/environ", "rb") as f:
            environ = f.read()
        # The kernel writes a new program's arguments, then its environment: in between,
        # /proc shows the new command line and an empty environment.
        return environ.split(b"\0") if environ else None

    environ = wait_until(exec_done, 10, "the declared command exec'd")
    assert b"TOOL_MODE=safe" in environ
    assert os.readlink(f"/proc/{running.pid}/cwd") == "/tmp"
    listed = ok(client.host("h1", m.ListNodes()))
    text = msgspec.json.encode(listed).decode()
    assert "sleep" not in text and "TOOL_MODE" not in text
    assert listed[0]["implementation"].startswith("command:")  # type: ignore[index]


def _realtime_allowed() -> bool:
    import resource

    return os.geteuid() == 0 or resource.getrlimit(resource.RLIMIT_RTPRIO)[0] >= 10


@pytest.mark.parametrize("agent", ["fork-server", "exec"], indirect=True)
def test_a_component_runs_with_the_scheduling_its_model_gives_it(agent, procs, tmp_path):
    """``scheduling`` in system.yaml is applied in the node before it runs: every thread it
    starts (Zenoh's too) inherits it. What the kernel refuses is a warning event and a line
    in the node's log; the node runs anyway."""
    from rra_agent.host.scheduling import observed

    _proc, client, watch = agent
    rt = start(client, watch, procs, relay_spec("rt_relay"))
    if _realtime_allowed():
        assert observed(rt.pid) == Scheduling(policy="fifo", priority=10, cpus=[0])
        threads = [int(t) for t in os.listdir(f"/proc/{rt.pid}/task")]
        assert len(threads) > 1  # Zenoh's threads
        assert all(os.sched_getscheduler(t) == os.SCHED_FIFO for t in threads)
        assert all(os.sched_getaffinity(t) == {0} for t in threads)
    odd = start(client, watch, procs, relay_spec("odd_cpus"))
    assert observed(odd.pid).nice == 5
    warning = wait_until(
        lambda: next((e for e in watch.events if e.kind == "scheduling"), None), 10,
        "the scheduling warning",
    )  # fmt: skip
    assert warning.level == "warning" and "odd_cpus" in warning.message
    assert "asked for CPUs [4095]" in warning.message
    assert "CPU affinity [4095] refused" in (tmp_path / "nodes" / "odd_cpus.log").read_text()
    if _realtime_allowed():  # nothing to say about the one that got what it asked for
        assert not any("rt_relay" in e.message for e in watch.events if e.kind == "scheduling")


# ---- component containers -----------------------------------------------------------------
def container_spec(name: str, offset: float | None = None, **kw) -> m.NodeSpec:
    impl = {"c_faulty": "faulty.Faulty", "c_badstart": "faulty.BadStart"}.get(
        name, "rra_agent.nodes.generic.Relay"
    )
    ports = {
        "c_faulty": {"in": m.PortSpec(direction="subscribe", type="X", keys=[K.data("src")])},
        "c_badstart": {},
    }.get(name)
    params = {} if name in ("c_faulty", "c_badstart") else {"offset": offset or 1.0}
    return m.NodeSpec(
        system=SYSTEM, name=name, host="h1", implementation=impl, params=params,
        ports=ports if ports is not None else {
            "in": m.PortSpec(direction="subscribe", type="X", keys=[K.data("src")]),
            "out": m.PortSpec(direction="publish", type="X", keys=[K.data(f"{name}/out")]),
        },
        **kw,
    )  # fmt: skip


class Outputs:
    """Data samples of the given output keys, by key."""

    def __init__(self, session: zenoh.Session, names: list[str]) -> None:
        self.by: dict[str, list[dict]] = {n: [] for n in names}
        self.subs = [
            session.declare_subscriber(
                K.data(f"{n}/out"),
                lambda s, n=n: self.by[n].append(decode_data(s.payload.to_bytes())),
            )
            for n in names
        ]

    def close(self) -> None:
        for s in self.subs:
            s.undeclare()


def send_until_seen(client: BusClient, outs: Outputs, names: list[str], value: float) -> None:
    pub = client.session.declare_publisher(K.data("src"))
    try:
        wait_until(lambda: pub.matching_status.matching, 5, "the relays' subscribers")

        def seen() -> bool:
            pub.put(encode_data({"seq": 1, "value": value}))
            return all(any(o["value"] > value for o in outs.by[n]) for n in names)

        wait_until(seen, 10, f"samples through {names}", interval=0.05)
    finally:
        pub.undeclare()


def test_components_in_a_container_share_a_process_and_keep_their_own_endpoints(agent, procs):
    """``container: box``: c_relay1 and c_relay2 run in one process (one pid, not the agent's
    and not each other's), each with its own ports, parameters, control endpoint and token;
    a parameter set on one is not set on the other; one stops alone, the other goes on."""
    proc, client, watch = agent
    one = start(client, watch, procs, container_spec("c_relay1", 1.0))
    two = start(client, watch, procs, container_spec("c_relay2", 2.0))
    assert one.pid == two.pid and one.pid not in (proc.pid, None)
    assert "forkserver" in cmdline(one.pid)  # forked like a node, not a thread of the agent
    outs = Outputs(client.session, ["c_relay1", "c_relay2"])
    try:
        send_until_seen(client, outs, ["c_relay1", "c_relay2"], 10.0)
        assert {o["value"] for o in outs.by["c_relay1"]} == {11.0}
        assert {o["value"] for o in outs.by["c_relay2"]} == {12.0}
        ok(client.node("c_relay1", m.SetParams(params={"offset": 5.0})))
        assert ok(client.node("c_relay1", m.Describe()))["params"]["offset"] == 5.0  # type: ignore[index]
        assert ok(client.node("c_relay2", m.Describe()))["params"]["offset"] == 2.0  # type: ignore[index]
        assert ok(client.node("c_relay2", m.Describe()))["pid"] == one.pid  # type: ignore[index]
        bad = client.node("c_relay2", m.SetParams(params={"offset": 99.0}))
        assert isinstance(bad, m.Err)  # its own declared bounds
        # state export and import, per component: c_relay2 takes c_relay1's count over
        counts = [ok(client.node(n, m.ExportState())) for n in ("c_relay1", "c_relay2")]
        for n, c in zip(("c_relay1", "c_relay2"), counts, strict=True):
            assert isinstance(c, dict) and c["count"] >= max(1, len(outs.by[n])), (n, c)
        ok(client.node("c_relay2", m.ImportState(state={"count": 1000})))
        assert ok(client.node("c_relay2", m.ExportState())) == {"count": 1000}
        assert ok(client.node("c_relay1", m.ExportState())) == counts[0]
        # rewire one input alone: c_relay2 now listens to "src2" only
        ok(client.node("c_relay2", m.Rewire(port="in", keys=[K.data("src2")])))
        n = len(watch.states)
        ok(client.host("h1", m.StopNode(node="c_relay1")))
        stopped = wait_until(lambda: watch.state("c_relay1", "STOPPED", n), 10, "STOPPED")
        assert stopped.pid == one.pid
        assert pid_alive(one.pid)  # the container and c_relay2 go on
        assert not list(client.session.liveliness().get(K.alive("h1", "c_relay1"), timeout=1))
        assert list(client.session.liveliness().get(K.alive("h1", "c_relay2"), timeout=1))
        with pytest.raises(Exception):  # noqa: B017 -- nobody answers for c_relay1 any more
            ok(client.node("c_relay1", m.Ping(), timeout=1.0))
        # and it starts again in the same container
        again = start(client, watch, procs, container_spec("c_relay1", 1.0))
        assert again.pid == one.pid
    finally:
        outs.close()


def test_a_batch_to_a_container_is_answered_as_each_component_would(agent, procs):
    """One `NodeBatch` query to container "box" (what the Run-time Resolution Engine sends
    for a switch's requests to several of its components): each call is handled by its
    component as its own endpoint would (its own bounds), the replies come in order, and a
    call to a component the container does not hold is refused alone."""
    _, client, watch = agent
    start(client, watch, procs, container_spec("c_relay1", 1.0))
    start(client, watch, procs, container_spec("c_relay2", 2.0))
    batch = m.NodeBatch(calls=[
        m.NodeCall(node="c_relay1", request=m.SetParams(params={"offset": 3.0})),
        m.NodeCall(node="c_relay2", request=m.SetParams(params={"offset": 99.0})),  # > max
        m.NodeCall(node="c_faulty", request=m.Deactivate()),  # not loaded
        m.NodeCall(node="c_relay2", request=m.Deactivate()),
    ])  # fmt: skip
    codec = m.Codec[m.Reply](m.Reply)
    [answer] = [codec.decode(r.ok.payload.to_bytes())
                for r in client.session.get(K.node_ctl("box"), payload=m.Codec[m.ContainerRequest](
                    m.ContainerRequest).encode(batch), timeout=5) if r.ok is not None]  # fmt: skip
    assert isinstance(answer, m.Ok) and isinstance(answer.result, list)
    replies = [msgspec.convert(r, m.Reply) for r in answer.result]
    assert [type(r).__name__ for r in replies] == ["Ok", "Err", "Err", "Ok"], replies
    assert replies[2].code == "unknown"  # type: ignore[union-attr]
    one = ok(client.node("c_relay1", m.Describe()))
    two = ok(client.node("c_relay2", m.Describe()))
    assert one["params"]["offset"] == 3.0 and one["active"] is True  # type: ignore[index]
    assert two["params"]["offset"] == 2.0 and two["active"] is False  # type: ignore[index]


def test_a_failing_component_does_not_take_its_neighbours_down(agent, procs):
    """c_faulty raises in every callback and c_badstart in on_start: both are counted and
    reported (c_badstart FATAL, nothing else), c_relay2 in the same process relays on."""
    _proc, client, watch = agent
    relay = start(client, watch, procs, container_spec("c_relay2", 2.0))
    faulty = start(client, watch, procs, container_spec("c_faulty"))
    assert faulty.pid == relay.pid
    n = len(watch.states)
    ok(client.host("h1", m.StartNode(spec=container_spec("c_badstart"))))
    fatal = wait_until(lambda: watch.state("c_badstart", "FATAL", n), 10, "c_badstart FATAL")
    assert "cannot start on purpose" in fatal.reason
    outs = Outputs(client.session, ["c_relay2"])
    try:
        send_until_seen(client, outs, ["c_relay2"], 20.0)
    finally:
        outs.close()
    stats = ok(client.node("c_faulty", m.Describe()))
    assert stats["received"] >= 1  # type: ignore[index]
    assert pid_alive(relay.pid)
    assert not any(s.node == "c_relay2" and s.state != "RUNNING"
                   for s in watch.states[n:])  # fmt: skip


def test_a_killed_container_restarts_with_every_component(agent, procs):
    proc, client, watch = agent
    one = start(client, watch, procs, container_spec("c_relay1", 1.0))
    two = start(client, watch, procs, container_spec("c_relay2", 2.0))
    n = len(watch.states)
    os.kill(one.pid, signal.SIGKILL)
    for name in ("c_relay1", "c_relay2"):
        back = wait_until(lambda name=name: watch.state(name, "RUNNING", n), 15, f"{name} back")
        assert back.pid not in (None, one.pid)
        procs.watch(back.pid)
    assert {watch.state(x, "RUNNING", n).pid for x in ("c_relay1", "c_relay2")} != {two.pid}  # type: ignore[union-attr]
    assert any(s.node == "c_relay1" and s.state == "BACKOFF" for s in watch.states[n:])
    outs = Outputs(client.session, ["c_relay1", "c_relay2"])
    try:
        send_until_seen(client, outs, ["c_relay1", "c_relay2"], 30.0)
    finally:
        outs.close()
    # Ctrl-C: every component unloaded, the container gone, nothing left
    pid = watch.state("c_relay1", "RUNNING", n).pid  # type: ignore[union-attr]
    proc.send_signal(signal.SIGINT)
    assert proc.wait(15) == 0
    assert not pid_alive(pid)  # type: ignore[arg-type]
    stops = [s for s in watch.states if s.node.startswith("c_") and s.state != "RUNNING"
             and s.previous == "STOPPING"]  # fmt: skip
    assert stops and all(s.state == "STOPPED" for s in stops)


@pytest.mark.skipif(not _realtime_allowed(), reason="SCHED_FIFO is refused to this user")
def test_a_real_time_agent_s_fork_server_is_real_time_and_its_nodes_are_not(procs, bus, tmp_path):
    """A host agent on SCHED_FIFO (``agents`` in rra.yaml, or chrt) keeps its fork server at
    its own priority (real-time nodes must not starve the process every start waits on),
    and what the fork server starts begins as a normal process: a component without
    ``scheduling`` is not real time because its host agent is."""
    from rra_agent.host.scheduling import observed

    proc, client = spawn_agent(procs, bus, tmp_path, prefix=("chrt", "-f", "10"))
    try:
        watch = Watch(client.session)
        relay = start(client, watch, procs)
        zygote = zygote_of(proc.pid)
        assert observed(zygote).policy == "fifo" and observed(zygote).priority == 10
        assert observed(relay.pid).policy == "other"
    finally:
        client.close()


def test_a_leader_refused_as_superseded_steps_down(agent, procs):
    """Two replicas claimed the same epoch at once; the host agent accepted the other's
    term (equal epoch, smaller name) first. The loser's start is refused ``stale_fence``:
    its actuator says it was superseded, and its election steps down and tells the engine
    (the Run-time Resolution Engine then reports ``superseded``, not a failed deployment)."""
    from rra_agent.bus.loop import MainLoop
    from rra_agent.engines.actuator import ZenohActuator
    from rra_agent.engines.election import Election
    from rra_agent.engines.executor import StepFailed

    _, client, _watch = agent
    ok(client.host("h1", m.Claim(fence=m.Fence(epoch=1, leader="resolution-a"))))
    act = ZenohActuator(client.session, K, start_timeout=5.0)
    act.fence = m.Fence(epoch=1, leader="resolution-b")
    with pytest.raises(StepFailed, match="stale_fence"):
        act.start([relay_spec()])
    assert act.superseded
    act.close()

    changes: list[bool] = []
    loop = MainLoop()
    election = Election(client.session, K, "resolution", "resolution-b", loop,
                        lambda: changes.append(election.leading), claim_after=30.0)  # fmt: skip
    try:
        election.start()
        assert election.leading and changes == [True]  # alone on the bus: it claims
        # the winner's claim, seen
        election.claims[("resolution-a", "1f")] = election.term[0]  # type: ignore[index]
        election.step_down()
        assert not election.leading and changes == [True, False]
    finally:
        election.close()


def test_a_container_s_members_load_only_once_its_token_is_routed(tmp_path):
    """A container is RUNNING for its supervisor as soon as its heartbeat's ready flag is
    set (shared memory: at once), but its control queryable is known to the router only
    once its declarations got there. Loads sent before found nobody ("no reply", seen with
    ten containers starting at once): the members wait for the container's liveliness
    token, declared after the queryable, as this agent's own session sees it."""
    from rra_agent.bus.config import BusConfig, free_port
    from rra_agent.deployment import deploy
    from rra_agent.host.agent import HostAgent
    from rra_agent.host.catalog import Catalog
    from rra_agent.host.supervisor import State, Transition

    dep = deploy(PACKAGE)
    agent = HostAgent(
        dep.system, "h1", BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"]), tmp_path,
        hub=True, catalog=Catalog(dep.configured, "h1", package_root=dep.package.root),
    )  # fmt: skip
    agent.supervisor.add(agent.catalog.container_spec("box"), agent.local)
    seen: list[tuple[str, State, int | None]] = []
    agent.members.on_container = lambda name, state, pid, now: seen.append((name, state, pid))

    def moved(state: State, previous: State) -> None:  # as the supervisor moves it
        box = agent.supervisor.procs["box"]
        box.state, box.pid = state, 42
        agent._on_transition(Transition("box", "h1", previous, state, 0.0, 42, 0, ""))

    moved(State.STARTING, State.STOPPED)
    moved(State.RUNNING, State.STARTING)  # the ready flag: the token is not seen yet
    assert seen == [("box", State.STARTING, 42)]
    agent._on_ready("box")  # its token, as the agent's session saw it
    assert seen[-1] == ("box", State.RUNNING, 42) and len(seen) == 2
    agent._on_ready("box")  # seen again: nothing is loaded twice
    assert len(seen) == 2
    moved(State.BACKOFF, State.RUNNING)  # it died: its next start waits for a new token
    moved(State.STARTING, State.BACKOFF)
    moved(State.RUNNING, State.STARTING)
    assert [s for _, s, _ in seen[2:]] == [State.BACKOFF, State.STARTING]
    agent._on_ready("box")
    assert seen[-1][1] == State.RUNNING


# ---- ReplaceNode: a stop-then-start swap in one request --------------------------------------
def holder_spec(name: str, tmp: Path, stop_seconds: float) -> m.NodeSpec:
    """A driver of the device ``tmp/device`` (tests/data/hosttest/device.py), noting what it
    does in ``tmp/witness``."""
    (tmp / "device").touch()
    return m.NodeSpec(
        system=SYSTEM, name=name, host="h1", implementation="device.Holder",
        params={"device": str(tmp / "device"), "witness": str(tmp / "witness"),
                "stop_seconds": stop_seconds},
        ports={"in": m.PortSpec(direction="subscribe", type="X", keys=[K.data(TOPIC[name])])},
    )  # fmt: skip


#: The input topic of each holder (one of its own: its subscriber says it is prepared).
TOPIC = {"holder_a": "src", "holder_b": "src_b"}


def witnessed(tmp: Path, rehearsals: bool = False) -> list[tuple[float, str, str]]:
    """(time, node, what) of each line of ``tmp/witness``; ``rehearsals``: the class's
    rehearsals instead, as (time, "rehearsal", pid)."""
    lines = (tmp / "witness").read_text().splitlines()
    notes = [(float(t), name, what) for t, name, what in (x.split(" ", 2) for x in lines)]
    return [n for n in notes if (n[1] == "rehearsal") == rehearsals]


@pytest.mark.parametrize("agent", ["fork-server", "exec"], indirect=True)
def test_a_replacement_runs_none_of_its_code_before_the_node_it_replaces_is_gone(
    agent, procs, tmp_path, request
):
    """``ReplaceNode``: holder_a holds a device (released only as its process ends) and takes
    0.5 s to stop; holder_b takes the device in its constructor. With the fork server
    holder_b is spawned at once and prepares meanwhile (its STARTING comes before holder_a's
    STOPPED), yet its constructor runs only after holder_a is gone: it starts the first
    time. Without a fork server the agent starts it once holder_a is gone."""
    _, client, watch = agent
    start(client, watch, procs, holder_spec("holder_a", tmp_path, 0.5))
    n = len(watch.states)
    replace = m.ReplaceNode(node="holder_a", spec=holder_spec("holder_b", tmp_path, 0.0))
    ok(client.host("h1", replace))
    running = wait_until(lambda: watch.state("holder_b", "RUNNING", n), 15, "holder_b RUNNING")
    procs.watch(running.pid)
    with watch.lock:
        after = watch.states[n:]
    assert not [s for s in after if s.node == "holder_b" and s.state in ("BACKOFF", "FATAL")]
    stopped = next(s for s in after if s.node == "holder_a" and s.state == "STOPPED")
    assert "exit status 0" in stopped.reason  # its on_stop ran: a stop, not a kill
    if request.node.callspec.params["agent"] == "fork-server":
        b_first = next(i for i, s in enumerate(after) if s.node == "holder_b")
        a_gone = after.index(stopped)
        assert b_first < a_gone and after[b_first].pid == running.pid, after
    notes = witnessed(tmp_path)
    a_stopped = next(t for t, name, what in notes if name == "holder_a" and what == "stopped")
    b_built = [t for t, name, what in notes if name == "holder_b" and what == "constructed"]
    assert len(b_built) == 1 and b_built[0] > a_stopped, notes
    assert ("holder_b", "holds the device") in [(name, what) for _, name, what in notes]
    # Its class rehearsed in its own process before its constructor: with the fork server
    # while holder_a was stopping (off the critical path), without it once holder_a was gone.
    rehearsed = [t for t, _, pid in witnessed(tmp_path, rehearsals=True) if pid == str(running.pid)]
    assert len(rehearsed) == 1 and rehearsed[0] < b_built[0], notes
    if request.node.callspec.params["agent"] == "fork-server":
        assert rehearsed[0] < a_stopped, notes


@pytest.mark.parametrize("agent", ["fork-server", "exec"], indirect=True)
def test_a_replacement_that_exports_starts_the_new_node_with_the_old_one_s_state(
    agent, procs, tmp_path
):
    """``ReplaceNode`` with ``export``: the agent asks holder_a for its state, then stops it,
    and holder_b imports that state (after its constructor, once holder_a is gone)."""
    _, client, watch = agent
    start(client, watch, procs, holder_spec("holder_a", tmp_path, 0.0))
    n = len(watch.states)
    new = holder_spec("holder_b", tmp_path, 0.0)
    ok(client.host("h1", m.ReplaceNode(node="holder_a", spec=new, export=True)))
    running = wait_until(lambda: watch.state("holder_b", "RUNNING", n), 15, "holder_b RUNNING")
    procs.watch(running.pid)
    notes = [(name, what) for _, name, what in witnessed(tmp_path)]
    assert notes == [
        ("holder_a", "constructed"), ("holder_a", "holds the device"),
        ("holder_a", "exported"), ("holder_a", "stopped"),
        ("holder_b", "constructed"), ("holder_b", "holds the device"),
        ("holder_b", "imported holder_a"),
    ], notes  # fmt: skip


def test_a_replacement_whose_old_node_cannot_export_leaves_it_running(agent, procs, tmp_path):
    """The old node raises in ``export_state``: the reply is an ``Err`` (code ``export``)
    saying so, holder_a runs on (same process) and holder_b is never started."""
    _, client, watch = agent
    spec = holder_spec("holder_a", tmp_path, 0.0)
    spec = msgspec.structs.replace(spec, params={**spec.params, "export_fails": True})
    first = start(client, watch, procs, spec)
    n = len(watch.states)
    new = holder_spec("holder_b", tmp_path, 0.0)
    reply = client.host("h1", m.ReplaceNode(node="holder_a", spec=new, export=True))
    assert isinstance(reply, m.Err) and reply.code == "export", reply
    assert "holder_a did not export its state" in reply.message
    assert "mid-transfer" in reply.message
    with watch.lock:
        after = watch.states[n:]
    assert not [s for s in after if s.node in ("holder_a", "holder_b")], after
    assert pid_alive(first.pid)  # the same process runs on


def holder_b_at_its_gate(
    client: BusClient, watch: Watch, procs, tmp_path: Path, stop_seconds: float
) -> tuple[m.NodeState, m.NodeState, int]:
    """holder_a running (its stop takes ``stop_seconds``), then replaced by holder_b, once
    holder_b is prepared (its subscriber declared: it waits at its gate): holder_a's
    RUNNING, holder_b's STARTING and where the states after the replacement begin."""
    a = start(client, watch, procs, holder_spec("holder_a", tmp_path, stop_seconds))
    n = len(watch.states)
    probe = client.session.declare_publisher(K.data("src_b"))
    replace = m.ReplaceNode(node="holder_a", spec=holder_spec("holder_b", tmp_path, 0.0))
    ok(client.host("h1", replace))
    gated = wait_until(lambda: watch.state("holder_b", "STARTING", n), 10, "holder_b STARTING")
    procs.watch(gated.pid)
    wait_until(lambda: probe.matching_status.matching, 10, "holder_b's subscriber")
    probe.undeclare()
    return a, gated, n


@pytest.mark.parametrize("agent", ["fork-server"], indirect=True)
def test_a_gated_replacement_starts_as_the_old_process_ends_with_its_agent_frozen(
    agent, procs, tmp_path
):
    """The gate is the kernel's, not a hop through the host agent: holder_b is gated behind
    holder_a, which takes 5 s to stop. Their host agent is frozen (SIGSTOP: it can neither
    reap holder_a nor signal anyone) and holder_a is killed: holder_b takes the device at
    once, holder_a a zombie. Once the agent runs again it reaps holder_a, and holder_b is
    RUNNING in the process that was gated."""
    proc, client, watch = agent
    a, gated, _ = holder_b_at_its_gate(client, watch, procs, tmp_path, 5.0)
    os.kill(proc.pid, signal.SIGSTOP)  # the agent and the router it holds, then holder_a's end
    try:
        killed = time.monotonic()
        os.kill(a.pid, signal.SIGKILL)
        wait_until(
            lambda: ("holder_b", "holds the device") in [(n, w) for _, n, w in witnessed(tmp_path)],
            10, "holder_b holding the device, its agent frozen",
        )  # fmt: skip
        assert process_state(a.pid) == "Z"  # ended, not reaped
    finally:
        os.kill(proc.pid, signal.SIGCONT)
    notes = witnessed(tmp_path)
    built = [t for t, name, what in notes if name == "holder_b" and what == "constructed"]
    assert len(built) == 1 and built[0] > killed

    # The freeze may outlast the bus's 500 ms lease: ask the agent rather than watch its news.
    def listed() -> dict | None:
        try:
            reply = client.host("h1", m.ListNodes(), timeout=1.0)
        except NoReply:  # the client's session is back in a moment
            return None
        nodes = {n["node"]: n for n in reply.result} if isinstance(reply, m.Ok) else {}
        b = nodes.get("holder_b")
        a_reaped = nodes.get("holder_a", {}).get("state") == "STOPPED"
        return b if b and b["state"] == "RUNNING" and a_reaped else None

    assert wait_until(listed, 15, "holder_b RUNNING, holder_a reaped")["pid"] == gated.pid


@pytest.mark.parametrize("agent", ["fork-server"], indirect=True)
def test_a_replacement_that_cannot_start_leaves_the_old_node_running(agent, procs, tmp_path):
    """The replacement is spawned (gated) before the old node is told to stop: one that
    cannot start (holder_b is still stopping from before: ``busy``) is an ``Err``, and
    holder_a runs on, never stopping, in the same process."""
    _, client, watch = agent
    first_b = holder_spec("holder_b", tmp_path, 3.0)
    (tmp_path / "device_b").touch()  # a device of its own: holder_a takes the other
    first_b = msgspec.structs.replace(
        first_b, params={**first_b.params, "device": str(tmp_path / "device_b")}
    )
    b = start(client, watch, procs, first_b)
    ok(client.host("h1", m.StopNode(node="holder_b")))  # 3 s in its on_stop
    wait_until(lambda: watch.state("holder_b", "STOPPING"), 10, "holder_b STOPPING")
    a = start(client, watch, procs, holder_spec("holder_a", tmp_path, 0.0))
    n = len(watch.states)
    replace = m.ReplaceNode(node="holder_a", spec=holder_spec("holder_b", tmp_path, 0.0))
    reply = client.host("h1", replace)
    assert isinstance(reply, m.Err) and reply.code == "busy", reply
    listed = {x["node"]: (x["state"], x["pid"]) for x in ok(client.host("h1", m.ListNodes()))}
    assert listed == {"holder_a": ("RUNNING", a.pid), "holder_b": ("STOPPING", b.pid)}
    with watch.lock:
        assert not [s for s in watch.states[n:] if s.node == "holder_a"], watch.states[n:]


def test_a_gated_replacement_stopped_before_its_gate_opens_runs_none_of_its_code(
    agent, procs, tmp_path
):
    """holder_b, gated behind holder_a's 2 s stop, is stopped once prepared (its subscriber
    is declared): it ends cleanly (exit status 0: it left its gate and closed its session)
    and its constructor never ran; holder_a stops as asked."""
    _, client, watch = agent
    _, _, n = holder_b_at_its_gate(client, watch, procs, tmp_path, 2.0)
    ok(client.host("h1", m.StopNode(node="holder_b")))
    stopped = wait_until(lambda: watch.state("holder_b", "STOPPED", n), 10, "holder_b STOPPED")
    assert "exit status 0" in stopped.reason
    wait_until(lambda: watch.state("holder_a", "STOPPED", n), 10, "holder_a STOPPED")
    assert "holder_b" not in [name for _, name, _ in witnessed(tmp_path)]


def _cpu_latency_settable() -> bool:
    from rra_agent.host.scheduling import CPU_LATENCY_DEVICE, cpu_latency

    return cpu_latency() is not None and os.access(CPU_LATENCY_DEVICE, os.W_OK)


@pytest.mark.skipif(not _cpu_latency_settable(), reason="/dev/cpu_dma_latency is not writable here")
@pytest.mark.parametrize("stop", [signal.SIGINT, signal.SIGKILL], ids=["stopped", "killed"])
def test_a_host_agent_holds_its_host_s_cpu_latency_while_it_runs(procs, bus, tmp_path, stop):
    """``agents: {cpu_latency_us: 0}`` in rra.yaml: while the host agent runs, the kernel
    keeps every CPU within 0 us of waking (PM QoS); once it is gone, stopped or killed, the
    request is too (none of the processes it started keeps it)."""
    from rra_agent.host.scheduling import cpu_latency

    before = cpu_latency()
    if not before:
        pytest.skip(f"another process holds the CPU latency at {before} us already")
    package = tmp_path / "pkg"
    shutil.copytree(PACKAGE, package)
    manifest = package / "rra.yaml"
    manifest.write_text(manifest.read_text() + "agents: {cpu_latency_us: 0}\n")
    proc, client = spawn_agent(procs, bus, tmp_path, package)
    try:
        assert cpu_latency() == 0
        proc.send_signal(stop)
        assert proc.wait(15) == (0 if stop == signal.SIGINT else -signal.SIGKILL)
        wait_until(lambda: cpu_latency() == before, 5, "the request dropped")
    finally:
        client.close()


def test_a_refused_cpu_latency_is_one_line(tmp_path):
    from rra_agent.host.scheduling import hold_cpu_latency

    line = hold_cpu_latency(0, str(tmp_path / "no_such_device"))
    assert line == (f"CPU latency 0 us refused ({tmp_path / 'no_such_device'}: "
                    "No such file or directory)")  # fmt: skip


def test_a_rehearsal_that_raises_is_a_log_line_and_the_node_starts(capsys):
    from rra_agent.node import Node
    from rra_agent.node.runtime import rehearse_class

    class Clumsy(Node):
        @classmethod
        def rehearse(cls) -> None:
            raise ValueError("no scratch device")

    rehearse_class(Clumsy, "clumsy")  # does not raise
    assert capsys.readouterr().err == "[clumsy] rehearse failed: ValueError: no scratch device\n"


def test_a_spare_rehearses_its_host_s_node_classes_before_it_knows_its_node(
    agent, procs, tmp_path
):
    """The fork server's spare runs the rehearsal of every node class of its host that has
    one (device.Holder's) while it waits for a request: the node it becomes finds it done
    (no second rehearsal in its process), off the start's path. (The fork server starts
    with the first node; the spare after it is forked a moment later.)"""
    _, client, watch = agent
    first = start(client, watch, procs, holder_spec("holder_a", tmp_path, 0.0))

    def spare_rehearsed() -> int | None:
        pids = [int(pid) for _, _, pid in witnessed(tmp_path, rehearsals=True)]
        return next((pid for pid in pids if pid != first.pid), None)

    spare = wait_until(spare_rehearsed, 15, "the next spare's rehearsal")
    ok(client.host("h1", m.StopNode(node="holder_a")))
    wait_until(lambda: watch.state("holder_a", "STOPPED"), 15, "holder_a STOPPED")
    node = start(client, watch, procs, holder_spec("holder_b", tmp_path, 0.0))
    assert node.pid == spare  # the spare became the node
    rehearsals = [pid for _, _, pid in witnessed(tmp_path, rehearsals=True) if int(pid) == spare]
    assert len(rehearsals) == 1, witnessed(tmp_path, rehearsals=True)


def test_a_component_loaded_into_a_container_rehearses_before_its_constructor(
    procs, bus, tmp_path
):
    """`Node.rehearse` runs in the container's process before the component is built."""
    package = tmp_path / "pkg"
    shutil.copytree(PACKAGE, package)
    system = package / "system.yaml"
    text = system.read_text()
    old = "  - name: holder_b\n    host: h1\n"
    assert text.count(old) == 1
    system.write_text(text.replace(old, old + "    container: box\n"))
    _, client = spawn_agent(
        procs, bus, tmp_path, package, env={"HOSTTEST_WITNESS": str(tmp_path / "witness")}
    )
    try:
        watch = Watch(client.session)
        running = start(client, watch, procs, holder_spec("holder_b", tmp_path, 0.0))
        assert "forkserver" in cmdline(running.pid)  # the container's process
        rehearsed = [t for t, _, pid in witnessed(tmp_path, rehearsals=True)
                     if pid == str(running.pid)]  # fmt: skip
        built = [t for t, name, what in witnessed(tmp_path) if (name, what) == ("holder_b",
                 "constructed")]  # fmt: skip
        assert len(rehearsed) == 1 and len(built) == 1 and rehearsed[0] < built[0]
    finally:
        client.close()
