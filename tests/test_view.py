"""Designed Rerun views: the blueprint in a saved recording, the simulation-time timeline,
``rra view`` and the headless rendering tool.

A recording is made the way ``rra up --rerun save`` makes one (`rerun_option`,
`attach_blueprint`, processes' loggers, `finish`) and read back with rerun's own reader
(`rra_agent.viz.blueprint.read_blueprint`): the views, their kinds and names, and the entity
paths each one shows. The object-storing map is drawn by the real ``RobotDriver`` node (in a
`NodeHarness`, logging because ``RRA_RERUN`` says so). The quadcopter's views are checked on
the real demo recording in tests/test_demo.py.
"""

from __future__ import annotations

import importlib.util
import os
import re
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.client import wait_until
from rra_agent.bus.config import free_port
from rra_agent.cli import view
from rra_agent.cli.commands import main
from rra_agent.errors import RraError
from rra_agent.node import NodeHarness
from rra_agent.nodes.object_storing import RobotDriver
from rra_agent.package.loader import load_package
from rra_agent.viz import recording
from rra_agent.viz.blueprint import layout_of, read_blueprint
from rra_agent.viz.rerun_log import ENV_VAR, SIM, open_logger

ROOT = Path(__file__).resolve().parents[1]
OBJECT_STORING = ROOT / "scenarios" / "object_storing"
TOOLS = ROOT / "tools"


def temporal_timelines(path: Path) -> dict[str, set[str]]:
    """Entity path -> the timelines of its temporal (non-static) chunks."""
    from rerun.chunk import RrdReader

    out: dict[str, set[str]] = {}
    for chunk in RrdReader(path).stream().to_chunks():
        if not chunk.is_static:
            out.setdefault(chunk.entity_path, set()).update(chunk.timeline_names)
    return out


def object_storing_recording(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A saved object-storing recording: the blueprint `rra up` attaches, the robot driver
    node's map and poses, and what the engines log (measurements, a selection that goes to
    the corridor and the low-power channel, an adaptation event)."""
    package = load_package(OBJECT_STORING)
    config, out = recording.rerun_option(["save", str(tmp_path / "os.rrd")], "object_storing",
                                         tmp_path / "run")  # fmt: skip
    assert out is not None
    recording.attach_blueprint(config, package)
    env = {ENV_VAR: config.to_env()}
    monkeypatch.setenv(ENV_VAR, config.to_env())
    now = time.time()
    robot = NodeHarness(
        RobotDriver,
        name="robot_driver",
        params={"battery_level": 80.0},
        ports={"cmd_vel": ("subscribe", "Twist"), "odom": ("publish", "Odometry"),
               "battery": ("publish", "BatteryState")},
        now=now,
    )  # fmt: skip
    for i in range(1, 31):  # 3 s driving forward at 1 m/s
        robot.send("cmd_vel", {"linear": 1.0, "angular": 0.0})
        robot.step(now + 0.1 * i)
    robot.core.stop()
    engines = open_logger("engines", env)
    assert engines is not None
    engines.measurement("BattLev", 80.0, now)
    engines.measurement("ObstDist", 2.0, now)
    engines.measurement("SemLoc", "RoomA", now)
    engines.measurement("SemLoc", "Corridor", now + 2)
    engines.measurement("Material", "Glass", now)
    base = ["Environment", "Communic. Channel", "Motion Behavior"]
    universe = load_package(OBJECT_STORING).features.runtime_features()
    engines.selection([*base, "Static", "ChannelB"], {"MaxVel": 0.8}, now, universe=universe)
    fired = ["Radio: select(ChannelA)"]
    engines.selection([*base, "Dynamic", "ChannelA"], {"MaxVel": 0.5}, now + 2,
                      universe=universe, fired=fired, changed=True)  # fmt: skip
    event = m.AdaptationEvent(stamp=now + 2, kind="adaptation", message="applied selection",
                              plan=["start radio_driver_a"], durations={"plan": 0.001})  # fmt: skip
    engines.event(event)
    engines.close()
    assert recording.finish(config, out) == []
    return out


@pytest.mark.system
def test_object_storing_recording_carries_its_designed_views(tmp_path, monkeypatch):
    out = object_storing_recording(tmp_path, monkeypatch)
    bp = read_blueprint(out)
    assert bp is not None, "the recording has no blueprint"
    assert bp.timeline == SIM
    views = {v.name: v for v in bp.views}
    assert {(v.kind, v.name) for v in bp.views} == {
        ("2D", "Floor map (m)"),
        ("TextLog", "Adaptation events"),
        ("TimeSeries", "BattLev (%)"),
        ("TimeSeries", "ObstDist (m)"),
        ("StateTimeline", "SemLoc, Material and selected Environment, Communic. Channel, "
                          "RackSize, Material"),
        ("TimeSeries", "MaxVel against VelocityLimit (m/s)"),
        ("TimeSeries", "Adaptation phases (ms)"),
    }  # fmt: skip
    paths = recording.entity_paths(out)
    empty = [v.name for v in bp.views if not v.shows(paths)]
    assert empty == [], f"views showing nothing: {empty}"
    assert {"/map/rooms", "/map/doors", "/map/racks", "/map/robot", "/map/path"} <= views[
        "Floor map (m)"
    ].shows(paths)
    assert views["BattLev (%)"].shows(paths) == {"/context/BattLev"}
    lanes = next(v for v in bp.views if v.kind == "StateTimeline").shows(paths)
    assert {"/context/SemLoc", "/choice/Communic.\\ Channel", "/choice/Environment"} <= lanes
    assert views["MaxVel against VelocityLimit (m/s)"].shows(paths) == {
        "/cv/MaxVel",
        "/cv/VelocityLimit",
    }
    assert views["Adaptation events"].shows(paths) == {"/events", "/rules"}


@pytest.mark.system
def test_every_sample_is_on_the_simulation_timeline(tmp_path, monkeypatch):
    out = object_storing_recording(tmp_path, monkeypatch)
    timelines = temporal_timelines(out)
    assert "/map/robot" in timelines and "/context/BattLev" in timelines
    missing = sorted(p for p, names in timelines.items() if SIM not in names)
    assert missing == [], f"temporal data without {SIM}: {missing}"


def sim_times(path: Path, entity: str) -> list[float]:
    """The ``sim_time`` values (s) of an entity's temporal rows."""
    from rerun.chunk import RrdReader

    out: list[float] = []
    for chunk in RrdReader(path).stream().to_chunks():
        if chunk.entity_path == entity and not chunk.is_static:
            column = chunk.to_record_batch().column(SIM).cast("int64").to_pylist()
            out += [ns / 1e9 for ns in column]
    return sorted(out)


def test_a_simulation_clock_is_placed_on_the_run_time_axis(tmp_path):
    """Engines stamp the seconds since the run started; the simulator's physics clock starts
    at its first sample's run time, so a fault and its adaptation line up."""
    config = recording.RerunConfig.new("save", "quad", dir=str(tmp_path / "rec"))
    t0 = config.t0
    env = {ENV_VAR: config.to_env()}
    sim, engine = open_logger("sim", env), open_logger("engine", env)
    assert sim is not None and engine is not None
    for i in range(3):  # the simulator armed 5 s into the run; physics time starts at 0
        sim.scalar("/vehicle/x", 1.0, sim_time=i * 0.5, wall_time=t0 + 5.0 + i * 0.5)
    engine.measurement("WorkingMotors", 3, t0 + 5.5)
    sim.close()
    engine.close()
    assert sim_times(sim.path, "/vehicle/x") == pytest.approx([5.0, 5.5, 6.0])
    assert sim_times(engine.path, "/context/WorkingMotors") == pytest.approx([5.5])


def text_rows(path: Path, entity: str) -> list[tuple[str, str]]:
    """(level, text) of an entity's TextLog rows, in time order."""
    from rerun.chunk import RrdReader

    rows: list[tuple[int, str, str]] = []
    for chunk in RrdReader(path).stream().to_chunks():
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            times = batch.column(SIM).cast("int64").to_pylist()
            texts = batch.column("TextLog:text").to_pylist()
            levels = batch.column("TextLog:level").to_pylist()
            rows += [(t, lv[0], tx[0]) for t, tx, lv in zip(times, texts, levels, strict=True)]
    return [(lv, tx) for _, lv, tx in sorted(rows)]


def test_the_events_view_shows_structural_changes_and_hides_cv_updates(tmp_path):
    config = recording.RerunConfig.new("save", "x", dir=str(tmp_path / "rec"))
    log = open_logger("adaptation", {ENV_VAR: config.to_env()})
    assert log is not None
    t = config.t0
    log.selection(["A"], {"V": 1.0}, t + 1, universe=["A", "B"], fired=["r1"], changed=True)
    log.selection(["A"], {"V": 2.0}, t + 2, universe=["A", "B"], fired=["r2"], changed=True)
    log.selection(["B"], {"V": 2.0}, t + 3, universe=["A", "B"], fired=["r3"], changed=True)
    for i, sel in enumerate(("['A']", "['A']", "['B']")):
        log.event(m.AdaptationEvent(stamp=t + 1 + i, kind="adaptation",
                                    message=f"applied selection {sel}, 1 action",
                                    durations={"plan": 0.002}))  # fmt: skip
    log.close()
    assert log.path is not None
    assert text_rows(log.path, "/rules") == [
        ("INFO", "selection ['A'] by r1"),
        ("DEBUG", "selection ['A'] by r2"),
        ("INFO", "selection +B -A by r3"),
    ]
    assert [lv for lv, _ in text_rows(log.path, "/events")] == ["INFO", "DEBUG", "INFO"]
    # the phases plot has the two structural adaptations only
    assert sim_times(log.path, "/timing/plan") == pytest.approx([1.0, 3.0])


def test_the_merged_recording_is_compacted_into_few_chunks(tmp_path):
    """Many small chunks (a process flushes every 0.1 s) made the web viewer take 45-90 s
    for the 4 MB demo recording: `finish` compacts them (``rrd optimize``)."""
    from rerun.chunk import RrdReader

    def chunks(path: Path) -> int:
        return len(RrdReader(path).stream().to_chunks())

    out = tmp_path / "x.rrd"
    config, _ = recording.rerun_option(["save", str(out)], "x", tmp_path / "run")
    log = open_logger("p", {ENV_VAR: config.to_env()})
    assert log is not None
    for i in range(200):  # one chunk per sample, as a slow stream of samples gives
        log.scalar("/x", float(i), sim_time=i * 0.01)
        log.flush()
    log.close()
    assert log.path is not None and chunks(log.path) >= 200
    recording.finish(config, out)
    assert chunks(out) <= 5


def test_layout_of_the_example_packages():
    quad = layout_of(load_package(ROOT / "scenarios" / "quadcopter"))
    assert quad.vehicle and not quad.floor_map
    assert quad.choices == (("Controller", ("Standard", "Proploss")),)
    assert quad.measurements == (("WorkingMotors", ""),)
    storing = layout_of(load_package(OBJECT_STORING))
    assert storing.floor_map and not storing.vehicle
    assert ("Communic. Channel", ("ChannelA", "ChannelB")) in storing.choices
    assert storing.limits == (("VelocityLimit", "Dynamic", 0.5, "MaxVel"),)
    assert storing.text_measurements == ("SemLoc", "Material")


SHIPPED = sorted(p.name for p in (ROOT / "scenarios").iterdir() if p.is_dir())


@pytest.mark.parametrize("name", SHIPPED)
def test_every_shipped_package_has_a_layout(name):
    # ros2_rover's components are commands (a Struct holding a list, so unhashable): its
    # layout raised TypeError, and `rra up --rerun` with it crashed before anything started.
    package = load_package(ROOT / "scenarios" / name)
    layout = layout_of(package)
    assert layout.system == package.system.system
    assert {n for n, _ in layout.measurements} | set(layout.text_measurements) == {
        m.name for m in package.measurements.measurements
    }


# ---- rra view ---------------------------------------------------------------------------------
def touch(path: Path, mtime: float | None = None) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"")
    if mtime is not None:
        os.utime(path, (mtime, mtime))
    return path


def test_view_resolves_a_file_a_run_folder_or_the_newest_recording(tmp_path):
    rrd = touch(tmp_path / "x.rrd")
    assert view.resolve_recording("x.rrd", tmp_path) == rrd
    assert view.resolve_recording(str(rrd), tmp_path) == rrd
    run = tmp_path / ".rra" / "sys-1"
    own = touch(run / "recording.rrd", 1000)
    assert view.resolve_recording(str(run), tmp_path) == own
    # --rerun save PATH elsewhere: the run folder names it
    other = tmp_path / ".rra" / "sys-2"
    (other / "rerun").mkdir(parents=True)
    (other / recording.POINTER).write_text(f"{rrd}\n")
    os.utime(rrd, (2000, 2000))
    assert view.resolve_recording(str(other), tmp_path) == rrd
    # a folder with some other .rrd: the newest
    loose = tmp_path / "loose"
    touch(loose / "a.rrd", 1000)
    newest = touch(loose / "b.rrd", 3000)
    assert view.resolve_recording(str(loose), tmp_path) == newest
    # no argument: the newest recording of the run folders
    assert view.resolve_recording(None, tmp_path) == rrd
    empty = tmp_path / "empty"
    empty.mkdir()
    demo = touch(empty / "demo.rrd")
    assert view.resolve_recording(None, empty) == demo


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["missing.rrd"], "rra view: missing.rrd: no such file or folder"),
        (["folder"], "rra view: folder: no recording in this run folder (run `rra up` with "
                     "`--rerun save`)"),
        (["notes.txt"], "rra view: notes.txt: not a Rerun recording (a .rrd file or a run folder)"),
        ([], "rra view: no recording under .rra/ and no demo.rrd here: give a RUN_DIR or "
             "FILE.rrd (record one with `rra demo` or `rra up PKG --rerun save`)"),
    ],
)  # fmt: skip
def test_view_errors_are_one_line_and_exit_1(tmp_path, monkeypatch, capsys, args, message):
    (tmp_path / "folder").mkdir()
    (tmp_path / "notes.txt").write_text("x")
    monkeypatch.chdir(tmp_path)
    assert main(["view", *args]) == 1
    captured = capsys.readouterr()
    assert captured.err == message + "\n" and captured.out == ""


def test_view_runs_the_environments_rerun_not_one_on_path(tmp_path, monkeypatch):
    impostor = touch(tmp_path / "bin" / "rerun")
    impostor.chmod(0o755)
    monkeypatch.setenv("PATH", f"{impostor.parent}:{os.environ.get('PATH', '')}")
    monkeypatch.delenv("RERUN_CLI_PATH", raising=False)
    rrd = tmp_path / "x.rrd"
    cmd = view.viewer_command(rrd, web=False, port=9090, grpc_port=0)
    exe = Path(cmd[0])
    assert cmd == [str(exe), str(rrd), "--bind", "127.0.0.1"] and exe != impostor
    spec = importlib.util.find_spec("rerun_cli")
    assert spec is not None and exe.parent == Path(next(iter(spec.submodule_search_locations)))
    web = view.viewer_command(rrd, web=True, port=8123, grpc_port=8124)
    assert web[2:] == ["--bind", "127.0.0.1", "--web-viewer", "--web-viewer-port", "8123",
                       "--port", "8124"]  # fmt: skip
    monkeypatch.setattr(recording, "venv_rerun", lambda: None)
    monkeypatch.setattr(view, "venv_rerun", lambda: None)
    with pytest.raises(RraError, match="not installed in this Python environment"):
        view.viewer_command(rrd, web=False, port=9090, grpc_port=0)


def no_display(monkeypatch) -> list[list[str]]:
    """No display in the environment; os.execve recorded (a viewer never starts)."""
    for var in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(var, raising=False)
    started: list[list[str]] = []
    monkeypatch.setattr(view.os, "execve", lambda exe, cmd, env: started.append(cmd))
    return started


def test_view_without_a_display_says_so_and_names_the_way_out(tmp_path, monkeypatch, capsys):
    rrd = touch(tmp_path / "x.rrd")
    started = no_display(monkeypatch)
    assert main(["view", str(rrd)]) == 1
    assert not started  # not the viewer's own "winit EventLoopError: ..." after it started
    err = capsys.readouterr().err
    assert err == (
        "rra view: no display here ($DISPLAY, $WAYLAND_DISPLAY unset): try `rra view --web` "
        "(in a browser)\n"
    )
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:  # a port no X server has
        s.bind(("127.0.0.1", 0))
        gone = s.getsockname()[1] - 6000
    monkeypatch.setenv("DISPLAY", f"127.0.0.1:{gone}")
    assert main(["view", str(rrd)]) == 1 and not started
    assert f"no X server answers at DISPLAY=127.0.0.1:{gone}: try `rra view --web`" in (
        capsys.readouterr().err
    )
    assert main(["view", str(rrd), "--web"]) == 1  # the browser needs no display
    assert started and "--web-viewer" in started[0]


def test_a_display_that_answers_is_used(tmp_path, monkeypatch):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as x:  # an "X server" on TCP
        x.bind(("127.0.0.1", 0))
        x.listen()
        n = x.getsockname()[1] - 6000
        assert view.display_problem({"DISPLAY": f"127.0.0.1:{n}.0"}) is None
    (tmp_path / "wayland-0").touch()
    wayland = {"WAYLAND_DISPLAY": "wayland-0", "XDG_RUNTIME_DIR": str(tmp_path)}
    assert view.display_problem(wayland) is None
    missing = view.display_problem({**wayland, "WAYLAND_DISPLAY": "w-9"})
    assert "no Wayland display" in (missing or "")


def listeners(port: int) -> set[str]:
    """Local addresses (hex, as in /proc/net/tcp) listening on ``port``."""
    out = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        with open(table) as f:
            for line in f.readlines()[1:]:
                local, state = line.split()[1], line.split()[3]
                addr, _, p = local.rpartition(":")
                if state == "0A" and int(p, 16) == port:
                    out.add(addr)
    return out


def test_view_web_serves_on_loopback_only_and_leaves_nothing(tmp_path, procs):
    out = tmp_path / "tiny.rrd"
    config, _ = recording.rerun_option(["save", str(out)], "tiny", tmp_path / "run")
    log = open_logger("p", {ENV_VAR: config.to_env()})
    assert log is not None
    log.scalar("/x", 1.0)
    log.close()
    recording.finish(config, out)
    port = free_port()
    proc = procs.python("rra_agent", "view", str(out), "--web", "--port", str(port),
                        env={"BROWSER": "/bin/true"}, name="view")  # fmt: skip

    def page() -> bytes | None:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=1) as r:
                return r.read()
        except OSError:
            return None

    try:
        body = wait_until(page, 30, "the web viewer's page")
    except TimeoutError:
        pytest.fail(procs.log("view"))
    assert b"Rerun" in body
    assert listeners(port) == {"0100007F"}  # 127.0.0.1, nothing else
    found = re.search(rf"at http://127\.0\.0\.1:{port}/\?url=.*127\.0\.0\.1%3A(\d+)%2F",
                      procs.log("view"))  # fmt: skip
    assert found, procs.log("view")
    grpc = int(found.group(1))
    assert listeners(grpc) == {"0100007F"}  # the viewer's data server, too
    proc.send_signal(signal.SIGTERM)
    proc.wait(10)
    children = subprocess.run(["pgrep", "-P", str(proc.pid)], capture_output=True, text=True)
    assert children.stdout == ""
    assert not listeners(port) and not listeners(grpc)


# ---- tools/render_rrd.py ----------------------------------------------------------------------
@pytest.mark.system
def test_render_rrd_saves_a_screenshot_of_the_web_viewer(tmp_path, monkeypatch):
    sys.path.insert(0, str(TOOLS))
    try:
        import render_rrd
    finally:
        sys.path.remove(str(TOOLS))
    if render_rrd.find_chromium() is None:
        pytest.skip("no Chromium on this machine (apt-get install chromium) to render with")
    if importlib.util.find_spec("websockets") is None:
        pytest.skip("no websockets package to drive Chromium with (pip install websockets)")
    out = object_storing_recording(tmp_path, monkeypatch)
    result = render_rrd.render(out, tmp_path / "shot.png", size=(1200, 800), timeout=240)
    png = (tmp_path / "shot.png").read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and len(png) > 20_000
    assert result["loaded_s"] > 0
