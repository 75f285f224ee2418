"""The simulated quadcopter: a MuJoCo rigid body driven by a motor/rotor model (no bus).

`QuadParams` holds the physical parameters (docs/quadcopter.md gives their sources); `mjcf`
turns them into the MuJoCo model (a free body, a floor, contact geoms); `Quadcopter` steps it.

Frames and conventions: world z up; body frame x forward, y left, z up (thrust direction).
Quaternions are [w, x, y, z] (MuJoCo's order). Motor ``i`` (0-based, as in the telemetry
lists) sits at angle 45 + 90 i degrees in the body xy plane: 0 front-left, 1 rear-left,
2 rear-right, 3 front-right. Spin directions alternate, ``SPIN = (+1, -1, +1, -1)``: +1 means
the rotor turns counter-clockwise seen from above (its angular velocity along +z body), so
opposite motors (0, 2) and (1, 3) turn the same way.

The rotor forces are not MuJoCo actuators: each physics step computes, from the rotor speeds
and the body's velocity, every rotor's thrust, in-plane drag and reaction torque, the rotors'
gyroscopic torque and the airframe's rotational drag, and applies their sum as an external
wrench (``xfrc_applied``). MuJoCo integrates the rigid body, gravity and floor contact.

Motor model (per motor): first-order speed dynamics ``dw/dt = (w_cmd - w) / tau`` with the
command clamped to ``[0, w_max]``; thrust ``k_f w^2 - k_v w v_z`` (``v_z``: the hub's axial
velocity; momentum-theory inflow damping), in-plane rotor drag ``-k_h w v_xy`` (blade flapping
and induced drag, linear in the hub's velocity), reaction torque ``-s (k_m w^2 + I_r dw/dt)``
and drawn current ``k_i w^2 + i_idle`` with ``k_i``, ``i_idle`` from
`rra_agent.library.motors` (the Context Monitor's expectation).

Faults: ``break_motor(k)``: no thrust, drag or reaction torque from then on, the rotor speed
decays to 0 with the motor time constant, and the motor draws no current (open circuit):
`working_motors` sees it in the first telemetry sample after the break. ``degrade_motor(k,
eff)``: thrust (and rotor drag) times ``eff`` (a damaged propeller); the motor torque, hence
its current and reaction torque, stay nominal, so the Context Monitor cannot see it.
``sensor noise``: Gaussian noise on the published state (`Quadcopter.measured_state`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from rra_agent.library.motors import CURRENT_PER_SPEED_SQ, IDLE_CURRENT

GRAVITY = 9.81
#: Rotor spin directions (+1: counter-clockwise seen from above).
SPIN = np.array([1.0, -1.0, 1.0, -1.0])
N_MOTORS = 4


@dataclass(frozen=True, slots=True)
class QuadParams:
    """Physical parameters of the 1 kg, 0.17 m-arm X quadcopter (see docs/quadcopter.md)."""

    mass: float = 1.0  # kg
    arm: float = 0.17  # m, centre to rotor axis
    ixx: float = 6.5e-3  # kg m^2
    iyy: float = 6.5e-3
    izz: float = 1.1e-2
    #: Thrust coefficient, N/(rad/s)^2: 4 rotors at 470 rad/s lift 1 kg.
    k_f: float = 1.11e-5
    #: Reaction (drag) torque per thrust, m (k_m = kappa k_f): 10x4.5" propeller data.
    kappa: float = 0.016
    #: Rotor + motor bell inertia about the spin axis, kg m^2.
    rotor_inertia: float = 3.0e-5
    #: Motor speed time constant, s.
    motor_tau: float = 0.03
    w_max: float = 900.0  # rad/s
    #: Axial inflow damping at hover speed, N/(m/s) per rotor (scales with w / w_hover).
    inflow_damping: float = 0.15
    #: In-plane rotor drag, mass-normalised, of the four rotors at hover speed, 1/s.
    rotor_drag: float = 0.3
    #: Airframe rotational drag, N m s (roll/pitch, yaw).
    body_damping_rp: float = 5.0e-4
    body_damping_yaw: float = 1.0e-3
    k_i: float = CURRENT_PER_SPEED_SQ  # A/(rad/s)^2
    i_idle: float = IDLE_CURRENT  # A

    @property
    def weight(self) -> float:
        return self.mass * GRAVITY

    @property
    def k_m(self) -> float:
        return self.kappa * self.k_f

    @property
    def hover_speed(self) -> float:
        return math.sqrt(self.weight / (4.0 * self.k_f))

    @property
    def f_max(self) -> float:
        return self.k_f * self.w_max**2

    @property
    def k_v(self) -> float:
        """Inflow damping per rotor speed: thrust loss k_v * w * v_axial."""
        return self.inflow_damping / self.hover_speed

    @property
    def k_h(self) -> float:
        """In-plane drag per rotor speed: force -k_h * w * v_inplane."""
        return self.rotor_drag * self.mass / (4.0 * self.hover_speed)

    @property
    def inertia(self) -> np.ndarray:
        return np.array([self.ixx, self.iyy, self.izz])

    @property
    def rotor_positions(self) -> np.ndarray:
        """(4, 2) body xy position of each rotor hub, m."""
        angles = np.deg2rad(45.0 + 90.0 * np.arange(N_MOTORS))
        return self.arm * np.stack([np.cos(angles), np.sin(angles)], axis=1)


def mjcf(p: QuadParams, timestep: float = 0.002) -> str:
    """The MuJoCo model: a floor and a free quadcopter body with explicit mass and inertia
    (geoms only collide and show; they add no mass)."""
    rotors = "\n".join(
        f'      <geom name="rotor{i}" type="cylinder" size="0.115 0.004" '
        f'pos="{x:.4f} {y:.4f} 0.03" rgba="0.2 0.2 0.8 0.4"/>'
        for i, (x, y) in enumerate(p.rotor_positions)
    )
    legs = "\n".join(
        f'      <geom type="sphere" size="0.012" pos="{0.6 * x:.4f} {0.6 * y:.4f} -0.07"/>'
        for x, y in p.rotor_positions
    )
    d = p.arm / math.sqrt(2.0)
    return f"""<mujoco model="quadcopter">
  <option timestep="{timestep}" gravity="0 0 {-GRAVITY}" integrator="RK4"/>
  <default><geom contype="1" conaffinity="1" friction="0.8 0.01 0.001" mass="0"/></default>
  <worldbody>
    <geom name="floor" type="plane" size="50 50 0.1" rgba="0.6 0.6 0.6 1"/>
    <body name="quad" pos="0 0 1">
      <freejoint name="root"/>
      <inertial pos="0 0 0" mass="{p.mass}" diaginertia="{p.ixx} {p.iyy} {p.izz}"/>
      <geom name="hub" type="box" size="0.06 0.05 0.025" rgba="0.3 0.3 0.3 1"/>
      <geom name="arm_a" type="capsule" size="0.008" fromto="{-d} {-d} 0 {d} {d} 0"/>
      <geom name="arm_b" type="capsule" size="0.008" fromto="{-d} {d} 0 {d} {-d} 0"/>
{rotors}
{legs}
    </body>
  </worldbody>
</mujoco>
"""


@dataclass
class Faults:
    broken: np.ndarray = field(default_factory=lambda: np.zeros(N_MOTORS, dtype=bool))
    efficiency: np.ndarray = field(default_factory=lambda: np.ones(N_MOTORS))
    #: Noise std per published channel: position m, velocity m/s, attitude rad, gyro rad/s.
    noise: dict[str, float] = field(default_factory=dict)


#: A crash: floor contact faster than this (m/s) or tilted more than this (rad), or the
#: centre of mass below CRASH_ALTITUDE (m).
CRASH_SPEED = 1.0
CRASH_TILT = math.radians(60.0)
CRASH_ALTITUDE = 0.05


class Quadcopter:
    """One simulated vehicle: ``set_command`` (rotor speeds, held), ``step``, read back."""

    def __init__(
        self,
        params: QuadParams | None = None,
        *,
        timestep: float = 0.002,
        position: tuple[float, float, float] = (0.0, 0.0, 1.0),
        yaw: float = 0.0,
        seed: int = 0,
    ) -> None:
        import mujoco  # here: the controllers import this module and never need MuJoCo

        self.p = p = params or QuadParams()
        self._mj_step = mujoco.mj_step
        self.model = mujoco.MjModel.from_xml_string(mjcf(p, timestep))
        self.data = mujoco.MjData(self.model)
        self.dt = float(self.model.opt.timestep)
        self._body = self.model.body("quad").id
        self._floor = self.model.geom("floor").id
        self.data.qpos[:3] = position
        self.data.qpos[3:7] = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
        mujoco.mj_forward(self.model, self.data)
        self.rng = np.random.default_rng(seed)
        self.faults = Faults()
        # Motors start at the hover speed (the vehicle starts hovering).
        self.speed = np.full(N_MOTORS, p.hover_speed)
        self.command = self.speed.copy()
        self._alpha = 1.0 - math.exp(-self.dt / p.motor_tau)
        self._pos = p.rotor_positions
        self._px, self._py = self._pos[:, 0].copy(), self._pos[:, 1].copy()
        self._damping = np.array([p.body_damping_rp, p.body_damping_rp, p.body_damping_yaw])
        self.crashed = False
        self.crash_reason = ""

    # ---- inputs --------------------------------------------------------------------------
    def set_command(self, speeds) -> None:
        """Desired rotor speeds (rad/s), held until the next command (clamped to [0, w_max])."""
        cmd = np.asarray(speeds, dtype=float)
        if cmd.shape != (N_MOTORS,) or not np.all(np.isfinite(cmd)):
            raise ValueError(f"expected {N_MOTORS} finite rotor speeds, got {speeds!r}")
        self.command = np.clip(cmd, 0.0, self.p.w_max)

    def break_motor(self, k: int) -> None:
        self._check_motor(k)
        self.faults.broken[k] = True

    def degrade_motor(self, k: int, efficiency: float) -> None:
        self._check_motor(k)
        if not 0.0 <= efficiency <= 1.0:
            raise ValueError(f"efficiency must be in [0, 1], got {efficiency}")
        self.faults.efficiency[k] = efficiency

    def set_sensor_noise(self, std: float, **channels: float) -> None:
        """Noise std on every published channel (position, velocity, attitude, gyro), each
        overridable by name; 0 switches the noise off."""
        if std < 0 or any(v < 0 for v in channels.values()):
            raise ValueError("noise std must be >= 0")
        unknown = set(channels) - {"position", "velocity", "attitude", "gyro"}
        if unknown:
            raise ValueError(f"unknown noise channel(s) {sorted(unknown)}")
        self.faults.noise = {
            c: float(channels.get(c, std)) for c in ("position", "velocity", "attitude", "gyro")
        }

    def clear_faults(self) -> None:
        """Repair every motor and switch the noise off (a broken rotor spins up again)."""
        self.faults = Faults()

    def _check_motor(self, k: int) -> None:
        if not (isinstance(k, int) and 0 <= k < N_MOTORS):
            raise ValueError(f"motor index must be 0..{N_MOTORS - 1}, got {k!r}")

    # ---- stepping ------------------------------------------------------------------------
    @property
    def time(self) -> float:
        return float(self.data.time)

    def step(self, n: int = 1) -> None:
        for _ in range(n):
            self._step_once()

    def _step_once(self) -> None:
        p, d = self.p, self.data
        broken = self.faults.broken
        target = np.where(broken, 0.0, self.command)
        old = self.speed
        self.speed = w = old + (target - old) * self._alpha
        w_dot = (w - old) / self.dt
        alive = np.where(broken, 0.0, 1.0)
        R = d.xmat[self._body].reshape(3, 3)
        v = R.T @ d.qvel[:3]  # body-frame velocity of the centre of mass
        wx, wy, wz = d.qvel[3], d.qvel[4], d.qvel[5]  # body-frame angular velocity
        px, py = self._px, self._py
        # Hub velocities (rotors in the body xy plane through the centre of mass).
        hx = v[0] - wz * py
        hy = v[1] + wz * px
        hz = v[2] + wx * py - wy * px
        thrust = alive * self.faults.efficiency * np.maximum(p.k_f * w * w - p.k_v * w * hz, 0.0)
        drag = alive * self.faults.efficiency * p.k_h * w
        dx, dy = -drag * hx, -drag * hy
        h_rot = p.rotor_inertia * float(SPIN @ (w * alive))
        force = np.array([dx.sum(), dy.sum(), thrust.sum()])
        torque = np.array(
            [
                float(py @ thrust) - wy * h_rot - self._damping[0] * wx,
                -float(px @ thrust) + wx * h_rot - self._damping[1] * wy,
                float(px @ dy - py @ dx)
                - float(SPIN @ (alive * (p.k_m * w * w + p.rotor_inertia * w_dot)))
                - self._damping[2] * wz,
            ]
        )
        d.xfrc_applied[self._body, :3] = R @ force
        d.xfrc_applied[self._body, 3:] = R @ torque
        self._mj_step(self.model, d)
        if not self.crashed:
            self._check_crash()

    def _check_crash(self) -> None:
        d = self.data
        z = float(d.qpos[2])
        if z < CRASH_ALTITUDE:
            self.crashed, self.crash_reason = True, f"below {CRASH_ALTITUDE} m (z={z:.3f})"
            return
        if d.ncon == 0:
            return
        touching = any(self._floor in (int(c.geom1), int(c.geom2)) for c in d.contact[: d.ncon])
        if not touching:
            return
        speed = float(np.linalg.norm(d.qvel[:3]))
        tilt = self.tilt
        if speed > CRASH_SPEED or tilt > CRASH_TILT:
            self.crashed = True
            self.crash_reason = (
                f"hit the floor at {speed:.2f} m/s, tilt {math.degrees(tilt):.0f} deg"
            )

    # ---- outputs -------------------------------------------------------------------------
    @property
    def position(self) -> np.ndarray:
        return self.data.qpos[:3].copy()

    @property
    def velocity(self) -> np.ndarray:
        return self.data.qvel[:3].copy()

    @property
    def quaternion(self) -> np.ndarray:
        return self.data.qpos[3:7].copy()

    @property
    def angular_velocity(self) -> np.ndarray:
        """Body frame (a gyro's reading), rad/s."""
        return self.data.qvel[3:6].copy()

    @property
    def tilt(self) -> float:
        """Angle between the body z axis and the world vertical, rad."""
        return math.acos(max(-1.0, min(1.0, float(self.data.xmat[self._body][8]))))

    def currents(self) -> np.ndarray:
        """Drawn current per motor, A: k_i w^2 + i_idle when healthy, 0 when broken."""
        healthy = self.p.k_i * self.speed * self.speed + self.p.i_idle
        return np.where(self.faults.broken, 0.0, healthy)

    def telemetry(self) -> dict[str, object]:
        """A ``MotorTelemetry`` sample (``time``: sim time)."""
        return {
            "time": float(self.data.time),
            "desired_speed": self.command.tolist(),
            "measured_speed": self.speed.tolist(),
            "current": self.currents().tolist(),
        }

    def true_state(self) -> dict[str, object]:
        """A noise-free ``VehicleState`` sample."""
        d = self.data
        return {
            "time": float(d.time),
            "position": d.qpos[:3].tolist(),
            "velocity": d.qvel[:3].tolist(),
            "quaternion": d.qpos[3:7].tolist(),
            "angular_velocity": d.qvel[3:6].tolist(),
        }

    def measured_state(self) -> dict[str, object]:
        """A ``VehicleState`` sample with the configured sensor noise."""
        noise = self.faults.noise
        if not noise or not any(noise.values()):
            return self.true_state()
        d, rng = self.data, self.rng
        quat = d.qpos[3:7].copy()
        att = noise.get("attitude", 0.0)
        if att > 0:
            quat = quat_multiply(quat, small_rotation(rng.normal(0.0, att, 3)))
        return {
            "time": float(d.time),
            "position": (d.qpos[:3] + rng.normal(0.0, noise["position"], 3)).tolist(),
            "velocity": (d.qvel[:3] + rng.normal(0.0, noise["velocity"], 3)).tolist(),
            "quaternion": quat.tolist(),
            "angular_velocity": (d.qvel[3:6] + rng.normal(0.0, noise["gyro"], 3)).tolist(),
        }


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def small_rotation(rotvec: np.ndarray) -> np.ndarray:
    """Unit quaternion of the rotation vector ``rotvec`` (rad)."""
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-12:
        return np.array([1.0, 0.0, 0.0, 0.0])
    axis = rotvec / angle
    s = math.sin(angle / 2)
    return np.array([math.cos(angle / 2), axis[0] * s, axis[1] * s, axis[2] * s])
