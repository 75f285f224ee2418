"""The manipulation chain (Manipulation task only): object storing, grasp planner, arm.

The arm is abstract, four joints in `JOINTS`: ``pan`` (rad, 0 = ahead of the robot, pi =
its storage tray), ``lift`` (m, height in the camera frame), ``reach`` (m, horizontal
distance from the camera) and ``gripper`` (0 open, 1 closed). The grasp planner maps an
object position from the camera frame (x right, y up, z forward) to it; the arm controller
executes the trajectories, retimed to its ``approach_speed``, and closes the gripper with
its ``grip_force`` (paper variation point (b): Fragile / Firm in runtime.yaml).
"""

from __future__ import annotations

import math
from typing import Any

from rra_agent.nodes.object_storing._common import Every, SafeNode, clamp, num, numbers, text

JOINTS = ("pan", "lift", "reach", "gripper")
HOME = (0.0, 0.3, 0.3, 0.0)
TRAY = (math.pi, 0.1, 0.35)  # where objects ride on the robot
PLACE = (0.0, 0.0, 0.7)  # the target rack's shelf, ahead of the robot
ACTIONS = {"pick": "picking", "store": "storing", "place": "placing"}
GRASP_TIMEOUT = 60.0  # s for one grasp action
NOMINAL_SPEED = 0.2  # m/s (and 0.4 rad/s of pan) the planner assumes
GRIPPER_TIME = 0.5  # s to open or close the gripper
PAN_RADIUS = 0.5  # m: a pan of 1 rad moves the hand this far

Waypoint = tuple[float, float, float, float]


class ObjectStoring(SafeNode):
    """Sequences grasp actions for each ``request`` (StoreRequest).

    An object not on board is picked and stored on the robot (``grasp_request`` actions
    ``pick`` then ``store``; ``status``: picking, storing, stored); an object on board is
    placed (``place``; placing, placed). A request while ``storage_slots`` objects are on
    board is answered ``full``, one while another object is in progress ``rejected``.
    ``grasp_status`` (GraspStatus) ``done`` moves on, ``failed`` (or 60 s without an
    answer) fails the request. Parameter: ``storage_slots``.
    """

    rate_hz = 1.0
    inputs = {"request": "_on_request", "grasp_status": "_on_grasp_status"}
    outputs = ("status", "grasp_request")

    def on_start(self) -> None:
        self.on_board: list[str] = []
        self.barcode = ""
        self.actions: list[str] = []  # still to do, the first in progress
        self.since = 0.0

    def _on_request(self, data: dict[str, Any]) -> bool:
        barcode = text(data.get("barcode"))
        if not barcode:
            return False
        if self.actions:
            if barcode != self.barcode:
                self.emit("status", {"barcode": barcode, "state": "rejected"})
            return True
        if barcode in self.on_board:
            self._start(barcode, ["place"])
        elif len(self.on_board) >= self.iparam("storage_slots", 2, 1, 1000):
            self.emit("status", {"barcode": barcode, "state": "full"})
        else:
            self._start(barcode, ["pick", "store"])
        return True

    def _on_grasp_status(self, data: dict[str, Any]) -> bool:
        barcode, action, state = (text(data.get(k)) for k in ("barcode", "action", "state"))
        if barcode is None or action is None or state is None:
            return False
        if not self.actions or (barcode, action) != (self.barcode, self.actions[0]):
            return True
        if state == "done":
            self._done(self.actions.pop(0))
        elif state == "failed":
            self._fail()
        return True

    def step(self, now: float) -> None:
        if self.actions and now - self.since >= GRASP_TIMEOUT:
            self.ctx.log(f"{self.actions[0]} of {self.barcode} timed out")
            self._fail()

    def _start(self, barcode: str, actions: list[str]) -> None:
        self.barcode, self.actions = barcode, actions
        self._request()

    def _request(self) -> None:
        action = self.actions[0]
        self.since = self.ctx.now()
        self.emit("grasp_request", {"barcode": self.barcode, "action": action})
        self.emit("status", {"barcode": self.barcode, "state": ACTIONS[action]})

    def _done(self, action: str) -> None:
        if action == "store":
            self.on_board.append(self.barcode)
        elif action == "place" and self.barcode in self.on_board:
            self.on_board.remove(self.barcode)
        if self.actions:
            self._request()
        else:
            self.emit(
                "status",
                {"barcode": self.barcode, "state": "placed" if action == "place" else "stored"},
            )

    def _fail(self) -> None:
        self.actions = []
        self.emit("status", {"barcode": self.barcode, "state": "failed"})


def _segment_time(a: Waypoint, b: Waypoint, speed: float) -> float:
    """Time from ``a`` to ``b`` at ``speed`` m/s of the hand (plus gripper motion)."""
    travel = max(abs(b[1] - a[1]), abs(b[2] - a[2]), abs(b[0] - a[0]) * PAN_RADIUS)
    return travel / speed + GRIPPER_TIME * abs(b[3] - a[3])


def plan(
    action: str, start: Waypoint, target: list[float] | None, approach: float
) -> list[Waypoint] | None:
    """Waypoints for ``action`` from ``start``; ``target`` is the object position for pick."""
    if action == "pick":
        if target is None:
            return None
        x, y, z = target
        pan, reach = math.atan2(x, z), math.hypot(x, z)
        pre = max(reach - approach, 0.0)
        return [(pan, y, pre, 0.0), (pan, y, reach, 0.0), (pan, y, reach, 1.0), (pan, y, pre, 1.0)]
    if action == "store":
        pan, lift, reach = TRAY
        return [
            (pan, lift + 0.2, reach, 1.0),
            (pan, lift, reach, 1.0),
            (pan, lift, reach, 0.0),
            HOME,
        ]
    if action == "place":
        pan, lift, reach = TRAY
        p_pan, p_lift, p_reach = PLACE
        pre = max(p_reach - approach, 0.0)
        return [
            (pan, lift, reach, 0.0),
            (pan, lift, reach, 1.0),
            (p_pan, p_lift, pre, 1.0),
            (p_pan, p_lift, p_reach, 1.0),
            (p_pan, p_lift, p_reach, 0.0),
            (p_pan, p_lift, pre, 0.0),
            HOME,
        ]
    return None


def trajectory(start: Waypoint, points: list[Waypoint]) -> dict[str, Any]:
    """An ArmTrajectory through ``points`` at the planner's nominal speed."""
    times, t, prev = [], 0.0, start
    for p in points:
        t += max(_segment_time(prev, p, NOMINAL_SPEED), 0.1)
        times.append(round(t, 3))
        prev = p
    return {
        "joint_names": list(JOINTS),
        "positions": [[round(v, 4) for v in p] for p in points],
        "times": times,
    }


class GraspPlanner(SafeNode):
    """Plans a ``trajectory`` (ArmTrajectory) for each ``request`` (GraspRequest).

    ``pick`` needs the object's position from the last ``objects`` (DetectedObjects) that
    read its barcode; ``store`` goes to the robot's tray, ``place`` from the tray to the rack
    ahead. ``status`` (GraspStatus): ``executing`` once the trajectory is sent, ``done`` when
    ``arm_status`` (ArmStatus) reports ``done`` after ``moving``, ``failed`` when the arm
    fails, the object is unknown or the action is not one of pick / store / place, and
    ``rejected`` while another action runs. Parameter: ``approach_distance`` (m, the
    pre-grasp / pre-place offset along the reach).
    """

    inputs = {"request": "_on_request", "objects": "_on_objects", "arm_status": "_on_arm_status"}
    outputs = ("trajectory", "status")

    def on_start(self) -> None:
        self.known: dict[str, list[float]] = {}
        self.arm: Waypoint = HOME
        self.current: tuple[str, str] | None = None
        self.seen_moving = False

    def _on_objects(self, data: dict[str, Any]) -> bool:
        objects = data.get("objects")
        if not isinstance(objects, list):
            return False
        for obj in objects:
            barcode = text(obj.get("barcode")) if isinstance(obj, dict) else None
            position = numbers(obj.get("position"), 3) if barcode else None
            if barcode and position is not None:
                self.known.pop(barcode, None)
                self.known[barcode] = position
        while len(self.known) > 64:
            del self.known[next(iter(self.known))]
        return True

    def _on_request(self, data: dict[str, Any]) -> bool:
        barcode, action = text(data.get("barcode")), text(data.get("action"))
        if not barcode or action is None:
            return False
        if self.current is not None:
            self._status(barcode, action, "rejected")
            return True
        approach = self.fparam("approach_distance", 0.1, 0.0, 1.0)
        points = plan(action, self.arm, self.known.get(barcode), approach)
        if points is None:
            self._status(barcode, action, "failed")
            return True
        self.current, self.seen_moving = (barcode, action), False
        self.emit("trajectory", trajectory(self.arm, points))
        self._status(barcode, action, "executing")
        return True

    def _on_arm_status(self, data: dict[str, Any]) -> bool:
        joints, state = numbers(data.get("joint_positions"), len(JOINTS)), text(data.get("state"))
        if joints is None or state is None:
            return False
        self.arm = (joints[0], joints[1], joints[2], joints[3])
        if self.current is None:
            return True
        if state == "moving":
            self.seen_moving = True
        elif (state == "done" and self.seen_moving) or state == "failed":
            barcode, action = self.current
            self.current = None
            self._status(barcode, action, "done" if state == "done" else "failed")
        return True

    def _status(self, barcode: str, action: str, state: str) -> None:
        self.emit("status", {"barcode": barcode, "action": action, "state": state})


IDLE_STATUS_PERIOD = 1.0  # s


class ArmController(SafeNode):
    """Executes ``trajectory`` (ArmTrajectory) samples and reports ``status`` (ArmStatus).

    Each segment takes at least its hand travel divided by ``approach_speed`` (m/s): the
    planner's times are stretched, never shortened. The gripper (joint ``gripper`` >= 0.5)
    closes with ``grip_force`` (N). Status, at 5 Hz while moving and each second otherwise,
    carries ``joint_positions``, ``gripper_closed``, ``state`` (idle, moving, done: the last
    trajectory finished; failed: a trajectory could not be used) and two extra fields:
    ``grip_force`` (N applied, 0 when open) and ``approach_speed``. A trajectory arriving
    while moving replaces the current one. Parameter changes apply at once (a closed
    gripper re-grips with the new force).
    """

    rate_hz = 5.0
    inputs = {"trajectory": "_on_trajectory"}
    outputs = ("status",)

    def on_start(self) -> None:
        self.joints: list[float] = list(HOME)
        self.segments: list[tuple[float, float, list[float], list[float]]] = []
        self.state = "idle"
        self.idle_timer = Every()

    def _on_trajectory(self, data: dict[str, Any]) -> bool:
        points = self._parse(data)
        if points is None:
            self.state = "failed"
            self._publish()
            return False
        speed = self.fparam("approach_speed", 0.1, 0.001)
        t, prev, self.segments = self.ctx.now(), list(self.joints), []
        for nominal, p in points:
            duration = max(nominal, _segment_time(tuple(prev), tuple(p), speed))  # type: ignore[arg-type]
            self.segments.append((t, t + duration, prev, p))
            t, prev = t + duration, p
        self.state = "moving"
        self._publish()
        return True

    def _parse(self, data: dict[str, Any]) -> list[tuple[float, list[float]]] | None:
        """(nominal segment duration, full joint vector) per point, or None if unusable."""
        names, raw, times = (
            data.get("joint_names"),
            data.get("positions"),
            numbers(data.get("times")),
        )
        if not isinstance(names, list) or not all(n in JOINTS for n in names):
            return None
        if not isinstance(raw, list) or times is None or len(raw) != len(times) or not raw:
            return None
        out, current, t0 = [], list(self.joints), 0.0
        for values, t in zip(raw, times, strict=True):
            row = numbers(values, len(names))
            if row is None or t < t0:
                return None
            for name, v in zip(names, row, strict=True):
                current[JOINTS.index(name)] = v
            out.append((t - t0, list(current)))
            t0 = t
        return out

    def step(self, now: float) -> None:
        if self.state != "moving":
            if self.idle_timer.due(now, IDLE_STATUS_PERIOD):
                self._publish()
            return
        self.joints = self._interpolate(now)
        if now >= self.segments[-1][1]:
            self.state = "done"
        self._publish()

    def _interpolate(self, now: float) -> list[float]:
        for start, end, a, b in self.segments:
            if now < end:
                f = clamp((now - start) / (end - start), 0.0, 1.0) if end > start else 1.0
                return [x + f * (y - x) for x, y in zip(a, b, strict=True)]
        return list(self.segments[-1][3])

    def on_params(self, changed: dict[str, Any]) -> None:
        if any(num(changed.get(k)) is not None for k in ("grip_force", "approach_speed")):
            self._publish()

    def _publish(self) -> None:
        closed = self.joints[3] >= 0.5
        self.emit(
            "status",
            {
                "joint_positions": [round(v, 4) for v in self.joints],
                "gripper_closed": closed,
                "state": self.state,
                "grip_force": self.fparam("grip_force", 10.0, 1.0, 40.0) if closed else 0.0,
                "approach_speed": self.fparam("approach_speed", 0.1, 0.001),
            },
        )
