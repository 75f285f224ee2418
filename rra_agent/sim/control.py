"""Trajectory, estimator and controllers of the quadcopter: pure classes, state in, command out.

Every class here works on plain data (the bus messages' maps, numpy arrays) and knows nothing
of nodes or Zenoh; `rra_agent.sim.nodes` wraps them. `simulate` closes the loop in-process
(vehicle, estimator, controllers, an optional controller switch), as fast as the CPU allows:
the tests and ``tools/sweep_switch_delay.py`` use it.

- `Trajectory`: hover, waypoints (minimum-jerk legs) or circle (speed ramped up smoothly).
- `Estimator`: steady-state Kalman filter on position/velocity, complementary filter on the
  attitude, low-pass on the gyro; a pure pass-through when the expected noise is 0.
- `StandardController`: cascaded position -> thrust direction (tilt first) -> body rates ->
  torques -> motor speeds for four motors, with saturation-aware mixing.
- `ProplossController`: after Mueller & D'Andrea (ICRA 2014), flies with the two propellers
  opposite each other that remain once motor k failed and its opposite is switched off: gives
  up yaw, lets the vehicle spin, and controls the direction of the thrust axis with an LQR on
  the linearised reduced-attitude dynamics about the spinning state (gain-scheduled on the
  measured yaw rate), plus an outer loop holding altitude and, roughly, position.

Derivations and tuning: docs/quadcopter.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from rra_agent.library.motors import expected_current, working_motors
from rra_agent.sim.model import GRAVITY, N_MOTORS, SPIN, Quadcopter, QuadParams

Vec = np.ndarray
E3 = np.array([0.0, 0.0, 1.0])


# ---- small geometry helpers -------------------------------------------------------------------
def quat_to_rot(q: Sequence[float]) -> np.ndarray:
    """Rotation matrix (body -> world) of the unit quaternion [w, x, y, z]."""
    w, x, y, z = (float(v) for v in q)
    n = w * w + x * x + y * y + z * z
    s = 2.0 / n if n > 0 else 0.0
    return np.array(
        [
            [1 - s * (y * y + z * z), s * (x * y - w * z), s * (x * z + w * y)],
            [s * (x * y + w * z), 1 - s * (x * x + z * z), s * (y * z - w * x)],
            [s * (x * z - w * y), s * (y * z + w * x), 1 - s * (x * x + y * y)],
        ]
    )


def yaw_of(R: np.ndarray) -> float:
    return math.atan2(R[1, 0], R[0, 0])


def wrap(angle: float) -> float:
    return (angle + math.pi) % (2 * math.pi) - math.pi


# ---- trajectory ------------------------------------------------------------------------------
MODES = ("hover", "waypoints", "circle")


@dataclass(frozen=True)
class Trajectory:
    """The reference flight: ``sample(t)`` gives a ``TrajectorySetpoint`` map.

    All modes start at ``(0, 0, altitude)`` (where the simulator starts the vehicle) and hold
    it for ``start_delay`` seconds (the other nodes start meanwhile). ``circle``: centre
    ``(0, radius)``, through the start point, counter-clockwise, its speed ramped up to
    ``speed`` over ``ramp`` seconds. ``waypoints``: minimum-jerk legs at ``speed`` on
    average between the points (``[x, y]`` at ``altitude``, or ``[x, y, z]``), 1 s dwell at
    each, looping.
    """

    mode: str = "hover"
    altitude: float = 1.5
    radius: float = 1.0
    speed: float = 0.5
    waypoints: tuple[tuple[float, ...], ...] = ()
    start_delay: float = 2.0
    ramp: float = 2.0
    dwell: float = 1.0

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {', '.join(MODES)}, got {self.mode!r}")
        if self.radius <= 0 or self.speed < 0 or self.altitude <= 0:
            raise ValueError("radius and altitude must be > 0, speed >= 0")
        for w in self.waypoints:
            if len(w) not in (2, 3):
                raise ValueError(f"a waypoint is [x, y] or [x, y, z], got {list(w)}")

    @property
    def start(self) -> Vec:
        return np.array([0.0, 0.0, self.altitude])

    def sample(self, t: float) -> dict[str, Any]:
        tau = t - self.start_delay
        if self.mode == "circle" and tau > 0 and self.speed > 0:
            p, v, a = self._circle(tau)
        elif self.mode == "waypoints" and tau > 0 and self.waypoints and self.speed > 0:
            p, v, a = self._waypoints(tau)
        else:
            p, v, a = self.start, np.zeros(3), np.zeros(3)
        return {
            "time": t,
            "position": p.tolist(),
            "velocity": v.tolist(),
            "acceleration": a.tolist(),
            "yaw": 0.0,
        }

    def _circle(self, tau: float) -> tuple[Vec, Vec, Vec]:
        r, w = self.radius, self.speed / self.radius
        x = min(tau / self.ramp, 1.0) if self.ramp > 0 else 1.0
        if x < 1.0:  # smoothstep speed ramp: phase rate w * (3x^2 - 2x^3)
            phi = w * self.ramp * (x**3 - x**4 / 2)
            dphi = w * (3 * x * x - 2 * x**3)
            ddphi = w * (6 * x - 6 * x * x) / self.ramp
        else:
            phi = w * (self.ramp / 2 + tau - self.ramp)
            dphi, ddphi = w, 0.0
        s, c = math.sin(phi), math.cos(phi)
        p = np.array([r * s, r - r * c, self.altitude])
        v = np.array([r * dphi * c, r * dphi * s, 0.0])
        a = np.array(
            [r * ddphi * c - r * dphi * dphi * s, r * ddphi * s + r * dphi * dphi * c, 0.0]
        )
        return p, v, a

    def _points(self) -> list[Vec]:
        return [
            np.array([w[0], w[1], w[2] if len(w) == 3 else self.altitude], dtype=float)
            for w in self.waypoints
        ]

    def _waypoints(self, tau: float) -> tuple[Vec, Vec, Vec]:
        points = self._points()
        legs = []  # (from, to, duration) from the start through every point, then a loop
        prev = self.start
        for target in points:
            legs.append((prev, target, self._leg_time(prev, target)))
            prev = target
        first = len(legs)
        legs.append((prev, points[0], self._leg_time(prev, points[0])))
        loop = legs[1:]
        t = tau
        for i, (a, b, T) in enumerate(legs[:first]):
            if t < T + self.dwell:
                return _min_jerk(a, b, T, t)
            t -= T + self.dwell
            if i == first - 1:
                break
        period = sum(T + self.dwell for _, _, T in loop)
        t %= period
        for a, b, T in loop:
            if t < T + self.dwell:
                return _min_jerk(a, b, T, t)
            t -= T + self.dwell
        return points[0], np.zeros(3), np.zeros(3)  # not reached

    def _leg_time(self, a: Vec, b: Vec) -> float:
        # A minimum-jerk leg peaks at 1.875x its mean speed: keep the peak near `speed`.
        return max(1.0, 1.875 * float(np.linalg.norm(b - a)) / self.speed)


def _min_jerk(a: Vec, b: Vec, T: float, t: float) -> tuple[Vec, Vec, Vec]:
    if t >= T:
        return b.copy(), np.zeros(3), np.zeros(3)
    x = t / T
    s = 10 * x**3 - 15 * x**4 + 6 * x**5
    ds = (30 * x**2 - 60 * x**3 + 30 * x**4) / T
    dds = (60 * x - 180 * x**2 + 120 * x**3) / (T * T)
    d = b - a
    return a + s * d, ds * d, dds * d


# ---- estimator -------------------------------------------------------------------------------
class Estimator:
    """State estimate from the simulator's (possibly noisy) ``VehicleState`` samples.

    ``noise`` is the std the sensors are expected to have (position m, velocity m/s, attitude
    rad, gyro rad/s: the simulator's ``sensor_noise`` semantics). 0 = pass-through. Otherwise:
    per axis a steady-state Kalman filter on [position, velocity] (constant-velocity model,
    white acceleration of ``accel_std``) fed by both measurements; the attitude is
    propagated with the filtered gyro and pulled towards the measured quaternion with a
    ``attitude_tau`` time constant; the gyro is low-passed at ``gyro_cutoff`` Hz.
    """

    def __init__(
        self,
        noise: float = 0.0,
        *,
        dt: float = 0.002,
        accel_std: float = 3.0,
        attitude_tau: float = 0.05,
        gyro_cutoff: float = 60.0,
    ) -> None:
        if noise < 0:
            raise ValueError("noise must be >= 0")
        self.noise = noise
        self.dt = dt
        self._gain = _cv_kalman_gain(dt, accel_std, noise) if noise > 0 else None
        self._k_att = 1.0 - math.exp(-dt / attitude_tau)
        self._k_gyro = 1.0 - math.exp(-2 * math.pi * gyro_cutoff * dt)
        self._x: np.ndarray | None = None  # (2, 3): position, velocity
        self._q = np.array([1.0, 0.0, 0.0, 0.0])
        self._w = np.zeros(3)
        self._t: float | None = None

    def update(self, sample: dict[str, Any]) -> dict[str, Any]:
        """Take one ``VehicleState``; return the ``StateEstimate``."""
        if self._gain is None:
            return {k: sample[k] for k in _STATE_FIELDS}
        t = float(sample["time"])
        if self._t is not None and t == self._t and self._x is not None:
            return self._output(t)  # the same sample again (the simulator idled)
        z = np.array([sample["position"], sample["velocity"]], dtype=float)
        zq = np.asarray(sample["quaternion"], dtype=float)
        zw = np.asarray(sample["angular_velocity"], dtype=float)
        if self._x is None or self._t is None or not 0 < t - self._t < 0.1:
            self._x, self._q, self._w = z, zq / np.linalg.norm(zq), zw
        else:
            dt = t - self._t
            x = self._x
            pred = np.array([x[0] + dt * x[1], x[1]])
            self._x = pred + self._gain @ (z - pred)
            self._w = self._w + self._k_gyro * (zw - self._w)
            self._q = _complementary(self._q, self._w, dt, zq, self._k_att)
        self._t = t
        return self._output(t)

    def _output(self, t: float) -> dict[str, Any]:
        assert self._x is not None
        return {
            "time": t,
            "position": self._x[0].tolist(),
            "velocity": self._x[1].tolist(),
            "quaternion": self._q.tolist(),
            "angular_velocity": self._w.tolist(),
        }


_STATE_FIELDS = ("time", "position", "velocity", "quaternion", "angular_velocity")


def _cv_kalman_gain(dt: float, accel_std: float, noise: float) -> np.ndarray:
    """Steady-state Kalman gain (2x2) of [p, v] with both measured, white acceleration."""
    F = np.array([[1.0, dt], [0.0, 1.0]])
    G = np.array([[dt * dt / 2], [dt]])
    Qn = (G @ G.T) * accel_std**2
    Rn = np.eye(2) * noise**2
    P = np.eye(2) * noise**2
    K = np.zeros((2, 2))
    for _ in range(5000):
        Pp = F @ P @ F.T + Qn
        K = Pp @ np.linalg.inv(Pp + Rn)
        P_new = (np.eye(2) - K) @ Pp
        if np.allclose(P_new, P, rtol=1e-10, atol=1e-14):
            break
        P = P_new
    return K


def _complementary(q: Vec, w: Vec, dt: float, zq: Vec, k: float) -> Vec:
    from rra_agent.sim.model import quat_multiply, small_rotation

    q = quat_multiply(q, small_rotation(w * dt))
    if float(q @ zq) < 0:
        zq = -zq
    # Error rotation q^-1 * zq, as a small rotation vector.
    conj = np.array([q[0], -q[1], -q[2], -q[3]])
    e = quat_multiply(conj, zq)
    q = quat_multiply(q, small_rotation(2.0 * k * e[1:]))
    return q / np.linalg.norm(q)


# ---- the standard controller --------------------------------------------------------------------
@dataclass(frozen=True)
class StandardGains:
    kp: tuple[float, float, float] = (4.0, 4.0, 9.0)  # 1/s^2
    kd: tuple[float, float, float] = (3.6, 3.6, 5.4)  # 1/s
    ki: tuple[float, float, float] = (0.5, 0.5, 3.0)  # 1/s^3
    i_limit: float = 3.0  # m/s^2
    k_tilt: float = 7.0  # 1/s: tilt error -> roll/pitch rate
    k_yaw: float = 2.0  # 1/s: yaw error -> yaw rate
    k_rate: tuple[float, float, float] = (18.0, 18.0, 6.0)  # 1/s: rate error -> ang. accel.
    ki_rate: tuple[float, float, float] = (8.0, 8.0, 2.0)  # 1/s^2
    max_rate: tuple[float, float, float] = (6.0, 6.0, 1.5)  # rad/s
    w_min: float = 150.0  # rad/s: idle speed in flight


class StandardController:
    """Cascaded controller for four working motors.

    Position PID -> desired acceleration -> thrust vector (tilt limited to ``max_tilt``) ->
    collective thrust along the current body z and a tilt-prioritised attitude error ->
    body-rate setpoints -> PI rate loop with gyroscopic feed-forward -> torques -> the four
    rotor thrusts (allocation inverse, collective and yaw given up first on saturation)
    -> rotor speeds.
    """

    def __init__(
        self,
        params: QuadParams | None = None,
        gains: StandardGains | None = None,
        *,
        max_tilt: float = 0.5,
    ) -> None:
        self.p = p = params or QuadParams()
        self.g = gains or StandardGains()
        self.max_tilt = max_tilt
        P = p.rotor_positions
        # [T, tx, ty, tz] = A f
        A = np.vstack([np.ones(N_MOTORS), P[:, 1], -P[:, 0], -SPIN * p.kappa])
        self.A_inv = np.linalg.inv(A)
        self.f_min = p.k_f * self.g.w_min**2
        self.f_max = p.f_max
        self.integral = np.zeros(3)
        self.rate_integral = np.zeros(3)
        self._last_t: float | None = None
        g = self.g
        self._kp, self._kd, self._ki = np.array(g.kp), np.array(g.kd), np.array(g.ki)
        self._k_rate, self._ki_rate = np.array(g.k_rate), np.array(g.ki_rate)
        self._max_rate, self._inertia = np.array(g.max_rate), p.inertia

    def update(self, est: dict[str, Any], sp: dict[str, Any]) -> np.ndarray:
        """Rotor speed commands (rad/s) for one estimate and the latest setpoint."""
        p, g = self.p, self.g
        t = float(est["time"])
        dt = _dt(self._last_t, t)
        self._last_t = t
        R = quat_to_rot(est["quaternion"])
        wx, wy, wz = (float(v) for v in est["angular_velocity"])
        omega = np.array([wx, wy, wz])

        e_p = np.array(sp["position"], dtype=float) - est["position"]
        e_v = np.array(sp["velocity"], dtype=float) - est["velocity"]
        self.integral = np.clip(self.integral + self._ki * e_p * dt, -g.i_limit, g.i_limit)
        acc = self._kp * e_p + self._kd * e_v + sp["acceleration"] + self.integral
        thrust_vec = _limit_tilt(acc + GRAVITY * E3, self.max_tilt)
        b3 = R[:, 2]
        collective = p.mass * float(thrust_vec @ b3)
        b3_des = thrust_vec / math.sqrt(float(thrust_vec @ thrust_vec))

        # Tilt first: the rotation taking b3 to b3_des, in the body frame; then yaw.
        tilt_axis = R.T @ _cross(b3, b3_des)
        yaw_err = wrap(float(sp.get("yaw", 0.0)) - yaw_of(R))
        rate_sp = np.array([g.k_tilt * tilt_axis[0], g.k_tilt * tilt_axis[1], g.k_yaw * yaw_err])
        rate_sp = np.minimum(np.maximum(rate_sp, -self._max_rate), self._max_rate)
        e_w = rate_sp - omega
        self.rate_integral = np.clip(self.rate_integral + self._ki_rate * e_w * dt, -3.0, 3.0)
        inertia = self._inertia
        torque = inertia * (self._k_rate * e_w + self.rate_integral)
        torque += _cross(omega, inertia * omega)
        return self.speeds(collective, torque)

    def speeds(self, collective: float, torque: np.ndarray) -> np.ndarray:
        f = _mix(self.A_inv, collective, torque, self.f_min, self.f_max)
        return np.sqrt(f / self.p.k_f)

    def export_state(self) -> dict[str, Any]:
        return {"integral": self.integral.tolist()}

    def import_state(self, state: dict[str, Any]) -> None:
        if isinstance(state, dict) and is_vec3(state.get("integral")):
            self.integral = np.asarray(state["integral"], dtype=float)


def _dt(last: float | None, t: float) -> float:
    if last is None or not 0 < t - last < 0.1:
        return 0.0
    return t - last


def is_vec3(v: Any) -> bool:
    """A list or tuple of three finite numbers (a vector in a state or a sample)."""
    return (
        isinstance(v, list | tuple)
        and len(v) == 3
        and all(isinstance(x, int | float) and math.isfinite(x) for x in v)
    )


def _cross(a: Vec, b: Vec) -> Vec:
    """Cross product of two 3-vectors (np.cross is ~10x slower on tiny arrays)."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])


def _limit_tilt(f: Vec, max_tilt: float) -> Vec:
    """Clip the horizontal part of a thrust vector to ``max_tilt`` from the vertical."""
    fz = max(float(f[2]), 0.1 * GRAVITY)
    horiz = math.hypot(f[0], f[1])
    limit = fz * math.tan(max_tilt)
    scale = min(1.0, limit / horiz) if horiz > 0 else 1.0
    return np.array([f[0] * scale, f[1] * scale, fz])


def _mix(A_inv: np.ndarray, collective: float, torque: Vec, f_min: float, f_max: float) -> Vec:
    """Rotor thrusts for (collective, torque) within [f_min, f_max]: keep roll/pitch, then the
    collective, then as much yaw as fits."""
    rp = A_inv[:, 1] * torque[0] + A_inv[:, 2] * torque[1]
    lo, hi = float(rp.min()), float(rp.max())
    room = f_max - f_min
    if hi - lo > room:  # roll/pitch alone do not fit: scale them down
        rp = rp * (room / (hi - lo))
        lo, hi = lo * room / (hi - lo), hi * room / (hi - lo)
    c = collective / N_MOTORS  # A_inv[:, 0] is 1/4 for every rotor
    # Shift the collective so that roll/pitch fit.
    c = min(max(c, f_min - lo), f_max - hi)
    base = rp + c
    yaw = A_inv[:, 3] * float(torque[2])
    out = base + yaw
    if float(out.max()) > f_max or float(out.min()) < f_min:
        scale = 1.0
        for b, y in zip(base.tolist(), yaw.tolist(), strict=True):
            if y > 0 and b + y > f_max:
                scale = min(scale, max(0.0, (f_max - b) / y))
            elif y < 0 and b + y < f_min:
                scale = min(scale, max(0.0, (f_min - b) / y))
        out = np.clip(base + scale * yaw, f_min, f_max)
    return out


# ---- the Proploss controller -------------------------------------------------------------------
def expm(M: np.ndarray) -> np.ndarray:
    """Matrix exponential (scaling and squaring of a Taylor series; fine for small, well-scaled
    matrices such as A*dt)."""
    norm = float(np.abs(M).sum(axis=1).max())
    k = max(0, math.ceil(math.log2(norm)) + 1) if norm > 0.5 else 0
    S = M / (2**k)
    E, term = np.eye(len(M)), np.eye(len(M))
    for i in range(1, 16):
        term = term @ S / i
        E = E + term
    for _ in range(k):
        E = E @ E
    return E


def discretize(A: np.ndarray, B: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Zero-order-hold discretisation of x' = A x + B u."""
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, B
    E = expm(M * dt)
    return E[:n, :n], E[:n, n:]


def dare(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Stabilising solution P of the discrete algebraic Riccati equation, by iterating the
    Riccati recursion with doubling (structure-preserving doubling: each iteration doubles
    the horizon, so ~30 iterations reach a horizon of 2^30 steps)."""
    n = len(A)
    Ak, Gk, Hk = A.copy(), B @ np.linalg.solve(R, B.T), Q.copy()
    eye = np.eye(n)
    for _ in range(60):
        W = np.linalg.inv(eye + Gk @ Hk)
        A_next = Ak @ W @ Ak
        G_next = Gk + Ak @ W @ Gk @ Ak.T
        H_next = Hk + Ak.T @ Hk @ W @ Ak
        done = np.allclose(H_next, Hk, rtol=1e-11, atol=1e-12)
        Ak, Gk, Hk = A_next, G_next, H_next
        if done:
            break
    return (Hk + Hk.T) / 2


def lqr_gain(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Discrete LQR gain K (u = -K x)."""
    P = dare(A, B, Q, R)
    return np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)


@dataclass(frozen=True)
class ProplossGains:
    kp: tuple[float, float, float] = (1.0, 1.0, 6.0)  # 1/s^2
    kd: tuple[float, float, float] = (1.6, 1.6, 4.5)  # 1/s
    ki_z: float = 0.5  # 1/s^3
    i_limit: float = 3.0  # m/s^2
    max_tilt: float = 0.25  # rad: horizontal acceleration budget of the spinning vehicle
    #: Collective floor (fraction of the weight) while the thrust axis is more than
    #: `recovery_angle` off its target: keeps the rotors' angular momentum (the gyroscopic
    #: coupling the attitude control works through) and the thrust-difference range.
    recovery_collective: float = 1.6
    recovery_angle: float = 0.3  # rad
    #: LQR weights: thrust-axis error (per unit of h1, h2), body rates, input (N).
    q_axis: float = 40.0
    q_rate: float = 0.2
    r_input: float = 1.0
    #: Gain schedule on the yaw rate: from 0 to this many times the steady spin, points.
    schedule_span: float = 1.6
    schedule_points: int = 33


#: Gain schedules by (params, gains, dt): they depend on nothing else, so one computation
#: serves every controller of a process, and every node forked from a warmed-up fork server.
_SCHEDULES: dict[tuple[QuadParams, ProplossGains, float], dict[int, Any]] = {}


class ProplossController:
    """Flies on the two opposing propellers left once motor ``k`` failed (Mueller & D'Andrea).

    The opposite motor is switched off too; the remaining pair spins the same way, so the
    vehicle yaws up to the spin rate where the yaw drag balances their reaction torque, and
    the direction of its thrust axis (the reduced attitude) is controlled through the
    gyroscopic coupling of the spinning body and rotors with the pair's thrust difference.

    Linear model (body frame, Ixx = Iyy = I), state x = (h1, h2, p, q, du): h = R^T d is the
    desired thrust direction d seen from the body (the equilibrium is h = e3, p = q = 0), du
    the pair's actual thrust difference (first-order motor lag). The yaw rate r enters as a
    parameter; LQR gains are computed at start-up on a grid of r and interpolated at run time
    on the measured r (the vehicle spins up over ~2 s after the failure, and the coupling
    term changes sign on the way, so one gain set does not fit all).

    ``failed`` may be given or found from ``MotorTelemetry`` (`observe_telemetry`).
    """

    def __init__(
        self,
        params: QuadParams | None = None,
        gains: ProplossGains | None = None,
        *,
        failed: int | None = None,
        dt: float = 0.002,
    ) -> None:
        self.p = params or QuadParams()
        self.g = gains or ProplossGains()
        self.dt = dt
        self.failed: int | None = None
        self.integral = np.zeros(3)
        self._last_t: float | None = None
        self._measured_speed: np.ndarray | None = None
        self._measured_time: float | None = None
        self._du_model = 0.0  # the pair's thrust difference, from our own commands
        self._last_cmd: np.ndarray | None = None
        key = (self.p, self.g, dt)
        if key not in _SCHEDULES:  # ~100 ms of LQR solves: once per process (see warm_up)
            _SCHEDULES[key] = {k: self._schedule(k) for k in range(N_MOTORS)}
        self.schedules = _SCHEDULES[key]
        self._recovery_cos = math.cos(self.g.recovery_angle)
        self._kp, self._kd = np.array(self.g.kp), np.array(self.g.kd)
        if failed is not None:
            self.set_failed(failed)

    # ---- failure -----------------------------------------------------------------------------
    def set_failed(self, k: int) -> None:
        if not (isinstance(k, int) and 0 <= k < N_MOTORS):
            raise ValueError(f"motor index must be 0..{N_MOTORS - 1}, got {k!r}")
        self.failed = k

    def observe_telemetry(self, tel: dict[str, Any]) -> int | None:
        """Record the measured rotor speeds; latch the first motor drawing clearly less
        current than expected (the largest deficit) as the failed one. Returns it."""
        measured, t = tel.get("measured_speed"), tel.get("time")
        if isinstance(measured, list) and len(measured) == N_MOTORS:
            self._measured_speed = np.asarray(measured, dtype=float)
            self._measured_time = float(t) if isinstance(t, int | float) else None
        if self.failed is None:
            k = failed_motor(tel)
            if k is not None:
                self.failed = k
        return self.failed

    # ---- design ------------------------------------------------------------------------------
    def pair(self, k: int) -> tuple[int, int, int]:
        """(a, b, opposite): the remaining pair (a, b) and the motor switched off with k."""
        return (k + 1) % N_MOTORS, (k + 3) % N_MOTORS, (k + 2) % N_MOTORS

    def spin_rate(self, k: int) -> float:
        """Steady yaw rate (rad/s, signed) of the vehicle hovering on the pair left by k."""
        p = self.p
        a, _, _ = self.pair(k)
        w = math.sqrt(p.weight / (2 * p.k_f))
        gamma = p.k_h * 2 * w * p.arm**2 + p.body_damping_yaw
        return -SPIN[a] * p.kappa * p.weight / gamma

    def model(self, k: int, r: float) -> tuple[np.ndarray, np.ndarray]:
        """Continuous (A, B) of (h1, h2, p, q, du) with input du_cmd, at yaw rate r."""
        p = self.p
        a, _, _ = self.pair(k)
        xa, ya = p.rotor_positions[a]
        w = math.sqrt(p.weight / (2 * p.k_f))
        h_rot = p.rotor_inertia * SPIN[a] * 2 * w
        kv = p.k_v * 2 * w
        D = kv * np.array([[ya * ya, -xa * ya], [-xa * ya, xa * xa]])
        D += np.eye(2) * p.body_damping_rp
        A = np.zeros((5, 5))
        A[0, 1], A[0, 3] = r, -1.0
        A[1, 0], A[1, 2] = -r, 1.0
        A[2, 2:4] = (np.array([0.0, (p.iyy - p.izz) * r - h_rot]) - D[0]) / p.ixx
        A[3, 2:4] = (np.array([-((p.ixx - p.izz) * r - h_rot), 0.0]) - D[1]) / p.iyy
        A[2, 4], A[3, 4] = ya / p.ixx, -xa / p.iyy
        A[4, 4] = -1.0 / p.motor_tau
        B = np.zeros((5, 1))
        B[4, 0] = 1.0 / p.motor_tau
        return A, B

    def _schedule(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        g = self.g
        r_bar = self.spin_rate(k)
        rates = np.linspace(0.0, g.schedule_span * r_bar, g.schedule_points)
        Q = np.diag([g.q_axis, g.q_axis, g.q_rate, g.q_rate, 0.0])
        R = np.array([[g.r_input]])
        gains = []
        for r in rates:
            Ad, Bd = discretize(*self.model(k, float(r)), self.dt)
            gains.append(lqr_gain(Ad, Bd, Q, R)[0])
        if r_bar < 0:
            rates, gains = rates[::-1], gains[::-1]
        return rates, np.array(gains)

    def gain(self, k: int, r: float) -> np.ndarray:
        rates, gains = self.schedules[k]
        r = min(max(r, float(rates[0])), float(rates[-1]))
        return np.array([np.interp(r, rates, gains[:, j]) for j in range(gains.shape[1])])

    # ---- control -----------------------------------------------------------------------------
    def update(self, est: dict[str, Any], sp: dict[str, Any]) -> np.ndarray | None:
        """Rotor speed commands, or None while the failed motor is unknown."""
        k = self.failed
        if k is None:
            return None
        p, g = self.p, self.g
        a, b, _ = self.pair(k)
        t = float(est["time"])
        dt = _dt(self._last_t, t)
        self._last_t = t
        R = quat_to_rot(est["quaternion"])
        omega = np.asarray(est["angular_velocity"], dtype=float)
        e_p = np.array(sp["position"], dtype=float) - est["position"]
        e_v = np.array(sp["velocity"], dtype=float) - est["velocity"]
        acc = self._kp * e_p + self._kd * e_v + self.integral
        thrust_vec = _limit_tilt(acc + GRAVITY * E3, g.max_tilt)
        d = thrust_vec / math.sqrt(float(thrust_vec @ thrust_vec))
        h = R.T @ d
        b3 = R[:, 2]
        collective = p.mass * float(thrust_vec @ b3)
        if h[2] < self._recovery_cos:  # far off: keep the rotors fast (see ProplossGains)
            collective = max(collective, g.recovery_collective * p.weight)
        else:  # integrate only in normal flight (no wind-up during a recovery)
            z_int = self.integral[2] + g.ki_z * float(e_p[2]) * dt
            self.integral[2] = min(max(z_int, -g.i_limit), g.i_limit)

        du = self._actual_du(a, b, t)
        scale = _axis_error_scale(float(h[2]))
        x = np.array([scale * h[0], scale * h[1], omega[0], omega[1], du])
        u = -float(self.gain(k, float(omega[2])) @ x)
        f_a, f_b = _pair_thrusts(collective, u, 0.0, p.f_max)
        self._du_model += (f_a - f_b - self._du_model) * (1 - math.exp(-dt / p.motor_tau))
        cmd = np.zeros(N_MOTORS)
        cmd[a], cmd[b] = math.sqrt(f_a / p.k_f), math.sqrt(f_b / p.k_f)
        self._last_cmd = cmd
        return cmd

    def _actual_du(self, a: int, b: int, t: float) -> float:
        """The pair's actual thrust difference: from the measured rotor speeds if they are
        fresh (telemetry within 20 ms of the estimate, or untimed), else from our own
        commands through the motor lag."""
        w, tw = self._measured_speed, self._measured_time
        if w is None or (tw is not None and abs(t - tw) > 0.02):
            return self._du_model
        return self.p.k_f * float(w[a] * w[a] - w[b] * w[b])

    @property
    def last_command(self) -> np.ndarray | None:
        return self._last_cmd

    def export_state(self) -> dict[str, Any]:
        return {"integral": self.integral.tolist(), "failed_motor": self.failed}

    def import_state(self, state: dict[str, Any]) -> None:
        """Take the controller's integrators (the thrust bias estimate) and, if known, the
        failed motor."""
        if not isinstance(state, dict):
            return
        if is_vec3(state.get("integral")):
            self.integral = np.asarray(state["integral"], dtype=float)
            self.integral[:2] = 0.0  # our horizontal loop has no integrator
        k = state.get("failed_motor")
        if self.failed is None and isinstance(k, int) and 0 <= k < N_MOTORS:
            self.failed = k


def rehearse_recovery(params: QuadParams | None = None) -> None:
    """Run the recovery's code once for each failed motor, on scratch controllers: telemetry
    of a dead motor, then two commands from a hover estimate; nothing is kept or published.

    In a process forked from a warmed-up interpreter (a node from the fork server), the first
    run of a code path writes to pages it shares with its parent (reference counts, Python
    3.11's specialised bytecode) and so copies them: ~0.35 ms for `ProplossController.update`
    on an idle machine, 1.2-1.9 ms on the loaded one of the quadcopter, between learning of
    the failure and its first command. The node's `rehearse` pays it before it runs.
    """
    p = params or QuadParams()
    hover = math.sqrt(p.weight / (N_MOTORS * p.k_f))
    est = {"time": 0.0, "position": [0.0, 0.0, 1.0], "velocity": [0.0, 0.0, 0.0],
           "quaternion": [1.0, 0.0, 0.0, 0.0], "angular_velocity": [0.0, 0.0, 0.0]}  # fmt: skip
    sp = {"position": [0.0, 0.0, 1.0], "velocity": [0.0, 0.0, 0.0],
          "acceleration": [0.0, 0.0, 0.0], "yaw": 0.0}  # fmt: skip
    for k in range(N_MOTORS):
        ctl = ProplossController(p)
        current = [expected_current(hover)] * N_MOTORS
        current[k] = 0.0
        tel = {"time": 0.0, "desired_speed": [hover] * N_MOTORS,
               "measured_speed": [hover] * N_MOTORS, "current": current}  # fmt: skip
        ctl.observe_telemetry(tel)
        for t in (0.0, ctl.dt):
            ctl.update({**est, "time": t}, sp)


def _axis_error_scale(h3: float) -> float:
    """theta / sin(theta) for the angle theta = acos(h3) between the thrust axis and its
    target: (h1, h2) scaled by it is the rotation vector of the error, which keeps growing
    past 90 degrees where (h1, h2) itself shrinks (bounded below 180 degrees)."""
    theta = math.acos(max(-1.0, min(1.0, h3)))
    return theta / max(math.sin(theta), 0.3) if theta > 1e-6 else 1.0


def _pair_thrusts(collective: float, du: float, f_min: float, f_max: float) -> tuple[float, float]:
    """Thrusts (a, b) with a - b = du and a + b = collective, within [f_min, f_max]: the
    difference (attitude) has priority over the collective."""
    du = max(-(f_max - f_min), min(f_max - f_min, du))
    lo, hi = 2 * f_min + abs(du), 2 * f_max - abs(du)
    collective = min(max(collective, lo), hi)
    return (collective + du) / 2, (collective - du) / 2


def failed_motor(tel: dict[str, Any]) -> int | None:
    """The motor (index) with the largest current deficit among those `working_motors` does
    not count as working, considering only under-current (a dead or unloaded motor), or None."""
    desired, current = tel.get("desired_speed"), tel.get("current")
    if not (isinstance(desired, list) and isinstance(current, list)):
        return None
    if len(desired) != N_MOTORS or len(current) != N_MOTORS:
        return None
    best, worst = None, 0.0
    for i, (w, c) in enumerate(zip(desired, current, strict=True)):
        one = {"desired_speed": [w], "current": [c]}
        if working_motors(one) == 1:
            continue
        deficit = expected_current(float(w)) - float(c)
        if deficit > worst:
            best, worst = i, deficit
    return best


# ---- in-process closed loop --------------------------------------------------------------------
@dataclass
class Run:
    """Sampled outcome of `simulate` (every ``record_every`` physics steps)."""

    time: np.ndarray
    position: np.ndarray
    setpoint: np.ndarray
    tilt: np.ndarray
    yaw_rate: np.ndarray
    working: np.ndarray
    crashed_at: float | None
    crash_reason: str
    switched_at: float | None

    def window(self, t0: float, t1: float) -> np.ndarray:
        return (self.time >= t0) & (self.time <= t1)


def simulate(
    duration: float,
    *,
    trajectory: Trajectory | None = None,
    params: QuadParams | None = None,
    fail_at: float | None = None,
    fail_motor: int = 2,
    switch_delay: float | None = 0.0,
    degrade: tuple[int, float] | None = None,
    noise: float = 0.0,
    estimator_noise: float | None = None,
    latency_steps: int = 1,
    record_every: int = 5,
    proploss: ProplossController | None = None,
    on_step: Callable[[Quadcopter, float], None] | None = None,
    seed: int = 0,
) -> Run:
    """Fly ``duration`` seconds of sim time in-process, as fast as possible.

    Motor ``fail_motor`` breaks at ``fail_at``; ``switch_delay`` later (None = never) the
    standard controller hands over to a Proploss controller that has been running in
    standby on the same estimates and telemetry (and takes the controller's state). The
    controllers see the estimate of ``latency_steps`` physics steps ago (the bus' delay).
    """
    p = params or QuadParams()
    traj = trajectory or Trajectory()
    quad = _build_quad(p, traj, degrade, noise, seed)
    est = Estimator(noise if estimator_noise is None else estimator_noise, dt=quad.dt)
    ctrl = StandardController(p)
    pl = proploss or ProplossController(p, dt=quad.dt)
    pipeline: list[dict[str, Any]] = []
    rec = _Recording()
    crashed_at = switched_at = None
    switch_at = None if fail_at is None or switch_delay is None else fail_at + switch_delay
    for i in range(round(duration / quad.dt)):
        t = quad.time
        if fail_at is not None and not quad.faults.broken[fail_motor] and t >= fail_at - 1e-9:
            quad.break_motor(fail_motor)
        tel = quad.telemetry()
        pipeline.append(est.update(quad.measured_state()))
        e = pipeline.pop(0) if len(pipeline) > latency_steps else pipeline[0]
        sp = traj.sample(t)
        pl.observe_telemetry(tel)
        cmd_std = ctrl.update(e, sp)
        cmd_pl = pl.update(e, sp)
        if switched_at is None and switch_at is not None and t >= switch_at - 1e-9:
            pl.import_state(ctrl.export_state() | {"failed_motor": None})
            switched_at = t
            cmd_pl = pl.update(e, sp)
        quad.set_command(cmd_pl if switched_at is not None and cmd_pl is not None else cmd_std)
        if on_step is not None:
            on_step(quad, t)
        quad.step()
        if quad.crashed and crashed_at is None:
            crashed_at = quad.time
        if i % record_every == 0:
            rec.add(quad, sp, tel)
    return rec.run(crashed_at, quad.crash_reason, switched_at)


def _build_quad(
    p: QuadParams,
    traj: Trajectory,
    degrade: tuple[int, float] | None,
    noise: float,
    seed: int,
) -> Quadcopter:
    """The simulated quadcopter at the trajectory's start, degraded and noisy as asked."""
    quad = Quadcopter(p, position=tuple(traj.start), seed=seed)
    if degrade is not None:
        quad.degrade_motor(*degrade)
    if noise > 0:
        quad.set_sensor_noise(noise)
    return quad


class _Recording:
    """The samples `simulate` keeps, turned into a `Run` at the end."""

    def __init__(self) -> None:
        self.rows: dict[str, list[Any]] = {k: [] for k in ("t", "pos", "sp", "tilt", "r", "work")}

    def add(self, quad: Quadcopter, sp: dict[str, Any], tel: dict[str, Any]) -> None:
        self.rows["t"].append(quad.time)
        self.rows["pos"].append(quad.position)
        self.rows["sp"].append(sp["position"])
        self.rows["tilt"].append(quad.tilt)
        self.rows["r"].append(float(quad.data.qvel[5]))
        self.rows["work"].append(working_motors(tel))

    def run(self, crashed_at: float | None, reason: str, switched_at: float | None) -> Run:
        r = self.rows
        return Run(
            time=np.array(r["t"]),
            position=np.array(r["pos"]),
            setpoint=np.array(r["sp"]),
            tilt=np.array(r["tilt"]),
            yaw_rate=np.array(r["r"]),
            working=np.array(r["work"]),
            crashed_at=crashed_at,
            crash_reason=reason,
            switched_at=switched_at,
        )
