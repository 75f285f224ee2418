"""The ROS 2 graph model, pure: tokens in, nodes with their endpoints out; odd tokens
counted; the listing for `rra status` fits 100 columns."""

from __future__ import annotations

import json

from rra_agent.ros2.graph import Graph, graph_lines
from rra_agent.ros2.tokens import Kind, Qos, Token

H = "RIHS01_" + "ab" * 32


def tok(kind: Kind, node: str = "talker", ns: str = "/", name: str = "/chatter",
        typ: str = "std_msgs/msg/String", zid: str = "a1", nid: int = 0, eid: int = 1,
        domain: int = 0) -> str:
    if kind is Kind.NODE:
        return Token(domain, zid, nid, nid, kind, node, ns).key
    return Token(domain, zid, nid, eid, kind, node, ns, name=name, ros_type=typ, type_hash=H,
                 qos=Qos(depth=10)).key


def test_nodes_gather_their_endpoints() -> None:
    g = Graph()
    for key in [tok(Kind.PUBLISHER), tok(Kind.NODE),
                tok(Kind.SERVICE, name="/talker/set_parameters",
                    typ="rcl_interfaces/srv/SetParameters", eid=2),
                tok(Kind.NODE, "listener", "/robot", zid="b2"),
                tok(Kind.SUBSCRIPTION, "listener", "/robot", zid="b2"),
                tok(Kind.CLIENT, "listener", "/robot", "/talker/set_parameters",
                    "rcl_interfaces/srv/SetParameters", zid="b2", eid=3)]:
        assert g.apply(key, True) is not None
    nodes = g.nodes()
    assert [n.fq_name for n in nodes] == ["/robot/listener", "/talker"]
    talker = g.find("/talker")[0]
    assert talker.announced and [e.name for e in talker.of(Kind.PUBLISHER)] == ["/chatter"]
    assert [e.ros_type for e in talker.of(Kind.SERVICE)] == ["rcl_interfaces/srv/SetParameters"]
    assert g.topics() == {"/chatter": {"std_msgs/msg/String"}}
    assert g.services() == {"/talker/set_parameters": {"rcl_interfaces/srv/SetParameters"}}
    assert len(g.endpoints(Kind.SUBSCRIPTION, "/chatter")) == 1
    assert g.to_json()["nodes"][1]["publishers"] == [
        {"name": "/chatter", "type": "std_msgs/msg/String",
         "qos": "reliable volatile keep_last(10)"}]


def test_endpoints_seen_before_their_node_and_tokens_that_go() -> None:
    g = Graph()
    g.apply(tok(Kind.PUBLISHER), True)
    assert not g.find("/talker")[0].announced
    g.apply(tok(Kind.NODE), True)
    assert g.find("/talker")[0].announced
    g.apply(tok(Kind.PUBLISHER), False)
    assert g.find("/talker")[0].endpoints == []
    g.apply(tok(Kind.NODE), False)
    assert g.nodes() == [] and len(g) == 0
    assert g.apply("never/seen", False) is None


def test_odd_tokens_are_counted_not_raised() -> None:
    g = Graph()
    for odd in ["@ros2_lv/0/zz/0/0/NN/%/%/x", "@ros2_lv/0/a1/0/0/QQ/%/%/x", "garbage", ""]:
        assert g.apply(odd, True) is None
    assert g.refused == 4 and "not an rmw_zenoh liveliness token" in (g.last_refused or "")
    assert g.nodes() == []
    g.apply("garbage", True)  # seen again: still one token
    assert g.refused == 4
    g.apply("garbage", False)
    assert g.refused == 3


def test_other_domains_are_left_out_unless_asked() -> None:
    g = Graph(0)
    g.apply(tok(Kind.NODE, domain=3), True)
    assert g.nodes() == [] and g.refused == 0
    every = Graph(None)
    every.apply(tok(Kind.NODE, domain=3), True)
    assert every.nodes()[0].domain == 3


def test_the_listing_fits_100_columns() -> None:
    g = Graph()
    long = "/" + "/".join(["segment_" + "x" * 20] * 6)
    g.apply(tok(Kind.NODE, "n" * 80), True)
    g.apply(tok(Kind.PUBLISHER, "n" * 80, name=long), True)
    g.apply("bad", True)
    lines = g.lines()
    assert lines[0] == "ROS 2 graph (domain 0): 1 nodes, 1 tokens refused"
    assert all(len(line) <= 100 for line in lines)
    assert lines[2].startswith("    pub /segment_")
    assert graph_lines(json.loads(json.dumps(g.to_json()))) == lines  # from rra status --json
