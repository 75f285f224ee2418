"""rra_agent.ros2 endpoints on real Zenoh sessions through an embedded router: bad input
on a ROS 2 key (truncated CDR, another type or hash), odd liveliness tokens, services that
never answer or get bad requests, parameters and lifecycle, topic fields as measurements,
events on a ROS 2 topic and the relay. Nothing crashes; everything is counted or raised as
one clear error."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh

from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.ros2 import attachment
from rra_agent.ros2.bridge import EventTopic, TopicField, check_measurement, parse_source
from rra_agent.ros2.endpoint import Received, Ros2Context
from rra_agent.ros2.errors import BadName, FieldError, ServiceFailed, ServiceTimeout
from rra_agent.ros2.graph import GraphWatcher, query_graph
from rra_agent.ros2.names import NO_TYPE_HASH, data_key
from rra_agent.ros2.params import (
    LifecycleClient,
    LifecycleServer,
    ParameterClient,
    ParameterServer,
)
from rra_agent.ros2.relay import Relay
from rra_agent.ros2.types import TypeRegistry

BATTERY = "sensor_msgs/msg/BatteryState"
TYPES = TypeRegistry()


class Bus:
    def __init__(self) -> None:
        ep = f"tcp/127.0.0.1:{free_port()}"
        self.router = zenoh.open(BusConfig(mode="router", listen=[ep], connect=[]).to_zenoh())
        self.sessions = [zenoh.open(BusConfig(connect=[ep]).to_zenoh()) for _ in range(2)]
        self.a, self.b = (Ros2Context(s, TYPES) for s in self.sessions)
        self.raw = self.sessions[0]

    def close(self) -> None:
        self.a.close()
        self.b.close()
        for s in self.sessions:
            s.close()
        self.router.close()


@pytest.fixture
def bus() -> Iterator[Bus]:
    b = Bus()
    try:
        yield b
    finally:
        b.close()


def battery_key(type_hash: str | None = None) -> str:
    return data_key(0, "/battery", BATTERY, type_hash or TYPES.type_hash(BATTERY)).key


def put_until(bus: Bus, key: str, payload: bytes, done: Any, what: str, **kw: Any) -> None:
    """Put on ``key`` until ``done()`` (a fresh subscription may not be routed yet)."""
    deadline = time.monotonic() + 10
    while not done():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        bus.raw.put(key, payload, **kw)
        time.sleep(0.02)


def test_truncated_cdr_on_the_key_is_counted_and_the_topic_goes_on(bus: Bus) -> None:
    got: list[Received] = []
    sub = bus.b.node("monitor").subscription("/battery", BATTERY, got.append)
    good = TYPES.encode(BATTERY, {"percentage": 0.7})
    put_until(bus, battery_key(), good[:-6], lambda: sub.dropped["decode"], "a drop")
    assert not got and "bytes are not a CDR sensor_msgs/msg/BatteryState" in sub.last_drop
    put_until(bus, battery_key(), good, lambda: got, "a good sample after the bad one")
    assert got[0].message["percentage"] == pytest.approx(0.7)
    assert got[0].attachment is None  # a raw put carries none; still delivered


def test_another_definition_of_the_type_is_refused_a_humble_one_accepted(bus: Bus) -> None:
    got: list[Received] = []
    sub = bus.b.node("monitor").subscription("/battery", BATTERY, got.append)
    good = TYPES.encode(BATTERY, {"percentage": 0.1})
    other = "RIHS01_" + "0" * 64
    put_until(bus, battery_key(other), good, lambda: sub.dropped["type_hash"], "a drop")
    assert not got
    put_until(bus, battery_key(NO_TYPE_HASH), good, lambda: got, "a Humble sample")
    assert sub.received == 1


def test_a_wrong_type_from_an_rra_publisher_and_a_failing_callback(bus: Bus) -> None:
    drops: list[str] = []

    def boom(_: Received) -> None:
        raise RuntimeError("callback bug")

    sub = bus.b.node("monitor").subscription("/battery", BATTERY, boom,
                                             on_drop=lambda r, d: drops.append(r))
    wrong = bus.a.node("talker").publisher("/battery", "std_msgs/msg/String")
    right = bus.a.node("talker2").publisher("/battery", BATTERY)
    deadline = time.monotonic() + 10
    while not (sub.dropped["wrong_type"] and sub.dropped["callback"]):
        assert time.monotonic() < deadline, sub.dropped
        wrong.publish({"data": "hello"})
        right.publish({"percentage": 0.5})
        time.sleep(0.02)
    assert {"wrong_type", "callback"} <= set(drops)


def test_odd_liveliness_tokens_are_refused_and_counted(bus: Bus) -> None:
    watcher = GraphWatcher(bus.sessions[1])
    try:
        lv = bus.raw.liveliness()
        odd = [lv.declare_token("@ros2_lv/0/abc/0/0/XX/%/%/weird"),
               lv.declare_token("@ros2_lv/0/abc/0/1/MP/%/%/n/%t/NotAType/H/::,:,:,:,,")]
        node = bus.a.node("fine")
        wait_until(lambda: watcher.snapshot().refused >= 2 and watcher.snapshot().find("/fine"),
                   10, "odd tokens refused, the good node seen")
        assert watcher.snapshot().refused == 2 and len(watcher.snapshot().nodes()) == 1
        once = query_graph(bus.sessions[0], timeout=2)  # as a one-shot tool would
        assert once.refused == 2 and [n.fq_name for n in once.nodes()] == ["/fine"]
        for t in odd:
            t.undeclare()
        node.close()
        wait_until(lambda: not watcher.snapshot().find("/fine") and not watcher.snapshot().refused,
                   10, "the node and the odd tokens gone")
    finally:
        watcher.close()


def test_a_service_that_never_answers_is_a_deadline_error(bus: Bus) -> None:
    srv_type = "lifecycle_msgs/srv/ChangeState"
    key = data_key(0, "/stuck/change_state", srv_type, TYPES.type_hash(srv_type)).key
    held: list[zenoh.Query] = []
    seen = threading.Event()

    def hold(q: zenoh.Query) -> None:
        held.append(q)
        seen.set()

    q = bus.raw.declare_queryable(key, hold, complete=True)
    try:
        client = LifecycleClient(bus.b.node("manager"), "/stuck")
        wait_until(client.available, 10, "the stuck server")
        start = time.monotonic()
        with pytest.raises(ServiceTimeout, match=r"/stuck/change_state .* did not answer within "
                                                 r"0.3 s"):
            client.change("activate", timeout=0.3)
        assert 0.3 <= time.monotonic() - start < 2.0
        assert seen.is_set()
    finally:
        q.undeclare()
        held.clear()


def test_no_server_fails_at_once(bus: Bus) -> None:
    client = bus.b.node("manager").client("/nobody/get_parameters",
                                          "rcl_interfaces/srv/GetParameters")
    start = time.monotonic()
    with pytest.raises(ServiceFailed, match="no server for service /nobody/get_parameters"):
        client.call({"names": ["x"]}, timeout=2.0)
    assert time.monotonic() - start < 1.5


def test_bad_requests_and_failing_handlers_get_error_replies(bus: Bus) -> None:
    def handler(req: dict[str, Any]) -> dict[str, Any]:
        if req["names"] == ["boom"]:
            raise RuntimeError("no such thing")
        if req["names"] == ["bad"]:
            return {"values": [{"type": "x"}]}
        return {"values": []}

    srv = bus.a.node("server").service("/server/get_parameters",
                                       "rcl_interfaces/srv/GetParameters", handler)
    client = bus.b.node("caller").client("/server/get_parameters",
                                         "rcl_interfaces/srv/GetParameters")
    wait_until(client.available, 10, "the server")
    assert client.call({"names": []}, timeout=2) == {"values": []}
    with pytest.raises(ServiceFailed, match="handler failed: no such thing"):
        client.call({"names": ["boom"]}, timeout=2)
    with pytest.raises(ServiceFailed, match="handler's response"):
        client.call({"names": ["bad"]}, timeout=2)
    # a request without rmw_zenoh's attachment, and one that is not CDR
    for payload, att in ((TYPES.encode("rcl_interfaces/srv/GetParameters_Request", {}), None),
                         (b"junk", attachment.make(1, b"g" * 16))):
        replies = list(bus.raw.get(srv.key.key, payload=payload, attachment=att, timeout=2))
        assert len(replies) == 1 and replies[0].err is not None
    assert srv.dropped == {"handler": 1, "bad_response": 1, "bad_request": 2}
    assert srv.served == 1


def test_parameters_and_lifecycle_between_rra_nodes(bus: Bus) -> None:
    transitions: list[str] = []
    node = bus.a.node("driver", "/robot")
    params = ParameterServer(node, {"speed": 1.0},
                             on_set=lambda n, v: None if n == "speed" else f"no parameter {n}")
    life = LifecycleServer(node, lambda t: transitions.append(t) or t != "cleanup")
    manager = bus.b.node("manager")
    pc = ParameterClient(manager, "/robot/driver")
    lc = LifecycleClient(manager, "/robot/driver")
    wait_until(lambda: pc.available() and lc.available(), 10, "the driver's services")
    assert lc.state(timeout=2) == "unconfigured"
    assert pc.set({"speed": 0.5, "color": "red"}) == {"speed": None, "color": "no parameter color"}
    assert pc.get(["speed", "color"]) == {"speed": 0.5, "color": None}
    assert params.values == {"speed": 0.5}
    assert lc.change("activate") is False  # not configured yet
    assert lc.change("configure") and lc.change("activate") and lc.state() == "active"
    assert lc.change("deactivate") and lc.state() == "inactive"
    assert lc.change("cleanup") is False and life.state == "inactive"  # refused by the node
    assert lc.change("shutdown") and lc.state() == "finalized"
    assert transitions == ["configure", "activate", "deactivate", "cleanup", "shutdown"]
    with pytest.raises(FieldError, match="unknown lifecycle transition"):
        lc.change("explode")


def test_a_topic_field_is_a_measurement_value(bus: Bus) -> None:
    values: list[Any] = []
    drops: list[str] = []
    field = TopicField(bus.b.node("monitor"), "/battery", BATTERY, "cell_voltage.1",
                       lambda v, _: values.append(v), on_drop=lambda r, d: drops.append(r))
    pub = bus.a.node("driver").publisher("/battery", BATTERY)
    deadline = time.monotonic() + 10
    while not (values and drops):
        assert time.monotonic() < deadline
        pub.publish({"cell_voltage": [3.5, 3.75]})
        pub.publish({"cell_voltage": [3.5]})  # no element 1: a counted drop
        time.sleep(0.02)
    assert values[0] == 3.75 and field.dropped["field"] >= 1 and drops[0] == "field"


def test_measurement_sources_are_checked_without_a_bus() -> None:
    assert parse_source("ros2:/battery") == "/battery"
    assert parse_source("ctx/battery") is None
    with pytest.raises(BadName):
        parse_source("ros2:/bad name")
    assert check_measurement(TYPES, "/battery", BATTERY, "percentage") == "float32"
    assert check_measurement(TYPES, "/battery", BATTERY, "header.frame_id") == "string"
    with pytest.raises(FieldError, match="is std_msgs/msg/Header, not a number"):
        check_measurement(TYPES, "/battery", BATTERY, "header")
    with pytest.raises(FieldError, match="has no field 'percent'"):
        check_measurement(TYPES, "/battery", BATTERY, "percent")


def test_adaptation_events_on_a_ros2_topic(bus: Bus) -> None:
    got: list[Received] = []
    bus.b.node("listener").subscription("/rra/events", "std_msgs/msg/String", got.append)
    events = EventTopic(bus.a.node("rra_engine"))
    deadline = time.monotonic() + 10
    while not got:
        assert time.monotonic() < deadline
        events.publish({"t": "event", "kind": "swap", "component": "controller"})
        time.sleep(0.02)
    assert json.loads(got[0].message["data"])["kind"] == "swap"


def test_the_relay_rewires_without_touching_the_subscriber(bus: Bus) -> None:
    got: list[Received] = []
    bus.b.node("controller").subscription("/cmd", "std_msgs/msg/String", got.append)
    src = bus.a.node("sources")
    a, b = src.publisher("/cmd_a", "std_msgs/msg/String"), src.publisher("/cmd_b",
                                                                          "std_msgs/msg/String")
    relay = Relay(bus.a.node("relay"), "/cmd", "std_msgs/msg/String", "/cmd_a")

    def pump(want: str) -> None:
        deadline = time.monotonic() + 10
        while not any(g.message["data"] == want for g in got):
            assert time.monotonic() < deadline
            a.publish({"data": "a"})
            b.publish({"data": "b"})
            time.sleep(0.02)

    pump("a")
    assert all(g.message["data"] == "a" for g in got)
    relay.switch("/cmd_b")
    got.clear()
    pump("b")
    n = len(got)
    pump("b")
    assert [g.message["data"] for g in got[n:]] == ["b"] * (len(got) - n)
    assert relay.first_after_switch_ns is not None
