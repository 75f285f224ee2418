"""Rerun logging (rra_agent.viz) with the real rerun SDK and CLI, headless.

Recordings are checked with the CLI (``rerun rrd verify`` and ``rrd print``); processes are
real (two loggers sharing a recording id; a whole ``rra up --rerun save``), and a process
that does not log must not import rerun (checked in ``/proc/<pid>/maps``: rerun's native
module is mapped in every process that imported it). Loopback only, a free hub port per
test, deadlines instead of sleeps.
"""

from __future__ import annotations

import re
import signal
import sys
import time
from pathlib import Path

import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, wait_until
from rra_agent.bus.why import change_lines
from rra_agent.viz import recording
from rra_agent.viz.rerun_log import (
    ENV_VAR,
    RULES_WIDTH,
    Every,
    RerunConfig,
    open_logger,
    rule_rows,
    viewer_reachable,
)

DATA = Path(__file__).parent / "data" / "relay_system"
ROTORS = [(0.2, 0.2, 0.0), (-0.2, 0.2, 0.0), (-0.2, -0.2, 0.0), (0.2, -0.2, 0.0)]


def save_env(tmp_path: Path, name: str = "rec") -> tuple[RerunConfig, dict[str, str]]:
    cfg = RerunConfig.new("save", "test_system", dir=str(tmp_path / name))
    return cfg, {ENV_VAR: cfg.to_env()}


# ---- (a) every kind of data, in one process --------------------------------------------------
def test_logger_writes_every_kind_into_a_verified_recording(tmp_path):
    _, env = save_env(tmp_path)
    log = open_logger("unit", env)
    assert log is not None and log.path == tmp_path / "rec" / "unit.rrd"
    now = time.time()
    log.measurement("Level", 7.5, now)
    log.measurement("Busy", True, now)
    log.measurement("Mode", "fast", now)
    log.selection(["Filtered", "Path"], {"Gain": 7.5}, now, universe=["Direct", "Filtered"],
                  fired=["PathRule: activate_feature(Filtered)"], changed=True)  # fmt: skip
    log.event(m.AdaptationEvent(stamp=now, kind="adaptation", message="applied", outcome="ok",
                                plan=["start filtered", "stop direct"],
                                durations={"plan": 0.001, "execute": 0.2}))  # fmt: skip
    log.event(m.AdaptationEvent(stamp=now, kind="adaptation", message="failed", level="error"))
    log.node_state(m.NodeState(stamp=now, node="sink", host="local", state="RUNNING", pid=42))
    log.node_state(m.NodeState(stamp=now, node="sink", host="local", state="FATAL", reason="x"))
    log.scalar("/misc/value", 1.0, sim_time=0.5)
    log.text("/misc/log", "hello", level="WARN")
    log.transform("/world/marker", (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0), sim_time=0.5)
    log.log("/world/ground", log.rr.Boxes3D(half_sizes=[(5.0, 5.0, 0.01)]), static=True)
    log.scalar_columns("/misc/batch", [[1.0, 2.0]] * 50, sim_times=[i * 0.01 for i in range(50)])
    log.vehicle_geometry(ROTORS)
    due = Every(0.02)
    for i in range(500):  # 1 s at 500 Hz: pose and arrows decimated to 50 Hz
        t = i * 0.002
        if due(t):
            log.vehicle_pose((0.0, 0.1 * t, 1.0 + t), (0.0, 0.0, 0.0, 1.0), sim_time=t)
            log.thrust([2.0, 2.0, 2.0, 0.0], sim_time=t, failed=[False, False, False, True])
        log.altitude(1.0 + t, sim_time=t, target=2.0)
        log.motors("thrust", [2.0, 2.0, 2.0, 0.0], sim_time=t)
        log.scalar_row("/misc/row", t, sim_time=t)
    assert log.errors == 0
    log.close()
    log.close()  # idempotent
    log.scalar("/misc/after_close", 1.0)  # a no-op, no error

    recording.verify(log.path)
    paths = recording.entity_paths(log.path)
    assert {
        "/context/Level", "/context/Busy", "/context/Mode", "/selection/Direct",
        "/selection/Filtered", "/selection/Path", "/cv/Gain", "/rules", "/events",
        "/timing/plan", "/timing/execute", "/nodes/sink/state", "/nodes/sink/running",
        "/misc/value", "/misc/log", "/misc/batch", "/misc/row", "/world/marker", "/world/ground",
        "/world/vehicle", "/world/vehicle/frame", "/world/vehicle/rotors", "/world/vehicle/arms",
        "/world/vehicle/thrust", "/world/trajectory", "/vehicle/altitude",
        "/vehicle/altitude_target", "/vehicle/motors/thrust",
    } <= paths  # fmt: skip
    assert "/misc/after_close" not in paths


def test_an_injected_fault_is_a_marker_on_the_altitude_plot_a_lane_and_a_line(tmp_path):
    """The fault had no marker on the timeline: the simulator logs each injection."""
    _, env = save_env(tmp_path)
    log = open_logger("sim", env)
    assert log is not None
    for i in range(10):
        log.altitude(2.0, sim_time=i * 0.1, target=2.0)
    log.injection("break_motor motor=2", sim_time=0.55, altitude=1.98)
    log.injection("clear_faults", sim_time=0.8)  # no altitude: the lane and the line only
    assert log.errors == 0
    log.close()
    recording.verify(log.path)
    assert {"/injections", "/vehicle/injections", "/events"} <= recording.entity_paths(log.path)


def test_a_logging_failure_is_counted_and_never_raised(tmp_path, capsys):
    _, env = save_env(tmp_path)
    log = open_logger("unit", env)
    assert log is not None
    log.thrust([1.0, 1.0], sim_time=0.0)  # no vehicle_geometry yet
    log.thrust([1.0, 1.0], sim_time=0.1)
    assert log.errors == 2
    assert capsys.readouterr().err.count("thrust failed") == 1  # printed once
    log.close()
    recording.verify(log.path)


def test_every_decimates_and_restarts_when_time_goes_back():
    due = Every(0.02)
    assert [t for t in (i * 0.002 for i in range(50)) if due(t)] == pytest.approx(
        [0.0, 0.02, 0.04, 0.06, 0.08]
    )
    assert due(0.0)  # the clock went back (a restarted simulation)
    assert not due(0.01)


def test_open_logger_is_none_unless_configured_and_usable(tmp_path, capsys):
    assert open_logger("x", {}) is None
    assert open_logger("x", {ENV_VAR: RerunConfig().to_env()}) is None
    assert open_logger("x", {ENV_VAR: "{not json"}) is None
    from conftest import free_port

    url = f"rerun+http://127.0.0.1:{free_port()}/proxy"  # nobody listens there
    t0 = time.monotonic()
    assert open_logger("x", {ENV_VAR: RerunConfig.new("connect", "s", url=url).to_env()}) is None
    assert time.monotonic() - t0 < 2.0  # not the ~11 s of an unreachable gRPC sink
    err = capsys.readouterr().err
    assert "bad RRA_RERUN" in err and "no Rerun viewer" in err


def test_rerun_option_forms(tmp_path):
    run = tmp_path / "run"
    cfg, out = recording.rerun_option(None, "sys", run)
    assert cfg.mode == "off" and out is None
    assert recording.rerun_option(["off"], "sys", run)[1] is None
    for values, expected in (([], run / "recording.rrd"), (["save"], run / "recording.rrd"),
                             (["save", str(tmp_path / "a.rrd")], tmp_path / "a.rrd"),
                             ([str(tmp_path / "b.rrd")], tmp_path / "b.rrd")):  # fmt: skip
        cfg, out = recording.rerun_option(values, "relay system", run)
        assert (cfg.mode, out) == ("save", expected)
        assert cfg.application_id == "rra-relay-system" and len(cfg.recording_id) == 32
        assert Path(cfg.dir) == run / "rerun" / cfg.recording_id
    for bad in (["save", "a.txt"], ["off", "x"], ["bogus"], ["save", "a.rrd", "b.rrd"]):
        with pytest.raises(ValueError):
            recording.rerun_option(bad, "sys", run)
    with pytest.raises(ValueError, match="no Rerun viewer"):
        recording.rerun_option(["connect", "rerun+http://127.0.0.1:1/proxy"], "sys", run)


# ---- (b) several processes, one recording --------------------------------------------------
_WRITER = """
import os, signal, sys, time
from rra_agent.bus import messages as m
from rra_agent.viz.rerun_log import open_logger
name = sys.argv[1]
log = open_logger(name)
for i in range(100):
    log.scalar(f"/{name}/value", float(i), sim_time=i * 0.01)
log.event(m.AdaptationEvent(stamp=time.time(), kind="test", message=f"hello from {name}"))
if name == "crash":  # dies without closing: its file has no footer
    log.flush()
    os.kill(os.getpid(), signal.SIGKILL)
log.close()
assert log.errors == 0
"""


def test_processes_with_one_recording_id_merge_into_one_verified_recording(tmp_path, procs):
    cfg, env = save_env(tmp_path)
    names = ("p", "q", "crash")
    writers = [procs.spawn([sys.executable, "-c", _WRITER, n], env=env, name=n) for n in names]
    statuses = [w.wait(30) for w in writers]
    assert statuses == [0, 0, -signal.SIGKILL], [procs.log(n) for n in names]
    with pytest.raises(recording.RecordingError, match="footer"):
        recording.verify(tmp_path / "rec" / "crash.rrd")
    out = tmp_path / "all.rrd"
    recording.finish(cfg, out)  # verifies the merged file
    assert {"/p/value", "/q/value", "/crash/value", "/events"} <= recording.entity_paths(out)
    printed = recording.run_cli("rrd", "print", str(out)).stdout
    assert set(re.findall(r'"([0-9a-f]{32})"', printed)) == {cfg.recording_id}


def test_merge_reports_a_missing_or_broken_recording(tmp_path):
    cfg, _ = save_env(tmp_path)
    with pytest.raises(recording.RecordingError, match="no process wrote"):
        recording.finish(cfg, tmp_path / "out.rrd")
    bad = tmp_path / "bad.rrd"
    bad.write_bytes(b"not an rrd file")
    with pytest.raises(recording.RecordingError, match="does not verify"):
        recording.verify(bad)


# ---- (c, d) a whole system under rra up ------------------------------------------------------
def rerun_loaded(pid: int) -> bool:
    """Whether process ``pid`` has imported rerun (its native module is mapped)."""
    return "rerun_bindings" in Path(f"/proc/{pid}/maps").read_text()


ENGINES = [f"{e}-{r}" for e in ("monitor", "adaptation", "resolution") for r in "ab"]


def children(pid: int) -> list[int]:
    return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]


def cmdline(pid: int) -> str:
    return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()


def run_system(procs, bus, run_dir: Path, *extra: str, adapt: bool) -> dict[str, bool]:
    """Run ``rra up`` on relay_system until deployed (with ``adapt``: until the source's level
    crossed 5 and the swap to Filtered happened), stop it with SIGINT; return which of its
    processes (by node name; ``up`` itself and the fork server ``zygote``) had loaded rerun."""
    proc = procs.python(
        "rra_agent", "up", str(DATA), "--run-dir", str(run_dir), "-q",
        "--connect", bus.connect[0], "--no-multicast", "--lease-ms", "500", *extra, name="up",
    )  # fmt: skip
    from rra_agent.bus.client import gather, set_params

    with BusClient(bus, "relay_system") as client:

        def engine(pred):
            def check():
                st = gather(client, timeout=1.0)
                for n in st["nodes"]:
                    procs.watch(n.get("pid"))
                # every process settled (the resolution engine turns RUNNING only after its
                # deployment is done, so "sink running" alone can be seen a moment earlier)
                settled = {n["node"]: n["state"] for n in st["nodes"]}
                ready = all(settled.get(e) == "RUNNING" for e in ENGINES) and all(
                    state in ("RUNNING", "STOPPED") for state in settled.values()
                )
                return st if ready and st["engine"] and pred(st["engine"]) else None

            try:
                return wait_until(check, 30, "the system", interval=0.05)
            except TimeoutError:
                raise AssertionError(f"not reached; up log:\n{procs.log('up')[-3000:]}") from None

        st = engine(lambda e: "sink" in e["running"] and not e["failed"])
        if adapt:
            set_params(client, "source", {"value": 7.0})
            st = engine(lambda e: "Filtered" in e["selection"] and "filtered" in e["running"])
    pids = {n["node"]: n["pid"] for n in st["nodes"] if n["state"] == "RUNNING"}
    nodes = set(pids.values())
    zygote = next(p for p in children(proc.pid) if p not in nodes and "forkserver" in cmdline(p))
    pids |= {"up": proc.pid, "zygote": zygote}
    loaded = {name: rerun_loaded(pid) for name, pid in pids.items()}
    proc.send_signal(signal.SIGINT)
    assert proc.wait(30) == 0, procs.log("up")[-3000:]
    return loaded


def test_rra_up_saves_one_verified_recording_of_the_whole_system(procs, bus, tmp_path):
    out = tmp_path / "X.rrd"
    run_dir = tmp_path / "run"
    loaded = run_system(procs, bus, run_dir, "--rerun", "save", str(out), adapt=True)
    # Only the engines that log imported rerun: not the nodes, the fork server or rra up.
    assert loaded == {
        **dict.fromkeys(ENGINES, True),
        "source": False, "filtered": False, "sink": False, "up": False, "zygote": False,
    }  # fmt: skip
    assert out.exists()
    recording.verify(out)
    paths = recording.entity_paths(out)
    assert {"/context/Level", "/selection/Filtered", "/selection/Direct", "/cv/Gain",
            "/events", "/timing/execute", "/rules"} <= paths  # fmt: skip
    assert {f"/nodes/{n}/state" for n in ("source", "direct", "filtered", "sink")} <= paths
    files = sorted(p.name for p in (run_dir / "rerun").glob("*/*.rrd"))
    assert files == sorted([*(f"{e}.rrd" for e in ENGINES), "blueprint.rrd"])
    printed = recording.run_cli("rrd", "print", "-vvv", str(out)).stdout
    assert "adaptation: applied selection ['Filtered', 'Path', 'Tuning']" in printed


def test_no_process_imports_rerun_when_rerun_is_off(procs, bus, tmp_path):
    run_dir = tmp_path / "run"
    loaded = run_system(procs, bus, run_dir, adapt=False)
    assert set(loaded) == {*ENGINES, "source", "direct", "sink", "up", "zygote"}
    assert not any(loaded.values()), loaded
    assert not (run_dir / "rerun").exists()


# ---- connect: streaming to a viewer -----------------------------------------------------------
def test_connect_mode_streams_to_a_viewer(procs, tmp_path):
    from conftest import free_port

    port = free_port()
    saved = tmp_path / "viewer.rrd"
    cli = recording.rerun_cli()
    viewer = procs.spawn([*cli, "--bind", "127.0.0.1", "--port", str(port), "--save", str(saved)],
                         name="viewer")  # fmt: skip
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    wait_until(lambda: viewer_reachable(url, 0.2), 20, "the viewer", interval=0.05)
    cfg = RerunConfig.new("connect", "test_system", url=url)
    log = open_logger("streamer", {ENV_VAR: cfg.to_env()})
    assert log is not None and log.path is None
    for i in range(20):
        log.measurement("Level", float(i), time.time())
    log.close()
    assert log.errors == 0
    wait_until(lambda: "/context/Level" in recording.entity_paths(saved), 10, "the data")
    viewer.terminate()  # SIGTERM: SIGINT may be ignored when the tests run in the background
    viewer.wait(10)


def test_the_rules_rows_carry_the_whole_cause_in_rows_the_events_view_shows_whole():
    """The events view shows about 72 characters of a row's body and one line of it: the
    cause of a selection goes in rows no longer than that, and none of it is lost."""
    fired = m.FiredRule(rule="SafetyZone", action="activate_feature(HumanZone)",
                        reads={"HumanDistance": 1.0}, values={"HumanDistance": 0.8})  # fmt: skip
    lost = m.Overruled(rule="Localisation", action="activate_feature(NormalZone)", wants="on",
                       why="later_rule", detail="rule SafetyZone, written later, wins (a "
                       "run-time conflict in rule set Zones, priority 3 against 1)")  # fmt: skip
    why = [
        m.Why(target="HumanZone", kind="feature", value="on", reason="rule", by=[fired],
              overruled=[lost]),
        m.Why(target="NormalZone", kind="feature", value="off", reason="rule", by=[fired]),
    ]  # fmt: skip
    rows = rule_rows(why)
    assert rows and all(len(r) <= RULES_WIDTH for r in rows), rows
    assert rows[0].startswith("selection +HumanZone -NormalZone by SafetyZone")
    words = " ".join(" ".join(change_lines(why)).split())
    assert " ".join(" ".join(rows).split()) == "selection " + words.replace("   ", " ")
    assert any(r.startswith("  overruled Localisation") for r in rows)
