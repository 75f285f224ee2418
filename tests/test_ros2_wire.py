"""rmw_zenoh's wire format, pure: names and data keys, liveliness tokens and their QoS,
the 33-byte attachment. Round trips are property-based; odd input is refused with the
layer's one error type, never another exception."""

from __future__ import annotations

import contextlib
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rra_agent.ros2 import attachment
from rra_agent.ros2.errors import BadAttachment, BadName, BadToken
from rra_agent.ros2.names import (
    NO_TYPE_HASH,
    data_key,
    dds_type,
    parse_data_key,
    qualify,
    ros_type,
)
from rra_agent.ros2.tokens import INFINITE, Kind, Qos, Token, parse_token

HASH = "RIHS01_4bee5dfce981c98faa6828b868307a0a73f992ed0789f374ee96c8f840e69741"
# What zenoh-ros2-sdk declared for a BatteryState publisher (docs/ros2.md).
SDK_NODE = "@ros2_lv/0/f1e2d3c4b5a69788/0/0/NN/%/%/battery_node"
SDK_PUB = ("@ros2_lv/0/f1e2d3c4b5a69788/0/0/MP/%/%/battery_node/%battery/"
           f"sensor_msgs::msg::dds_::BatteryState_/{HASH}/::,10:,:,:,,")
# rmw_zenoh's design.md examples.
RMW_SUB = ("@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/"
           "std_msgs::msg::dds_::String_/RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743"
           "503259e948f6b1a18/::,10:,:,:,,")

token_chunk = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,8}", fullmatch=True)
names = st.lists(token_chunk, min_size=1, max_size=4).map(lambda ts: "/" + "/".join(ts))
namespaces = st.one_of(st.just("/"), names)
type_names = st.tuples(
    st.from_regex(r"[a-z][a-z0-9_]{0,8}", fullmatch=True),
    st.sampled_from(["msg", "srv"]),
    st.from_regex(r"[A-Z][A-Za-z0-9]{0,8}", fullmatch=True),
).map("/".join)
hashes = st.one_of(st.just(NO_TYPE_HASH), st.from_regex(r"RIHS01_[0-9a-f]{64}", fullmatch=True))
durations = st.one_of(st.just(INFINITE), st.tuples(st.integers(0, 2**31), st.integers(0, 10**9)))
qoses = st.builds(
    Qos,
    reliability=st.sampled_from([0, 1, 2, 4]),
    durability=st.sampled_from([0, 1, 2, 4]),
    history=st.sampled_from([0, 1, 2]),
    depth=st.integers(0, 10_000),
    deadline=durations,
    lifespan=durations,
    liveliness=st.sampled_from([0, 1, 3, 5]),
    lease=durations,
)


def test_data_keys_are_rmw_zenohs() -> None:
    assert data_key(0, "/chatter", "std_msgs/msg/String", NO_TYPE_HASH).key == (
        "0/chatter/std_msgs::msg::dds_::String_/TypeHashNotSupported")
    key = data_key(2, "/robot1/battery", "sensor_msgs/msg/BatteryState", HASH)
    assert key.key == f"2/robot1/battery/sensor_msgs::msg::dds_::BatteryState_/{HASH}"
    assert key.any_type == "2/robot1/battery/*/*"
    assert parse_data_key(key.key) == key
    assert dds_type("example_interfaces/srv/AddTwoInts") == (
        "example_interfaces::srv::dds_::AddTwoInts_")
    assert ros_type("std_msgs::msg::dds_::String_") == "std_msgs/msg/String"


@pytest.mark.parametrize("bad", ["", "a//b", "/a/", "/1abc", "/a b", "~/x", "/{ns}/x", "/a-b"])
def test_bad_names_are_refused(bad: str) -> None:
    with pytest.raises(BadName):
        qualify(bad)


def test_relative_names_go_under_the_namespace() -> None:
    assert qualify("battery", "/robot") == "/robot/battery"
    assert qualify("/battery", "/robot") == "/battery"


@pytest.mark.parametrize("bad", [
    "0/battery", "x/battery/T/H", f"0/battery/std_msgs/String/{HASH}",
    "0/battery/std_msgs::msg::dds_::String_/RIHS01_zz", "0//std_msgs::msg::dds_::String_/"
    + NO_TYPE_HASH, f"999/battery/std_msgs::msg::dds_::String_/{HASH}",
])
def test_bad_data_keys_are_refused(bad: str) -> None:
    with pytest.raises(BadToken):
        parse_data_key(bad)


@settings(deadline=None)
@given(st.integers(0, 232), names, type_names, hashes)
def test_data_key_round_trip(domain: int, name: str, typ: str, h: str) -> None:
    key = data_key(domain, name, typ, h)
    assert parse_data_key(key.key) == key


def test_tokens_seen_from_zenoh_ros2_sdk_and_rmw_zenoh_parse() -> None:
    node = parse_token(SDK_NODE)
    assert (node.kind, node.node, node.namespace, node.enclave) == (
        Kind.NODE, "battery_node", "/", "/")
    pub = parse_token(SDK_PUB)
    assert (pub.kind, pub.name, pub.ros_type, pub.type_hash) == (
        Kind.PUBLISHER, "/battery", "sensor_msgs/msg/BatteryState", HASH)
    assert pub.qos == Qos(depth=10) and pub.node_key == node.node_key
    assert pub.key == SDK_PUB and node.key == SDK_NODE
    sub = parse_token(RMW_SUB)
    assert (sub.domain, sub.entity_id, sub.kind, sub.name) == (2, 10, Kind.SUBSCRIPTION,
                                                               "/chatter")


def test_qos_defaults_are_left_empty() -> None:
    assert Qos().encode() == "::,:,:,:,,"
    assert Qos(depth=10).encode() == "::,10:,:,:,,"
    assert Qos(reliability=2, durability=1, history=2).encode() == "2:1:2,:,:,:,,"
    assert Qos.decode("2:1:2,:,:,:,,").describe() == "best_effort transient_local keep_all"


@settings(deadline=None)
@given(qoses)
def test_qos_round_trip(qos: Qos) -> None:
    assert Qos.decode(qos.encode()) == qos


@settings(deadline=None)
@given(st.integers(0, 232), st.from_regex(r"[0-9a-f]{1,32}", fullmatch=True),
       st.integers(0, 10**6), st.integers(0, 10**6), st.sampled_from(list(Kind)),
       token_chunk, namespaces, names, type_names, hashes, qoses)
def test_token_round_trip(domain, zid, nid, eid, kind, node, ns, name, typ, h, qos) -> None:
    if kind is Kind.NODE:
        token = Token(domain, zid, nid, nid, kind, node, ns)
    else:
        token = Token(domain, zid, nid, eid, kind, node, ns, name=name, ros_type=typ,
                      type_hash=h, qos=qos)
    assert parse_token(token.key) == token


ODD_TOKENS = [
    "", "@ros2_lv", "@ros2_lv/0", SDK_NODE + "/extra", SDK_PUB.replace("/MP/", "/XX/"),
    SDK_NODE.replace("/NN/", "/MP/"), SDK_PUB.replace("/MP/", "/NN/"),
    SDK_NODE.replace("@ros2_lv", "@ros3_lv"), SDK_NODE.replace("/0/0/NN", "/x/0/NN"),
    SDK_NODE.replace("/0/f1e2", "/-1/f1e2"), SDK_NODE.replace("f1e2d3c4b5a69788", "ZID"),
    SDK_NODE.replace("battery_node", "bad-name"), SDK_NODE.replace("/%/%/", "/x/%/"),
    SDK_PUB.replace("::,10:,:,:,,", "::,10"), SDK_PUB.replace("::,10:", "9:9:,10:"),
    SDK_PUB.replace("::,10:", "::,ten:"), SDK_PUB.replace("%battery", "battery%%x"),
    SDK_PUB.replace("sensor_msgs::msg::dds_::BatteryState_", "BatteryState"),
    SDK_PUB.replace(HASH, "RIHS02_x"), "@ros2_lv/" + "/".join(["0"] * 12),
    SDK_NODE.replace("/0/0/NN", "/99999999999999999999/0/NN"),
]


@pytest.mark.parametrize("odd", ODD_TOKENS)
def test_odd_tokens_are_refused(odd: str) -> None:
    with pytest.raises(BadToken):
        parse_token(odd)


@settings(deadline=None)
@given(st.lists(st.one_of(st.sampled_from(["@ros2_lv", "0", "%", "NN", "MP", "SS", "::,:,:,:,,",
                                            "a", "", "1:2:3", "std_msgs::msg::dds_::S_"]),
                          st.text(max_size=6)), max_size=14).map("/".join))
def test_any_string_is_a_token_or_refused(key: str) -> None:
    with contextlib.suppress(BadToken):
        parse_token(key)


def test_the_attachment_is_33_bytes_as_rmw_zenoh_documents() -> None:
    gid = bytes(range(16))
    packed = attachment.Attachment(7, 1_700_000_000_123_456_789, gid).pack()
    assert len(packed) == attachment.SIZE == 33
    assert packed == struct.pack("<qq", 7, 1_700_000_000_123_456_789) + b"\x10" + gid
    assert attachment.unpack(packed) == attachment.Attachment(7, 1_700_000_000_123_456_789, gid)


def test_the_attachment_is_zenohs_own_serialization() -> None:
    from zenoh.ext import Int64, UInt8, z_serialize

    gid = bytes(range(16, 32))
    theirs = z_serialize((Int64(3), Int64(42), [UInt8(b) for b in gid])).to_bytes()
    assert attachment.Attachment(3, 42, gid).pack() == theirs


def test_the_attachment_reads_zenoh_ros2_sdks() -> None:
    sdk = pytest.importorskip("zenoh_ros2_sdk.attachment")
    raw = sdk.Attachment(sequence_id=5, timestamp_ns=99, gid=b"g" * 16).to_bytes()
    assert attachment.unpack(raw) == attachment.Attachment(5, 99, b"g" * 16)
    ours = attachment.Attachment(6, 100, b"h" * 16).pack()
    back = sdk.Attachment.from_bytes(ours)
    assert (back.sequence_id, back.timestamp_ns, back.gid) == (6, 100, b"h" * 16)


@settings(deadline=None)
@given(st.integers(-(2**63), 2**63 - 1), st.integers(-(2**63), 2**63 - 1),
       st.binary(min_size=16, max_size=16))
def test_attachment_round_trip(seq: int, ts: int, gid: bytes) -> None:
    assert attachment.unpack(attachment.Attachment(seq, ts, gid).pack()) == attachment.Attachment(
        seq, ts, gid)


@settings(deadline=None)
@given(st.one_of(st.none(), st.binary(max_size=40)))
def test_any_bytes_are_an_attachment_or_refused(data: bytes | None) -> None:
    with contextlib.suppress(BadAttachment):
        attachment.unpack(data)


def test_bad_attachments_say_why() -> None:
    good = attachment.Attachment(1, 2, b"x" * 16).pack()
    with pytest.raises(BadAttachment, match="no attachment"):
        attachment.unpack(None)
    with pytest.raises(BadAttachment, match="32 bytes"):
        attachment.unpack(good[:-1])
    with pytest.raises(BadAttachment, match="GID length 17"):
        attachment.unpack(good[:16] + b"\x11" + good[17:])
    with pytest.raises(BadAttachment):
        attachment.Attachment(1, 2, b"short").pack()


def test_a_gid_is_stable_and_unique_per_token() -> None:
    assert attachment.gid_of(SDK_PUB) == attachment.gid_of(SDK_PUB)
    assert attachment.gid_of(SDK_PUB) != attachment.gid_of(SDK_NODE)
    assert len(attachment.gid_of(SDK_PUB)) == 16
