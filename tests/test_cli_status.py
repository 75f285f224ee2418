"""`rra status`, `rra events` and `rra param` of a running system, as a new user runs them.

They find the system without ``--system`` when one runs at the endpoint (and list the
systems when several do), list the host agents with their router endpoints and node counts,
fit in 100 columns (``--wide`` for the rest; ``--json`` complete); ``rra events`` hides the
CV updates unless ``--all``, prints a saved log in time order, and its phase totals run
from the triggering context value to the end of execution. On a machine whose two cores are
busy, a running system is still found (no false "no system").
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import pytest
from conftest import ROOT, edit_yaml, package_copy, wait_until
from test_secure_system import secure  # noqa: F401 (the fixture)

from rra_agent.bus import messages as m
from rra_agent.cli import main
from rra_agent.cli.common import WIDTH
from rra_agent.cli.events import EventFilter, format_event
from rra_agent.cli.status import refused_section
from rra_agent.engines.events import phase_durations


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


# ---- a running system -----------------------------------------------------------------------
def test_status_finds_the_one_system_lists_hosts_and_fits(system, bus, capsys) -> None:
    system()
    ep = bus.connect[0]
    rc, out, err = run(["status", "--connect", ep], capsys)
    assert rc == 0, err
    assert out.startswith("system      relay_system (Relay)"), out
    assert max(len(line) for line in out.splitlines()) <= WIDTH, out
    host = next(line for line in out.splitlines() if line.startswith("local "))
    fields = host.split()
    assert fields[1] == "up" and int(fields[2]) >= 9, host  # 6 engine replicas, 3 components
    assert f"listens {ep}" in host

    rc, wide, _ = run(["status", "--connect", ep, "--wide"], capsys)
    assert rc == 0 and "IMPLEMENTATION" in wide
    source = next(line for line in wide.splitlines() if line.startswith("source "))
    assert source.endswith("  rra_agent.nodes.generic.Ticker") and len(source) > WIDTH
    assert "rra_agent.nodes.generic" not in out

    rc, raw, _ = run(["status", "--connect", ep, "--json"], capsys)
    status = json.loads(raw)
    assert {a["host"]: a["listen"] for a in status["host_agents"]} == {"local": [ep]}
    source = next(n for n in status["nodes"] if n["node"] == "source")
    assert source["implementation"] == "rra_agent.nodes.generic.Ticker"
    assert status["stats"] and status["engine"]["running"]


def test_several_systems_at_one_endpoint_are_listed(system, bus, capsys) -> None:
    s = system()
    ep = bus.connect[0]
    # Another system's host agent on the same hub (its liveliness token is all it takes).
    token = s.client.session.liveliness().declare_token("rra/other_system/hostagent/h2")
    try:
        wait_until(lambda: main(["status", "--connect", ep]) == 1, 10, "the second system")
        for cmd in (["status"], ["events"], ["param", "source"]):
            capsys.readouterr()
            assert main([*cmd, "--connect", ep]) == 1
            err = capsys.readouterr().err.strip()
            assert err == (
                f"rra {cmd[0]}: 2 systems run at {ep} (other_system, relay_system): choose "
                "one with --system NAME"
            )
        rc, out, _ = run(["status", "--connect", ep, "--system", "relay_system"], capsys)
        assert rc == 0 and "relay_system" in out
        rc, _, err = run(["status", "--connect", ep, "--system", "nope"], capsys)
        assert rc == 1
        assert err.strip() == f"rra status: no rra system 'nope' answers at {ep}; start one " \
            "with `rra up PKG` or give --connect ENDPOINT"  # fmt: skip
    finally:
        token.undeclare()


def test_param_without_system(system, bus, capsys) -> None:
    system()
    rc, out, err = run(["param", "source", "--connect", bus.connect[0]], capsys)
    assert rc == 0, err
    assert "value = " in out


def test_param_of_a_node_that_is_not_running(system, bus, capsys) -> None:
    """One rule both ways: a node not running now (filtered: Direct is selected) takes a
    value as the one it will start with, and its read shows what it will start with; both
    say it is not running; it starts with it. An unknown node is refused at once."""
    s = system()
    ep = bus.connect[0]
    started = time.monotonic()
    rc, out, err = run(["param", "nosuch", "--connect", ep], capsys)
    elapsed = time.monotonic() - started
    assert (rc, out) == (1, "")
    assert err == ("rra param: no node 'nosuch' in system 'relay_system' (its nodes: direct, "
                   "filtered, sink, source)\n")  # fmt: skip
    assert elapsed < 2.0, f"{elapsed:.2f} s"  # generous: the engine knows its model (was 2.2 s)
    header = "filtered is not running; it will start with:\n"
    assert run(["param", "filtered", "--connect", ep], capsys)[1:] == (
        header + "offset = 100.0\n", "")
    assert run(["param", "filtered", "offset=3", "--connect", ep], capsys)[1] == (
        header + "offset = 3.0\n")
    assert run(["param", "filtered", "--connect", ep], capsys)[1] == header + "offset = 3.0\n"
    s.set_level(9.0)  # Filtered: filtered starts, with the operator's value
    s.wait(lambda st: s.node(st, "filtered")["state"] == "RUNNING", "filtered running")
    rc, out, _ = run(["param", "filtered", "--connect", ep], capsys)
    assert (rc, out) == (0, "offset = 3.0\n")


def test_a_busy_machine_still_finds_the_system(system, bus, hog, capsys) -> None:
    """Both cores busy: every ``rra status`` finds the running system (no false negative)."""
    system()
    for _ in range(5):
        rc, out, err = run(["status", "--connect", bus.connect[0]], capsys)
        assert rc == 0, err
        assert "relay_system" in out


def watch(ep: str, stdout: int, tmp_path: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "rra_agent", "status", "--watch", "0.2", "--connect", ep],
        stdout=stdout, stderr=subprocess.STDOUT, cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip


def test_watch_writes_no_escape_codes_into_a_pipe(system, bus, tmp_path: Path) -> None:
    """Into a pipe: the refreshes one after the other, each after a time line; on a terminal
    (a pseudo-terminal here): the screen cleared before each."""
    import pty
    import select

    system()
    ep = bus.connect[0]
    out = tmp_path / "watch.out"
    with out.open("wb") as f:
        proc = watch(ep, f.fileno(), tmp_path)
    try:
        wait_until(lambda: out.read_bytes().count(b"\nsystem ") >= 2, 60, "two refreshes")
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
    text = out.read_bytes()
    assert b"\x1b" not in text, text[:200]
    assert text.startswith(b"system      relay_system")
    lines = text.decode().splitlines()
    assert any(line.startswith("-- ") and line[3:].count(":") == 2 for line in lines)
    master, slave = pty.openpty()
    proc = watch(ep, slave, tmp_path)
    os.close(slave)
    seen = b""
    try:
        def cleared() -> bool:
            nonlocal seen
            if select.select([master], [], [], 0.2)[0]:
                seen += os.read(master, 65536)
            return seen.count(b"\x1b[2J\x1b[H") >= 2

        wait_until(cleared, 60, "two redraws on the terminal")
    finally:
        proc.send_signal(signal.SIGINT)
        proc.wait(30)
        os.close(master)


# ---- rra events -----------------------------------------------------------------------------
def test_events_shows_swaps_not_cv_updates(system, bus, tmp_path: Path) -> None:
    s = system()
    ep = bus.connect[0]
    shown = tmp_path / "events.out"
    with shown.open("wb") as out:
        follower = subprocess.Popen(
            [sys.executable, "-m", "rra_agent", "events", "--connect", ep],
            stdout=out, stderr=subprocess.STDOUT, cwd=ROOT,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )  # fmt: skip
    try:
        wait_until(lambda: "following system 'relay_system'" in shown.read_text(), 30,
                   "rra events following")  # fmt: skip
        for level in (2.0, 3.0, 7.0):  # two CV updates (Gain), then a swap (Filtered)
            s.set_level(level)
            s.wait(lambda st, v=level: st["engine"]["cv"].get("Gain") == v, f"Gain {level}")
        wait_until(lambda: "start filtered" in shown.read_text(), 15, "the swap shown")
    finally:
        follower.send_signal(signal.SIGINT)
        follower.wait(10)
    text = shown.read_text()
    assert "Traceback" not in text
    assert "param: operator set source" in text
    assert text.count("applied selection") == 1, text  # the swap; not the two CV updates
    assert "node  local/filtered: STOPPED -> STARTING" in text

    log = str(s.run_dir / "events.jsonl")
    default = run_rra_out("events", "--log", log)
    everything = run_rra_out("events", "--log", log, "--all")
    applied = [
        e
        for e in s.events()
        if isinstance(e, m.AdaptationEvent) and e.kind == "adaptation" and e.outcome == "ok"
    ]
    assert everything.count("applied selection") == len(applied) >= 3
    # Shown by default: the first deployment and the swap (the CV updates are not).
    assert default.count("applied selection") == 2, default
    swap = next(e for e in applied if any(p.startswith("start filtered") for p in e.plan))
    d = swap.durations
    assert d["total"] == pytest.approx(d["decide"] + d["deliver"] + d["plan"] + d["execute"])
    # The number an event says is the number of plan lines it shows (was "3 step(s)" above
    # five lines: the plan's steps, not its actions). The deployment says it too.
    counted = [e for e in s.events() if isinstance(e, m.AdaptationEvent) and e.plan]
    assert {e.kind for e in counted} >= {"deploy", "adaptation"}
    for ev in counted:
        said = re.search(r"(\d+) actions?\b", ev.message)
        assert said is not None, ev.message
        shown = format_event(ev).splitlines()
        actions = [line for line in shown if line.startswith("    - ") and "- note:" not in line]
        assert int(said[1]) == len(actions), (ev.message, shown)


def run_rra_out(*args: str) -> str:
    r = subprocess.run([sys.executable, "-m", "rra_agent", *args], capture_output=True,
                       text=True, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                       timeout=60, check=True)  # fmt: skip
    return r.stdout


def node_state(stamp: float, node: str, state: str) -> m.NodeState:
    return m.NodeState(stamp=stamp, node=node, host="local", state=state)  # type: ignore[arg-type]


def applied(stamp: float, features: list[str], *plan: str) -> m.AdaptationEvent:
    return m.AdaptationEvent(
        stamp=stamp,
        kind="adaptation",
        message=f"applied selection {sorted(features)}, {len(plan)} actions",
        outcome="ok",
        plan=list(plan),
    )


def test_a_saved_log_is_printed_in_time_order(tmp_path: Path, capsys) -> None:
    """events.jsonl is appended to in arrival order by several processes: a swap's node
    states reach the leader after its own adaptation event; a standby writes its own."""
    t = 1000.0
    written = [
        applied(t + 0.050, ["B"], "stop a (1.0 ms) ok", "start b (2.0 ms) ok"),
        node_state(t + 0.010, "a", "STOPPING"),
        node_state(t + 0.020, "a", "STOPPED"),
        node_state(t + 0.030, "b", "STARTING"),
        m.AdaptationEvent(stamp=t, kind="takeover", message="resolution-b leads"),
        node_state(t + 0.040, "b", "RUNNING"),
    ]
    log = tmp_path / "events.jsonl"
    log.write_bytes(b"".join(msgspec.json.encode(e) + b"\n" for e in written))
    rc, out, _ = run(["events", "--log", str(log), "--json"], capsys)
    assert rc == 0
    stamps = [json.loads(line)["stamp"] for line in out.splitlines()]
    assert stamps == sorted(e.stamp for e in written)


def test_refused_samples_are_the_monitor_leaders_per_source_and_reason_in_100_columns():
    def monitor(leading: int, count: int) -> dict:
        rows = [
            {
                "source": "robot_driver.battery",
                "reason": "missing_field",
                "count": count,
                "last": "BatteryState: Object missing required field `voltage`\n" * 5,
            },
            {"source": "laser_scanner.scan", "reason": "non_finite", "count": 2},
        ]
        return {"role": "monitor", "counters": {"leading": leading}, "refused": rows}

    status = {"stats": {"monitor:monitor-b": monitor(0, 3), "monitor:monitor-a": monitor(1, 4),
                        "node:sink": {"role": "node", "counters": {}}}}  # fmt: skip
    lines = refused_section(status)
    assert lines[0].split() == ["REFUSED", "SAMPLES", "OF", "REASON", "COUNT", "LAST"]
    assert lines[1].split()[:3] == ["robot_driver.battery", "missing_field", "4"]
    assert lines[2].split() == ["laser_scanner.scan", "non_finite", "2"]
    assert max(map(len, lines)) <= WIDTH and len(refused_section(status, wide=True)[1]) > WIDTH
    assert refused_section({"stats": {}}) == []


def test_the_filter_hides_only_cv_updates() -> None:
    f = EventFilter(["A"])
    kept = [
        applied(1.0, ["A"], "set_params sink  (1.0 ms) ok"),  # a CV update: hidden
        applied(2.0, ["B"], "set_params sink  (1.0 ms) ok"),  # a new selection: shown
        applied(3.0, ["B"], "stop a (1.0 ms) ok", "start b (1.0 ms) ok"),  # a swap: shown
        applied(4.0, ["B"]),  # nothing to do, same selection: hidden
        m.AdaptationEvent(stamp=5.0, kind="conflict", message="rules R1, R2 disagree"),
        m.AdaptationEvent(stamp=6.0, kind="override", message="operator forces X on"),
        m.AdaptationEvent(stamp=7.0, kind="param", message="operator set sink"),
        m.AdaptationEvent(
            stamp=8.0,
            kind="adaptation",
            message="adaptation failed, rolled back: boom",
            level="error",
            outcome="rolled_back",
        ),
        node_state(9.0, "b", "BACKOFF"),
    ]
    assert [e.stamp for e in kept if f.shows(e)] == [2.0, 3.0, 5.0, 6.0, 7.0, 8.0, 9.0]
    # Following from an unknown selection: the first applied adaptation is shown.
    assert EventFilter().shows(applied(1.0, ["A"], "set_params sink  (1.0 ms) ok"))


def test_events_fit_in_100_columns_unless_wide() -> None:
    ev = applied(1.0, [f"Feature{i}" for i in range(30)], "set_params sink  (1.0 ms) ok")
    ev = msgspec.structs.replace(
        ev,
        cause=[m.FiredRule(rule=f"Rule{i}", action="activate_feature(F)") for i in range(20)],
        durations={"decide": 0.001, "total": 0.002},
    )
    narrow, wide = format_event(ev, wide=False), format_event(ev, wide=True)
    assert max(map(len, narrow.splitlines())) <= WIDTH
    assert max(map(len, wide.splitlines())) > WIDTH
    assert narrow.split() == wide.split()  # the same words, only wrapped


# ---- phase totals ---------------------------------------------------------------------------
def test_the_total_runs_from_the_newest_value_read() -> None:
    """A rule read a flag set 3.4 s ago and a value computed 10 ms before the decision: the
    trigger is the new value, not the old flag (the total was 3.4 s)."""
    t = 1000.0
    d = phase_durations(
        [t - 3.4, t - 0.010], decided=t, received=t + 0.002, plan=0.001, execute=0.020
    )
    assert d["decide"] == pytest.approx(0.010)
    assert d["deliver"] == pytest.approx(0.002)
    assert d["total"] == pytest.approx(0.033)
    assert d["total"] == pytest.approx(d["decide"] + d["deliver"] + d["plan"] + d["execute"])


def test_the_total_without_values_read_starts_at_the_decision() -> None:
    t = 1000.0
    d = phase_durations([], decided=t, received=t + 0.002, plan=0.001, execute=0.020, switch=0.01)
    assert d == pytest.approx(
        {
            "decide": 0.0,
            "deliver": 0.002,
            "plan": 0.001,
            "execute": 0.020,
            "total": 0.023,
            "switch": 0.01,
        }
    )


def test_phases_are_never_negative_across_clocks() -> None:
    t = 1000.0  # a value stamped by a host whose clock is ahead
    d = phase_durations([t + 0.5], decided=t, received=t - 0.001, plan=0.001, execute=0.002)
    assert min(d.values()) >= 0.0


def test_an_operator_with_certificates_names_the_system(secure, capsys) -> None:  # noqa: F811
    """With --certs, the hub's access control lets an operator see its own system's keys
    only, so a system is not found unless named: the line says so; named, it is found."""
    endpoint, certs, _ = secure
    args = ["--certs", str(certs / "operator"), "--connect", endpoint]
    rc, _, err = run(["status", *args], capsys)
    assert rc == 1
    assert err.strip().endswith("give --system NAME"), err

    def engine_up() -> str | None:
        rc, out, err = run(["status", *args, "--system", "relay_system"], capsys)
        assert rc == 0, err
        return out if out.startswith("system      relay_system (Relay)") else None

    out = wait_until(engine_up, 60, "the engine's status", interval=0.2)
    assert any(line.split()[:2] == ["local", "up"] for line in out.splitlines()), out


@pytest.mark.skipif(
    not os.access("/dev/cpu_dma_latency", os.W_OK), reason="/dev/cpu_dma_latency is not writable"
)
def test_status_shows_the_cpu_latency_a_host_agent_holds(system, bus, tmp_path, capsys) -> None:
    """What is in effect: ``agents: {cpu_latency_us: 0}`` held by the host agent is in its
    host's line and in ``--json`` (the kernel's value, not the model's)."""
    pkg = package_copy(tmp_path)
    edit_yaml(pkg / "rra.yaml", lambda d: d.update(agents={"cpu_latency_us": 0}))
    system(pkg)
    ep = bus.connect[0]
    rc, out, err = run(["status", "--connect", ep], capsys)
    assert rc == 0, err
    host = next(line for line in out.splitlines() if line.startswith("local "))
    assert host.endswith(", CPU latency 0 us"), host
    rc, raw, _ = run(["status", "--connect", ep, "--json"], capsys)
    assert [a["cpu_latency_us"] for a in json.loads(raw)["host_agents"]] == [0]
