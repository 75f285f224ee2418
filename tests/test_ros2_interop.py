"""rra_agent.ros2 against zenoh-ros2-sdk, an independent implementation of rmw_zenoh, in a
process of its own (tests/data/ros2/sdk_peer.py), through an embedded Zenoh router: topics
both ways, services both ways (SetParameters, GetParameters, ChangeState), each side's
graph seeing the other's nodes, and a wrong type on a topic refused and counted."""

from __future__ import annotations

import contextlib
import json
import os
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.ros2.endpoint import Received, Ros2Context
from rra_agent.ros2.graph import GraphWatcher
from rra_agent.ros2.params import LifecycleClient, LifecycleServer, ParameterClient, ParameterServer
from rra_agent.ros2.types import TypeRegistry

#: Every test here starts processes or opens Zenoh sessions (pytest -m 'not system').
pytestmark = pytest.mark.system

pytest.importorskip("zenoh_ros2_sdk")

PEER = Path(__file__).parent / "data" / "ros2" / "sdk_peer.py"
TYPES = [
    "sensor_msgs/msg/BatteryState",
    "std_msgs/msg/String",
    "rcl_interfaces/srv/SetParameters",
    "rcl_interfaces/srv/GetParameters",
    "lifecycle_msgs/srv/ChangeState",
]


class Peer:
    """A zenoh-ros2-sdk process: JSON lines out, runs until its stdin closes."""

    def __init__(self, port: int, msg_dir: Path, role: str, *args: str) -> None:
        env = {**os.environ, "ZENOH_CONFIG_OVERRIDE": "scouting/delay=0"}
        self.proc = subprocess.Popen(
            [sys.executable, str(PEER), str(port), str(msg_dir), role, *args],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            text=True, env=env,
        )
        self.lines: queue.Queue[dict[str, Any]] = queue.Queue()
        self.seen: list[dict[str, Any]] = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout
        for line in self.proc.stdout:
            with contextlib.suppress(ValueError):
                self.lines.put(json.loads(line))

    def expect(self, pred: Callable[[dict[str, Any]], bool], timeout: float = 15.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0 or (self.proc.poll() is not None and self.lines.empty()):
                err = self.proc.stderr.read() if self.proc.poll() is not None else ""
                raise AssertionError(f"peer gave no matching line; seen {self.seen[-3:]}\n{err}")
            try:
                obj = self.lines.get(timeout=min(left, 0.2))
            except queue.Empty:
                continue
            self.seen.append(obj)
            if pred(obj):
                return obj

    def close(self) -> None:
        try:
            assert self.proc.stdin
            self.proc.stdin.close()
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture
def router() -> Iterator[int]:
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    session = zenoh.open(BusConfig(mode="router", listen=[ep], connect=[]).to_zenoh())
    try:
        yield port
    finally:
        session.close()


@pytest.fixture(scope="module")
def types() -> TypeRegistry:
    return TypeRegistry("jazzy")


@pytest.fixture
def msg_dir(tmp_path: Path, types: TypeRegistry) -> Path:
    types.export(tmp_path / "msgs", TYPES)
    return tmp_path / "msgs"


@pytest.fixture
def rra(router: int, types: TypeRegistry) -> Iterator[Ros2Context]:
    session = zenoh.open(BusConfig(connect=[f"tcp/127.0.0.1:{router}"]).to_zenoh())
    ctx = Ros2Context(session, types)
    try:
        yield ctx
    finally:
        ctx.close()
        session.close()


@pytest.fixture
def peers() -> Iterator[list[Peer]]:
    started: list[Peer] = []
    try:
        yield started
    finally:
        for p in started:
            p.close()


def test_rra_decodes_the_sdks_battery_state(rra, router, msg_dir, peers) -> None:
    got: list[Received] = []
    sub = rra.node("monitor").subscription("/battery", "sensor_msgs/msg/BatteryState", got.append)
    peer = Peer(router, msg_dir, "pub_battery")
    peers.append(peer)
    ready = peer.expect(lambda o: "ready" in o)
    assert ready["ready"] == sub.key.key  # the same key expression, type hash included
    wait_until(lambda: len(got) >= 3, 15, "BatteryState samples from zenoh-ros2-sdk")
    msg = got[-1].message
    assert msg is not None and 0 < msg["percentage"] <= 1 and msg["voltage"] == 12.0
    assert msg["cell_voltage"] == pytest.approx([3.7, 3.8])
    assert got[-1].attachment is not None and got[-1].attachment.seq > got[0].attachment.seq
    assert not sub.dropped


def test_the_sdk_decodes_rras_battery_state(rra, router, msg_dir, peers) -> None:
    pub = rra.node("battery_driver").publisher("/battery", "sensor_msgs/msg/BatteryState")
    peer = Peer(router, msg_dir, "sub_battery")
    peers.append(peer)
    assert peer.expect(lambda o: "ready" in o)["ready"] == pub.key.key
    wait_until(pub.matched, 15, "the SDK's subscriber to match")
    deadline = time.monotonic() + 15
    msg = {"percentage": 0.33, "voltage": 11.5, "cell_voltage": [3.6, 3.7, 3.8],
           "header": {"frame_id": "base"}}
    got = None
    while got is None and time.monotonic() < deadline:
        pub.publish(msg)  # the SDK's peer-mode session may take a moment to route to it
        with contextlib.suppress(AssertionError):
            got = peer.expect(lambda o: "percentage" in o, timeout=0.5)
    assert got is not None
    assert got["percentage"] == pytest.approx(0.33) and got["frame"] == "base"
    assert got["cells"] == pytest.approx([3.6, 3.7, 3.8])


def test_a_wrong_type_on_the_topic_is_refused_and_counted(rra, router, msg_dir, peers) -> None:
    got: list[Received] = []
    drops: list[tuple[str, str]] = []
    sub = rra.node("monitor").subscription(
        "/battery", "sensor_msgs/msg/BatteryState", got.append,
        on_drop=lambda r, d: drops.append((r, d)))
    peers.append(peer := Peer(router, msg_dir, "pub_string"))
    peer.expect(lambda o: "ready" in o)
    wait_until(lambda: sub.dropped["wrong_type"] >= 2, 15, "String samples refused")
    assert not got
    assert drops[0][0] == "wrong_type" and "std_msgs/msg/String" in drops[0][1]


def test_the_sdks_client_calls_rras_parameter_and_lifecycle_services(
    rra, router, msg_dir, peers
) -> None:
    node = rra.node("controller")
    params = ParameterServer(node, {"gain": 1.0})
    lifecycle = LifecycleServer(node, state="inactive")
    peers.append(peer := Peer(router, msg_dir, "call", "/controller"))
    assert peer.expect(lambda o: "set" in o)["set"] == [[True, ""]]
    assert params.values["gain"] == 0.25
    assert peer.expect(lambda o: "get" in o)["get"] == [[3, 0.25]]
    assert peer.expect(lambda o: "change" in o)["change"] is True
    assert lifecycle.state == "active"


def test_rras_clients_call_the_sdks_services(rra, router, msg_dir, peers) -> None:
    peers.append(peer := Peer(router, msg_dir, "serve"))
    peer.expect(lambda o: "ready" in o)
    node = rra.node("rra_manager")
    graph = GraphWatcher(rra.session)
    try:
        wait_until(lambda: "/sdk_node/change_state" in graph.snapshot().services(), 15,
                   "the SDK's services in the graph")
    finally:
        graph.close()
    params = ParameterClient(node, "/sdk_node")
    life = LifecycleClient(node, "/sdk_node")
    wait_until(lambda: params.available() and life.available(), 15, "the SDK's queryables")
    assert params.set({"speed": 2.5, "forbidden": 1.0}, timeout=5) == {
        "speed": None, "forbidden": "no"}
    assert params.get(["speed", "missing"], timeout=5) == {"speed": 2.5, "missing": None}
    assert life.change("activate", timeout=5) is True
    assert peer.expect(lambda o: "transition" in o) == {"transition": 3, "success": True}
    assert life.change("activate", timeout=5) is False  # already active


def test_each_graph_sees_the_other_sides_nodes(rra, router, msg_dir, peers) -> None:
    node = rra.node("battery_driver", "/robot")
    node.publisher("/battery", "sensor_msgs/msg/BatteryState")
    ParameterServer(node, {})
    peers.append(sdk := Peer(router, msg_dir, "serve"))
    sdk.expect(lambda o: "ready" in o)
    graph = GraphWatcher(rra.session)
    try:
        def sdk_services() -> set[str]:
            # zenoh-ros2-sdk declares a node per endpoint: three nodes named /sdk_node
            return {e.name for n in graph.snapshot().find("/sdk_node") for e in n.endpoints}

        want = {"/sdk_node/set_parameters", "/sdk_node/get_parameters", "/sdk_node/change_state"}
        wait_until(lambda: sdk_services() >= want, 15, "the SDK's node and its services")
        seen = graph.snapshot()
        assert all(n.announced for n in seen.find("/sdk_node"))
        assert seen.services()["/sdk_node/change_state"] == {"lifecycle_msgs/srv/ChangeState"}
        assert seen.refused == 0
    finally:
        graph.close()
    peers.append(info := Peer(router, msg_dir, "topic_info", "/battery"))
    found = info.expect(lambda o: "types" in o)
    assert found["types"] == ["sensor_msgs/msg/BatteryState"]
    assert found["publishers"] == ["battery_driver"]
    assert ["/robot/battery_driver/set_parameters", ["rcl_interfaces/srv/SetParameters"]] in \
        found["services"]
