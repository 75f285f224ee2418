"""Saying why a node failed, without processes: `rra_agent.bus.failure` (where in the node's own
code, the report file), the Node SDK's handling of exceptions of node code (`NodeHarness`),
the supervisor's reasons, and how ``rra events``, ``rra status``, the Rerun log and
``rra test`` show a failure. The same with real processes: tests/test_failure_reports.py."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import pytest

from rra_agent.bus import failure
from rra_agent.bus import messages as m
from rra_agent.cli.common import WIDTH
from rra_agent.cli.events import format_event
from rra_agent.cli.status import render
from rra_agent.errors import RraError
from rra_agent.host.supervisor import State, Supervisor
from rra_agent.node import Node, NodeHarness
from rra_agent.node.core import NodeCore
from rra_agent.scenario import runner

HERE = Path(__file__).name
CAMERA = m.Failure(
    type="RuntimeError",
    message="camera /dev/video0 not found",
    where="agv_nodes.py:42",
    function="open_camera",
    during="on_start",
    stamp=1000.0,
    log="/var/log/rra/camera.log",
)


def line_of(fn: Any, token: str) -> int:
    """The line of ``token`` in the source of function ``fn`` (of this file)."""
    import inspect

    lines, first = inspect.getsourcelines(fn)
    return first + next(i for i, text in enumerate(lines) if token in text)


# ---- rra_agent.bus.failure ----------------------------------------------------------------
def _helper() -> None:
    raise KeyError("gain")


def _raises() -> None:
    _helper()


def test_describe_names_the_innermost_frame_of_the_nodes_own_code(tmp_path: Path) -> None:
    try:
        _raises()
    except KeyError as e:
        f = failure.describe(e, "step", roots=[str(Path(__file__).parent)])
    assert (f.type, f.message, f.function, f.during) == ("KeyError", "'gain'", "_helper", "step")
    assert f.where == f"{HERE}:{line_of(_helper, 'raise')}"  # relative to the package root
    assert failure.summary(f) == f"KeyError: 'gain' ({f.where} in _helper, during step)"


def test_a_wrapped_import_error_and_a_syntax_error_are_shown_as_what_raised(tmp_path) -> None:
    (tmp_path / "bad_syntax.py").write_text("x = 1\ndef f(:\n")
    sys.path.append(str(tmp_path))
    try:
        with pytest.raises(SyntaxError) as syntax:
            __import__("bad_syntax")
        f = failure.describe(syntax.value, "import", roots=[str(tmp_path)])
        assert (f.type, f.where) == ("SyntaxError", "bad_syntax.py:2")
        try:
            try:
                __import__("no_such_driver_sdk")
            except ImportError as e:
                raise RraError("cannot import the node's module") from e
        except RraError as e:
            f = failure.describe(e, "import")
        assert (f.type, f.message) == (
            "ModuleNotFoundError",
            "No module named 'no_such_driver_sdk'",
        )
    finally:
        sys.path.remove(str(tmp_path))


def test_a_report_is_written_whole_and_read_once(tmp_path: Path) -> None:
    path = tmp_path / "camera.failure"
    failure.write_report(CAMERA, str(path))
    assert not (tmp_path / "camera.failure.tmp").exists()
    assert failure.take_report(path) == CAMERA
    assert failure.take_report(path) is None  # removed: a later exit is not this one
    path.write_text("{not json")
    assert failure.take_report(path) is None


def test_tail_reads_what_the_process_wrote_since_it_started(tmp_path: Path) -> None:
    log = tmp_path / "tool.log"
    log.write_text("an earlier run's last words\n")
    start = log.stat().st_size
    with log.open("a") as f:
        f.write("probing\n\n  no device /dev/video0  \n")
    assert failure.tail(log, start) == "probing\nno device /dev/video0"
    assert failure.tail(log, log.stat().st_size) == ""
    f = m.Failure(message=failure.tail(log, start))
    assert failure.summary(f) == "last output: no device /dev/video0"


def test_a_reason_carries_the_summary_and_it_can_be_taken_off() -> None:
    why = failure.reason("exited with status 1", CAMERA)
    assert why == (
        "exited with status 1: RuntimeError: camera /dev/video0 not found "
        "(agv_nodes.py:42 in open_camera, during on_start)"
    )
    assert failure.without_summary(why, CAMERA) == "exited with status 1"
    assert failure.details(CAMERA) == [
        "RuntimeError: camera /dev/video0 not found",
        "at agv_nodes.py:42 in open_camera during on_start",
        "log: /var/log/rra/camera.log",
    ]


# ---- the Node SDK -----------------------------------------------------------------------------
class Drifting(Node):
    def on_start(self) -> None:
        self.ticks = 0

    def step(self, now: float) -> None:
        self.ticks += 1
        raise ValueError(f"lost sync at tick {self.ticks}")

    def on_params(self, changed: dict[str, Any]) -> None:
        raise OSError("cannot retune now")


class Quitter(Node):
    def step(self, now: float) -> None:
        sys.exit(3)


def test_a_step_that_raises_is_logged_with_its_traceback_once_and_kept_for_stats() -> None:
    h = NodeHarness(Drifting, params={"gain": 1.0})
    for t in range(5):
        h.step(float(t))
    text = "\n".join(h.logs)
    assert text.count("Traceback (most recent call last):") == 1
    assert all(line.startswith("[node] ") for line in text.splitlines())
    assert sum("step raised" in line for line in h.logs) == 2  # the traceback, then one line
    stats = h.core.stats()
    assert stats.counters["errors"] == 5 and stats.failure is not None
    assert stats.failure.message == "lost sync at tick 5" and stats.failure.during == "step"
    assert stats.failure.where == f"{HERE}:{line_of(Drifting.step, 'raise')}"


def test_a_hook_raising_in_a_control_request_answers_with_its_failure() -> None:
    h = NodeHarness(Drifting, params={"gain": 1.0})
    reply = h.request(m.SetParams(params={"gain": 2.0}))
    assert isinstance(reply, m.Err) and reply.code == "node_error"
    assert reply.failure is not None
    assert (reply.failure.type, reply.failure.during) == ("OSError", "on_params")


def test_on_start_raising_is_marked_and_sys_exit_is_caught_only_in_a_container() -> None:
    class Broken(Node):
        def on_start(self) -> None:
            raise RuntimeError("camera not found")

    with pytest.raises(RuntimeError) as e:
        NodeHarness(Broken)
    assert failure.describe(e.value).during == "on_start"
    h = NodeHarness(Quitter)
    with pytest.raises(SystemExit):  # a node process: it ends with status 3
        h.step(1.0)
    component = NodeCore(h.core.spec, Quitter, h.transport, contained=True)  # in a container
    component.step(2.0)
    assert component.last_error is not None and component.last_error.type == "SystemExit"


# ---- supervision ------------------------------------------------------------------------------
class _Host:
    name = "h1"

    def spawn(self, spec: m.NodeSpec) -> int:
        return 42

    def signal(self, pid: int, sig: int) -> None:
        pass

    def probe(self, name: str, pid: int, timeout: float) -> None:
        pass


def test_the_supervisor_puts_the_failure_on_the_transition_and_keeps_the_last() -> None:
    seen = []
    sup = Supervisor(listener=seen.append)
    sup.add(m.NodeSpec(system="s", name="camera", host="h1", implementation="a.B"), _Host())
    sup.start("camera", 0.0)
    sup.on_exit(42, 1, 0.1, CAMERA)
    crash = seen[-2]  # reported on BACKOFF, then restarted at once (its first crash)
    assert crash.state == State.BACKOFF and crash.failure == CAMERA
    assert crash.reason == failure.reason("exited with status 1", CAMERA)
    assert seen[-1].state == State.STARTING and seen[-1].failure is None
    p = sup.procs["camera"]
    assert (p.last_failure, p.failure) == (crash.reason, CAMERA)
    sup.tick(1.0)  # restarted, ready: the last failure stays on record
    sup.on_ready("camera", 1.1)
    assert sup.procs["camera"].state == State.RUNNING and p.failure == CAMERA
    sup.on_exit(42, -9, 2.0)  # killed: a failure without a report
    assert seen[-1].failure is None and p.failure is None
    assert p.last_failure == "exited with status -9"


# ---- what the tools show ----------------------------------------------------------------------
STATE = m.NodeState(
    stamp=time.time(), node="camera", host="h1", state="BACKOFF", previous="STARTING", pid=7,
    reason=failure.reason("exited with status 1", CAMERA), failure=CAMERA,
)  # fmt: skip


def test_rra_events_shows_the_failure_under_its_node_line() -> None:
    lines = format_event(STATE, wide=False).splitlines()
    assert lines[0].endswith("node  h1/camera: STARTING -> BACKOFF (exited with status 1)")
    assert lines[1:] == [f"    {x}" for x in failure.details(CAMERA)]
    wordy = m.Failure(type="ValueError", message="word " * 60, where="nodes/n.py:1", log="/l")
    fatal = failure.reason("exited with status 1; 5 restarts within 60 s; retrying in 30 s", wordy)
    narrow = format_event(
        m.NodeState(**{**_fields(STATE), "state": "FATAL", "reason": fatal, "failure": wordy}),
        wide=False,
    ).splitlines()
    assert max(map(len, narrow)) <= WIDTH
    assert narrow[1].startswith(" " * 19)  # the transition's own line goes on, indented
    assert narrow[2].startswith("    ValueError: word word")


def _fields(st: m.NodeState) -> dict[str, Any]:
    return {k: getattr(st, k) for k in st.__struct_fields__}


def test_rra_status_lists_each_nodes_last_failure_in_100_columns() -> None:
    step = m.Failure(type="ValueError", message="lost sync", where="n.py:3", during="step",
                     function="step", stamp=time.time())  # fmt: skip
    status = {
        "engine": None,
        "hosts": ["h1"],
        "host_agents": [],
        "nodes": [
            {"node": "camera", "host": "h1", "state": "FATAL", "pid": 7, "restarts": 1,
             "reason": STATE.reason, "failure": _dict(CAMERA)},
            {"node": "drifting", "host": "h1", "state": "RUNNING", "pid": 8, "restarts": 0},
            {"node": "quiet", "host": "h1", "state": "RUNNING", "pid": 9, "restarts": 0},
        ],
        "stats": {"node:drifting": {"counters": {"errors": 12}, "failure": _dict(step)}},
    }  # fmt: skip
    out = render(status).splitlines()
    assert max(map(len, out)) <= WIDTH
    head = out.index(f"{'NODE':<24} {'WHEN':<8} LAST FAILURE")
    rows = out[head + 1 :]
    assert [r.split()[0] for r in rows] == ["camera", "drifting"]
    assert "RuntimeError: camera /dev/video0 not found" in rows[0]
    assert rows[1].endswith("runs on after 12 errors: ValueError: lost sync (n.py:3 in step)")


def _dict(f: m.Failure) -> dict[str, Any]:
    import msgspec

    return msgspec.to_builtins(f)


def test_the_rerun_event_log_gets_a_failure(tmp_path: Path) -> None:
    from rra_agent.viz.rerun_log import ENV_VAR, RerunConfig, open_logger

    cfg = RerunConfig.new("save", "test_system", dir=str(tmp_path / "rec"))
    log = open_logger("unit", {ENV_VAR: cfg.to_env()})
    assert log is not None
    logged: list[tuple[str, Any]] = []
    original = log.rec.log
    log.rec.log = lambda path, item, **kw: (logged.append((path, item)), original(path, item, **kw))  # type: ignore[method-assign]
    try:
        log.node_state(STATE)
    finally:
        log.close()
    texts = {p: i.text.as_arrow_array().to_pylist()[0] for p, i in logged if hasattr(i, "text")}
    assert "RuntimeError: camera /dev/video0 not found" in texts["/events"]
    assert "log: /var/log/rra/camera.log" in texts["/nodes/camera/state"]
    assert log.errors == 0


# ---- rra test ---------------------------------------------------------------------------------
def test_a_crash_is_named_in_the_verdict_and_its_log_outlives_a_passed_run(tmp_path) -> None:
    run_dir = tmp_path / "case"
    (run_dir / "logs").mkdir(parents=True)
    (run_dir / "logs" / "camera.log").write_text("Traceback (most recent call last):\n")
    (run_dir / "events.jsonl").write_text("")
    earlier = m.NodeState(**{**_fields(STATE), "stamp": STATE.stamp - 1.0})
    states = runner.crashed_states([STATE, earlier, m.NodeState(stamp=0.0, node="ok", host="h1",
                                                                state="RUNNING")])  # fmt: skip
    assert states == [STATE]  # the last failure of each node that failed
    crashes = runner.keep_crash_logs(run_dir, states, ())
    assert crashes[0].log == run_dir / "crashed" / "camera.log"  # its failure's log is gone
    assert crashes[0].log.read_text().startswith("Traceback")

    case = type("Case", (), {"id": "camera", "file": "c.scenario.yaml"})()
    run = runner.CaseRun(case, run_dir, crashes=crashes)  # type: ignore[arg-type]
    text = runner.render_crashes([run])
    *head, log = text.splitlines()  # the crash's line is wrapped at 100 columns
    assert " ".join(line.strip() for line in head) == (
        f"camera: node camera crashed (BACKOFF): {failure.summary(CAMERA)}"
    )
    assert max(map(len, head)) <= 100
    assert log == f"    log: {run_dir / 'crashed' / 'camera.log'}"
    described = " ".join(line.strip() for line in runner.describe_failure(run).splitlines())
    assert f"node camera crashed (BACKOFF): {failure.summary(CAMERA)}" in described
    (run_dir / runner.RESULTS).write_text(text)
    runner.prune(run)
    assert sorted(p.name for p in run_dir.iterdir()) == ["crashed", "results.txt"]
