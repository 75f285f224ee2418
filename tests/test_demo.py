"""`rra demo`: the paper's evaluation end to end, and its report."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from rra_agent.bus import messages as m
from rra_agent.demo import recovery_report
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


def test_report_of_a_crash():
    r = recovery_report(synthetic(crash=True), setpoint=2.0)
    assert not r.airborne and r.crash == "hit the floor" and r.min_altitude == 0.03


def test_rra_demo_prints_the_report_and_writes_a_verifying_recording(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "rra_agent", "demo", "--out", str(tmp_path / "demo.rrd"),
         "--run-dir", str(tmp_path / "run")],
        capture_output=True, text=True, timeout=240, cwd=tmp_path,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
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
            "/vehicle/altitude", "/vehicle/altitude_target"},
        ("TimeSeries", "Motor currents (A)"): {"/vehicle/motors/current"},
        ("TimeSeries", "Motor speeds (rad/s)"): {"/vehicle/motors/measured_speed"},
        ("TimeSeries", "WorkingMotors"): {"/context/WorkingMotors"},
        ("StateTimeline", "Selected Controller"): {"/choice/Controller"},
        ("TimeSeries", "Adaptation phases (ms)"): {p for p in paths if p.startswith("/timing/")},
    }  # fmt: skip
    assert {"/world/vehicle/thrust", "/world/trajectory", "/timing/switch"} <= paths
