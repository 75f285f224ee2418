"""The host agent and node processes on a real Zenoh bus (loopback, free port, no multicast)."""

from __future__ import annotations

import signal
import threading
import time

import pytest
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, wait_until
from rra_agent.bus.keys import Keys
from rra_agent.node import decode_data, encode_data

SYSTEM = "hosttest"
K = Keys(SYSTEM)


class Watch:
    """Collects NodeState events and data samples seen by the test's own session."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.states: list[m.NodeState] = []
        self.data: list[dict] = []
        codec = m.Codec[m.EventMessage](m.EventMessage)

        def on_event(sample: zenoh.Sample) -> None:
            msg = codec.decode(sample.payload.to_bytes())
            if isinstance(msg, m.NodeState):
                with self.lock:
                    self.states.append(msg)

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


def relay_spec(name: str = "relay") -> m.NodeSpec:
    return m.NodeSpec(
        system=SYSTEM,
        name=name,
        host="h1",
        implementation="rra_agent.nodes.generic.Relay",
        params={"offset": 1.0},
        ports={
            "in": m.PortSpec(direction="subscribe", type="X", keys=[K.data("src")]),
            "out": m.PortSpec(direction="publish", type="X", keys=[K.data("relay/out")]),
        },
    )


@pytest.fixture
def agent(procs, bus, tmp_path):
    proc = procs.python(
        "rra_agent.host.agent",
        "--system", SYSTEM, "--host", "h1", "--hub", "--log-dir", str(tmp_path / "nodes"),
        "--connect", bus.connect[0], "--no-multicast", "--lease-ms", "500",
        name="agent",
    )  # fmt: skip
    client = BusClient(bus, SYSTEM)
    watch = Watch(client.session)
    wait_until(
        lambda: list(client.session.liveliness().get(K.host_alive("h1"), timeout=0.5)),
        15,
        "the host agent's token",
    )
    yield proc, client, watch
    client.close()


def test_start_run_data_and_stop(agent, procs):
    _proc, client, watch = agent
    reply = client.host("h1", m.StartNode(spec=relay_spec()))
    assert isinstance(reply, m.Ok), reply
    running = wait_until(lambda: watch.state("relay", "RUNNING"), 15, "relay RUNNING")
    procs.watch(running.pid)
    pub = client.session.declare_publisher(K.data("src"))
    wait_until(lambda: pub.matching_status.matching, 5, "the relay's subscriber")
    pub.put(encode_data({"value": 41.0}))
    wait_until(lambda: watch.data, 5, "relayed sample")
    assert watch.data[0]["value"] == 42.0

    reply = client.host("h1", m.StopNode(node="relay"))
    assert isinstance(reply, m.Ok)
    stopped = wait_until(lambda: watch.state("relay", "STOPPED"), 10, "relay STOPPED")
    assert "exit status 0" in stopped.reason  # SIGINT was enough: a clean shutdown
    listed = client.host("h1", m.ListNodes())
    assert isinstance(listed, m.Ok)
    assert [n["state"] for n in listed.result] == ["STOPPED"]


def test_kill9_is_detected_and_restarted(agent, procs):
    _, client, watch = agent
    client.host("h1", m.StartNode(spec=relay_spec()))
    first = wait_until(lambda: watch.state("relay", "RUNNING"), 15, "relay RUNNING")
    procs.watch(first.pid)
    n = len(watch.states)
    assert isinstance(client.host("h1", m.SignalNode(node="relay", signal=signal.SIGKILL)), m.Ok)
    backoff = wait_until(lambda: watch.state("relay", "BACKOFF", n), 10, "BACKOFF after kill")
    # Normally the exit (status -9) is seen first; the token can win a sub-ms race.
    assert "status -9" in backoff.reason or "liveliness lost" in backoff.reason
    again = wait_until(lambda: watch.state("relay", "RUNNING", n), 15, "relay RUNNING again")
    procs.watch(again.pid)
    assert again.pid != first.pid and again.restarts == 1


def test_frozen_node_is_detected_by_lease_and_replaced(agent, procs):
    _, client, watch = agent
    client.host("h1", m.StartNode(spec=relay_spec()))
    first = wait_until(lambda: watch.state("relay", "RUNNING"), 15, "relay RUNNING")
    procs.watch(first.pid)
    n = len(watch.states)
    t0 = time.time()
    client.host("h1", m.SignalNode(node="relay", signal=signal.SIGSTOP))
    lost = wait_until(lambda: watch.state("relay", "BACKOFF", n), 10, "frozen node detected")
    assert "liveliness lost" in lost.reason
    # Detected by the 500 ms lease, not Zenoh's default 10 s one.
    assert lost.stamp - t0 < 2.0
    again = wait_until(lambda: watch.state("relay", "RUNNING", n), 15, "replacement RUNNING")
    procs.watch(again.pid)
    assert again.pid != first.pid


def test_unusable_implementation_goes_fatal_not_restarted(agent):
    _, client, watch = agent
    spec = m.NodeSpec(system=SYSTEM, name="bad", host="h1", implementation="no.such.Node")
    client.host("h1", m.StartNode(spec=spec))
    fatal = wait_until(lambda: watch.state("bad", "FATAL"), 15, "bad node FATAL")
    assert fatal.restarts == 0


def test_malformed_requests_and_samples_crash_nothing(agent, procs):
    proc, client, watch = agent
    client.host("h1", m.StartNode(spec=relay_spec()))
    running = wait_until(lambda: watch.state("relay", "RUNNING"), 15, "relay RUNNING")
    procs.watch(running.pid)
    junk = [b"", b"\xc1", b"\x81\xa1t\xa3zzz", bytes(range(256))]
    for key in (K.host_ctl("h1"), K.node_ctl("relay")):
        for payload in junk:
            replies = list(client.session.get(key, payload=payload, timeout=2))
            reply = m.Codec[m.Reply](m.Reply).decode(replies[0].ok.payload.to_bytes())
            assert isinstance(reply, m.Err) and reply.code == "malformed"
    for key in (K.data("src"), K.events, K.selection, K.ctx("x"), K.inject("motor")):
        for payload in junk:
            client.session.put(key, payload)
    info = client.node("relay", m.Describe())
    assert isinstance(info, m.Ok)
    assert info.result["dropped"] >= len(junk)  # counted, not crashed
    assert proc.poll() is None
    assert watch.state("relay", "BACKOFF") is None


def test_killed_host_agent_takes_its_nodes_along(agent, procs):
    proc, client, watch = agent
    client.host("h1", m.StartNode(spec=relay_spec()))
    running = wait_until(lambda: watch.state("relay", "RUNNING"), 15, "relay RUNNING")
    procs.watch(running.pid)
    proc.kill()  # SIGKILL: no chance to stop anything
    proc.wait()
    from conftest import pid_alive

    wait_until(lambda: not pid_alive(running.pid), 10, "the orphaned node to die")
