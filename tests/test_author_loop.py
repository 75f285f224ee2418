"""The rule author's loop against a running system (issue 24, items 1, 2, 3 and 6): what the
monitor sees now (``rra status``, ``rra watch``), injecting from the terminal (``rra
inject``), why a selection is what it is (``rra why``, the selection's and the event's
``why``), and what the rules can reach. Real processes: ``rra up`` of tests/data/relay_system
(Level above 5 selects Filtered; Gain follows Level) and of scenarios/quadcopter.
"""

from __future__ import annotations

import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import pytest
from conftest import RELAY_KEYS as K
from conftest import ROOT, listening, package_copy, run_rra

from rra_agent.bus import messages as m
from rra_agent.bus.client import connect_system, engine_request, gather, wait_until
from rra_agent.cli.common import WIDTH
from rra_agent.errors import RraError

SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
CTX = m.Codec[m.CtxMessage](m.CtxMessage)
QUADCOPTER = ROOT / "scenarios" / "quadcopter"

#: Written after PathRule: for a Level above 3 it selects Filtered where PathRule wants Direct.
SAFETY = "\nrule Safety:\n    if (cdm.Level > 3)\n        activate_feature(Filtered)\n"


def rra(sys_, *args: str) -> subprocess.CompletedProcess[str]:
    return run_rra(*args, "--system", "relay_system", "--connect", sys_.connect)


def one_line_error(out: subprocess.CompletedProcess[str], text: str) -> None:
    assert out.returncode == 1, out.stdout
    assert "Traceback" not in out.stderr
    (line,) = out.stderr.strip().splitlines()
    assert text in line, line


def fits(text: str) -> None:
    too_wide = [line for line in text.splitlines() if len(line) > WIDTH]
    assert not too_wide, too_wide


def decoded(payload: bytes) -> m.Selection | None:
    """A selection, or None for anything else (--hostile puts garbage on the key too)."""
    try:
        msg = SEL.decode(payload)
    except msgspec.MsgspecError:
        return None
    return msg if isinstance(msg, m.Selection) else None


def explains(client) -> bool:
    """The Adaptation Engine leader answers ``rra why`` (it has resumed)."""
    try:
        engine_request(client, "adaptation", m.Explain(), 2.0)
    except RraError:
        return False
    return True


def events_of(sys_, kind: str) -> list[m.AdaptationEvent]:
    return [e for e in sys_.events() if getattr(e, "kind", "") == kind]


def with_derived(tmp_path: Path) -> Path:
    """relay_system with a derived measurement: whether the sink's implementation is
    available (its monitor computes it from the Run-time Resolution Engine's state)."""
    pkg = package_copy(tmp_path)
    meas = pkg / "measurements.yaml"
    meas.write_text(meas.read_text() + "  - {name: SinkUp, type: bool, available: sink}\n")
    return pkg


# ---- 1. the context, live ----------------------------------------------------------------------
def test_status_shows_every_measurement_with_its_value_age_and_source(system, bus, tmp_path):
    sys_ = system(with_derived(tmp_path))
    sys_.connect = bus.connect[0]
    sys_.set_level(4.5)
    sys_.wait(lambda s: s["engine"]["cv"].get("Gain") == 4.5, "Level 4.5 decided")
    out = rra(sys_, "status")
    assert out.returncode == 0, out.stderr
    fits(out.stdout)
    rows = {line.split()[0]: line for line in out.stdout.splitlines() if line.strip()}
    assert "MEASUREMENT" in rows
    assert rows["Level"].split()[1] == "4.5" and "source.out (sent" in rows["Level"]
    assert rows["SinkUp"].split()[1] == "true" and "available: sink" in rows["SinkUp"]
    out = rra(sys_, "status", "--json")
    context = {c["name"]: c for c in msgspec.json.decode(out.stdout)["context"]}
    level = context["Level"]
    assert level["value"] == 4.5 and set(level["sources"]) == {"source.out"}
    assert 0 <= time.time() - level["stamp"] < 5 and level["from"] == "source.out"
    assert context["SinkUp"]["derived"] and context["SinkUp"]["value"] is True


def test_watch_prints_a_line_per_change_until_the_system_stops(system, bus, procs, tmp_path):
    sys_ = system(with_derived(tmp_path))
    sys_.connect = bus.connect[0]
    out = rra(sys_, "watch", "Levle")
    one_line_error(out, "no measurement 'Levle' (did you mean Level?)")
    watch = subprocess.Popen(
        [sys.executable, "-m", "rra_agent", "watch", "--connect", sys_.connect],  # all
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
    )  # fmt: skip
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(watch.stdout), daemon=True)
    reader.start()
    try:
        wait_until(lambda: any(" Level = 1 " in x for x in lines), 20, "the current value")
        wait_until(lambda: any(" SinkUp = true" in x for x in lines), 20, "a derived one")
        for level in (2.5, 3.5):
            sys_.set_level(level)
            text = f" Level = {level:g} "
            wait_until(lambda t=text: any(t in x for x in lines), 20, text)
        assert sys_.stop() == 0
        assert watch.wait(30) == 0
    finally:
        if watch.poll() is None:
            watch.kill()
    reader.join(5)
    changes = [x for x in lines if " Level = " in x]
    assert [x.split(" Level = ")[1].split()[0] for x in changes] == ["1", "2.5", "3.5"]
    assert all("(source.out sent " in x and len(x.rstrip()) <= WIDTH for x in changes)
    assert "stopped" in lines[-1]


# ---- 2. inject from the terminal ---------------------------------------------------------------
def test_a_measurement_override_drives_the_rules_for_its_duration(system, bus):
    sys_ = system()
    sys_.connect = bus.connect[0]
    out = rra(sys_, "inject", "measurement", "Level=7", "--for", "3s")
    assert out.returncode == 0, out.stderr
    assert out.stdout.startswith("Level = 7.0 (override) until ")
    st = sys_.wait(lambda s: "filtered" in s["engine"]["running"], "Filtered, from the override")
    (level,) = [c for c in st["context"] if c["name"] == "Level"]
    assert level["value"] == 7.0 and "@" in level["override"]
    status = rra(sys_, "status").stdout
    assert "7 OVERRIDE" in status and "override by " in status, status
    why = rra(sys_, "why", "Filtered").stdout  # the value the rule read was the operator's
    assert "by rule PathRule: activate_feature(Filtered)" in why, why
    assert "reading Level = 7.0 (override by " in why, why
    (event,) = events_of(sys_, "injection")
    assert event.injection is not None and event.injection.kind == "measurement"
    assert event.injection.target == "Level" and event.operator and "@" in event.operator
    # the time is up: the computed Level (1) again, and the rules follow it
    sys_.wait(lambda s: "direct" in s["engine"]["running"], "Direct again after 3 s", 20)
    ended = wait_until(lambda: len(events_of(sys_, "injection")) == 2, 10, "the end event")
    assert ended and "ended" in events_of(sys_, "injection")[1].message
    log = " ".join(run_rra("events", "--log", str(sys_.run_dir / "events.jsonl")).stdout.split())
    assert "+Filtered by PathRule: activate_feature(Filtered) reading Level=7 (override " in log
    # computed: the value's time of day, not "override ..."
    assert re.search(r"by PathRule: activate_feature\(Direct\) reading Level=1 \(\d\d:", log), log


def test_bad_injections_are_refused_in_one_line_and_change_nothing(system, bus, request):
    sys_ = system()
    sys_.connect = bus.connect[0]
    if not request.config.getoption("--hostile"):  # it subscribes to every key, inject/** too
        text = "no process of system relay_system takes injections"
        one_line_error(rra(sys_, "inject", "break_motor", "2"), text)
    for args, text in (
        (("measurement", "Lvl=7"), "no measurement 'Lvl' (did you mean Level?)"),
        (("measurement", "Level=high"), "Level is a float measurement: 'high' is not a number"),
        (("measurement", "Level=1e9"), "Level may not be 1000000000.0, outside [-1000, 1000]"),
        (("measurement", "Level=nan"), "Level may not be nan"),
        (("measurement", "Level=7", "--for", "soon"), "expected a duration"),
        (("set_params", "source", "value=high"), "source"),
        (("set_params", "nobody", "value=1"), "no node 'nobody'"),
        (("relay", "x"), "expected key=value arguments"),
    ):
        one_line_error(rra(sys_, "inject", *args), text)
    st = sys_.gather()
    assert "direct" in st["engine"]["running"] and st["engine"]["cv"]["Gain"] == 1.0
    assert not events_of(sys_, "injection")


def test_set_params_is_an_injection_event(system, bus):
    sys_ = system()
    sys_.connect = bus.connect[0]
    out = rra(sys_, "inject", "set_params", "source", "value=7")
    assert out.returncode == 0 and out.stdout.strip() == "set source: value=7.0", out.stderr
    sys_.wait(lambda s: "filtered" in s["engine"]["running"], "Filtered")
    (event,) = events_of(sys_, "injection")
    assert event.injection is not None and event.injection.kind == "set_params"
    assert event.injection.target == "source" and event.injection.args == {"value": 7.0}
    assert "@" in event.operator and not events_of(sys_, "param")


def test_a_forged_override_is_refused_and_counted(system, bus):
    """A client that is not the Context Monitor leader puts an 'override' of Level on the
    bus: without the leader's fence (none, or one naming a real replica with another epoch or
    instance) the Adaptation Engine refuses it, and the rules never see Level 9."""
    sys_ = system()
    sys_.connect = bus.connect[0]
    session = sys_.client.session
    leader = sys_.leader(sys_.gather(), "monitor")
    fences = [
        None,
        m.Fence(epoch=999, leader=leader),
        m.Fence(epoch=1, leader=leader, instance="x"),
    ]
    deciding = sys_.leader(sys_.gather(), "adaptation")
    seen: list[m.Selection] = []  # the Adaptation Engine leader's (--hostile forges others)
    sub = session.declare_subscriber(K.selection, lambda s: seen.extend(
        x for x in [decoded(s.payload.to_bytes())] if x and x.fence and x.fence.leader == deciding
    ))  # fmt: skip

    def rejected() -> int:
        stats = gather(sys_.client, timeout=1.0)["stats"]
        return sum(v.get("rejected", 0) for k, v in stats.items() if k.startswith("adaptation:"))

    before = rejected()
    pub = session.declare_publisher(K.ctx("Level"))
    try:
        deadline = time.monotonic() + 3.0
        while time.monotonic() < deadline:  # for 3 s, ten a second
            for fence in fences:
                msg = m.Measurement(name="Level", value=9.0, stamp=time.time(),
                                    override="mallory", fence=fence)  # fmt: skip
                pub.put(CTX.encode(msg))
            time.sleep(0.1)
        wait_until(lambda: rejected() >= before + 3 * 20, 10, "the refusals counted")
    finally:
        pub.undeclare()
        sub.undeclare()
    assert seen and not [x for x in seen if "Filtered" in x.features or x.cv.get("Gain") == 9.0]
    st = sys_.gather()
    assert "direct" in st["engine"]["running"] and st["engine"]["cv"]["Gain"] == 1.0


# ---- 3. why ----------------------------------------------------------------------------------
def test_the_selection_names_the_rule_that_changed_it_and_what_it_overruled(system, bus, tmp_path):
    pkg = package_copy(tmp_path)
    (pkg / "adaptation.rra").write_text((pkg / "adaptation.rra").read_text() + SAFETY)
    sys_ = system(pkg)
    sys_.connect = bus.connect[0]
    seen: list[m.Selection] = []
    sub = sys_.client.session.declare_subscriber(K.selection, lambda s: seen.extend(
        x for x in [decoded(s.payload.to_bytes())] if x and x.why
    ))  # fmt: skip
    try:
        sys_.set_level(4.0)  # PathRule wants Direct; Safety, written later, selects Filtered
        sys_.wait(lambda s: "filtered" in s["engine"]["running"], "Filtered by Safety")
        sel = wait_until(
            lambda: next((x for x in seen if "Filtered" in x.features), None), 10, "the selection"
        )
    finally:
        sub.undeclare()
    assert {c.rule for c in sel.cause} == {"Safety", "GainRule"}  # not PathRule: it lost
    why = {w.target: w for w in sel.why}
    filtered = why["Filtered"]
    assert [f.rule for f in filtered.by] == ["Safety"]
    assert filtered.by[0].values == {"Level": 4.0} and filtered.by[0].reads["Level"] > 0
    assert [(o.rule, o.why) for o in filtered.overruled] == [("PathRule", "later_rule")]
    # the adaptation event that applied it says the same
    event = wait_until(
        lambda: next(
            (e for e in events_of(sys_, "adaptation") if "Filtered" in {w.target for w in e.why}),
            None,
        ),
        10,
        "the adaptation event of Filtered",
    )
    assert {w.target for w in event.why} == {"Filtered", "Direct", "Gain"}
    assert {c.rule for c in event.cause} == {"Safety", "GainRule"}
    log = run_rra("events", "--log", str(sys_.run_dir / "events.jsonl"))
    fits(log.stdout)
    assert "-Direct +Filtered by Safety: activate_feature(Filtered) reading Level=4" in log.stdout
    assert "overruled PathRule: activate_feature(Direct) (wants on)" in log.stdout
    # rra why: the current state, and what is overruled now
    out = rra(sys_, "why", "Filtered")
    assert out.returncode == 0, out.stderr
    fits(out.stdout)
    assert "by rule Safety: activate_feature(Filtered)" in out.stdout
    assert "reading Level = 4.0 (computed " in out.stdout
    assert "overruled PathRule: activate_feature(Direct)" in out.stdout
    assert "written later, wins" in out.stdout
    out = rra(sys_, "why")
    fits(out.stdout)
    assert "reachable   2 run-time configurations" in out.stdout, out.stdout
    one_line_error(rra(sys_, "why", "Filterd"), "did you mean Filtered?")


def test_why_names_an_operator_override(system, bus):
    sys_ = system()
    sys_.connect = bus.connect[0]
    assert rra(sys_, "select", "Filtered=on").returncode == 0
    sys_.wait(lambda s: "filtered" in s["engine"]["running"], "Filtered forced")
    out = rra(sys_, "why", "Filtered", "Direct")
    assert out.returncode == 0, out.stderr
    assert "an operator forced Filtered on" in out.stdout
    assert "overruled PathRule: activate_feature(Direct)" in out.stdout


# ---- 6. reachable, and the README's quadcopter path ------------------------------------------
@pytest.mark.system
def test_break_a_motor_from_the_terminal_and_ask_why(procs, bus, tmp_path):
    """README: `rra up scenarios/quadcopter`, then `rra inject break_motor 2`."""
    port = int(bus.connect[0].rsplit(":", 1)[1])
    up = procs.python("rra_agent", "up", str(QUADCOPTER), "--run-dir", str(tmp_path / "run"),
                      "-q", "--connect", bus.connect[0], "--no-multicast", name="up")  # fmt: skip
    wait_until(lambda: up.poll() is not None or listening(port), 60, "rra up", interval=0.05)
    connect = ("--connect", bus.connect[0])
    with connect_system(bus, "quadcopter") as client:

        def selection() -> list[str]:
            eng = gather(client, timeout=1.0)["engine"] or {}
            return eng.get("effective", [])

        wait_until(lambda: "Standard" in selection(), 60, "the deployment", interval=0.1)
        wait_until(lambda: explains(client), 60, "the Adaptation Engine leader", interval=0.1)
        out = run_rra("status", "--reachable", *connect)
        assert "2 run-time configurations" in out.stdout and "*Standard | Proploss" in out.stdout
        out = run_rra("inject", "break_motor", "2", *connect)
        assert out.returncode == 0 and out.stdout.strip() == "injected break_motor motor=2", (
            out.stderr
        )
        wait_until(lambda: "Proploss" in selection(), 10, "Proploss", interval=0.05)
    out = run_rra("why", "Proploss", *connect)
    assert "by rule MotorLoss: activate_feature(Proploss)" in out.stdout, out.stdout
    assert "reading WorkingMotors = 3 (computed " in out.stdout
    out = run_rra("why", *connect)
    assert "reachable   1 run-time configuration " in out.stdout  # the choice latches
    assert "never       Standard" in out.stdout
    log = run_rra("events", "--log", str(tmp_path / "run" / "events.jsonl")).stdout
    assert "injection: operator " in log and "injected break_motor motor=2" in log
    assert "+Proploss -Standard by MotorLoss" in log
    up.send_signal(2)
    assert up.wait(30) == 0


@pytest.mark.system
def test_check_warns_of_a_run_time_feature_no_rule_selects(tmp_path):
    pkg = package_copy(tmp_path)
    uvl = pkg / "features.uvl"
    text = uvl.read_text().replace("                    Filtered\n",
                                   "                    Filtered\n                    Bypass\n")
    uvl.write_text(text)  # fmt: skip
    out = run_rra("check", str(pkg))
    assert out.returncode == 0, out.stderr
    line = text.splitlines().index("                    Bypass") + 1
    warning = "warning: no rule can ever select run-time feature Bypass"
    assert out.stdout == f"{uvl}:{line}:21: {warning}\n"
    assert "1 feature(s) never selected" in out.stderr
    out = run_rra("check", str(ROOT / "tests" / "data" / "relay_system"))
    assert out.stdout == "" and "0 feature(s) never selected" in out.stderr
