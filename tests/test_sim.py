"""The simulated quadcopter (rra_agent.sim.model) and its simulator node, without a bus."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.library.motors import expected_current, working_motors
from rra_agent.node import NodeHarness
from rra_agent.sim.model import GRAVITY, SPIN, Quadcopter, QuadParams
from rra_agent.sim.nodes import VehicleSimulator

P = QuadParams()
HOVER = P.hover_speed


def hovering(**kw) -> Quadcopter:
    return Quadcopter(position=(0.0, 0.0, 2.0), **kw)


# ---- parameters and the motor model -----------------------------------------------------------
def test_parameters_describe_a_1kg_quad_hovering_near_470_rad_s() -> None:
    assert P.mass == 1.0 and P.arm == pytest.approx(0.17)
    assert 465 < HOVER < 475
    assert np.allclose(np.linalg.norm(P.rotor_positions, axis=1), P.arm)
    assert 2 * P.f_max > 1.5 * P.weight  # two rotors can still lift it (Proploss)
    assert list(SPIN) == [1, -1, 1, -1]  # opposite rotors turn the same way


def test_hover_speed_is_an_equilibrium() -> None:
    q = hovering()
    q.step(500)  # 1 s, open loop
    assert np.allclose(q.position, [0, 0, 2], atol=1e-6)
    assert np.allclose(q.angular_velocity, 0, atol=1e-9)


def test_rotor_speed_is_first_order_with_the_motor_time_constant() -> None:
    q = hovering()
    q.set_command([HOVER + 100.0] * 4)
    q.step(round(P.motor_tau / q.dt))
    assert q.speed[0] - HOVER == pytest.approx(100 * (1 - math.exp(-1)), rel=0.02)
    q.set_command([5000.0] * 4)  # clamped to w_max
    assert q.command[0] == P.w_max


def test_reaction_torque_spins_the_body_against_the_faster_rotors() -> None:
    q = hovering()
    q.set_command([HOVER + 50, HOVER - 50, HOVER + 50, HOVER - 50])  # CCW pair faster
    q.step(100)
    r = q.angular_velocity[2]
    assert r < -0.1  # the body turns clockwise
    assert abs(q.angular_velocity[0]) < 1e-6 and abs(q.angular_velocity[1]) < 1e-6


def test_healthy_current_is_what_the_monitor_expects() -> None:
    q = hovering()
    tel = q.telemetry()
    assert tel["current"] == pytest.approx([expected_current(HOVER)] * 4)
    assert 3.5 < tel["current"][0] < 4.5
    assert working_motors(tel) == 4


def test_rotor_drag_damps_horizontal_motion_and_yaw() -> None:
    q = hovering()
    q.data.qvel[0] = 2.0  # 2 m/s forward
    q.data.qvel[5] = 5.0  # 5 rad/s yaw
    q.step(50)
    vx, r = q.velocity[0], q.angular_velocity[2]
    assert vx == pytest.approx(2.0 * math.exp(-P.rotor_drag * 0.1), rel=0.05)
    assert 0 < r < 5.0 * math.exp(-0.1 * P.k_h * 4 * HOVER * P.arm**2 / P.izz) + 0.05


# ---- faults -------------------------------------------------------------------------------------
def test_a_broken_motor_is_seen_in_the_next_telemetry_sample() -> None:
    q = hovering()
    q.break_motor(2)
    q.step()  # one physics step: 2 ms
    tel = q.telemetry()
    assert working_motors(tel) == 3
    assert tel["current"][2] == 0.0
    assert tel["desired_speed"][2] == pytest.approx(HOVER)  # the controller still asks
    assert tel["measured_speed"][2] < HOVER
    q.step(100)
    assert q.speed[2] < 0.05 * HOVER  # the rotor stops
    assert q.velocity[2] < -0.1  # a quarter of the lift is gone
    assert q.angular_velocity[0] > 0.5 and q.angular_velocity[1] < -0.5  # rolls toward it


def test_a_degraded_motor_loses_thrust_but_draws_the_nominal_current() -> None:
    q = hovering()
    q.degrade_motor(0, 0.7)
    q.step(50)
    assert working_motors(q.telemetry()) == 4
    assert q.velocity[2] < -0.05
    with pytest.raises(ValueError):
        q.degrade_motor(0, 1.5)
    with pytest.raises(ValueError):
        q.break_motor(4)


def test_sensor_noise_and_clear_faults() -> None:
    q = hovering(seed=3)
    assert q.measured_state() == q.true_state()
    q.set_sensor_noise(0.05, gyro=0.0)
    xs = np.array([q.measured_state()["position"] for _ in range(2000)])
    assert xs.std(axis=0) == pytest.approx([0.05] * 3, rel=0.1)
    assert q.measured_state()["angular_velocity"] == q.true_state()["angular_velocity"]
    quat = np.array(q.measured_state()["quaternion"])
    assert np.linalg.norm(quat) == pytest.approx(1.0)
    q.break_motor(1)
    q.clear_faults()
    assert q.measured_state() == q.true_state() and not q.faults.broken.any()
    with pytest.raises(ValueError):
        q.set_sensor_noise(0.1, altitude=1.0)


def test_falling_from_2_m_is_a_crash() -> None:
    q = hovering()
    q.set_command([0.0] * 4)
    steps = 0
    while not q.crashed and steps < 1000:
        q.step()
        steps += 1
    fall = math.sqrt(2 * (2.0 - 0.07) / GRAVITY)
    assert q.crashed and "floor" in q.crash_reason
    assert steps * q.dt == pytest.approx(fall, abs=0.1)


def test_a_gentle_touchdown_is_not_a_crash() -> None:
    q = Quadcopter(position=(0.0, 0.0, 0.12))
    q.set_command([0.97 * HOVER] * 4)
    q.step(1000)
    assert q.data.ncon > 0 and not q.crashed


# ---- the simulator node -------------------------------------------------------------------------
PORTS = {
    "motor_cmd": ("subscribe", "MotorCommand"),
    "state": ("publish", "VehicleState"),
    "telemetry": ("publish", "MotorTelemetry"),
    "events": ("publish", "SimEvent"),
}


def sim(**params) -> NodeHarness:
    p = {"initial_position": [0.0, 0.0, 2.0], "realtime_factor": 0.0} | params
    return NodeHarness(VehicleSimulator, name="vehicle_simulator", params=p, ports=PORTS)


def hover_cmd(controller: str = "controller") -> dict:
    return {"speeds": [HOVER] * 4, "controller": controller}


def events(h: NodeHarness) -> list[dict]:
    return h.outputs("events")


def test_frozen_until_the_first_command_then_armed() -> None:
    h = sim()
    h.step(0.002)
    h.step(0.004)
    states = h.outputs("state")
    assert [s["time"] for s in states] == [0.0, 0.0]
    assert states[0]["position"] == [0.0, 0.0, 2.0]
    tel = h.outputs("telemetry")[0]
    assert working_motors(tel) == 4 and tel["time"] == 0.0
    h.send("motor_cmd", hover_cmd())
    h.step(0.006)
    assert h.outputs("state")[-1]["time"] == pytest.approx(0.002)
    assert [(e["kind"], e["detail"]) for e in events(h)] == [
        ("armed", "controller"),
        ("controller", "controller"),
    ]


def test_the_first_command_of_a_new_controller_is_an_event() -> None:
    h = sim()
    h.send("motor_cmd", hover_cmd())
    h.step(0.002)
    h.send("motor_cmd", hover_cmd())
    h.step(0.004)
    assert len(events(h)) == 2
    h.send("motor_cmd", hover_cmd("proploss_controller"))
    h.time = 0.0061
    h.step()
    ev = events(h)[-1]
    assert ev["kind"] == "controller" and ev["detail"] == "proploss_controller"
    assert ev["wall_time"] == 0.0061 and ev["sim_time"] == pytest.approx(0.006)


def test_bad_commands_are_ignored() -> None:
    h = sim()
    h.send("motor_cmd", {"speeds": [1.0, 2.0], "controller": "x"})
    h.send("motor_cmd", {"speeds": "fast"})
    h.step(0.002)
    assert events(h) == [] and len(h.logs) == 2


def test_injections_break_degrade_noise_and_clear() -> None:
    h = sim()
    node = h.node
    assert isinstance(node, VehicleSimulator)
    h.send("motor_cmd", hover_cmd())
    h.step(0.002)
    codec = m.Codec[m.Injection](m.Injection)
    node.on_injection(codec.encode(m.Inject(kind="break_motor", args={"motor": 2}, stamp=1.0)))
    node.on_injection(b"\x93garbage")
    node.inject("degrade_motor", {"k": 1, "efficiency": 0.5})
    node.inject("sensor_noise", {"std": 0.01})
    node.inject("unknown_kind", {})
    node.inject("break_motor", {"motor": 0}, target="another_node")
    node.inject("break_motor", {"motor": 9})
    h.step(0.004)
    q = node.quad
    assert list(q.faults.broken) == [False, False, True, False]
    assert q.faults.efficiency[1] == 0.5 and q.faults.noise["position"] == 0.01
    faults = [e["detail"] for e in events(h) if e["kind"] == "fault"]
    assert faults == [
        "break_motor motor=2",
        "degrade_motor efficiency=0.5 k=1",
        "sensor_noise std=0.01",
    ]
    assert any("malformed" in line for line in h.logs)
    assert any("refused injection break_motor" in line for line in h.logs)
    assert working_motors(h.outputs("telemetry")[-1]) == 3
    node.inject("clear_faults")
    h.step(0.006)
    assert not q.faults.broken.any() and events(h)[-1]["detail"] == "clear_faults"


def test_realtime_pacing_catches_up_boundedly_and_drops_the_rest() -> None:
    h = sim(realtime_factor=1.0, max_catchup=5)
    node = h.node
    assert isinstance(node, VehicleSimulator)
    h.send("motor_cmd", hover_cmd())
    h.step(10.000)  # armed: one step
    assert node.quad.time == pytest.approx(0.002)
    h.step(10.002)
    assert node.quad.time == pytest.approx(0.004)
    h.step(10.0030)  # early: nothing due, nothing published
    n_states = len(h.outputs("state"))
    assert node.quad.time == pytest.approx(0.004)
    h.step(10.0061)  # 2 due
    assert node.quad.time == pytest.approx(0.008)
    assert len(h.outputs("state")) == n_states + 1
    h.step(10.1061)  # 50 due: 5 run, 45 dropped
    assert node.quad.time == pytest.approx(0.018) and node.dropped_steps == 45
    h.step(10.1081)
    assert node.quad.time == pytest.approx(0.020)


def test_telemetry_rate_and_crash_event() -> None:
    h = sim(telemetry_rate_hz=100.0, initial_position=[0.0, 0.0, 0.5])
    h.send("motor_cmd", {"speeds": [0.0] * 4, "controller": "controller"})
    for i in range(1, 301):
        h.step(i * 0.002)
    assert len(h.outputs("state")) == 300
    assert 55 <= len(h.outputs("telemetry")) <= 61
    crashes = [e for e in events(h) if e["kind"] == "crash"]
    assert len(crashes) == 1 and 0.25 < crashes[0]["sim_time"] < 0.45


# ---- where injections come from -----------------------------------------------------------------
INJECT = m.Codec[m.Injection](m.Injection)


def test_injections_through_the_sdk_raw_subscription() -> None:
    h = sim()
    h.send("motor_cmd", hover_cmd())
    payload = INJECT.encode(m.Inject(kind="break_motor", args={"motor": 1}))
    assert h.deliver_raw(Keys("test").inject_all, payload) == 1
    h.step(0.002)
    assert [e["detail"] for e in events(h) if e["kind"] == "fault"] == ["break_motor motor=1"]
