"""Nodes as peers (``--peer-nodes``): the nodes of a host link to each other directly, as
rmw_zenoh's nodes do, so that data between two of them skips the host's router; engines and
tools stay its clients; refused on a bus with certificates (the routers enforce access
control). Real `rra up` of tests/data/relay_system on loopback.

How the test tells where data goes: ``rra up`` (the host's router, in its host agent) is
stopped for 1 s, shorter than the bus lease, so no link is lost. While it is stopped, a
node that takes its input over a direct link goes on relaying (its outputs' send stamps fall
inside the stall); one that takes it through the router gets nothing until the router runs
again.
"""

from __future__ import annotations

import contextlib
import time

import msgspec
import pytest
from conftest import RELAY
from conftest import RELAY_KEYS as K
from test_failures import stall

from rra_agent.bus import messages as m
from rra_agent.bus.client import wait_until
from rra_agent.bus.config import PEER_LISTEN, ROUTER_ONLY, BusConfig, Tls
from rra_agent.bus.session import open_session
from rra_agent.errors import RraError
from rra_agent.models.system import Command

#: How long the router is stopped, and the margin at each end of the stall within which a
#: sample's stamp is not counted as inside it (a send just before the stop, or the resume).
STALL, MARGIN = 1.0, 0.2


def relayed_during_a_stall_of_the_router(sys_, bus) -> tuple[list[float], tuple[float, float]]:
    """Send stamps of sink's own outputs, and the stall's (start, end) on the same clock.
    Seen by a session with the shipped lease (the test's own has 500 ms: its link to the
    stopped router would expire, and the samples the router held for it with it)."""
    stamps: list[float] = []

    def on(sample) -> None:
        with contextlib.suppress(msgspec.DecodeError):  # --hostile forges on sink/out too
            data = msgspec.msgpack.decode(sample.payload.to_bytes())
            stamp = m.unpack_stamp(sample.attachment.to_bytes() if sample.attachment else None)
            if isinstance(data, dict) and data.get("relay") == "sink" and stamp is not None:
                stamps.append(stamp)

    session = open_session(BusConfig(connect=bus.connect, multicast=False))
    sub = session.declare_subscriber(K.data("sink/out"), on)
    try:
        wait_until(lambda: len(stamps) >= 3, 20, "sink relaying the source's ticks")
        start = time.time()
        stall(sys_.proc.pid, STALL)
        end = time.time()
        wait_until(lambda: any(s > end for s in stamps), 20, "sink's outputs after the stall")
    finally:
        sub.undeclare()
        session.close()
    return stamps, (start, end)


def inside(stamps: list[float], window: tuple[float, float]) -> list[float]:
    start, end = window
    return [s for s in stamps if start + MARGIN < s < end - MARGIN]


def test_with_peer_nodes_data_between_nodes_of_a_host_flows_while_its_router_is_stopped(
    system, bus
):
    sys_ = system(RELAY, "--peer-nodes")
    stamps, window = relayed_during_a_stall_of_the_router(sys_, bus)
    # the source ticks at 20 Hz: ~12 samples in the 0.6 s counted; a few make it certain
    assert len(inside(stamps, window)) >= 3, (window, stamps)


def test_as_clients_of_the_router_nodes_get_nothing_while_it_is_stopped(system, bus):
    """The default: every sample crosses the router, so the stall stops the data (this is
    what makes the test above tell the two apart)."""
    sys_ = system(RELAY)
    stamps, window = relayed_during_a_stall_of_the_router(sys_, bus)
    assert inside(stamps, window) == [], (window, stamps)


def test_a_peer_node_drops_an_oversized_sample_it_gets_directly_before_python_sees_it(
    system, bus
):
    """A peer of the host (this test's session, linked to the nodes like one of them) puts
    2 MiB on source.out, then a marker sample on the same link: ``direct`` relays the marker,
    and its own counters never saw the big one, because its Zenoh session dropped it with
    the router's limits (without them it reached Python, which counted it ``too_large``)."""
    sys_ = system(RELAY, "--peer-nodes")
    as_peer = BusConfig(connect=bus.connect, multicast=False, peer_nodes=True).for_nodes()
    peer = open_session(as_peer)
    relayed: list[int] = []

    def on(sample) -> None:
        with contextlib.suppress(msgspec.DecodeError):
            data = msgspec.msgpack.decode(sample.payload.to_bytes())
            if isinstance(data, dict) and data.get("relay") == "direct":
                relayed.append(data.get("seq"))

    sub = peer.declare_subscriber(K.data("direct/out"), on)
    pub = peer.declare_publisher(K.data("source/out"))
    try:
        wait_until(lambda: relayed, 20, "direct relaying the source's ticks")
        marker = 10**9

        def marked() -> bool:
            pub.put(b"\x80" * (2 * 1024 * 1024))
            pub.put(msgspec.msgpack.encode({"seq": marker, "value": 1.0}))
            return marker in relayed

        wait_until(marked, 20, "the marker relayed by direct", interval=0.5)
    finally:
        pub.undeclare()
        sub.undeclare()
        peer.close()
    # counted per reason (a zero count is left out); under --hostile direct drops the
    # hostile client's malformed samples too, but its oversized ones die in the router
    stats = sys_.gather()["stats"]["node:direct"]
    assert stats.get("counters", {}).get("too_large", 0) == 0, stats


# ---- the configuration ---------------------------------------------------------------------
def test_nodes_are_peers_listening_on_loopback_and_everything_else_stays_a_client():
    bus = BusConfig(peer_nodes=True).host_router(hub=True).local_client()
    assert bus.mode == "client" and bus.peer_nodes
    nodes = bus.for_nodes()
    assert (nodes.mode, nodes.listen, nodes.connect) == ("peer", [PEER_LISTEN], bus.connect)
    config = nodes.to_zenoh()
    assert config.get_json("mode") == '"peer"'
    gossip = msgspec.json.decode(config.get_json("scouting/gossip"))
    assert gossip["enabled"] is True and gossip["multihop"] is False
    assert gossip["autoconnect"]["peer"] == ["router", "peer"]
    assert BusConfig().host_router(hub=True).local_client().for_nodes().mode == "client"


def test_peer_nodes_are_refused_on_a_bus_with_certificates(tmp_path):
    tls = Tls(ca=str(tmp_path / "ca.pem"), cert=str(tmp_path / "n.pem"), key=str(tmp_path / "k"))
    with pytest.raises(RraError, match="--peer-nodes needs a bus without certificates"):
        BusConfig(peer_nodes=True, tls=tls).check_peer_nodes()
    BusConfig(tls=tls).check_peer_nodes()  # no peers asked: fine


def test_the_host_agent_makes_its_nodes_peers_and_its_engines_clients(tmp_path):
    from rra_agent.bus.config import free_port
    from rra_agent.deployment import deploy
    from rra_agent.host.agent import HostAgent
    from rra_agent.host.catalog import Catalog

    dep = deploy(RELAY)
    catalog = Catalog.of(dep, "local", default_host=True)
    engine = m.NodeSpec(system=dep.system, name="resolution-a", host="local",
                        implementation=Command(command=["python3", "-m", "x"]))  # fmt: skip
    catalog.add_builtins([engine])
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"], peer_nodes=True)
    agent = HostAgent(dep.system, "local", bus, tmp_path, hub=True, catalog=catalog)
    node = m.NodeSpec(system=dep.system, name="sink", host="local",
                      implementation="rra_agent.nodes.generic.Relay")  # fmt: skip
    nodes = agent._child_bus(node)
    assert nodes.mode == "peer"
    assert agent._child_bus(engine).mode == "client"
    assert agent.local.spare_bus == nodes  # the spares open their sessions ahead as peers
    # a peer applies its router's payload limits itself: what it gets from another node
    # directly never crosses the router
    router = agent.session_bus.zenoh
    for key in ROUTER_ONLY:
        assert nodes.zenoh[key] == router[key], key
    assert ROUTER_ONLY.isdisjoint(agent._child_bus(engine).zenoh)
    nodes.to_zenoh()  # Zenoh takes the limits in a peer's configuration
