"""The ROS 2 side of a system package, in process: its models, their validation (each
problem located at the model element that says it), the spec a host agent derives, the
access control, ``rra status``'s graph section and a node's ROS 2 ports mirrored as CDR.
The example package is scenarios/ros2_rover; each case plants one problem in a copy."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import msgspec
import pytest
from conftest import plant, position

from rra_agent.bus import messages as m
from rra_agent.cli.status import render, ros2_section
from rra_agent.deployment import deploy
from rra_agent.host.catalog import Catalog
from rra_agent.node.ros2mirror import Ros2Mirror
from rra_agent.package.loader import load_package
from rra_agent.package.validate import validate_package
from rra_agent.ros2.graph import Graph, graph_lines
from rra_agent.ros2.tokens import node_token
from rra_agent.security.acl import access_control

ROVER = Path(__file__).resolve().parents[1] / "scenarios" / "ros2_rover"


def rover(tmp_path: Path) -> Path:
    root = tmp_path / "ros2_rover"
    shutil.copytree(ROVER, root, ignore=shutil.ignore_patterns("__pycache__", "*.scenario.yaml"))
    return root


def problems(root: Path) -> list[str]:
    return [e.headline for e in validate_package(load_package(root, validate=False))]


def at(root: Path, file: str, text: str, token: str, nth: int = 1) -> str:
    line, col = position(text, token, nth)
    return f"{root / file}:{line}:{col}"


# ---- validation ---------------------------------------------------------------------------
def test_the_example_package_is_valid() -> None:
    assert problems(ROVER) == []


@pytest.mark.parametrize(
    ("file", "old", "new", "token", "message"),
    [
        ("measurements.yaml", "field: percentage", "field: percent", "percent",
         "sensor_msgs/msg/BatteryState has no field 'percent'"),
        ("measurements.yaml", "ros2_type: sensor_msgs/msg/BatteryState",
         "ros2_type: sensor_msgs/msg/BatteryStat", "sensor_msgs/msg/BatteryStat",
         "unknown ROS 2 type 'sensor_msgs/msg/BatteryStat' in jazzy"),
        ("measurements.yaml", "    field: planner\n", "    field: limit\n", "limit",
         "field 'limit' of rover_msgs/msg/Drive is float64, but measurement 'DrivePlanner' is str"),
        ("measurements.yaml", "field: percentage", "field: header", "header",
         "is std_msgs/msg/Header, not a number, bool or string"),
        ("system.yaml", "ros2_type: rover_msgs/msg/Command}\n\n  - name: planner_eco",
         "ros2_type: rover_msgs/msg/Comand}\n\n  - name: planner_eco", "rover_msgs/msg/Comand",
         "unknown ROS 2 type 'rover_msgs/msg/Comand'"),
        ("runtime.yaml", "planner_eco: standby", "planner_eco: start-then-stop",
         "start-then-stop", "ROS 2 node planner_eco is not managed"),
    ],
)
def test_a_ros2_problem_is_located_where_it_is_written(
    tmp_path: Path, file: str, old: str, new: str, token: str, message: str
) -> None:
    root = rover(tmp_path)
    text = plant(root, file, old, new)
    if "not managed" in message:  # only the eco planner loses its lifecycle
        plant(root, "system.yaml", "Plans to save the battery (0.4 m/s); a managed node.\n"
              "    ros2: {lifecycle: true}", "Plans to save the battery (0.4 m/s).\n    ros2: {}")
    found = problems(root)
    mine = [p for p in found if message in p]
    assert len(mine) == 1 and mine[0].startswith(at(root, file, text, token) + ": "), found
    if "Comand" in token:  # the port's type is no longer its ROS 2 type either
        assert "type rover_msgs/msg/Command is not the port's ros2_type" in found[0]
    else:
        assert found == mine


def test_a_ros2_node_port_needs_a_ros2_type(tmp_path: Path) -> None:
    root = rover(tmp_path)
    text = plant(root, "system.yaml", "type: rover_msgs/msg/Drive,\n         ros2_type: "
                 "rover_msgs/msg/Drive}", "type: rover_msgs/msg/Drive}")
    found = problems(root)
    assert f"{at(root, 'system.yaml', text, 'drive, direction')}: port controller.drive of ROS 2 "\
        "node controller needs a `ros2_type` (its samples are ROS 2 messages)" in found


def test_ros2_parts_need_the_ros2_section(tmp_path: Path) -> None:
    root = rover(tmp_path)
    manifest = (root / "rra.yaml").read_text()
    (root / "rra.yaml").write_text(manifest[: manifest.index("\nros2:")])
    found = problems(root)
    assert len(found) == 5 + 3  # five components, three measurements
    assert all("needs a `ros2:` section in rra.yaml" in p for p in found)


def test_a_measurement_from_ros2_needs_its_type(tmp_path: Path) -> None:
    root = rover(tmp_path)
    text = plant(root, "measurements.yaml", "    ros2_type: sensor_msgs/msg/BatteryState\n", "")
    with pytest.raises(Exception) as info:
        load_package(root, validate=False)
    assert "a ROS 2 source needs 'ros2_type'" in str(info.value)
    assert at(root, "measurements.yaml", text, "name: BattLev") in str(info.value)


def test_a_bad_ros2_implementation_is_located(tmp_path: Path) -> None:
    root = rover(tmp_path)
    text = plant(root, "system.yaml", "    implementation:\n      command: [sh, -c, 'exec "
                 "\"$RRA_PYTHON\" ros2_side/rover_node.py saboteur \"$@\"', saboteur]",
                 '    implementation: "ros2: rover nodes/saboteur"')
    found = problems(root)
    assert len(found) == 1 and found[0].startswith(at(root, "system.yaml", text, '"ros2:', 2))
    assert "expected 'ros2: PACKAGE EXECUTABLE'" in found[0]


# ---- what a host agent runs ------------------------------------------------------------------
def test_the_host_agent_derives_the_ros2_side_from_its_model() -> None:
    dep = deploy(ROVER)
    catalog = Catalog(dep.configured, "local", package_root=ROVER, default_host=True,
                      ros2=dep.package.manifest.ros2)
    planner = dep.configured.component("planner_eco")
    assert planner is not None
    asked = m.NodeSpec(system="ros2_rover", name="planner_eco", host="local",
                       implementation=planner.implementation, params={"speed": 0.4})
    spec = catalog.admit(asked)
    assert spec.ros2 == m.Ros2Spec(
        domain=0, distro="jazzy", interfaces=str(ROVER / "interfaces"), folder=str(ROVER),
        node="planner_eco", executable=True, lifecycle=True,
        ports={"cmd": "rover_msgs/msg/Command"},
    )
    assert m.spec_digest(spec) == m.spec_digest(msgspec.structs.replace(spec, ros2=None))
    assert "ros2:" not in " ".join(catalog.preload)


def test_the_access_control_opens_the_ros_domain_to_who_speaks_ros2() -> None:
    acl = access_control(deploy(ROVER), "local")
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["node:controller/ros2"]["key_exprs"] == ["0/**", "@ros2_lv/0/**"]
    assert "@ros2_lv/0/**" in rules["engines/all"]["key_exprs"]
    assert "@ros2_lv/0/**" in rules["operator/read"]["key_exprs"]


# ---- rra status ------------------------------------------------------------------------------
def test_the_graph_section_fits_100_columns_and_shows_a_name_once() -> None:
    graph = Graph(0)
    for i in range(3):  # zenoh-ros2-sdk declares a node per endpoint
        graph.apply(node_token(0, "a1", i, "battery_driver").key, True)
    graph.apply(node_token(0, "b2", 0, "x" * 120).key, True)
    graph.apply("@ros2_lv/0/zz/odd", True)
    status: dict[str, Any] = {"engine": None, "nodes": [], "hosts": [], "host_agents": [],
                              "stats": {}, "ros2": graph.to_json()}
    lines = ros2_section(status)
    assert lines[0] == "ROS 2 graph (domain 0): 4 nodes, 1 tokens refused"
    assert lines[1] == "  /battery_driver  (3 nodes of this name)"
    assert all(len(line) <= 100 for line in render(status).splitlines())
    assert any(len(line) > 100 for line in render(status, wide=True).splitlines())
    assert graph_lines(graph.to_json()) == lines


# ---- a Python node's ROS 2 ports --------------------------------------------------------------
class _Pub:
    def __init__(self) -> None:
        self.sent: list[dict[str, Any]] = []
        self.key = type("K", (), {"name": "/ticker/out"})()

    def publish(self, message: dict[str, Any]) -> None:
        from rra_agent.ros2.types import TypeRegistry

        TypeRegistry().encode("std_msgs/msg/Float64", message)  # raises as the real one does
        self.sent.append(message)


class _Inner:
    core: Any = None

    def __init__(self) -> None:
        self.published: list[bytes] = []

    def publish(self, port: str, payload: bytes, stamp: float) -> None:
        self.published.append(payload)


def test_a_sample_that_does_not_fit_its_ros2_type_is_counted_not_raised() -> None:
    from rra_agent.bus.counters import Counters
    from rra_agent.bus.data import encode_data

    mirror = Ros2Mirror.__new__(Ros2Mirror)  # without a session: the publishing path only
    mirror.inner, mirror.unencodable = _Inner(), 0
    mirror.publishers = {"out": _Pub()}  # type: ignore[dict-item]
    mirror.fields = {"out": frozenset({"data"})}
    mirror._log = lambda *a: None  # type: ignore[method-assign,assignment]
    mirror.inner.core = type("C", (), {"counters": Counters()})()
    mirror.publish("out", encode_data({"data": 2.5, "seq": 3}), 0.0)
    mirror.publish("out", encode_data({"data": "not a number"}), 0.0)
    assert mirror.publishers["out"].sent == [{"data": 2.5}]  # type: ignore[attr-defined]
    assert mirror.unencodable == 1
    assert mirror.inner.core.counters.extra == {"ros2_unencodable": 1}
    assert len(mirror.inner.published) == 2  # the bus sample goes out whatever ROS 2 takes


# ---- the Context Monitor's ROS 2 sources ----------------------------------------------------
def test_a_ros2_sample_becomes_a_sample_of_its_source_or_a_counted_refusal() -> None:
    from rra_agent.core.samples import Refusal
    from rra_agent.engines.ros2 import TopicSources
    from rra_agent.models.measurements import Measurement
    from rra_agent.ros2.attachment import Attachment
    from rra_agent.ros2.endpoint import Received

    class Node:  # what TopicSources asks of a ROS 2 node: subscriptions
        def __init__(self) -> None:
            self.subs: dict[str, Any] = {}

        def subscription(self, topic: str, ros_type: str, callback: Any, *, on_drop: Any):
            self.subs[topic] = (ros_type, callback, on_drop)
            return None

    cell = Measurement(name="Cell", type="float", source="ros2:/battery",
                       ros2_type="sensor_msgs/msg/BatteryState", field="cell_voltage.1")
    level = Measurement(name="Level", type="float", source="ros2:/battery",
                        ros2_type="sensor_msgs/msg/BatteryState", field="percentage")
    node, got, refusals = Node(), [], []
    TopicSources(node, [cell, level], lambda *a: got.append(a), refusals.append)  # type: ignore[arg-type]
    ros_type, callback, on_drop = node.subs["/battery"]  # one subscription for both
    assert ros_type == "sensor_msgs/msg/BatteryState"
    stamped = Attachment(seq=1, timestamp_ns=1_500_000_000, gid=bytes(16))
    callback(Received({"percentage": 0.5, "cell_voltage": [3.7, 3.8]}, b"", "k", stamped, 9))
    assert got == [("ros2:/battery", {"percentage": 0.5, "cell_voltage": [3.7, 3.8],
                                      "cell_voltage.1": 3.8}, 1.5)]
    callback(Received({"percentage": 0.5, "cell_voltage": [3.7]}, b"", "k", None, 2_000_000_000))
    assert len(got) == 1 and refusals[0].reason == "missing_field"
    on_drop("wrong_type", "/battery: a std_msgs/msg/String sample")
    on_drop("decode", "/battery: 7 bytes are not CDR")
    assert [(r.reason, r.detail) for r in refusals[1:]] == [
        ("wrong_type", "/battery: a std_msgs/msg/String sample"),
        ("malformed", "/battery: 7 bytes are not CDR"),
    ]
    assert all(isinstance(r, Refusal) and r.source == "ros2:/battery" for r in refusals)


def test_a_started_nodes_first_call_outlasts_a_moment_of_no_server() -> None:
    """Its services were seen, yet the first call (configure) may reach no server for a
    moment (seen under load: the deployment failed); tried again within the grace, while any
    other failure stands at once."""
    import threading
    import time
    from types import SimpleNamespace

    from rra_agent.node.ros2 import Executable
    from rra_agent.ros2.errors import NoServer, ServiceFailed

    me = SimpleNamespace(_cancel=threading.Event())
    calls: list[int] = []

    def flaky() -> None:
        calls.append(1)
        if len(calls) < 4:
            raise NoServer("no server for service /p/change_state")

    Executable._first_call(me, flaky, 2.0)  # type: ignore[arg-type]
    assert len(calls) == 4

    def refused() -> None:
        calls.append(1)
        raise ServiceFailed("service /p/change_state answered with an error")

    calls.clear()
    with pytest.raises(ServiceFailed):
        Executable._first_call(me, refused, 2.0)  # type: ignore[arg-type]
    assert len(calls) == 1

    def gone() -> None:
        raise NoServer("no server for service /p/change_state")

    start = time.monotonic()
    with pytest.raises(NoServer):
        Executable._first_call(me, gone, 0.2)  # type: ignore[arg-type]
    assert time.monotonic() - start < 1.5
