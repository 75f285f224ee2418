"""The object-storing case study's component nodes (rra_agent.nodes.object_storing).

Each node is driven through `NodeHarness` (no bus, simulated time, no sleeping): one
behaviour test per class, a robustness test feeding every input port garbage, a check that
every implementation of system.yaml is a Node using exactly its component's ports and
parameters, and a whole-system run of the resolved configured models, wired as their
connections say, that completes tasks end to end (including a radio channel switch).
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import msgspec
import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.data import decode_data
from rra_agent.core.resolution import resolve_deployment, resolve_runtime
from rra_agent.library.laser import closest_obstacle
from rra_agent.models.system import Component, SystemModel, parse_endpoint
from rra_agent.node import Node, NodeHarness
from rra_agent.node.loading import load_node_class
from rra_agent.nodes.object_storing import (
    ArmController,
    DwaLocalNavigation,
    GraspPlanner,
    LaserScanner,
    MapBasedNavigation,
    ObjectDetector,
    ObjectStoring,
    RadioDriver,
    RadioSwitch,
    RgbdCamera,
    RobotDriver,
    TaskManager,
    VfhLocalNavigation,
    world,
)
from rra_agent.nodes.object_storing._common import SafeNode
from rra_agent.nodes.object_storing.radio import pack, unpack
from rra_agent.package.loader import load_package

ROOT = Path(__file__).resolve().parents[1]
PKG = "rra_agent.nodes.object_storing"
PACKAGE = load_package(ROOT / "scenarios" / "object_storing")
SYSTEM: SystemModel = PACKAGE.system
ALL_CLASSES = [
    TaskManager,
    RadioSwitch,
    RadioDriver,
    MapBasedNavigation,
    VfhLocalNavigation,
    DwaLocalNavigation,
    LaserScanner,
    RobotDriver,
    RgbdCamera,
    ObjectDetector,
    ObjectStoring,
    GraspPlanner,
    ArmController,
]
#: Parameters the nodes honour beyond those system.yaml declares, with the defaults proposed
#: for system.yaml (the SDK refuses to set an undeclared parameter, so the harnesses here
#: declare them; a value in system.yaml wins).
PROPOSED: dict[str, dict[str, Any]] = {
    "robot_driver": {"battery_level": 100.0, "battery_drain": 1.0, "motion_drain": 2.0},
    "laser_scanner": {"obstacle_distance": None, "obstacle_bearing": 0.0, "obstacle_width": 0.35},
    "map_based_navigation": {"location": ""},
    "radio_switch": {"material": ""},
    "radio_driver_a": {"latency_ms": 300.0, "request_period": 20.0, "task": "detect"},
    "radio_driver_b": {"latency_ms": 30.0, "request_period": 20.0, "task": "detect"},
}


# ---- helpers ------------------------------------------------------------------------------
def component(name: str) -> Component:
    c = SYSTEM.component(name)
    assert c is not None, name
    return c


def spec_params(c: Component) -> dict[str, Any]:
    """The component's parameters as a node gets them (its spec travels as JSON: inf -> null),
    with the `PROPOSED` ones system.yaml does not declare."""
    declared = {k: p.value for k, p in c.parameters.items()}
    return PROPOSED.get(c.name, {}) | msgspec.json.decode(msgspec.json.encode(declared))


def harness(
    cls: type[Node], name: str, params: dict[str, Any] | None = None, now: float = 0.0
) -> NodeHarness:
    """``cls`` as component ``name`` of system.yaml: its ports, parameters (+ ``params``)."""
    c = component(name)
    return NodeHarness(
        cls,
        name=name,
        params=spec_params(c) | (params or {}),
        ports={p.name: (p.direction, p.type) for p in c.ports},
        now=now,
    )


def set_params(h: NodeHarness, **params: Any) -> None:
    reply = h.request(m.SetParams(params=params))
    assert isinstance(reply, m.Ok), reply


def last(h: NodeHarness, port: str) -> dict[str, Any]:
    out = h.outputs(port)
    assert out, f"nothing published on {port}"
    return out[-1]


def run(h: NodeHarness, until: float, dt: float = 0.1) -> None:
    """Step ``h`` every ``dt`` s of simulated time up to ``until``."""
    t = h.time
    while t < until - 1e-9:
        t = round(t + dt, 6)
        h.step(t)


def clear(h: NodeHarness) -> None:
    h.transport.published.clear()


def odom(x: float, y: float = 0.0, theta: float = 0.0) -> dict[str, Any]:
    return {"pose": {"x": x, "y": y, "theta": theta}, "v": 0.0, "w": 0.0}


def scan_with(distance: float) -> dict[str, Any]:
    """A three-beam scan with an obstacle straight ahead at ``distance`` (inf: none)."""
    return {
        "angle_min": -0.1,
        "angle_max": 0.1,
        "angle_increment": 0.1,
        "range_min": 0.05,
        "range_max": 10.0,
        "ranges": [math.inf, distance, math.inf],
    }


# ---- robot driver -------------------------------------------------------------------------
def test_robot_driver_integrates_velocity_commands_and_stops_without_them() -> None:
    h = harness(RobotDriver, "robot_driver")
    h.step(0.0)
    for i in range(1, 11):
        h.send("cmd_vel", {"linear": 0.5, "angular": 0.0})
        h.step(i * 0.1)
    pose = last(h, "odom")["pose"]
    assert pose["x"] == pytest.approx(0.5, abs=1e-6)
    assert pose["y"] == pytest.approx(0.0)
    assert last(h, "odom")["v"] == 0.5
    h.send("cmd_vel", {"linear": 0.0, "angular": 1.0})  # turn on the spot
    run(h, 1.5)
    assert last(h, "odom")["pose"]["theta"] == pytest.approx(0.5, abs=1e-6)
    assert last(h, "odom")["pose"]["x"] == pytest.approx(0.5, abs=1e-6)
    run(h, 3.0)  # no command for > 0.5 s: the base stops
    assert last(h, "odom")["v"] == 0.0 and last(h, "odom")["w"] == 0.0
    assert last(h, "odom")["pose"]["theta"] == pytest.approx(0.5, abs=1e-6)


def test_robot_driver_battery_drains_and_battery_level_parameter_sets_it() -> None:
    h = harness(RobotDriver, "robot_driver", {"battery_drain": 6.0, "motion_drain": 0.0})
    h.step(0.0)
    assert last(h, "battery")["level"] == 100.0
    run(h, 10.0)  # 6 %/min for 10 s
    battery = last(h, "battery")
    assert battery["level"] == pytest.approx(99.0, abs=0.02)
    assert len(h.outputs("battery")) == 11  # battery_rate_hz 1
    assert 22.0 < battery["voltage"] < 25.2 and battery["charging"] is False
    set_params(h, battery_level=30.0)  # the context: a low battery, published at once
    assert last(h, "battery")["level"] == 30.0
    run(h, 20.0)
    assert last(h, "battery")["level"] == pytest.approx(29.0, abs=0.02)
    set_params(h, battery_level=250.0)
    assert last(h, "battery")["level"] == 100.0  # clamped


def test_robot_driver_drains_faster_when_moving_and_stops_when_empty() -> None:
    h = harness(RobotDriver, "robot_driver", {"battery_drain": 0.0, "motion_drain": 60.0})
    for i in range(101):  # 10 s at 1 m/s: 1 %/s
        h.send("cmd_vel", {"linear": 5.0, "angular": 0.0})  # clamped to 1 m/s
        h.step(i * 0.1)
    assert last(h, "battery")["level"] == pytest.approx(90.0, abs=0.2)
    assert last(h, "battery")["current"] > 1.5
    set_params(h, battery_level=0.0)
    x = last(h, "odom")["pose"]["x"]
    for i in range(101, 111):
        h.send("cmd_vel", {"linear": 1.0, "angular": 0.0})
        h.step(i * 0.1)
    assert last(h, "odom")["pose"]["x"] == pytest.approx(x)


# ---- laser scanner ------------------------------------------------------------------------
def test_laser_scanner_obstacle_is_set_by_parameters() -> None:
    h = harness(LaserScanner, "laser_scanner")
    assert h.core.rate_hz == component("laser_scanner").parameters["rate_hz"].value
    h.step(0.0)
    scan = last(h, "scan")
    assert closest_obstacle(scan) == math.inf  # .inf in system.yaml, null in the spec
    assert scan["frame_id"] == "base_laser" and len(scan["ranges"]) == 91
    set_params(h, obstacle_distance=1.2)
    h.step(0.2)
    scan = last(h, "scan")
    assert closest_obstacle(scan) == 1.2
    hit = [i for i, r in enumerate(scan["ranges"]) if r == 1.2]
    assert hit and abs(scan["angle_min"] + hit[len(hit) // 2] * scan["angle_increment"]) < 1e-9
    set_params(h, obstacle_distance=12.0)  # beyond range_max: not seen
    h.step(0.4)
    assert closest_obstacle(last(h, "scan")) == math.inf
    set_params(h, obstacle_distance=0.8, obstacle_bearing=1.0, range_max=5.0)
    h.step(0.6)
    scan = last(h, "scan")
    assert closest_obstacle(scan) == 0.8 and scan["range_max"] == 5.0
    assert scan["ranges"][len(scan["ranges"]) // 2] == math.inf  # nothing straight ahead


# ---- map-based navigation -----------------------------------------------------------------
@pytest.mark.parametrize(
    ("x", "label"),
    [(-1.0, "RoomA"), (3.99, "RoomA"), (4.0, "Corridor"), (6.0, "Corridor"), (8.0, "RoomB")],
)
def test_semantic_location_is_labelled_by_position(x: float, label: str) -> None:
    h = harness(MapBasedNavigation, "map_based_navigation")
    h.step(0.0)
    assert h.outputs("semantic_location") == []  # no pose yet
    h.send("odom", odom(x, 0.5))
    h.step(1.0)
    assert last(h, "semantic_location") == {"label": label, "x": x, "y": 0.5}


def test_location_parameter_overrides_the_semantic_location() -> None:
    h = harness(MapBasedNavigation, "map_based_navigation", {"location": ""})
    h.send("odom", odom(1.0))
    set_params(h, location="Corridor")  # published at once
    assert last(h, "semantic_location")["label"] == "Corridor"
    h.step(1.0)
    assert last(h, "semantic_location")["label"] == "Corridor"
    set_params(h, location="")
    assert last(h, "semantic_location")["label"] == "RoomA"


def test_map_navigation_plans_through_the_doors_and_reports_progress() -> None:
    h = harness(MapBasedNavigation, "map_based_navigation")
    h.send("odom", odom(0.0))
    h.send("goal", {"rack_id": "B1", "x": 0.0, "y": 0.0, "theta": 0.0})
    poses = last(h, "path")["poses"]
    assert [(p["x"], p["y"]) for p in poses] == [(4.0, 0.0), (8.0, 0.0), (9.5, 1.5)]
    assert last(h, "status") == {"rack_id": "B1", "state": "active"}
    h.send("odom", odom(4.1))  # the first door is passed
    h.step(1.0)
    assert len(last(h, "path")["poses"]) == 2
    h.send("odom", odom(9.45, 1.45))  # within goal_tolerance (0.1 m)
    assert last(h, "status") == {"rack_id": "B1", "state": "reached"}
    assert last(h, "path") == {"poses": []}
    h.send("goal", {"rack_id": "", "x": 2.0, "y": 0.0, "theta": 0.0})  # a point, back
    poses = last(h, "path")["poses"]
    assert [(p["x"], p["y"]) for p in poses] == [(8.0, 0.0), (4.0, 0.0), (2.0, 0.0)]
    h.send("goal", {"rack_id": "Z9", "x": 0.0, "y": 0.0, "theta": 0.0})
    assert last(h, "status") == {"rack_id": "Z9", "state": "failed"}


def test_map_navigation_fails_a_goal_blocked_too_long() -> None:
    h = harness(MapBasedNavigation, "map_based_navigation")
    h.send("odom", odom(0.0))
    h.send("goal", {"rack_id": "A1"})
    h.send("scan", scan_with(0.2))
    run(h, 14.5, dt=0.5)
    assert last(h, "status")["state"] == "active"
    run(h, 15.5, dt=0.5)
    assert last(h, "status") == {"rack_id": "A1", "state": "failed"}


# ---- local navigation ---------------------------------------------------------------------
def local_nav(cls: type[Node], **params: Any) -> NodeHarness:
    h = harness(cls, "local_navigation", params)
    h.send("path", {"poses": [{"x": 10.0, "y": 0.0, "theta": 0.0}]})
    h.send("odom", odom(0.0))
    h.send("scan", scan_with(math.inf))
    return h


def linear(h: NodeHarness) -> float:
    return last(h, "cmd_vel")["linear"]


@pytest.mark.parametrize("cls", [VfhLocalNavigation, DwaLocalNavigation])
def test_local_navigation_speed_is_capped_by_max_vel_set_at_run_time(cls: type[Node]) -> None:
    h = local_nav(cls)
    h.step(0.1)
    assert linear(h) == pytest.approx(0.6)  # max_vel of system.yaml
    set_params(h, max_vel=0.45)  # what MotionBehavior does
    h.step(0.2)
    assert linear(h) == pytest.approx(0.45)
    # Never above max_vel, whatever the pose, path and obstacle.
    for i in range(200):
        set_params(h, max_vel=(i % 9) / 10)
        h.send("odom", odom(i % 13 - 2.0, (i % 7 - 3) / 2, (i % 11 - 5) / 2))
        h.send("scan", scan_with(0.1 + (i % 17) / 4))
        h.step(0.3 + i * 0.1)
        cmd = last(h, "cmd_vel")
        assert 0.0 <= cmd["linear"] <= (i % 9) / 10 + 1e-12
        assert abs(cmd["angular"]) <= 1.0


def test_vfh_slows_near_static_obstacles_and_dwa_keeps_a_larger_margin() -> None:
    vfh, dwa = local_nav(VfhLocalNavigation), local_nav(DwaLocalNavigation)
    speeds: dict[float, tuple[float, float]] = {}
    for i, d in enumerate([2.0, 1.0, 0.5, 0.25]):
        for h in (vfh, dwa):
            h.send("scan", scan_with(d))
            h.step(0.1 * (i + 1))
        speeds[d] = (linear(vfh), linear(dwa))
    assert speeds[2.0] == pytest.approx((0.6, 0.6))
    assert speeds[1.0][0] == pytest.approx(0.6) and speeds[1.0][1] < 0.5  # DWA slows earlier
    assert 0.0 < speeds[0.5][0] < 0.6 and speeds[0.5][1] == 0.0  # within DWA's 0.6 m margin
    assert speeds[0.25] == (0.0, 0.0)
    vfh.send("scan", scan_with(math.inf))
    run(vfh, 2.0)  # no scan for more than 1 s: crawl
    assert linear(vfh) == pytest.approx(0.1)


def test_local_navigation_follows_the_path_stops_and_hands_it_over() -> None:
    vfh = local_nav(VfhLocalNavigation)
    vfh.send("path", {"poses": [{"x": 1.0, "y": 0.0}, {"x": 1.0, "y": 1.0, "theta": 0.0}]})
    vfh.step(0.1)
    assert linear(vfh) > 0 and last(vfh, "cmd_vel")["angular"] == 0.0
    state = vfh.node.export_state()
    dwa = harness(DwaLocalNavigation, "local_navigation")
    dwa.node.import_state(msgspec.msgpack.decode(msgspec.msgpack.encode(state)))
    dwa.send("odom", odom(1.0, 0.0, 0.0))  # at the first waypoint, facing +x
    dwa.send("scan", scan_with(math.inf))
    dwa.step(0.1)
    assert linear(dwa) == 0.0 and last(dwa, "cmd_vel")["angular"] > 0  # turns left first
    dwa.send("odom", odom(1.0, 0.99, math.pi / 2))  # at the goal
    dwa.step(0.2)
    assert last(dwa, "cmd_vel") == {"linear": 0.0, "angular": 0.0}
    n = len(dwa.outputs("cmd_vel"))
    dwa.step(0.3)
    assert len(dwa.outputs("cmd_vel")) == n  # one stop command, then silence
    dwa.send("path", {"poses": []})
    assert dwa.node.command(0.4) is None


def test_local_navigation_logs_an_algorithm_mismatch() -> None:
    h = harness(DwaLocalNavigation, "local_navigation")  # obstacle_avoidance: vfh
    assert any("obstacle_avoidance='vfh'" in line for line in h.logs)
    assert not harness(VfhLocalNavigation, "local_navigation").logs


# ---- camera and detector ------------------------------------------------------------------
def test_rgbd_camera_publishes_the_synthetic_rack_at_a_low_rate() -> None:
    h = harness(RgbdCamera, "rgbd_camera", {"rate_hz": 2.0})
    assert h.core.rate_hz == 2.0 and RgbdCamera.rate_hz <= 5
    h.step(0.0)
    cloud = last(h, "point_cloud")
    assert cloud["frame_id"] == "camera_depth"
    assert len(cloud["points"]) == 16 * 11 + 25 * len(world.OBJECTS)
    assert all(len(p) == 3 for p in cloud["points"])


def detector(**params: Any) -> NodeHarness:
    h = harness(ObjectDetector, "object_detector", params)
    h.send("point_cloud", {"frame_id": "camera_depth", "points": world.camera_scene()})
    return h


def detect(h: NodeHarness, barcode: str = "OBJ-001") -> list[dict[str, Any]]:
    h.send("request", {"rack_id": "A1", "barcode": barcode})
    out = last(h, "objects")
    assert out["rack_id"] == "A1"
    return out["objects"]


def test_detector_output_depends_on_subsampling_and_roi() -> None:
    small = runtime_parameters("Small")["object_detector"]
    large = runtime_parameters("Large")["object_detector"]
    h = detector(**small)
    full = detect(h)
    assert [o["position"][0] for o in full] == [-0.3, -0.05, 0.2]  # narrow ROI: 3 of 5
    assert all(o["size"][:2] == [0.08, 0.12] for o in full)
    assert [o["barcode"] for o in full].count("OBJ-001") == 1
    assert {o["barcode"] for o in full} == {"OBJ-001", ""}
    set_params(h, **large)  # subsampling 4, wide ROI
    coarse = detect(h)
    assert len(coarse) == 5
    assert coarse[1]["position"] != full[0]["position"]  # fewer points, shifted centroid
    set_params(h, subsampling=8)
    assert len(detect(h)) < len(coarse)  # too few points left per object
    set_params(h, subsampling=1, roi=[1.0, 0.0])  # invalid: the default region
    assert len(detect(h)) == 3
    assert any("invalid roi" in line for line in h.logs)


def test_detector_answers_a_request_made_before_the_first_cloud() -> None:
    h = harness(ObjectDetector, "object_detector")
    h.send("request", {"rack_id": "B2", "barcode": "OBJ-003"})
    assert h.outputs("objects") == []
    h.send("point_cloud", {"frame_id": "camera_depth", "points": world.camera_scene()})
    out = last(h, "objects")
    assert out["rack_id"] == "B2" and len(out["objects"]) == 3


# ---- radio --------------------------------------------------------------------------------
def frame(kind: str, body: dict[str, Any] | None = None, channel: str = "A") -> dict[str, Any]:
    return {"channel": channel, "seq": 1, "payload": pack(kind, body)}


REQUEST = world.server_task(0, "store")


def test_radio_switch_forwards_requests_and_publishes_the_material() -> None:
    h = harness(RadioSwitch, "radio_switch", {"material": ""})
    h.send("radio_in", frame("request", REQUEST, channel="B"))
    assert last(h, "request") == REQUEST
    assert last(h, "object_material") == {"barcode": "OBJ-000", "material": "Glass"}
    set_params(h, material="Wood")  # the override, published at once
    assert last(h, "object_material") == {"barcode": "OBJ-000", "material": "Wood"}
    clear(h)
    run(h, 5.0, dt=0.5)
    assert h.outputs("object_material") == [{"barcode": "OBJ-000", "material": "Wood"}]


def test_radio_switch_replies_on_the_connected_channel_and_queues_while_the_link_is_down() -> None:
    h = harness(RadioSwitch, "radio_switch")
    reply = {"barcode": "OBJ-000", "success": True, "position": [0.1, 0.2, 0.3], "message": "ok"}
    h.send("radio_in", frame("beacon", channel="B"))
    h.send("reply", reply)
    out = last(h, "radio_out")
    assert out["channel"] == "B" and out["seq"] == 1
    assert unpack(out["payload"]) == {"kind": "reply", **reply}
    h.time = 10.0  # silence longer than link_timeout: the link is down
    ready = {"barcode": "", "success": False, "position": [], "message": "ready"}
    h.send("reply", reply | {"barcode": "OBJ-001"})
    h.send("reply", ready)
    h.send("reply", ready)
    h.step()
    assert len(h.outputs("radio_out")) == 1
    h.send("radio_in", frame("beacon", channel="A"))  # channel A comes up
    sent = [unpack(f["payload"]) for f in h.outputs("radio_out")[1:]]
    assert [(s["barcode"], s["message"]) for s in sent] == [("OBJ-001", "ok"), ("", "ready")]
    assert [f["channel"] for f in h.outputs("radio_out")[1:]] == ["A", "A"]
    assert [f["seq"] for f in h.outputs("radio_out")] == [1, 2, 3]


def request_times(h: NodeHarness) -> list[float]:
    """When the driver sent request frames (the harness stamps publications with its time)."""
    return [
        t
        for port, payload, t in h.transport.published
        if (unpack(decode_data(payload)["payload"]) or {}).get("kind") == "request"
    ]


def test_radio_driver_serves_requests_with_its_channel_latency() -> None:
    first = {}
    for name in ("radio_driver_a", "radio_driver_b"):
        h = harness(RadioDriver, name, {"task": "store"})
        run(h, 2.0, dt=0.01)
        bodies = [unpack(f["payload"]) for f in h.outputs("rx")]
        assert {"kind": "request", **REQUEST} in bodies
        assert {"kind": "beacon"} in bodies
        assert {f["channel"] for f in h.outputs("rx")} == {name[-1].upper()}
        first[name] = request_times(h)[0]
    assert first["radio_driver_a"] == pytest.approx(1.3, abs=0.02)  # 1 s + 300 ms
    assert first["radio_driver_b"] == pytest.approx(1.03, abs=0.02)  # 1 s + 30 ms


def test_radio_driver_server_moves_on_after_a_reply_and_asks_again_otherwise() -> None:
    h = harness(RadioDriver, "radio_driver_b", {"request_period": 10.0})

    def requests() -> list[str]:
        bodies = [unpack(f["payload"]) for f in h.outputs("rx")]
        return [b["barcode"] for b in bodies if b and b["kind"] == "request"]

    run(h, 2.0)
    assert requests() == ["OBJ-000"]
    run(h, 12.0)
    assert requests() == ["OBJ-000", "OBJ-000"]  # not answered: asked again
    reply = {"barcode": "OBJ-004", "success": True, "position": [], "message": "done"}
    h.send("tx", frame("reply", reply, channel="B"))  # e.g. heard on the other channel
    run(h, 12.5)
    assert requests()[-1] == "OBJ-005"
    assert h.node.server.replies == [reply]
    h.send("tx", frame("reply", reply | {"barcode": "", "message": "ready"}))
    run(h, 13.0)
    assert requests()[-1] == "OBJ-005"  # a ready ask: the current request again


# ---- task manager -------------------------------------------------------------------------
def task_manager(**params: Any) -> NodeHarness:
    return harness(TaskManager, "task_manager", params)


def test_task_manager_runs_a_detection_task() -> None:
    h = task_manager()
    h.send("request", world.server_task(0, "detect"))
    assert last(h, "nav_goal")["rack_id"] == "A1"
    h.send("nav_status", {"rack_id": "A1", "state": "active"})
    h.send("nav_status", {"rack_id": "B1", "state": "reached"})  # not ours
    assert h.outputs("detect") == []
    h.send("nav_status", {"rack_id": "A1", "state": "reached"})
    assert last(h, "detect") == {"rack_id": "A1", "barcode": "OBJ-000"}
    found = {"barcode": "OBJ-000", "position": [0.1, 0.0, 1.0], "size": [0.1, 0.1, 0.1]}
    h.send("detected_objects", {"rack_id": "A1", "objects": [found]})
    assert last(h, "reply") == {
        "barcode": "OBJ-000",
        "success": True,
        "position": [0.1, 0.0, 1.0],
        "message": "detected",
    }
    clear(h)
    h.send("request", world.server_task(0, "detect"))  # asked again: answered from memory
    assert h.outputs("reply")[0]["success"] is True and h.outputs("nav_goal") == []


def test_task_manager_retries_up_to_retry_limit_then_fails() -> None:
    h = task_manager(retry_limit=2)
    h.send("request", world.server_task(1, "detection"))
    for _ in range(2):
        h.send("nav_status", {"rack_id": "B2", "state": "failed"})
    h.send("nav_status", {"rack_id": "B2", "state": "reached"})
    assert len(h.outputs("nav_goal")) == 3 and len(h.outputs("detect")) == 1
    run(h, 5.0, dt=0.5)  # no answer: detection retried
    h.send("detected_objects", {"rack_id": "B2", "objects": []})  # not found
    assert len(h.outputs("detect")) == 3 and h.outputs("reply") == []
    h.send("detected_objects", {"rack_id": "B2", "objects": []})
    reply = last(h, "reply")
    assert reply["success"] is False and "not found" in reply["message"]


def test_task_manager_asks_the_server_when_idle_and_ignores_requests_while_busy() -> None:
    h = task_manager(server_timeout=2.0)
    run(h, 1.5, dt=0.5)
    assert h.outputs("reply") == []
    run(h, 2.0, dt=0.5)
    assert last(h, "reply") == {"barcode": "", "success": False, "position": [], "message": "ready"}
    h.send("request", world.server_task(0, "detect"))
    h.send("request", world.server_task(1, "detect"))  # busy with OBJ-000
    assert [g["rack_id"] for g in h.outputs("nav_goal")] == ["A1"]
    run(h, 10.0, dt=0.5)
    assert len(h.outputs("reply")) == 1  # no "ready" while busy
    h.send("request", {"task": "dance", "rack_id": "A1", "barcode": "X"})  # bad: ignored
    assert any("malformed request" in line for line in h.logs)


def test_task_manager_runs_a_manipulation_task() -> None:
    h = task_manager()
    h.send("request", REQUEST)  # OBJ-000 from A1 to B1
    h.send("nav_status", {"rack_id": "A1", "state": "reached"})
    obj = {"barcode": "OBJ-000", "position": [0.0, 0.1, 0.9], "size": [0.1, 0.1, 0.1]}
    h.send("detected_objects", {"rack_id": "A1", "objects": [obj]})
    store = {"barcode": "OBJ-000", "target_rack": "B1", "material": "Glass"}
    assert last(h, "store") == store
    h.send("store_status", {"barcode": "OBJ-000", "state": "picking"})
    h.send("store_status", {"barcode": "OBJ-000", "state": "stored"})
    assert last(h, "nav_goal")["rack_id"] == "B1"
    h.send("nav_status", {"rack_id": "B1", "state": "reached"})
    assert h.outputs("store") == [store, store]  # the second one places it
    h.send("store_status", {"barcode": "OBJ-000", "state": "placed"})
    assert last(h, "reply")["success"] is True and last(h, "reply")["position"] == [0.0, 0.1, 0.9]


# ---- manipulation -------------------------------------------------------------------------
def test_object_storing_picks_stores_and_places() -> None:
    h = harness(ObjectStoring, "object_storing", {"storage_slots": 1})

    def done(barcode: str, action: str) -> None:
        h.send("grasp_status", {"barcode": barcode, "action": action, "state": "done"})

    h.send("request", {"barcode": "OBJ-1", "target_rack": "B1", "material": "Glass"})
    h.send("request", {"barcode": "OBJ-2"})  # busy
    done("OBJ-1", "pick")
    done("OBJ-1", "store")
    h.send("request", {"barcode": "OBJ-2"})  # one slot, taken
    h.send("request", {"barcode": "OBJ-1"})  # on board: place it
    done("OBJ-1", "place")
    assert [(s["barcode"], s["state"]) for s in h.outputs("status")] == [
        ("OBJ-1", "picking"),
        ("OBJ-2", "rejected"),
        ("OBJ-1", "storing"),
        ("OBJ-1", "stored"),
        ("OBJ-2", "full"),
        ("OBJ-1", "placing"),
        ("OBJ-1", "placed"),
    ]
    assert [g["action"] for g in h.outputs("grasp_request")] == ["pick", "store", "place"]
    h.send("request", {"barcode": "OBJ-2"})
    h.send("grasp_status", {"barcode": "OBJ-2", "action": "pick", "state": "failed"})
    assert last(h, "status") == {"barcode": "OBJ-2", "state": "failed"}
    h.send("request", {"barcode": "OBJ-3"})
    run(h, 61.0, dt=1.0)  # the grasp planner never answers
    assert last(h, "status") == {"barcode": "OBJ-3", "state": "failed"}


def test_grasp_planner_plans_to_the_detected_object_and_follows_the_arm() -> None:
    h = harness(GraspPlanner, "grasp_planner", {"approach_distance": 0.2})
    h.send("request", {"barcode": "OBJ-7", "action": "pick"})
    assert last(h, "status") == {"barcode": "OBJ-7", "action": "pick", "state": "failed"}
    obj = {"barcode": "OBJ-7", "position": [0.3, 0.1, 0.4], "size": [0.1, 0.1, 0.1]}
    h.send("objects", {"rack_id": "A1", "objects": [obj]})
    h.send("request", {"barcode": "OBJ-7", "action": "pick"})
    traj = last(h, "trajectory")
    assert traj["joint_names"] == ["pan", "lift", "reach", "gripper"]
    pre, at, grip = traj["positions"][:3]
    assert at[:3] == pytest.approx([math.atan2(0.3, 0.4), 0.1, 0.5], abs=1e-4)
    assert pre[2] == pytest.approx(0.3) and grip[3] == 1.0  # approach_distance before it
    assert traj["times"] == sorted(traj["times"]) and len(traj["times"]) == 4
    h.send("request", {"barcode": "OBJ-8", "action": "store"})
    assert last(h, "status")["state"] == "rejected"
    status = {"joint_positions": [0.0, 0.3, 0.3, 0.0], "gripper_closed": False}
    h.send("arm_status", status | {"state": "done"})  # an old "done": not ours
    assert last(h, "status")["state"] == "rejected"
    h.send("arm_status", status | {"state": "moving"})
    h.send("arm_status", status | {"state": "done"})
    assert last(h, "status") == {"barcode": "OBJ-7", "action": "pick", "state": "done"}
    h.send("request", {"barcode": "OBJ-7", "action": "fly"})
    assert last(h, "status")["state"] == "failed"


def arm_run(**params: Any) -> tuple[NodeHarness, float]:
    """Execute a pick trajectory; return the harness and when the arm reported done."""
    h = harness(ArmController, "arm_controller", params)
    h.step(0.0)
    traj = {
        "joint_names": ["pan", "lift", "reach", "gripper"],
        "positions": [[0.0, 0.3, 0.5, 0.0], [0.0, 0.3, 0.6, 0.0], [0.0, 0.3, 0.6, 1.0]],
        "times": [1.0, 1.5, 2.0],
    }
    h.send("trajectory", traj)
    assert last(h, "status")["state"] == "moving"
    while last(h, "status")["state"] == "moving" and h.time < 60:
        h.step(round(h.time + 0.2, 6))
    return h, h.time


def test_arm_status_reflects_the_grip_force_and_speed_of_the_material() -> None:
    fragile = runtime_parameters("Fragile")["arm_controller"]
    firm = runtime_parameters("Firm")["arm_controller"]
    slow, t_slow = arm_run(**fragile)
    fast, t_fast = arm_run(**firm)
    for h, params in ((slow, fragile), (fast, firm)):
        status = last(h, "status")
        assert status["state"] == "done" and status["gripper_closed"] is True
        assert status["joint_positions"] == [0.0, 0.3, 0.6, 1.0]
        assert status["grip_force"] == params["grip_force"]
        assert status["approach_speed"] == params["approach_speed"]
    # Segments of 0.2 m, 0.1 m (planned 1.0 s, 0.5 s) and closing the gripper (0.5 s).
    assert t_fast == pytest.approx(0.2 / 0.15 + 0.1 / 0.15 + 0.5, abs=0.21)
    assert t_slow == pytest.approx(0.2 / 0.05 + 0.1 / 0.05 + 0.5, abs=0.21)
    set_params(fast, grip_force=7.5)  # re-grips at once
    assert last(fast, "status")["grip_force"] == 7.5
    fast.send("trajectory", {"joint_names": ["gripper"], "positions": [[0.0]], "times": [0.5]})
    run(fast, fast.time + 1.0, dt=0.2)
    assert last(fast, "status")["grip_force"] == 0.0 and not last(fast, "status")["gripper_closed"]
    fast.send("trajectory", {"joint_names": ["elbow"], "positions": [[1.0]], "times": [1.0]})
    assert last(fast, "status")["state"] == "failed"


# ---- robustness ---------------------------------------------------------------------------
GARBAGE: list[Any] = [
    {},
    {"x": 1},
    {"linear": "fast", "angular": None},
    {"pose": [1, 2]},
    {"pose": {"x": "a"}},
    {"poses": "none"},
    {"poses": [None, {"x": 1}]},
    {"ranges": [1, "a", None], "angle_min": "x"},
    {"ranges": 5, "angle_min": 0.0, "angle_increment": 0.1},
    {"points": [[1], "p", None, [1, 2, "z"], [True, 1, 2]]},
    {"points": {"a": 1}},
    {"objects": [1, None, {"barcode": 5}, {"barcode": "b", "position": "p"}]},
    {"rack_id": 7, "state": ["reached"], "barcode": None},
    {"task": 1, "rack_id": None},
    {"channel": 3, "payload": "text"},
    {"channel": "A", "payload": b"\xc1\xff"},
    {"channel": "A", "payload": pack("request", {"task": 5})},
    {"channel": "A", "payload": msgspec.msgpack.encode([1, 2])},
    {"barcode": "b", "success": "yes", "position": [1, "a"]},
    {"joint_names": ["pan"], "positions": [[1.0, 2.0]], "times": [1.0]},
    {"joint_names": "pan", "positions": 3, "times": None},
    {"joint_names": ["pan"], "positions": [[1.0], [2.0]], "times": [2.0, 1.0]},
    {"joint_positions": [1, 2], "state": 4},
    {"barcode": "b", "action": 3, "state": None},
    {"level": float("nan"), "linear": float("inf"), "angular": 0.0},
]


@pytest.mark.parametrize("name", [c.name for c in SYSTEM.components])
def test_nodes_ignore_malformed_samples_without_raising(name: str) -> None:
    c = component(name)
    for impl in implementations(c):
        h = harness(load_node_class(impl), name)
        for i, sample in enumerate(GARBAGE):
            for port in [p.name for p in c.ports if p.direction == "subscribe"] + ["nope"]:
                h.send(port, sample)
            h.send_raw("nope", b"\x01")
            h.step(i * 0.1)
        run(h, 20.0, dt=0.5)
        assert h.core.errors == 0, h.logs
        assert not any("no output port" in line for line in h.logs), h.logs


# ---- the system package -------------------------------------------------------------------
def implementations(c: Component) -> list[str]:
    paths = [c.implementation, *c.implementations.values()]
    return list(dict.fromkeys(p for p in paths if isinstance(p, str)))


def module_sources(cls: type) -> str:
    """Source of the modules of ``cls`` and its bases in this package."""
    mods = {inspect.getmodule(k) for k in cls.__mro__ if k.__module__.startswith(PKG)}
    return "\n".join(inspect.getsource(mod) for mod in mods if mod is not None)


@pytest.mark.parametrize("name", [c.name for c in SYSTEM.components])
def test_every_implementation_is_a_node_using_its_components_ports_and_parameters(
    name: str,
) -> None:
    c = component(name)
    subscribed = {p.name for p in c.ports if p.direction == "subscribe"}
    published = {p.name for p in c.ports if p.direction == "publish"}
    for impl in implementations(c):
        assert impl.startswith(PKG + ".")
        cls = load_node_class(impl)
        assert issubclass(cls, SafeNode) and cls in ALL_CLASSES
        assert set(cls.inputs) == subscribed, impl
        assert set(cls.outputs) == published, impl
        source = module_sources(cls)
        for port in subscribed | published:
            assert f'"{port}"' in source, (impl, port)
        for param in set(c.parameters) - {"rate_hz"}:  # rate_hz is the SDK's
            assert f'"{param}"' in source, (impl, param)
        for param in PROPOSED.get(name, {}):
            assert f'"{param}"' in source, (impl, param)
        assert cls.rate_hz <= 10  # cheap: ~14 of these share two cores


def test_every_class_is_named_by_system_yaml() -> None:
    named = {load_node_class(i) for c in SYSTEM.components for i in implementations(c)}
    assert named == set(ALL_CLASSES)


# ---- the whole system, wired as the configured models say --------------------------------
def runtime_parameters(*features: str) -> dict[str, dict[str, Any]]:
    """Component -> parameters set by the run-time resolution of ``features``."""
    out: dict[str, dict[str, Any]] = {}
    for feature in features:
        for t in PACKAGE.runtime.features[feature]:
            if t.set_parameter is not None and t.set_parameter.value is not None:
                sp = t.set_parameter
                out.setdefault(sp.component, {})[sp.parameter] = sp.value
    return out


def configured(deployment: str, runtime: Iterable[str], max_vel: float = 0.6) -> SystemModel:
    fm = PACKAGE.features
    dep = resolve_deployment(SYSTEM, PACKAGE.deployment, fm, [deployment])
    return resolve_runtime(dep, PACKAGE.runtime, fm, [deployment, *runtime], {"MaxVel": max_vel})


class Wiring:
    """Harnesses of every component of a configured model, connected in process."""

    #: Sensor rates lowered to keep the test fast (system.yaml's would be fine, only slower).
    RATES = {"laser_scanner": 5.0, "rgbd_camera": 1.0}

    def __init__(self, model: SystemModel, extra: dict[str, dict[str, Any]]) -> None:
        self.time = 0.0
        self.extra = extra
        self.nodes: dict[str, NodeHarness] = {}
        self.read: dict[str, int] = {}
        self.due: dict[str, float] = {}
        self.published: set[tuple[str, str]] = set()
        self.apply(model)

    def apply(self, model: SystemModel) -> None:
        """Become ``model``: stop what is gone, start what is new, swap implementations
        (handing the state over), set changed parameters, rewire everything."""
        for name in set(self.nodes) - {c.name for c in model.components}:
            del self.nodes[name]
        for c in model.components:
            assert isinstance(c.implementation, str)
            params = spec_params(c) | self.extra.get(c.name, {})
            if c.name in self.RATES:
                params["rate_hz"] = self.RATES[c.name]
            old = self.nodes.get(c.name)
            if old is not None and old.core.spec.implementation == c.implementation:
                changed = {k: v for k, v in params.items() if old.core.params.get(k) != v}
                if changed:
                    set_params(old, **changed)
                continue
            self.nodes[c.name] = NodeHarness(
                load_node_class(c.implementation),
                name=c.name,
                params=params,
                ports={p.name: (p.direction, p.type) for p in c.ports},
                now=self.time,
                state=old.node.export_state() if old is not None else None,
            )
            self.read[c.name], self.due[c.name] = 0, self.time
        self.routes: dict[tuple[str, str], list[tuple[str, str]]] = {}
        for conn in model.connections:
            s, t = parse_endpoint(conn.source), parse_endpoint(conn.target)
            self.routes.setdefault((s.component, s.port), []).append((t.component, t.port))

    def run(self, until: float, dt: float = 0.05) -> None:
        while self.time < until - 1e-9:
            self.time = round(self.time + dt, 6)
            for name, h in self.nodes.items():
                rate = h.core.rate_hz
                if rate > 0 and self.time >= self.due[name] - 1e-9:
                    h.step(self.time)
                    self.due[name] = self.time + 1.0 / rate
            self._route()

    def _route(self) -> None:
        moved = True
        while moved:
            moved = False
            for name, h in list(self.nodes.items()):
                published = h.transport.published
                while self.read[name] < len(published):
                    port, payload, _ = published[self.read[name]]
                    self.read[name] += 1
                    self.published.add((name, port))
                    moved = True
                    for target, tport in self.routes.get((name, port), []):
                        self.nodes[target].time = self.time
                        self.nodes[target].core.deliver(tport, payload, self.time)

    def replies(self, driver: str) -> list[dict[str, Any]]:
        return self.nodes[driver].node.server.replies  # type: ignore[attr-defined]


@pytest.fixture(scope="module")
def manipulation() -> Wiring:
    model = configured("Manipulation", ["ChannelA", "Static", "Small", "Firm", "MotionBehavior"])
    w = Wiring(model, {"radio_driver_a": {"task": "store"}})
    w.run(90.0)
    return w


@pytest.fixture(scope="module")
def detection() -> tuple[Wiring, list[dict[str, Any]]]:
    """Detection over channel B, then (after the first reply) channel A in the corridor."""
    extra = {"radio_driver_a": {"task": "detect"}, "radio_driver_b": {"task": "detect"}}
    w = Wiring(configured("Detection", ["ChannelB", "Static", "Large", "MotionBehavior"]), extra)
    w.run(8.0)
    before = list(w.replies("radio_driver_b"))
    w.apply(configured("Detection", ["ChannelA", "Dynamic", "Large", "MotionBehavior"], 0.5))
    w.run(60.0)
    return w, before


def test_the_manipulation_system_stores_an_object_end_to_end(manipulation: Wiring) -> None:
    w = manipulation
    assert [r["barcode"] for r in w.replies("radio_driver_a")] == ["OBJ-000"]
    reply = w.replies("radio_driver_a")[0]
    assert reply["success"] is True and reply["message"] == "stored on rack B1"
    assert w.nodes["object_storing"].node.on_board == []  # type: ignore[attr-defined]
    arm = w.nodes["arm_controller"].outputs("status")
    assert {s["grip_force"] for s in arm if s["gripper_closed"]} == {20.0}  # Firm
    job = w.nodes["task_manager"].node.job  # type: ignore[attr-defined]
    assert job is not None and job.barcode == "OBJ-001"  # the server's next request
    for h in w.nodes.values():
        assert h.core.errors == 0 and not h.logs, h.logs


def test_the_detection_system_survives_a_radio_channel_switch(
    detection: tuple[Wiring, list[dict[str, Any]]],
) -> None:
    w, before = detection
    assert [r["barcode"] for r in before] == ["OBJ-000"] and before[0]["success"]
    assert "object_storing" not in w.nodes and "radio_driver_b" not in w.nodes
    assert isinstance(w.nodes["local_navigation"].node, DwaLocalNavigation)
    assert w.nodes["local_navigation"].core.params["max_vel"] == 0.5
    replies = w.replies("radio_driver_a")
    # Channel A's server starts over with OBJ-000: answered from memory, then it moves on.
    assert [r["barcode"] for r in replies] == ["OBJ-000", "OBJ-001"]
    assert replies[0] == before[0] and replies[1]["success"]
    for h in w.nodes.values():
        assert h.core.errors == 0


def test_every_publish_port_is_used_in_the_system_runs(
    manipulation: Wiring, detection: tuple[Wiring, list[dict[str, Any]]]
) -> None:
    wanted = {
        (c.name, p.name) for c in SYSTEM.components for p in c.ports if p.direction == "publish"
    }
    assert wanted - manipulation.published - detection[0].published == set()
