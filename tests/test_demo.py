"""`rra demo`: the paper's evaluation end to end, and its report."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import pytest

from rra_agent.bus import messages as m
from rra_agent.demo import recovery_report, render_report
from rra_agent.scenario.expectations import Applied, DataSample, Recording
from rra_agent.viz.blueprint import read_blueprint
from rra_agent.viz.recording import entity_paths, verify

#: Every test here starts processes or opens Zenoh sessions (pytest -m 'not system').
pytestmark = pytest.mark.system

ROOT = Path(__file__).resolve().parents[1]


def synthetic(crash: bool) -> Recording:
    t_f = 105.0
    state = [DataSample(100.0 + i * 0.01, "vehicle_simulator/state", {"position": [0, 0, z]})
             for i, z in enumerate([2.0] * 500 + [1.98, 1.95, 1.97, 2.0])]  # fmt: skip
    if crash:
        state.append(DataSample(106.0, "vehicle_simulator/state", {"position": [0, 0, 0.03]}))
    sim_events = [
        {"kind": "fault", "wall_time": t_f, "sim_time": 5.0, "detail": "break_motor motor=2"},
        {"kind": "controller", "wall_time": t_f + 0.012, "sim_time": 5.01,
         "detail": "proploss_controller"},
    ] + ([{"kind": "crash", "wall_time": 106.0, "sim_time": 6.0, "detail": "hit the floor"}]
         if crash else [])  # fmt: skip
    return Recording(
        system="quadcopter",
        t0=100.0,
        end=20.0,
        measurements=[m.Measurement(name="WorkingMotors", value=3, stamp=t_f + 0.001)],
        selections=[
            m.Selection(
                seq=1, stamp=t_f + 0.002, deployment=[], features=["Controller", "Proploss"]
            )
        ],
        events=[
            m.AdaptationEvent(
                stamp=t_f + 0.02,
                kind="adaptation",
                message="",
                plan=["activate proploss_controller (1.0 ms) ok"],
                durations={"plan": 0.0005, "switch": 0.008, "execute": 0.03},
            )
        ],
        data=[
            *state,
            *(DataSample(e["wall_time"], "vehicle_simulator/events", e) for e in sim_events),
        ],
        injections=[Applied(name="motor_failure", at=5.0, stamp=t_f)],
    )


def test_report_measures_every_phase_from_the_recording():
    r = recovery_report(synthetic(crash=False), setpoint=2.0)
    assert round(r.detected, 4) == 0.001 and round(r.decided, 4) == 0.001
    assert r.plan == 0.0005 and r.switch == 0.008 and r.execute == 0.03
    assert round(r.first_proploss_command, 4) == 0.012
    assert round(r.altitude_lost, 3) == 0.05 and r.airborne and not r.crash


def test_report_gives_the_largest_deviation_each_way_and_the_time_to_settle():
    """The report said "altitude lost 0.023 m" of a run whose recording shows a +0.34 m
    overshoot and ~1 m of horizontal drift: it gives all three, and when it settled."""
    rec = synthetic(crash=False)
    t_f = 105.0
    path = [(0.0, 0.0, 1.9), (0.6, 0.8, 2.34), (0.3, 0.0, 2.1), (0.05, 0.05, 2.03)]
    path += [(0.05, 0.05, 2.02)] * 150  # within 5 cm / 10 cm from t_f + 0.4 s on
    rec.data = [d for d in rec.data if d.topic != "vehicle_simulator/state" or d.stamp < t_f]
    rec.data += [DataSample(t_f + 0.1 * i, "vehicle_simulator/state", {"position": list(p)})
                 for i, p in enumerate(path)]  # fmt: skip
    r = recovery_report(rec, setpoint=2.0)
    assert round(r.overshoot, 3) == 0.34 and round(r.altitude_lost, 3) == 0.1
    assert round(r.drift, 3) == 1.0
    assert round(r.settled, 3) == 0.3 and round(r.altitude_settled, 3) == 0.3
    text = render_report(r)
    rows = {line[:49].strip(): line[49:].strip() for line in text.splitlines()}
    assert rows["largest deviation up (overshoot)"] == "0.340 m", text
    assert rows["largest deviation down (altitude lost)"] == "0.100 m", text
    assert rows["largest deviation sideways (drift)"] == "1.000 m", text
    assert rows["settled (+-5 cm up/down, 10 cm sideways, 1 s)"] == "0.30 s", text
    assert max(len(line) for line in text.splitlines()) <= 100


def test_report_of_a_run_that_never_settles():
    rec = synthetic(crash=False)
    rec.data.append(DataSample(105.5, "vehicle_simulator/state", {"position": [0, 0, 2.2]}))
    r = recovery_report(rec, setpoint=2.0)
    assert r.settled is None and "never (within the recording)" in render_report(r)


def test_report_of_a_vehicle_that_holds_its_altitude_but_circles():
    """What `rra demo` shows: the altitude settles, the vehicle keeps circling ~0.35 m around
    its hover point (the Proploss controller spins it): settled never, altitude settled."""
    rec = synthetic(crash=False)
    rec.data += [DataSample(105.1 + 0.1 * i, "vehicle_simulator/state",
                            {"position": [0.35 * math.cos(i / 5), 0.35 * math.sin(i / 5), 2.01]})
                 for i in range(40)]  # fmt: skip
    r = recovery_report(rec, setpoint=2.0)
    assert r.settled is None and round(r.altitude_settled, 2) == 0.02  # 1.95 m at 0.01 s
    assert round(r.drift, 2) == 0.35


def test_report_of_a_crash():
    r = recovery_report(synthetic(crash=True), setpoint=2.0)
    assert not r.airborne and r.crash == "hit the floor" and r.min_altitude == 0.03


def test_rra_demo_prints_the_report_and_writes_a_verifying_recording(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "rra_agent", "demo", "--out", str(tmp_path / "demo.rrd"),
         "--run-dir", str(tmp_path / "run"), "--duration", "10"],
        capture_output=True, text=True, timeout=240, cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert "stops at t = 10 s" in out.stdout  # the flight is scenarios/quadcopter's, cut short
    assert "fault -> first Proploss command applied" in out.stdout
    assert "STAYED AIRBORNE" in out.stdout
    assert f"rra view {tmp_path / 'demo.rrd'}" in out.stdout
    verify(tmp_path / "demo.rrd")
    paths = entity_paths(tmp_path / "demo.rrd")
    expected = [
        "/world/vehicle", "/world/vehicle/thrust", "/world/trajectory", "/vehicle/altitude",
        "/vehicle/motors/current", "/context/WorkingMotors", "/selection/Proploss",
        "/events", "/nodes/proploss_controller/state",
    ]  # fmt: skip
    assert [e for e in expected if e not in paths] == []
    # the designed views (rra_agent.viz.blueprint), each showing data, on simulation time
    bp = read_blueprint(tmp_path / "demo.rrd")
    assert bp is not None and bp.timeline == "sim_time"
    shown = {(v.kind, v.name): v.shows(paths) for v in bp.views}
    assert shown == {
        ("3D", "Vehicle"): {p for p in paths if p.startswith("/world/")},
        ("TextLog", "Adaptation events"): {"/events", "/rules"},
        ("TimeSeries", "Altitude against its target (m)"): {
            "/vehicle/altitude", "/vehicle/altitude_target", "/vehicle/injections"},
        ("TimeSeries", "Motor currents (A)"): {"/vehicle/motors/current"},
        ("TimeSeries", "Motor speeds (rad/s)"): {"/vehicle/motors/measured_speed"},
        ("TimeSeries", "WorkingMotors"): {"/context/WorkingMotors"},
        ("StateTimeline", "Selected Controller and faults injected"): {
            "/choice/Controller", "/injections"},
        ("TimeSeries", "Adaptation phases (ms)"): {p for p in paths if p.startswith("/timing/")},
    }  # fmt: skip
    assert {"/world/vehicle/thrust", "/world/trajectory", "/timing/switch"} <= paths


@pytest.mark.parametrize("value", ["3", "soon"])
def test_rra_demo_refuses_a_duration_that_ends_before_the_failure_in_one_line(tmp_path, value):
    out = subprocess.run(
        [sys.executable, "-m", "rra_agent", "demo", "--duration", value],
        capture_output=True, text=True, timeout=60, cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert "--duration" in out.stderr.splitlines()[-1], out.stderr
