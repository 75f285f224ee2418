"""The robot's hardware, simulated: base (odometry and battery), laser scanner, RGB-D camera.

`RobotDriver` integrates velocity commands into odometry and drains a battery.
`LaserScanner` publishes a planar scan whose only obstacle is set by parameters, the way a
scenario sets the context. `RgbdCamera` publishes a fixed synthetic rack (`world.camera_scene`).
"""

from __future__ import annotations

import math
from typing import Any

from rra_agent.nodes.object_storing import world
from rra_agent.nodes.object_storing._common import (
    Every,
    Pose,
    SafeNode,
    StepClock,
    clamp,
    num,
    real,
    wrap_angle,
)

MAX_LINEAR = 1.0  # m/s, the base's hardware limit
MAX_ANGULAR = 2.0  # rad/s
CMD_TIMEOUT = 0.5  # s without a Twist -> the base stops
IDLE_CURRENT = 1.5  # A
MOTION_CURRENT = 3.0  # A per m/s
VOLTAGE_EMPTY, VOLTAGE_FULL = 22.0, 25.2  # V


class RobotDriver(SafeNode):
    """The mobile base: ``cmd_vel`` (Twist) in, ``odom`` (Odometry) and ``battery`` out.

    Steps at 10 Hz, integrating the last velocity command (unicycle model, clamped to 1 m/s
    and 2 rad/s; a command older than 0.5 s, or an empty battery, stops the base).

    Parameters:

    - ``odom_rate_hz``: odometry rate, at most the step rate (10 Hz).
    - ``battery_rate_hz``: BatteryState rate.
    - ``battery_level`` (%): the initial level; **setting it at run time sets the level**,
      which is how a test or scenario puts the robot in a low- or full-battery context. The
      SDK only reports a *changed* parameter, so to set the level twice to the same value set
      another value in between.
    - ``battery_drain`` (%/min, default 1.0) drained at rest, plus ``motion_drain``
      (%/min per m/s, default 2.0) while moving.
    """

    rate_hz = 10.0
    inputs = {"cmd_vel": "_on_cmd_vel"}
    outputs = ("odom", "battery")

    def on_start(self) -> None:
        self.pose = Pose(0.0, 0.0, 0.0)
        self.v = self.w = 0.0
        self.cmd = (0.0, 0.0)
        self.cmd_time: float | None = None
        self.level = self.fparam("battery_level", 100.0, 0.0, 100.0)
        self.clock = StepClock()
        self.odom_timer, self.battery_timer, self.viz_timer = Every(), Every(), Every()
        # Rerun (only when the run records one: RRA_RERUN): the floor map and the robot on it.
        from rra_agent.viz.rerun_log import open_logger

        self.viz = open_logger(self.ctx.name)
        if self.viz is not None:
            world.draw_map(self.viz)

    def on_stop(self) -> None:
        if self.viz is not None:
            self.viz.close()

    def _on_cmd_vel(self, data: dict[str, Any]) -> bool:
        linear, angular = num(data.get("linear")), num(data.get("angular"))
        if linear is None or angular is None:
            return False
        self.cmd = (
            clamp(linear, -MAX_LINEAR, MAX_LINEAR),
            clamp(angular, -MAX_ANGULAR, MAX_ANGULAR),
        )
        self.cmd_time = self.ctx.now()
        return True

    def step(self, now: float) -> None:
        dt = self.clock.dt(now)
        self._drive(now, dt)
        self._drain(dt)
        if self.odom_timer.due(now, 1.0 / self.fparam("odom_rate_hz", 50.0, 0.1, 1000.0)):
            self.emit("odom", {"pose": self.pose.to_msg(), "v": self.v, "w": self.w})
        if self.battery_timer.due(now, 1.0 / self.fparam("battery_rate_hz", 1.0, 0.01, 100.0)):
            self._publish_battery()
        if self.viz is not None and self.viz_timer.due(now, 0.1):
            self.viz.robot_pose_2d(self.pose.x, self.pose.y, self.pose.theta, wall_time=now)

    def on_params(self, changed: dict[str, Any]) -> None:
        level = num(changed.get("battery_level"))
        if level is not None:
            self.level = clamp(level, 0.0, 100.0)
            self._publish_battery()

    def _drive(self, now: float, dt: float) -> None:
        fresh = self.cmd_time is not None and now - self.cmd_time <= CMD_TIMEOUT
        self.v, self.w = self.cmd if fresh and self.level > 0.0 else (0.0, 0.0)
        p = self.pose
        theta = wrap_angle(p.theta + self.w * dt)
        mid = p.theta + self.w * dt / 2
        self.pose = Pose(
            p.x + self.v * dt * math.cos(mid), p.y + self.v * dt * math.sin(mid), theta
        )

    def _drain(self, dt: float) -> None:
        idle, moving = self.fparam("battery_drain", 1.0, 0.0), self.fparam("motion_drain", 2.0, 0.0)
        rate = idle + moving * abs(self.v)  # %/min
        self.level = max(0.0, self.level - rate * dt / 60.0)

    def _publish_battery(self) -> None:
        self.emit(
            "battery",
            {
                "level": round(self.level, 3),
                "voltage": round(
                    VOLTAGE_EMPTY + (VOLTAGE_FULL - VOLTAGE_EMPTY) * self.level / 100, 3
                ),
                "current": round(IDLE_CURRENT + MOTION_CURRENT * abs(self.v), 3),
                "charging": False,
            },
        )


N_BEAMS = 91
ANGLE_MIN, ANGLE_MAX = -math.pi / 2, math.pi / 2
RANGE_MIN = 0.05


class LaserScanner(SafeNode):
    """A 180 degree, 91-beam planar scan (2 degree steps), ``scan`` (LaserScan) at ``rate_hz``.

    Nothing is in range (every range is ``inf``) except one obstacle set by parameters:

    - ``obstacle_distance`` (m): distance of the closest obstacle; ``inf``, null, or <= 0
      means none. An obstacle beyond ``range_max`` is not seen.
    - ``obstacle_bearing`` (rad, default 0: straight ahead) and ``obstacle_width`` (rad,
      default 0.35): the beams that see it.
    - ``range_max`` (m), ``frame_id`` (sent as an extra ``frame_id`` field), ``rate_hz``.
    """

    rate_hz = 5.0
    outputs = ("scan",)

    def step(self, now: float) -> None:
        self.emit("scan", self.scan())

    def scan(self) -> dict[str, Any]:
        range_max = self.fparam("range_max", 10.0, RANGE_MIN)
        increment = (ANGLE_MAX - ANGLE_MIN) / (N_BEAMS - 1)
        ranges = [math.inf] * N_BEAMS
        dist = real(self.ctx.param("obstacle_distance"))
        if dist is not None and RANGE_MIN <= dist <= range_max:
            bearing = self.fparam("obstacle_bearing", 0.0)
            half = self.fparam("obstacle_width", 0.35, 0.0) / 2
            for i in range(N_BEAMS):
                if abs(wrap_angle(ANGLE_MIN + i * increment - bearing)) <= half + 1e-9:
                    ranges[i] = dist
        return {
            "frame_id": self.sparam("frame_id", "base_laser"),
            "angle_min": ANGLE_MIN,
            "angle_max": ANGLE_MAX,
            "angle_increment": increment,
            "range_min": RANGE_MIN,
            "range_max": range_max,
            "ranges": ranges,
        }


class RgbdCamera(SafeNode):
    """``point_cloud`` (PointCloud): the synthetic rack of `world.camera_scene` (~300 points)
    in frame ``camera_depth``, at ``rate_hz`` (class default 2 Hz; keep it low, the detector
    only needs the latest cloud)."""

    rate_hz = 2.0
    outputs = ("point_cloud",)

    def on_start(self) -> None:
        self.cloud = {"frame_id": "camera_depth", "points": world.camera_scene()}

    def step(self, now: float) -> None:
        self.emit("point_cloud", self.cloud)
