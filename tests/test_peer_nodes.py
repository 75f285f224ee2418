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
from rra_agent.bus.config import PEER_LISTEN, BusConfig, Tls
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
    assert agent._child_bus(node).mode == "peer"
    assert agent._child_bus(engine).mode == "client"
    assert agent.local.spare_bus is not None and agent.local.spare_bus.mode == "peer"
