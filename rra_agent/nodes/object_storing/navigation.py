"""Navigation: global planning on the map (`MapBasedNavigation`) and two local planners.

`MapBasedNavigation` turns a ``NavigationGoal`` into a ``Path`` through the doors of the
two-room map (`world`), reports ``NavigationStatus`` and names the area the robot is in.
Local navigation follows that path with ``Twist`` commands capped at ``max_vel``; its two
implementations differ in how they treat the obstacle ahead (closest laser return within
their front sector):

- `VfhLocalNavigation` (static obstacles, rooms): full speed until 1.0 m, then slows
  linearly, stopping at 0.3 m: furniture does not move, so it may come close.
- `DwaLocalNavigation` (moving obstacles, corridor): keeps a 0.6 m safety margin and only
  drives at velocities from which it can stop (0.3 m/s^2) before the margin,
  ``v <= sqrt(2 a (d - 0.6))``, over a wider front sector: people may step in.

Both stop when no path is left and crawl at 0.1 m/s when no scan is fresher than 1 s.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar

from rra_agent.nodes.object_storing import world
from rra_agent.nodes.object_storing._common import (
    Every,
    Pose,
    SafeNode,
    clamp,
    num,
    pose,
    text,
    wrap_angle,
)

BLOCKED_DISTANCE = 0.35  # m: an obstacle this close ahead blocks the path
BLOCKED_TIMEOUT = 15.0  # s blocked -> the goal fails
STATUS_PERIOD = 1.0  # s between status / path repeats while a goal is active
LOCATION_PERIOD = 0.5  # s between SemanticLocation samples


def _closest_ahead(data: dict[str, Any], half_angle: float) -> float | None:
    """Closest valid range within ``half_angle`` of straight ahead (inf: none); None if bad."""
    ranges = data.get("ranges")
    a0, inc = num(data.get("angle_min")), num(data.get("angle_increment"))
    if not isinstance(ranges, list) or a0 is None or inc is None:
        return None
    low = num(data.get("range_min")) or 0.0
    high = num(data.get("range_max")) or math.inf
    closest = math.inf
    for i, r in enumerate(ranges):
        d = num(r)
        if d is not None and low <= d <= high and abs(wrap_angle(a0 + i * inc)) <= half_angle:
            closest = min(closest, d)
    return closest


class MapBasedNavigation(SafeNode):
    """Global navigation on the built-in two-room map (see `world`).

    - ``goal`` (NavigationGoal): a known ``rack_id`` (A1, A2, B1, B2) is driven to its
      approach pose; an empty ``rack_id`` uses ``x``, ``y``, ``theta``; an unknown one fails.
    - ``odom`` (Odometry) is the localisation (perfect odometry in this simulation).
    - ``scan`` (LaserScan): an obstacle closer than 0.35 m ahead blocks the path; blocked for
      15 s, the goal fails.
    - ``status`` (NavigationStatus): ``active`` (repeated each second), ``reached``,
      ``failed``. ``path`` (Path): the remaining waypoints, repeated each second while
      active (so a replacement local planner picks it up); empty once the goal is reached.
    - ``semantic_location`` (SemanticLocation) at 2 Hz: ``RoomA`` x < 4 m, ``Corridor``
      4 <= x < 8 m, ``RoomB`` x >= 8 m (published once a pose is known).

    Parameters: ``goal_tolerance`` (m); ``map`` (only the built-in map exists; another
    name is logged and the built-in map used); ``location`` (str, default empty): when not
    empty, the published label, whatever the position (tests and scenarios set the context).
    """

    rate_hz = 2.0
    inputs = {"goal": "_on_goal", "odom": "_on_odom", "scan": "_on_scan"}
    outputs = ("status", "path", "semantic_location")

    def on_start(self) -> None:
        self.pose: Pose | None = None
        self.goal: Pose | None = None
        self.rack_id = ""
        self.path: list[Pose] = []
        self.blocked_since: float | None = None
        self.status_timer, self.location_timer = Every(), Every()
        name = self.sparam("map", world.DEFAULT_MAP)
        if not name.endswith("two_rooms.yaml"):
            self.ctx.log(f"unknown map {name!r}: using the built-in two-room map")

    # -- inputs ---------------------------------------------------------------------------
    def _on_goal(self, data: dict[str, Any]) -> bool:
        rack_id = text(data.get("rack_id", ""))
        if rack_id is None:
            return False
        goal = world.RACKS.get(rack_id) if rack_id else pose(data)
        self.rack_id = rack_id
        if goal is None:
            self._finish("failed")
            return True
        self.goal, self.blocked_since = goal, None
        self.path = world.plan_path(self.pose or Pose(0.0, 0.0), goal)
        self._publish_progress()
        return True

    def _on_odom(self, data: dict[str, Any]) -> bool:
        p = pose(data.get("pose"))
        if p is None:
            return False
        self.pose = p
        while len(self.path) > 1 and p.distance(self.path[0]) < 0.3:
            self.path.pop(0)
        if self.goal is not None and p.distance(self.goal) <= self._tolerance():
            self._finish("reached")
        return True

    def _on_scan(self, data: dict[str, Any]) -> bool:
        closest = _closest_ahead(data, math.pi / 6)
        if closest is None:
            return False
        if closest >= BLOCKED_DISTANCE:
            self.blocked_since = None
        elif self.blocked_since is None:
            self.blocked_since = self.ctx.now()
        return True

    # -- periodic -------------------------------------------------------------------------
    def step(self, now: float) -> None:
        if self.location_timer.due(now, LOCATION_PERIOD):
            self._publish_location()
        if self.goal is None:
            return
        if self.blocked_since is not None and now - self.blocked_since >= BLOCKED_TIMEOUT:
            self.ctx.log(f"path to {self.rack_id or 'goal'} blocked for {BLOCKED_TIMEOUT} s")
            self._finish("failed")
        elif self.status_timer.due(now, STATUS_PERIOD):
            self._publish_progress()

    def on_params(self, changed: dict[str, Any]) -> None:
        if "location" in changed:
            self._publish_location()

    # -- helpers --------------------------------------------------------------------------
    def _tolerance(self) -> float:
        return self.fparam("goal_tolerance", 0.1, 0.01, 1.0)

    def _finish(self, state: str) -> None:
        self.goal, self.path, self.blocked_since = None, [], None
        self.emit("path", {"poses": []})
        self.emit("status", {"rack_id": self.rack_id, "state": state})

    def _publish_progress(self) -> None:
        self.emit("path", {"poses": [p.to_msg() for p in self.path]})
        self.emit("status", {"rack_id": self.rack_id, "state": "active"})

    def _publish_location(self) -> None:
        override = self.sparam("location", "")
        if self.pose is None and not override:
            return
        p = self.pose or Pose(0.0, 0.0)
        label = override or world.region_label(p.x)
        self.emit("semantic_location", {"label": label, "x": p.x, "y": p.y})


WAYPOINT_TOLERANCE = 0.2  # m: an intermediate waypoint counts as passed
FINAL_TOLERANCE = 0.03  # m: the last waypoint counts as reached
TURN_IN_PLACE = 0.8  # rad of heading error above which the robot only turns
ANGULAR_GAIN, MAX_ANGULAR = 1.5, 1.0
APPROACH_GAIN, MIN_APPROACH = 0.8, 0.02  # slow down near the goal: v <= max(0.8 d, 0.02)
SCAN_TIMEOUT, BLIND_SPEED = 1.0, 0.1


class _LocalNavigation(SafeNode):
    """Path following shared by both local planners; subclasses limit speed by obstacle.

    Inputs: ``path`` (Path; empty = stop), ``scan`` (LaserScan), ``odom`` (Odometry). Output:
    ``cmd_vel`` (Twist) at 10 Hz while following a path, one zero Twist when it stops.
    Parameters: ``max_vel`` (m/s, read at every step: a run-time change applies at once; the
    linear velocity never exceeds it); ``obstacle_avoidance`` (vfh or dwa) documents the
    algorithm: the class decides, a mismatch is logged. The path is handed over as state
    when the implementation is swapped.
    """

    rate_hz = 10.0
    inputs = {"path": "_on_path", "scan": "_on_scan", "odom": "_on_odom"}
    outputs = ("cmd_vel",)
    ALGORITHM: ClassVar[str] = ""
    FRONT_HALF_ANGLE: ClassVar[float] = math.pi / 4

    def on_start(self) -> None:
        self.path: list[Pose] = []
        self.pose: Pose | None = None
        self.obstacle = math.inf
        self.scan_time: float | None = None
        self.moving = False
        self._check_algorithm()

    def _on_path(self, data: dict[str, Any]) -> bool:
        raw = data.get("poses")
        if not isinstance(raw, list):
            return False
        poses = [pose(p) for p in raw]
        if any(p is None for p in poses):
            return False
        self.path = poses  # type: ignore[assignment]
        return True

    def _on_scan(self, data: dict[str, Any]) -> bool:
        closest = _closest_ahead(data, self.FRONT_HALF_ANGLE)
        if closest is None:
            return False
        self.obstacle, self.scan_time = closest, self.ctx.now()
        return True

    def _on_odom(self, data: dict[str, Any]) -> bool:
        p = pose(data.get("pose"))
        if p is None:
            return False
        self.pose = p
        return True

    def step(self, now: float) -> None:
        cmd = self.command(now)
        if cmd is not None:
            self.moving = True
            self.emit("cmd_vel", {"linear": cmd[0], "angular": cmd[1]})
        elif self.moving:
            self.moving = False
            self.emit("cmd_vel", {"linear": 0.0, "angular": 0.0})

    def command(self, now: float) -> tuple[float, float] | None:
        """(linear, angular) towards the next waypoint, or None when there is nothing to do."""
        if self.pose is None or not self._prune(self.pose):
            return None
        max_vel = self.fparam("max_vel", 0.6, 0.0)
        target = self.path[0]
        error = wrap_angle(
            math.atan2(target.y - self.pose.y, target.x - self.pose.x) - self.pose.theta
        )
        angular = clamp(ANGULAR_GAIN * error, -MAX_ANGULAR, MAX_ANGULAR)
        if abs(error) > TURN_IN_PLACE:
            return 0.0, angular
        remaining = self._remaining(self.pose)
        linear = min(
            max_vel * math.cos(error),
            max(APPROACH_GAIN * remaining, MIN_APPROACH),
            self._obstacle_limit(now, max_vel),
        )
        return clamp(linear, 0.0, max_vel), angular

    def _prune(self, p: Pose) -> bool:
        """Drop the waypoints reached; False when the path is done."""
        while self.path:
            last = len(self.path) == 1
            if p.distance(self.path[0]) >= (FINAL_TOLERANCE if last else WAYPOINT_TOLERANCE):
                return True
            self.path.pop(0)
        return False

    def _remaining(self, p: Pose) -> float:
        total, prev = 0.0, p
        for w in self.path:
            total, prev = total + prev.distance(w), w
        return total

    def _obstacle_limit(self, now: float, max_vel: float) -> float:
        if self.scan_time is None or now - self.scan_time > SCAN_TIMEOUT:
            return BLIND_SPEED
        return self.obstacle_speed(self.obstacle, max_vel)

    def obstacle_speed(self, distance: float, max_vel: float) -> float:
        """The speed allowed with the closest obstacle ahead at ``distance`` m."""
        raise NotImplementedError

    def on_params(self, changed: dict[str, Any]) -> None:
        if "obstacle_avoidance" in changed:
            self._check_algorithm()

    def _check_algorithm(self) -> None:
        wanted = self.sparam("obstacle_avoidance", self.ALGORITHM)
        if wanted != self.ALGORITHM:
            self.ctx.log(
                f"obstacle_avoidance={wanted!r} but this implementation is {self.ALGORITHM}"
            )

    def export_state(self) -> Any:
        return {"path": [p.to_msg() for p in self.path]}

    def import_state(self, state: Any) -> None:
        if isinstance(state, dict) and isinstance(state.get("path"), list):
            poses = [pose(p) for p in state["path"]]
            self.path = [p for p in poses if p is not None]


class VfhLocalNavigation(_LocalNavigation):
    """Vector Field Histogram style, for static obstacles: slows from 1.0 m, stops at 0.3 m."""

    ALGORITHM = "vfh"
    FRONT_HALF_ANGLE = math.pi / 6
    STOP, SLOW = 0.3, 1.0

    def obstacle_speed(self, distance: float, max_vel: float) -> float:
        return max_vel * clamp((distance - self.STOP) / (self.SLOW - self.STOP), 0.0, 1.0)


class DwaLocalNavigation(_LocalNavigation):
    """Dynamic Window style, for moving obstacles: only velocities that can stop (0.3 m/s^2)
    before a 0.6 m margin are admissible, over a wider (+-60 degree) front sector."""

    ALGORITHM = "dwa"
    FRONT_HALF_ANGLE = math.pi / 3
    MARGIN, DECELERATION = 0.6, 0.3

    def obstacle_speed(self, distance: float, max_vel: float) -> float:
        if distance <= self.MARGIN:
            return 0.0
        return min(max_vel, math.sqrt(2 * self.DECELERATION * (distance - self.MARGIN)))
