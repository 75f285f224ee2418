"""A node that fails says why: real host agents and nodes (tests/data/crashy), loopback only.

Each node of the crashy package fails its own way (raises in ``on_start``, its constructor,
its import, ``step``, ``on_stop``; calls ``sys.exit``; an external command exits with a
message). Checked: the node's log keeps the whole traceback, the `NodeState` of the failure
carries the exception's type, message and ``file:line`` in the package's code, ``rra events``
and ``rra status`` show it within 100 columns, a component failing in a container takes no
neighbour down, and ``rra test`` keeps a crashed node's log with the verdict.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import msgspec
import pytest
import zenoh
from conftest import RELAY, ROOT, listening, pid_alive, plant, position, run_rra

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply, wait_until
from rra_agent.bus.data import decode_data, encode_data
from rra_agent.bus.keys import Keys
from rra_agent.deployment import deploy
from rra_agent.host.catalog import Catalog

PACKAGE = Path(__file__).parent / "data" / "crashy"
NODES = (PACKAGE / "crashy_nodes.py").read_text()
K = Keys("crashy")
pytest_plugins = ["pytester"]
WIDTH = 100
#: Waits are conditions with deadlines; these are generous for ``--cpu-hog``.
DEADLINE = 60


def line_of(token: str, text: str = NODES) -> int:
    return position(text, token)[0]


class Watch:
    """The NodeStates the test's session sees."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.states: list[m.NodeState] = []
        codec = m.Codec[m.EventMessage](m.EventMessage)

        def on_event(sample: zenoh.Sample) -> None:
            try:
                msg = codec.decode(sample.payload.to_bytes())
            except (msgspec.DecodeError, msgspec.ValidationError):
                return  # junk (``--hostile``)
            if isinstance(msg, m.NodeState):
                with self.lock:
                    self.states.append(msg)

        self.sub = session.declare_subscriber(K.events, on_event)

    def state(self, node: str, state: str, after: int = 0) -> m.NodeState | None:
        with self.lock:
            return next(
                (s for s in self.states[after:] if s.node == node and s.state == state), None
            )

    def failed(self, node: str) -> m.NodeState | None:
        """The node's first NodeState that came with a failure."""
        with self.lock:
            return next((s for s in self.states if s.node == node and s.failure), None)


CATALOG = Catalog(deploy(str(PACKAGE), []).configured, "h1", package_root=PACKAGE)


def spec_of(name: str) -> m.NodeSpec:
    """A StartNode spec of component ``name`` as the model declares it (ports on ``src``
    and ``<name>/out``)."""
    c = CATALOG.components[name]
    ports = {
        p.name: m.PortSpec(
            direction=p.direction,
            type=p.type,
            keys=[K.data("src") if p.direction == "subscribe" else K.data(f"{name}/out")],
        )
        for p in c.ports
    }
    return m.NodeSpec(
        system="crashy", name=name, host="h1", implementation=c.implementation, ports=ports
    )


@pytest.fixture(params=["fork-server"])
def agent(procs, bus, hub_port, tmp_path, request):
    """A host agent of host h1 of the crashy package (``exec``: every node its own
    ``python -m rra_agent.node``, no fork server); with ``--hostile``, a hostile client on
    its bus."""
    env = {"RRA_FORK_SERVER": "0"} if request.param == "exec" else None
    proc = procs.python(
        "rra_agent.host.agent",
        "--package", str(PACKAGE), "--host", "h1", "--hub", "--log-dir", str(tmp_path / "nodes"),
        "--connect", bus.connect[0], "--no-multicast", "--lease-ms", "500",
        name="agent", env=env,
    )  # fmt: skip
    # A loaded machine can take seconds to start the agent: connect once it listens.
    wait_until(lambda: proc.poll() is not None or listening(hub_port), 60, "the agent's router")
    client = BusClient(bus, "crashy")
    if request.config.getoption("--hostile"):
        procs.spawn([sys.executable, str(ROOT / "tools" / "hostile.py"), bus.connect[0],
                     "crashy"], name="hostile")  # fmt: skip
    try:
        watch = Watch(client.session)
        wait_until(
            lambda: list(client.session.liveliness().get(K.host_alive("h1"), timeout=0.5)),
            DEADLINE,
            "the host agent's token",
        )
        yield proc, client, watch
    finally:
        client.close()


def start(client: BusClient, procs, name: str) -> None:
    """StartNode, again if the query ended without a reply: under ``--cpu-hog`` beside other
    suites one came back empty at once, after the agent had acted on it (not chased; the
    500 ms lease dropping the link is the likeliest); StartNode of a started node is
    answered ``already``."""

    def started() -> m.Reply | None:
        try:  # the first start waits for the fork server to import the package
            return client.host("h1", m.StartNode(spec=spec_of(name)), timeout=DEADLINE)
        except NoReply:
            return None

    reply = wait_until(started, DEADLINE, f"the start of {name} answered", interval=0.1)
    assert isinstance(reply, m.Ok), reply
    procs.watch(reply.result.get("pid"))  # type: ignore[union-attr]


def failed(watch: Watch, name: str) -> m.NodeState:
    return wait_until(lambda: watch.failed(name), DEADLINE, f"{name}'s failure")


def node_log(tmp_path: Path, name: str) -> str:
    return (tmp_path / "nodes" / f"{name}.log").read_text()


# ---- a node process ---------------------------------------------------------------------------
@pytest.mark.parametrize("agent", ["fork-server", "exec"], indirect=True)
def test_a_node_raising_in_on_start_says_what_where_and_keeps_its_traceback(agent, procs, tmp_path):
    """The camera is not plugged in: the NodeState of its exit names the exception, the
    line of the package's code that raised it (in a helper on_start called) and the log;
    the log holds the whole traceback; ListNodes keeps the last failure once it is FATAL."""
    _, client, watch = agent
    start(client, procs, "camera")
    st = failed(watch, "camera")
    f = st.failure
    # BACKOFF; or FATAL when its first start did not get as far as running its code (a
    # fork server slower than its 5 s to answer, seen at a load of 17 on two cores).
    assert st.state in ("BACKOFF", "FATAL") and f is not None
    raised = line_of('raise RuntimeError(f"camera {device} not found")')
    assert (f.type, f.message) == ("RuntimeError", "camera /dev/video0 not found")
    assert f.where == f"crashy_nodes.py:{raised}"
    assert (f.function, f.during) == ("open_camera", "on_start")
    assert f.log == str((tmp_path / "nodes" / "camera.log").resolve())
    assert st.reason.startswith("exited with status 1")
    assert st.reason.endswith(
        ": RuntimeError: camera /dev/video0 not found "
        f"(crashy_nodes.py:{raised} in open_camera, during on_start)"
    )
    log = node_log(tmp_path, "camera")
    assert "Traceback (most recent call last):" in log
    called = line_of('open_camera(self.ctx.param("device", "/dev/video0"))')
    assert re.search(rf'crashy_nodes\.py", line {called}, in on_start', log), log
    assert re.search(rf'crashy_nodes\.py", line {raised}, in open_camera', log), log
    fatal = wait_until(lambda: watch.state("camera", "FATAL"), DEADLINE, "camera FATAL")
    assert fatal.failure is not None and fatal.failure.type == "RuntimeError"
    reply = client.host("h1", m.ListNodes(), timeout=DEADLINE)
    [listed] = msgspec.convert(reply.result, list[m.NodeState])  # type: ignore[union-attr]
    assert listed.state == "FATAL" and listed.failure is not None
    assert listed.failure.where == f"crashy_nodes.py:{raised}"
    assert "RuntimeError: camera /dev/video0 not found" in listed.reason


@pytest.mark.parametrize(
    ("name", "state", "status", "type_", "message", "where", "during"),
    [
        ("badinit", "BACKOFF", 1, "KeyError", "'gain'",
         ("crashy_nodes.py", 'self.gain = {}["gain"]'), "constructor"),
        ("broken", "FATAL", 2, "ModuleNotFoundError", "No module named 'camera_driver_sdk'",
         ("crashy_broken.py", "import camera_driver_sdk"), "import"),
        ("quitter", "BACKOFF", 3, "SystemExit", "3", ("crashy_nodes.py", "        sys.exit(3)"),
         "on_start"),
    ],
)  # fmt: skip
def test_constructor_import_and_exit_failures_say_why(
    agent, procs, tmp_path, name, state, status, type_, message, where, during
):
    _, client, watch = agent
    start(client, procs, name)
    st = failed(watch, name)
    f = st.failure
    assert f is not None and st.state in {state, "FATAL"}  # FATAL: see the camera's test
    line = line_of(where[1], (PACKAGE / where[0]).read_text())
    assert (f.type, f.message, f.where, f.during) == (type_, message, f"{where[0]}:{line}", during)
    assert re.search(rf"(status|exit) {status}\b", st.reason), st.reason
    assert f"{type_}: {message}" in st.reason
    log = node_log(tmp_path, name)
    assert "Traceback (most recent call last):" in log
    assert re.search(rf'{where[0]}", line {line}', log), log


def test_an_external_command_says_its_last_output(agent, procs, tmp_path):
    """No report from a program in any language: its exit status and the last line it
    wrote (here its stderr, through ``sys.exit(message)``)."""
    _, client, watch = agent
    start(client, procs, "tool")
    st = failed(watch, "tool")
    f = st.failure
    assert f is not None and f.type == ""
    assert f.message.splitlines()[-1] == "camera driver: no device /dev/video0"
    assert st.reason == "exited with status 1: last output: camera driver: no device /dev/video0"
    assert f.log == str((tmp_path / "nodes" / "tool.log").resolve())


def test_a_node_raising_in_step_goes_on_and_says_why(agent, procs, tmp_path, bus):
    """Raising in every step after the third: the node runs on (nothing restarts it), its
    log has the traceback once, its Stats the exception, and ``rra status`` shows it."""
    _, client, watch = agent
    start(client, procs, "drifting")
    wait_until(lambda: watch.state("drifting", "RUNNING"), DEADLINE, "drifting RUNNING")

    def stats_failure() -> m.Failure | None:
        reply = client.node("drifting", m.Stats(), timeout=DEADLINE)
        return msgspec.convert(reply.result, m.ProcessStats).failure  # type: ignore[union-attr]

    f = wait_until(stats_failure, DEADLINE, "the exception in Stats")
    raised = line_of('raise ValueError(f"lost sync after {self.ticks - 1} ticks")')
    assert (f.type, f.where, f.during) == ("ValueError", f"crashy_nodes.py:{raised}", "step")
    assert f.message.startswith("lost sync after ")
    lines = lambda: node_log(tmp_path, "drifting").count("step raised")  # noqa: E731
    wait_until(lambda: lines() >= 2, DEADLINE, "a second line")
    log = node_log(tmp_path, "drifting")
    assert log.count("Traceback (most recent call last):") == 1  # then one line at a time
    assert f'crashy_nodes.py", line {raised}, in step' in log
    status = run_rra("status", "--connect", bus.connect[0], "--system", "crashy")
    assert status.returncode == 0, status.stderr
    [row] = [x for x in status.stdout.splitlines() if x.startswith("drifting ") and "Value" in x]
    assert "runs on after" in row and "errors: ValueError: lost sync after" in row
    assert max(map(len, status.stdout.splitlines())) <= WIDTH
    assert watch.state("drifting", "BACKOFF") is None


def test_an_exception_in_on_stop_is_reported_with_the_stop(agent, procs, tmp_path):
    _, client, watch = agent
    start(client, procs, "badstop")
    wait_until(lambda: watch.state("badstop", "RUNNING"), DEADLINE, "badstop RUNNING")
    assert isinstance(client.host("h1", m.StopNode(node="badstop"), timeout=DEADLINE), m.Ok)
    st = wait_until(lambda: watch.state("badstop", "STOPPED"), DEADLINE, "badstop STOPPED")
    f = st.failure
    assert f is not None and (f.type, f.during) == ("OSError", "on_stop")
    raised = line_of('raise OSError("could not park the arm")')
    assert st.reason == (
        f"stopped (exit status 0): OSError: could not park the arm (crashy_nodes.py:{raised} "
        "in on_stop)"
    )
    assert "Traceback (most recent call last):" in node_log(tmp_path, "badstop")


# ---- a component in a container ------------------------------------------------------------
def test_a_failing_component_reports_its_own_exception_and_its_neighbour_goes_on(
    agent, procs, tmp_path
):
    """In container ``box``: c_camera raises in on_start, c_quitter calls sys.exit(3) (it
    used to end the container and so c_relay); each is FATAL with its own exception, the
    traceback is in the container's log under the component's name, and c_relay relays on
    in the same process, never restarted."""
    _, client, watch = agent
    start(client, procs, "c_relay")
    relay = wait_until(lambda: watch.state("c_relay", "RUNNING"), DEADLINE, "c_relay RUNNING")
    n = len(watch.states)
    for name in ("c_camera", "c_quitter"):
        start(client, procs, name)
    camera, quitter = failed(watch, "c_camera"), failed(watch, "c_quitter")
    box_log = str((tmp_path / "nodes" / "box.log").resolve())
    for st, type_, where in (
        (camera, "RuntimeError", 'raise RuntimeError(f"camera {device} not found")'),
        (quitter, "SystemExit", "        sys.exit(3)"),
    ):
        f = st.failure
        assert st.state == "FATAL" and f is not None and f.type == type_
        assert f.where == f"crashy_nodes.py:{line_of(where)}"
        assert (f.during, f.log) == ("on_start", box_log)
        assert st.reason.startswith(f"load refused: {type_}")
    log = (tmp_path / "nodes" / "box.log").read_text()
    assert "[c_camera] Traceback (most recent call last):" in log
    assert "[c_quitter] Traceback (most recent call last):" in log
    assert pid_alive(relay.pid)  # type: ignore[arg-type]
    assert not [s for s in watch.states[n:] if s.node in ("c_relay", "box")]
    pub = client.session.declare_publisher(K.data("src"))
    got: list[dict] = []
    sub = client.session.declare_subscriber(
        K.data("c_relay/out"), lambda s: got.append(decode_data(s.payload.to_bytes()))
    )
    try:
        wait_until(lambda: pub.matching_status.matching, DEADLINE, "c_relay's subscriber")

        def relayed() -> bool:
            pub.put(encode_data({"seq": 1, "value": 1.0}))
            return any(o.get("relay") == "c_relay" for o in got)

        wait_until(relayed, DEADLINE, "a sample through c_relay", interval=0.05)
    finally:
        sub.undeclare()
        pub.undeclare()
    assert ok_pid(client, "c_relay") == relay.pid


def ok_pid(client: BusClient, node: str) -> int:
    reply = client.node(node, m.Ping(), timeout=DEADLINE)
    assert isinstance(reply, m.Ok), reply
    return reply.result["pid"]  # type: ignore[index]


# ---- the tools --------------------------------------------------------------------------------
def test_rra_events_and_rra_status_show_it(agent, procs, bus):
    """``rra events``: the transition on one line, what was raised, where, and the log on
    indented lines under it; ``rra status``: the node's last failure; 100 columns each."""
    _, client, watch = agent
    procs.python("rra_agent", "events", "--connect", bus.connect[0], "--no-multicast",
                 "--system", "crashy", name="events")  # fmt: skip
    wait_until(lambda: "following system" in procs.log("events"), DEADLINE, "rra events to follow")
    start(client, procs, "camera")
    fatal = wait_until(lambda: watch.state("camera", "FATAL"), DEADLINE, "camera FATAL")
    wait_until(lambda: "FATAL" in procs.log("events"), DEADLINE, "rra events to show FATAL")
    lines = procs.log("events").splitlines()
    raised = line_of('raise RuntimeError(f"camera {device} not found")')
    head = next(i for i, x in enumerate(lines) if "h1/camera: STARTING -> BACKOFF" in x)
    assert lines[head].endswith("(exited with status 1)")
    assert lines[head + 1 : head + 4] == [
        "    RuntimeError: camera /dev/video0 not found",
        f"    at crashy_nodes.py:{raised} in open_camera during on_start",
        f"    log: {fatal.failure.log}",  # type: ignore[union-attr]
    ]
    assert max(map(len, lines)) <= WIDTH
    status = run_rra("status", "--connect", bus.connect[0], "--system", "crashy")
    assert status.returncode == 0, status.stderr
    out = status.stdout.splitlines()
    assert max(map(len, out)) <= WIDTH
    assert any(
        x.startswith("camera ") and "RuntimeError: camera /dev/video0 not found" in x for x in out
    ), status.stdout


# ---- rra test ---------------------------------------------------------------------------------
SCENARIO = """\
name: camera
description: Level above 5 selects Filtered, whose node cannot open its camera
package: pkg
duration: 6
timeline:
  - {at: 0.5, name: high, set_params: {node: source, params: {value: 7.0}}}
expect:
  - no orphan process
"""


def camera_package(root: Path) -> Path:
    """A copy of relay_system whose ``filtered`` node cannot open its camera (crashy_nodes)."""
    pkg = root / "pkg"
    shutil.copytree(RELAY, pkg, ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(PACKAGE / "crashy_nodes.py", pkg)
    filtered = "  - name: filtered\n    implementation: "
    plant(pkg, "system.yaml", f"{filtered}rra_agent.nodes.generic.Relay",
          f"{filtered}crashy_nodes.Camera")  # fmt: skip
    return pkg


@pytest.mark.system
def test_rra_test_keeps_a_crashed_nodes_log_with_the_verdict(tmp_path):
    """relay_system whose ``filtered`` node cannot open its camera: the case passes (it
    expects no more than a clean stop), and still the verdict names what filtered raised
    and where, and its log is kept beside the verdict, the rest of the run folder gone."""
    camera_package(tmp_path)
    (tmp_path / "camera.scenario.yaml").write_text(SCENARIO)
    out = tmp_path / "runs"
    r = subprocess.run(
        [sys.executable, "-m", "rra_agent", "test", str(tmp_path / "camera.scenario.yaml"),
         "--out", str(out)],
        capture_output=True, text=True, timeout=240, cwd=ROOT, check=False,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout + r.stderr
    raised = line_of('raise RuntimeError(f"camera {device} not found")')
    crash = re.search(
        # The state the node was in when the run ended (a first crash restarts at once, so it
        # may be stopped by then); the line wraps at 100 columns, the rest indented.
        r"^camera: node filtered crashed \((BACKOFF|FATAL|STOPPED)\): "
        r"RuntimeError: camera /dev/video0 "
        rf"not found\s+\(crashy_nodes\.py:{raised} in open_camera, during on_start\)\n"
        r"    log: (\S+)$",
        r.stdout,
        re.M,
    )
    assert crash is not None, r.stdout
    kept = Path(crash[2])
    assert kept == out / "camera" / "crashed" / "filtered.log"
    assert "Traceback (most recent call last):" in kept.read_text()
    assert sorted(p.name for p in (out / "camera").iterdir()) == ["crashed", "results.txt"]
    assert "node filtered crashed" in (out / "camera" / "results.txt").read_text()


def test_the_pytest_plugin_reports_a_crash_and_keeps_its_log(pytester: pytest.Pytester) -> None:
    """The same case as a pytest item: it passes, its report names what filtered raised,
    and its run folder keeps only the crashed node's log and the verdict."""
    camera_package(pytester.path)
    (pytester.path / "camera.scenario.yaml").write_text(SCENARIO)
    runs = pytester.path / "runs"
    pytester.makeini(f"[pytest]\nrra_scenario_runs = {runs}\n")
    result = pytester.runpytest_subprocess(
        "-p", "no:rra", "-p", "rra_agent.scenario.plugin", "-p", "no:cacheprovider", "-rA"
    )
    result.assert_outcomes(passed=1)
    out = result.stdout.str()
    assert "camera: node filtered crashed (" in out
    # Wrapped at 100 columns: compare the words.
    assert "RuntimeError: camera /dev/video0 not found (crashy_nodes.py:" in " ".join(out.split())
    [run] = runs.iterdir()
    assert sorted(p.name for p in run.iterdir()) == ["crashed", "results.txt"]
    assert "Traceback (most recent call last):" in (run / "crashed" / "filtered.log").read_text()
