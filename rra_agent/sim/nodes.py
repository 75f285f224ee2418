"""The quadcopter case study's components as Nodes (scenarios/quadcopter/system.yaml).

- `VehicleSimulator`: MuJoCo vehicle in real time; ``motor_cmd`` in; ``state``,
  ``telemetry``, ``events`` out; fault injections from ``rra/<system>/inject/**``.
- `TrajectoryGenerator`: ``setpoint`` at ``rate_hz`` (mode set by the Flight feature).
- `Estimator`: one ``estimate`` per ``state`` sample.
- `Controller`: one ``motor_cmd`` per ``estimate`` (four motors).
- `ProplossController`: same ports as `Controller`; runs in standby (computing, its
  publishes dropped by the SDK) and publishes its latest command the moment it is activated.

The logic lives in `rra_agent.sim.control` and `rra_agent.sim.model`; these classes only map
messages and parameters onto it.
"""

from __future__ import annotations

import collections
import math
from typing import Any

import numpy as np

from rra_agent import trace
from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.node import Node, NodeContext
from rra_agent.sim import control
from rra_agent.sim.model import N_MOTORS, Quadcopter, QuadParams

_INJECTIONS = m.Codec[m.Injection](m.Injection)


# ---- simulator ---------------------------------------------------------------------------------
class VehicleSimulator(Node):
    """The simulated quadcopter, stepped in real time by `step` (``rate_hz`` 500).

    Parameters: ``timestep`` (physics step, s), ``realtime_factor`` (sim seconds per wall
    second; 0 = one physics step per call, unpaced), ``telemetry_rate_hz``,
    ``initial_position`` ([x, y, z], m), ``max_catchup`` (physics steps per call at most),
    ``noise_seed``.

    Real-time policy: sim time is frozen, the vehicle hovering at ``initial_position`` with
    its rotors at hover speed, until the first motor command arrives ("armed"). From then
    on each call runs as many physics steps as the wall clock asks for (normally one), at
    most ``max_catchup``; if it fell further behind (a stalled process), the remainder is
    dropped: sim time slips behind wall time (counted in ``dropped_steps``) rather than
    running a burst the controllers never see. Motor commands are held (zero-order hold)
    until the next one. Each call publishes one ``state`` (with the configured sensor
    noise) and, at ``telemetry_rate_hz``, one ``telemetry`` sample.

    ``events`` (``SimEvent``: kind, sim_time, wall_time, detail) marks the moments that
    matter: ``armed``, ``fault`` (an injection applied; detail = kind and args),
    ``controller`` (the first physics step using the command of a controller other than
    the previous one; detail = its name), ``crash`` (detail = why).

    Injections (`rra_agent.bus.messages.Inject` on ``Keys(system).inject_all``, target ""
    or this node's name; other kinds and targets are ignored): ``break_motor {motor: k}``,
    ``degrade_motor {motor: k, efficiency: x}``, ``sensor_noise {std: s}`` (optional per
    channel: position, velocity, attitude, gyro), ``clear_faults {}``; motors are 0-based
    (``k`` is accepted for ``motor``). They are queued by whatever thread receives them
    and applied at the start of the next `step`.
    """

    rate_hz = 500.0

    def __init__(self, ctx: NodeContext) -> None:
        # Set up here, not in on_start: samples may be delivered before on_start runs.
        super().__init__(ctx)
        x, y, z = (float(v) for v in self.ctx.param("initial_position", [0.0, 0.0, 1.5]))
        self.quad = Quadcopter(
            QuadParams(),
            timestep=float(self.ctx.param("timestep", 0.002)),
            position=(x, y, z),
            seed=int(self.ctx.param("noise_seed", 0)),
        )
        self.armed = False
        self.dropped_steps = 0
        self._wall0: float | None = None
        self._pending: collections.deque[m.Inject] = collections.deque()
        self._controller = ""  # whose command is held
        self._announce: str | None = None  # a new controller's command not yet stepped
        self._crash_reported = False
        self._next_telemetry = 0.0
        self.viz: Any = None

    def on_start(self) -> None:
        self._subscribe_injections()
        self._open_viz()

    def on_stop(self) -> None:
        if self.viz is not None:
            self.viz.close()
            self.viz = None

    # ---- Rerun (only when the run records one: RRA_RERUN) ----------------------------------
    def _open_viz(self) -> None:
        from rra_agent.viz.rerun_log import Every, open_logger

        self.viz = open_logger(self.ctx.name)
        self._draw = Every(0.02)  # 3D at 50 Hz of simulated time; scalars every step
        if self.viz is not None:
            p = self.quad.p
            rotors = [(float(x), float(y), 0.0) for x, y in p.rotor_positions]
            self.viz.vehicle_geometry(rotors, thrust_scale=0.5 / p.weight)

    def _log(self) -> None:
        viz, q = self.viz, self.quad
        t = float(q.time)
        target = self.ctx.param("initial_position", [0.0, 0.0, 0.0])[2]
        viz.altitude(float(q.position[2]), sim_time=t, target=float(target))
        tel = q.telemetry()
        for quantity in ("desired_speed", "measured_speed", "current"):
            viz.motors(quantity, tel[quantity], sim_time=t)
        if self._draw(t):
            w, x, y, z = (float(v) for v in q.quaternion)  # MuJoCo: w first; Rerun: w last
            viz.vehicle_pose([float(v) for v in q.position], (x, y, z, w), sim_time=t)
            thrusts = (q.p.k_f * q.speed * q.speed).tolist()
            viz.thrust(thrusts, sim_time=t, failed=[bool(b) for b in q.faults.broken])

    # ---- inputs ----------------------------------------------------------------------------
    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        if port != "motor_cmd":
            return
        speeds = data.get("speeds")
        try:
            self.quad.set_command(speeds)
        except (ValueError, TypeError) as e:
            self.ctx.log(f"ignored motor command: {e}")
            return
        sender = str(data.get("controller", ""))
        if sender != self._controller:
            trace.mark("sim:command_from", sender)
            self._controller = sender
            self._announce = sender

    def inject(self, kind: str, args: dict[str, Any] | None = None, target: str = "") -> None:
        """Queue an injection (applied at the next step); thread-safe."""
        self._pending.append(m.Inject(kind=kind, target=target, args=dict(args or {})))

    def on_injection(self, payload: bytes) -> None:
        """A raw ``Injection`` sample (any thread): decode and queue it."""
        try:
            self._pending.append(_INJECTIONS.decode(payload))
        except Exception as e:  # malformed: drop, the bus callback must not raise
            self.ctx.log(f"dropped malformed injection: {e}")

    # ---- stepping --------------------------------------------------------------------------
    def step(self, now: float) -> None:
        while self._pending:
            self._apply(self._pending.popleft())
        if not self.armed and self._announce is not None:
            self.armed = True
            self._wall0 = None
            self._event("armed", self._announce)
        if not self.armed or self._advance(now) > 0:
            self._publish()
            if self.viz is not None and self.armed:
                self._log()

    def _advance(self, now: float) -> int:
        """Run the physics steps due at wall time ``now``; return how many ran."""
        q = self.quad
        rtf = float(self.ctx.param("realtime_factor", 1.0))
        n = 1
        if rtf > 0:
            if self._wall0 is None:
                self._wall0 = now - (q.time + q.dt) / rtf
            due = math.floor(((now - self._wall0) * rtf - q.time) / q.dt + 1e-6)
            limit = max(1, int(self.ctx.param("max_catchup", 5)))
            if due > limit:  # fell behind: drop the rest (sim time slips)
                self.dropped_steps += due - limit
                self._wall0 += (due - limit) * q.dt / rtf
                due = limit
            n = due
        for _ in range(n):
            q.step()
            if self._announce is not None:
                trace.mark("sim:commanded_by", self._announce)
                self._event("controller", self._announce)
                self._announce = None
        if q.crashed and not self._crash_reported:
            self._crash_reported = True
            trace.mark("sim:crash", q.crash_reason)
            self._event("crash", q.crash_reason)
        return n

    def _publish(self) -> None:
        q = self.quad
        self.ctx.publish("state", q.measured_state())
        if q.time + 1e-9 >= self._next_telemetry or not self.armed:
            self.ctx.publish("telemetry", q.telemetry())
            rate = float(self.ctx.param("telemetry_rate_hz", 500.0))
            self._next_telemetry = q.time + (1.0 / rate if rate > 0 else 0.0)

    def _event(self, kind: str, detail: str) -> None:
        self.ctx.publish(
            "events",
            {
                "kind": kind,
                "sim_time": self.quad.time,
                "wall_time": self.ctx.now(),
                "detail": detail,
            },
        )

    def _apply(self, inj: m.Inject) -> None:
        if inj.target not in ("", self.ctx.name):
            return
        args = inj.args
        q = self.quad
        try:
            match inj.kind:
                case "break_motor":
                    q.break_motor(_motor(args))
                case "degrade_motor":
                    q.degrade_motor(_motor(args), float(args.get("efficiency", 1.0)))
                case "sensor_noise":
                    channels = {c: float(v) for c, v in args.items() if c != "std"}
                    q.set_sensor_noise(float(args.get("std", 0.0)), **channels)
                case "clear_faults":
                    q.clear_faults()
                case _:
                    return  # not ours
        except (ValueError, TypeError) as e:
            self.ctx.log(f"refused injection {inj.kind} {args}: {e}")
            return
        detail = f"{inj.kind} " + " ".join(f"{k}={v}" for k, v in sorted(args.items()))
        trace.mark("sim:fault", self.ctx.name)
        self._event("fault", detail.strip())
        if self.viz is not None:
            self.viz.injection(detail.strip(), sim_time=q.time, altitude=float(q.position[2]))

    # ---- injection subscription ------------------------------------------------------------
    def _subscribe_injections(self) -> None:
        """Listen on ``rra/<system>/inject/**`` (a raw subscription the runtime owns; in a
        `NodeHarness`, deliver with ``deliver_raw`` or call `on_injection` directly)."""
        key = Keys(self.ctx.system).inject_all
        self.ctx.subscribe(key, lambda _key, payload, _stamp: self.on_injection(payload))


def _motor(args: dict[str, Any]) -> int:
    k = args.get("motor", args.get("k"))
    if isinstance(k, bool) or not isinstance(k, int):
        raise ValueError(f"motor must be an int 0..{N_MOTORS - 1}, got {k!r}")
    return k


# ---- trajectory ---------------------------------------------------------------------------------
class TrajectoryGenerator(Node):
    """Publishes ``setpoint`` (``TrajectorySetpoint``) at ``rate_hz`` (default 100).

    Parameters: ``mode`` (hover, waypoints, circle), ``altitude`` (m), ``radius`` (m),
    ``speed`` (m/s), ``waypoints`` ([[x, y] or [x, y, z], ...]), ``start_delay`` (s of
    hovering at the start point before the motion begins). Trajectory time is wall time
    since the node started. A parameter change rebuilds the trajectory (time goes on); an
    invalid combination is refused with a log line and the previous one kept.
    """

    rate_hz = 100.0

    def __init__(self, ctx: NodeContext) -> None:
        super().__init__(ctx)
        self.trajectory = self._build()
        self._t0: float | None = None

    def _build(self) -> control.Trajectory:
        param = self.ctx.param
        return control.Trajectory(
            mode=str(param("mode", "hover")),
            altitude=float(param("altitude", 1.5)),
            radius=float(param("radius", 1.0)),
            speed=float(param("speed", 0.5)),
            waypoints=tuple(tuple(float(c) for c in w) for w in param("waypoints", []) or []),
            start_delay=float(param("start_delay", 2.0)),
        )

    def on_params(self, changed: dict[str, Any]) -> None:
        try:
            self.trajectory = self._build()
        except (ValueError, TypeError) as e:
            self.ctx.log(f"kept the previous trajectory: {e}")

    def step(self, now: float) -> None:
        if self._t0 is None:
            self._t0 = now
        self.ctx.publish("setpoint", self.trajectory.sample(now - self._t0))


# ---- estimator ----------------------------------------------------------------------------------
class Estimator(Node):
    """One ``estimate`` per ``state`` sample (event-driven: the simulator's 500 Hz).

    ``position_noise``: the sensor noise std to filter for (`control.Estimator`); 0 = pass
    the state through.
    """

    def __init__(self, ctx: NodeContext) -> None:
        super().__init__(ctx)
        self.filter = control.Estimator(float(self.ctx.param("position_noise", 0.0)))

    def on_params(self, changed: dict[str, Any]) -> None:
        if "position_noise" in changed:
            self.filter = control.Estimator(float(self.ctx.param("position_noise", 0.0)))

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        if port == "state":
            self.ctx.publish("estimate", self.filter.update(data))


# ---- controllers --------------------------------------------------------------------------------
class _ControllerNode(Node):
    """What both controllers share: latest setpoint, telemetry, one command per estimate."""

    def __init__(self, ctx: NodeContext) -> None:
        # Set up here, not in on_start: samples (and the spec's state) may come first.
        super().__init__(ctx)
        self.setpoint: dict[str, Any] | None = None
        self.estimate: dict[str, Any] | None = None
        self.failed_motor: int | None = None
        self.last_command: list[float] | None = None
        self.setup()

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        if port == "setpoint":
            self.setpoint = data
        elif port == "telemetry":
            self.on_telemetry(data)
        elif port == "estimate":
            self.estimate = data
            if self.setpoint is None:  # hold the first position until a setpoint arrives
                self.setpoint = _hold(data)
            cmd = self.compute(data, self.setpoint)
            if cmd is not None:
                self.last_command = [float(w) for w in cmd]
                self.ctx.publish("motor_cmd", self._message(self.last_command))

    def _message(self, speeds: list[float]) -> dict[str, Any]:
        return {"speeds": speeds, "controller": self.ctx.name}

    def _take_setpoint(self, state: Any) -> None:
        """The setpoint of the controller this one replaces (its exported state), until one
        arrives: a replacement's first command aims where the vehicle was told to go, not
        where it is (its first samples may come before any setpoint)."""
        sp = state.get("setpoint") if isinstance(state, dict) else None
        if self.setpoint is None and isinstance(sp, dict) and control.is_vec3(sp.get("position")):
            self.setpoint = sp

    # ---- what a controller provides ------------------------------------------------------
    def setup(self) -> None:
        raise NotImplementedError

    def on_telemetry(self, data: dict[str, Any]) -> None:
        if self.failed_motor is None:
            self.failed_motor = control.failed_motor(data)

    def compute(self, est: dict[str, Any], sp: dict[str, Any]) -> np.ndarray | None:
        raise NotImplementedError


def _hold(est: dict[str, Any]) -> dict[str, Any]:
    return {
        "time": est.get("time", 0.0),
        "position": list(est["position"]),
        "velocity": [0.0, 0.0, 0.0],
        "acceleration": [0.0, 0.0, 0.0],
        "yaw": 0.0,
    }


class Controller(_ControllerNode):
    """The standard cascaded controller (`control.StandardController`) for four motors.

    Parameters: ``max_tilt`` (rad). Exports ``{integral, failed_motor, setpoint}``: the
    position integrators (an acceleration bias, m/s^2), the motor it saw fail in the
    telemetry (it does nothing else with the telemetry: it is the Proploss controller's
    business) and the last setpoint (a replacement aims at it until its own comes).
    """

    def setup(self) -> None:
        self.ctl = control.StandardController(max_tilt=float(self.ctx.param("max_tilt", 0.5)))

    def on_params(self, changed: dict[str, Any]) -> None:
        if "max_tilt" in changed:
            self.ctl.max_tilt = float(self.ctx.param("max_tilt", 0.5))

    def compute(self, est: dict[str, Any], sp: dict[str, Any]) -> np.ndarray:
        return self.ctl.update(est, sp)

    def export_state(self) -> Any:
        return self.ctl.export_state() | {
            "failed_motor": self.failed_motor, "setpoint": self.setpoint,
        }

    def import_state(self, state: Any) -> None:
        self.ctl.import_state(state)
        self._take_setpoint(state)


class ProplossController(_ControllerNode):
    """Two-propeller flight after a motor loss (`control.ProplossController`).

    Parameters: ``failed_motor`` (0..3, or -1: find it from the telemetry). Finds the
    failed motor in ``telemetry`` (latched), computes a command on every estimate while in
    standby (the SDK drops the publish), publishes the latest one at once on activation.
    Imports the standard controller's state (position integrators, failed motor, setpoint).
    """

    @classmethod
    def warm_up(cls) -> None:
        control.ProplossController()  # computes and caches the gain schedules

    @classmethod
    def rehearse(cls) -> None:
        # The first command after a failure (a standby's, or a replacement's) must not pay
        # this process's first run of the recovery's code: 0.35 ms idle, 1-2 ms under load.
        control.rehearse_recovery()

    def setup(self) -> None:
        self.ctl = control.ProplossController()
        self._apply_failed_param()

    def _apply_failed_param(self) -> None:
        k = self.ctx.param("failed_motor", -1)
        if isinstance(k, int) and not isinstance(k, bool) and 0 <= k < N_MOTORS:
            self.ctl.set_failed(k)
            self.failed_motor = k

    def on_params(self, changed: dict[str, Any]) -> None:
        if "failed_motor" in changed:
            self._apply_failed_param()

    def on_telemetry(self, data: dict[str, Any]) -> None:
        known = self.failed_motor is not None
        k = self.ctl.observe_telemetry(data)
        if k is not None:
            self.failed_motor = k
        if k is not None and not known and self.estimate is not None and self.setpoint:
            # The failure is known: a command at once, from the newest estimate, rather
            # than at the next estimate (up to a step later): a consumer that has just
            # switched to this controller (a reflex) gets it one hop after the telemetry.
            trace.mark("node:failure_known", self.ctx.name)
            cmd = self.ctl.update(self.estimate, self.setpoint)
            if cmd is not None:
                self.last_command = [float(w) for w in cmd]
                self.ctx.publish("motor_cmd", self._message(self.last_command))

    def compute(self, est: dict[str, Any], sp: dict[str, Any]) -> np.ndarray | None:
        return self.ctl.update(est, sp)

    def on_active(self, active: bool) -> None:
        if not active:
            return
        if self.last_command is None and self.estimate is not None and self.setpoint:
            cmd = self.ctl.update(self.estimate, self.setpoint)
            self.last_command = None if cmd is None else [float(w) for w in cmd]
        if self.last_command is not None:
            trace.mark("node:activated_publish", self.ctx.name)
            self.ctx.publish("motor_cmd", self._message(self.last_command))
        else:
            self.ctx.log("activated without a known failed motor: no command yet")

    def export_state(self) -> Any:
        return self.ctl.export_state() | {"setpoint": self.setpoint}

    def import_state(self, state: Any) -> None:
        self.ctl.import_state(state)
        if self.ctl.failed is not None:
            self.failed_motor = self.ctl.failed
        self._take_setpoint(state)
