"""Scenario files, the expectation language and its evaluation (rra_agent.scenario).

Everything here is in process and fast: parsing, loading with located errors (positions are
computed from the planted text, never hard-coded), evaluation on synthetic recordings, the
verdict's wording, the package copy for replacement overrides, the publish schedule and the
marker that finds a run's processes. Real runs are in tests/test_scenario_plugin.py and
scenarios/.
"""

from __future__ import annotations

import importlib.util
import math
import operator
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from conftest import position

from rra_agent.bus import messages as m
from rra_agent.cli.test import find_scenarios
from rra_agent.errors import ErrorGroup, Location, ModelError, RraError
from rra_agent.package.loader import flatten_errors
from rra_agent.scenario import expectations as x
from rra_agent.scenario.model import Scenario, load_scenario
from rra_agent.scenario.plugin import matches
from rra_agent.scenario.runner import (
    MARKER_ENV,
    CaseRun,
    Row,
    _Run,
    describe_failure,
    evaluate_case,
    marked_pids,
    prepare_package,
    render_rows,
)

ROOT = Path(__file__).resolve().parents[1]
OBJECT_STORING = ROOT / "scenarios" / "object_storing"
RELAY = ROOT / "tests" / "data" / "relay_system"
T0 = 1000.0


# ---- parsing ------------------------------------------------------------------------------------
def test_the_forms_of_the_issue_parse() -> None:
    e = x.parse("feature Proploss selected within 0.1 s after injection motor_failure")
    assert isinstance(e, x.FeatureExpectation)
    assert (e.feature, e.selected) == ("Proploss", True)
    assert e.when == x.When(
        "eventually", x.TimeRef(injection="motor_failure"), x.TimeRef(0.1, "motor_failure")
    )
    e = x.parse("node proploss_controller RUNNING")
    assert isinstance(e, x.StateExpectation) and e.state == "RUNNING"
    assert e.when == x.EVENTUALLY
    e = x.parse("node controller STOPPED at or after motor_failure + 0.5")
    assert e.when == x.When("always", x.TimeRef(0.5, "motor_failure"))
    e = x.parse("measurement WorkingMotors == 3 within 200 ms after motor_failure")
    assert isinstance(e, x.ValueExpectation)
    assert (e.quantity, e.op, e.value) == (x.Quantity("measurement", "WorkingMotors"), "==", 3.0)
    assert e.when.stop == x.TimeRef(0.2, "motor_failure")
    e = x.parse("altitude > 0.5 during [7, 20]")
    assert isinstance(e, x.ValueExpectation) and e.quantity == x.Quantity("name", "altitude")
    assert e.when == x.When("always", x.TimeRef(7.0), x.TimeRef(20.0))
    e = x.parse("swap(controller -> proploss_controller) before motor_failure + 0.1")
    assert isinstance(e, x.EventExpectation) and not e.negated
    assert e.event == x.EventPattern("swap", ("controller", "proploss_controller"))
    assert e.when == x.When("eventually", x.TimeRef(), x.TimeRef(0.1, "motor_failure"))
    assert isinstance(x.parse("no conflict"), x.EventExpectation)
    assert x.parse("no conflict").negated  # type: ignore[attr-defined]
    assert x.parse("no node FATAL") == x.NoStateExpectation("no node FATAL", None, x.ALWAYS)
    assert isinstance(x.parse("no orphan process"), x.NoOrphanExpectation)


W = x.When
TR = x.TimeRef
EP = x.EventPattern


@pytest.mark.parametrize(
    ("text", "field", "expected"),
    [
        ("feature 'Communic. Channel' not selected always", "feature", "Communic. Channel"),
        ("feature Large deselected at end", "when.mode", "end"),
        ("node a RUNNING at 3", "when", W("at", TR(3.0))),
        ("node a RUNNING from k - 1", "when", W("always", TR(-1.0, "k"))),
        ("cv MaxVel == 0.5 +- 0.01 from 2", "tolerance", 0.01),
        ("cv MaxVel == 0.5 ± 0.01", "tolerance", 0.01),
        ("cv MaxVel in [0.4, 0.8] always", "high", 0.8),
        ("measurement SemLoc == Corridor by 3", "value", "Corridor"),
        ('measurement SemLoc != "Room A" after 1', "value", "Room A"),
        ("measurement ObstDist < inf", "value", math.inf),
        ("measurement X == -2.5e1", "value", -25.0),
        ("param nav.max_vel <= 0.5", "quantity", x.Quantity("param", "nav.max_vel")),
        ("param object_detector.roi[3] == 0.4", "quantity.path", (3,)),
        (
            "sim.state.position[2] > 0.5",
            "quantity",
            x.Quantity("data", "sim.state", ("position", 2)),
        ),
        ("data a.b.c.d == true", "value", True),
        ("data a.b.c.d == true", "quantity.path", ("c", "d")),
        ("implementation nav == dynamic", "quantity", x.Quantity("implementation", "nav")),
        ("rewire(radio_switch.radio_in) after x", "event.args", ("radio_switch", "radio_in")),
        ("rewire(radio_switch)", "event.args", ("radio_switch", "*")),
        ("no crash(*) after garbage", "when", W("always", TR(injection="garbage"))),
        ("no restart(a) during [1, 2]", "when", W("always", TR(1.0), TR(2.0))),
        ("no failed adaptation", "event", EP("rollback")),
        ("no node arm_controller", "node", "arm_controller"),
        ("adaptation within 1 s after k", "event", EP("adaptation")),
        ("start(b) after select(ChannelB)", "when.start.event", EP("select", ("ChannelB",))),
        (
            "sample(L) within 1 s after restart(n) + 0.5",
            "when.start",
            TR(0.5, event=EP("restart", ("n",))),
        ),
        ("stop(a) during [1, end - 1]", "when", W("eventually", TR(1.0), TR(-1.0, end=True))),
    ],
)
def test_forms(text: str, field: str, expected: object) -> None:
    assert operator.attrgetter(field)(x.parse(text)) == expected


@pytest.mark.parametrize(
    ("text", "message", "at"),
    [
        ("", "empty expectation", ""),
        ("feature", "expected a feature name, found the end", None),
        ("feature A chosen", "expected 'selected' or 'deselected'", "chosen"),
        ("node a ALIVE", "expected a node state", "ALIVE"),
        ("cv MaxVel ~ 3", "unexpected character '~'", "~"),
        ("cv MaxVel = 3", "expected a comparison", "="),
        ("cv MaxVel == 3 soon", "expected a time clause", "soon"),
        ("cv MaxVel == 3 within 1 s after", "expected a time (seconds", None),
        ("swap(a, b)", "expected '->'", ","),
        ("start(a) at 3", "an event happens at an instant", "at"),
        ("no crash(a) from 2", "an event happens at an instant", "from"),
        ("no nothing", "expected 'orphan process'", "nothing"),
        ("cv A == 3 always extra", "unexpected text after the expectation", "extra"),
        ("measurement A == x +- 1", "a tolerance needs a number", "1"),
        ("param a.b[1.5] == 2", "an index must be an integer", "]"),
    ],
)
def test_syntax_errors_say_what_and_where(text: str, message: str, at: str | None) -> None:
    with pytest.raises(x.ExpectationError) as info:
        x.parse(text)
    assert message in info.value.message
    assert info.value.offset == (len(text) if at is None else text.index(at) if at else 0)


# ---- loading ------------------------------------------------------------------------------------
def test_every_object_storing_scenario_loads_and_binds_every_name() -> None:
    files = find_scenarios([str(OBJECT_STORING)])
    names = {p.name.removesuffix(".scenario.yaml") for p in files}
    assert names == {"radio", "location", "max_velocity", "material", "detection", "faults"}
    cases = [c for f in files for c in load_scenario(f).cases]
    assert {c.id for c in cases} >= {"radio::adaptive", "radio::standby", "radio::control"}
    for c in cases:
        assert c.system == "object_storing" and c.expectations
        assert sum(c.duration for c in cases) < 120  # the suite's budget on 2 cores
        for e in c.expectations:
            if isinstance(e, x.ValueExpectation):
                assert e.quantity.kind != "name", e.text  # bare names are bound
            assert e.location is not None and e.location.file.endswith(".scenario.yaml")
    control = next(c for c in cases if c.id == "radio::control")
    assert not control.adaptation and control.replacement is None
    standby = next(c for c in cases if c.id == "radio::standby")
    assert standby.replacement is not None
    assert standby.replacement.strategy_for("radio_driver_a") == "standby"
    assert ("radio_driver_a", "radio_driver_b") in standby.swap_pairs
    location = next(c for c in cases if c.id == "location")
    assert location.param_nodes() == {"local_navigation", "object_detector"}
    dyn = next(e for e in location.expectations if "== dynamic" in e.text)
    assert dyn.value == "rra_agent.nodes.object_storing.DwaLocalNavigation"  # type: ignore[attr-defined]
    material = next(c for c in cases if c.id == "material")
    assert material.data_topics() == {"arm_controller/status"}
    assert [t.key for t in material.timeline if t.step.publish] == [
        "data/radio_switch/object_material"
    ]
    detection = next(c for c in cases if c.id == "detection")
    assert "Manipulation" not in detection.deployment
    assert "arm_controller" not in {n for t in detection.timeline for n in [t.step.kill]}


def write(tmp_path: Path, text: str, name: str = "s.scenario.yaml") -> Path:
    path = tmp_path / name
    path.write_text(f"package: {RELAY}\n" + text)
    return path


def located(path: Path, token: str, nth: int = 1) -> Location:
    return Location(str(path), *position(path.read_text(), token, nth))


def errors_of(path: Path) -> list[ModelError]:
    with pytest.raises(RraError) as info:
        load_scenario(path)
    errs = flatten_errors(info.value)
    assert all(isinstance(e, ModelError) for e in errs), errs
    return errs  # type: ignore[return-value]


def test_a_schema_error_is_located(tmp_path: Path) -> None:
    p = write(tmp_path, "name: s\ndurashun: 3\n")
    (err,) = errors_of(p)
    assert err.location == located(p, "durashun")
    assert "unknown field 'durashun'" in err.message and "duration" in err.message
    p = write(tmp_path, "name: s\nduration: -1\n")
    (err,) = errors_of(p)
    assert err.location == located(p, "-1") and "Expected `float` > 0.0" in err.message


def test_a_step_needs_exactly_one_action(tmp_path: Path) -> None:
    p = write(tmp_path, "name: s\nduration: 3\ntimeline:\n  - {at: 1, kill: a, freeze: a}\n")
    (err,) = errors_of(p)
    assert err.location == located(p, "{at: 1")
    assert "exactly one action" in err.message and "found: kill, freeze" in err.message


def test_unknown_names_are_located_in_the_expectation_text(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "name: s\nduration: 3\n"
        "timeline:\n"
        "  - {at: 1, name: high, set_params: {node: source, params: {valeu: 7}}}\n"
        "  - {at: 2, kill: sorce}\n"
        "  - {at: 2, publish: {port: sink.in, data: {}}}\n"
        "  - {at: 9, name: late, freeze: source}\n"
        "expect:\n"
        "  - feature Filterd selected within 1 s after high\n"
        '  - "node snk RUNNING from hihg"\n'
        "  - measurement Levl > 5\n"
        "  - param sink.ofset == 7\n"
        "  - cv Gian == 7\n"
        "  - sink.output.value > 1\n"
        "  - altitude > 1\n"
        "  - feature Direct selected within 1 s after\n",
    )
    errs = {e.message.split(" (")[0]: e for e in errors_of(p)}
    expected = {
        "unknown parameter 'valeu' of source": located(p, "valeu"),
        "unknown node 'sorce'": located(p, "sorce"),
        "port 'sink.in' does not publish": located(p, "sink.in"),
        "step at 9 s is after the end of the run": located(p, "9", 1),
        "unknown feature 'Filterd'": located(p, "Filterd"),
        "unknown node 'snk'": located(p, "snk"),
        "unknown injection 'hihg'": located(p, "hihg"),
        "unknown measurement 'Levl'": located(p, "Levl"),
        "unknown parameter 'ofset' of sink": located(p, "sink.ofset"),
        "unknown CV attribute 'Gian'": located(p, "Gian"),
        "component 'sink' has no port 'output'": located(p, "sink.output"),
        "unknown quantity 'altitude'": located(p, "altitude"),
        "expectation: expected a time": Location(
            str(p), located(p, "feature Direct").line, located(p, "feature Direct").col + 40
        ),
    }  # fmt: skip
    assert {k: errs[k].location for k in expected if k in errs} == expected
    assert "did you mean 'Filtered'?" in str(errs["unknown feature 'Filterd'"])
    assert "did you mean 'high'?" in str(errs["unknown injection 'hihg'"])
    assert len(errs) == len(expected)


def test_duplicates_bad_selection_and_aliases(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "name: s\nduration: 3\nselect: [Nope]\ncases:\n  - {name: a}\n  - {name: a}\n",
    )
    (err,) = errors_of(p)
    assert "duplicate case name(s) a" in err.message
    p = write(tmp_path, "name: s\nduration: 3\nselect: [Nope]\n")
    (err,) = errors_of(p)
    assert err.location == located(p, "[Nope]") and "deployment-time selection" in err.message
    p = write(
        tmp_path,
        "name: s\nduration: 3\nquantities: {lvl: measurement Level, out: sink.out.value,"
        " bad: nope}\ntimeline:\n  - {at: 1, name: k, kill: sink}\n"
        "  - {at: 2, name: k, kill: sink}\nexpect: [lvl > 1, out > 1, bad > 1]\n",
    )
    errs = errors_of(p)
    assert [e.location for e in errs] == [located(p, "k, kill", 2), located(p, "nope")]
    assert "duplicate step name 'k' (first at line 6)" in errs[0].message


def test_a_good_file_binds_aliases_features_and_topics(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "name: s\nduration: 3\nquantities: {out: sink.out.value}\n"
        "timeline: [{at: 1, name: k, set_params: {node: source, params: {value: 7.0}}}]\n"
        "expect:\n  - out > 100 within 1 s after k\n  - Level > 5\n  - Gain < 8\n"
        "  - select(Filtered) within 1 s after k\n",
    )
    (case,) = load_scenario(p).cases
    out, level, gain, _ = case.expectations
    assert out.quantity == x.Quantity("data", "sink.out", ("value",), "sink/out")  # type: ignore[attr-defined]
    assert level.quantity == x.Quantity("measurement", "Level")  # type: ignore[attr-defined]
    assert gain.quantity == x.Quantity("cv", "Gain")  # type: ignore[attr-defined]
    assert case.data_topics() == {"sink/out"}
    assert case.initial_features >= {"Direct", "Path", "Tuning"}
    assert case.initial_cv == {"Gain": 0.0}
    assert ("direct", "filtered") in case.swap_pairs
    assert out.location == located(p, "out > 100")


# ---- evaluation -----------------------------------------------------------------------------
def ns(t: float, node: str, state: str, previous: str | None = "STARTING", **kw) -> m.NodeState:
    return m.NodeState(stamp=T0 + t, node=node, host="local", state=state, previous=previous, **kw)  # type: ignore[arg-type]


def sel(t: float, *features: str, cv: dict[str, float] | None = None) -> m.Selection:
    return m.Selection(seq=0, stamp=T0 + t, deployment=["D"], features=list(features), cv=cv or {})


def adapt(t: float, *plan: str, outcome: str = "ok", kind: str = "adaptation") -> m.AdaptationEvent:
    return m.AdaptationEvent(stamp=T0 + t, kind=kind, message="", plan=list(plan), outcome=outcome)  # type: ignore[arg-type]


def meas(t: float, name: str, value: object) -> m.Measurement:
    return m.Measurement(name=name, value=value, stamp=T0 + t)  # type: ignore[arg-type]


def recording(**kw) -> x.Recording:
    base = dict(
        system="s",
        t0=T0,
        end=10.0,
        deployment=["D"],
        initial_features=["A"],
        initial_cv={"V": 0.4},
        swap_pairs=[("a", "b"), ("b", "a")],
        injections=[x.Applied(name="k", at=4.0, stamp=T0 + 4.0)],
        orphans=[],
    )
    return x.Recording(**{**base, **kw})  # type: ignore[arg-type]


REC = recording(
    events=[
        ns(-1.0, "a", "RUNNING"),
        ns(-1.0, "c", "RUNNING", implementation="pkg.Vfh"),
        adapt(0.0, "start a,c (10.0 ms) ok", kind="deploy"),
        ns(4.1, "a", "STOPPING"),
        ns(4.2, "a", "STOPPED", previous="STOPPING"),
        ns(4.3, "b", "RUNNING"),
        adapt(4.35, "stop a (1.0 ms) ok", "start b (1.0 ms) ok", "rewire in of s  (0.5 ms) ok"),
        ns(6.0, "c", "BACKOFF", previous="RUNNING"),
        ns(6.2, "c", "RUNNING", implementation="pkg.Dwa"),
        adapt(
            7.0, "set_params c  (1 ms) ok", "activate d  (1 ms) FAILED: x", outcome="rolled_back"
        ),
    ],
    selections=[
        sel(0.1, "A", cv={"V": 0.6}),
        sel(4.05, "B", cv={"V": 0.5}),
        m.ConflictReport(stamp=T0 + 8.0, target="X", rules=["r1", "r2"], resolution=""),
    ],
    measurements=[meas(1.0, "L", 80.0), meas(4.0, "L", 40.0), meas(5.0, "Loc", "Corridor")],
    data=[
        x.DataSample(T0 + 2.0, "s/out", {"pos": [0.0, 0.0, 1.5]}),
        x.DataSample(T0 + 6.0, "s/out", {"pos": [0, 0, 0.2]}),
    ],
    params=[
        x.ParamSample(T0 + 1.0, "c", {"max_vel": 0.6, "roi": [1, 2]}),
        x.ParamSample(T0 + 5.0, "c", {"max_vel": 0.5, "roi": [1, 3]}),
    ],
)


def judge(text: str, rec: x.Recording = REC) -> x.Outcome:
    return x.evaluate(x.parse(text, Location("f.scenario.yaml", 7, 5)), x.Index(rec))


@pytest.mark.parametrize(
    ("text", "passed", "observed"),
    [
        # features: deployment features count as selected; initial selection before any message
        ("feature D selected always", True, "selected over [0.00, 10.00] s"),
        ("feature A selected at 0", True, "selected at 0.00 s"),
        ("feature B selected within 0.1 s after k", True, "selected at 4.05 s (0.05 s after k)"),
        ("feature B selected within 0.01 s after k", False, "never in [4.00, 4.01] s: not"),
        ("feature A selected from k", False, "not selected at 4.05 s (0.05 s after k)"),
        ("feature A not selected at end", True, "not selected at 10.00 s"),
        ("feature A selected within 2 s after 9", False, "(window cut by the end of the run at"),
        ("measurement L == 80 during [1, k - 0.5]", True, "80 over [1.00, 3.50] s"),
        # node states
        ("node a STOPPED from k + 0.5", True, "STOPPED over [4.50, 10.00] s"),
        ("node b RUNNING during [k, end]", False, "STOPPED at 4.00 s (0.00 s after k)"),
        ("node b RUNNING within 1 s after k", True, "RUNNING at 4.30 s (0.30 s after k)"),
        ("node zz STOPPED always", True, "STOPPED over [0.00, 10.00] s"),
        # already so at the window's start: said, with whether it ever changed in the window
        ("node c RUNNING within 1 s after k", True,
         "RUNNING already, since -1.00 s; never changed in [4.00, 5.00] s"),
        ("node a RUNNING within 2 s after k", True,
         "RUNNING already, since -1.00 s; first changed at 4.10 s"),
        ("node zz STOPPED within 1 s after k", True,
         "STOPPED already, since the start; never changed in [4.00, 5.00] s"),
        ("measurement L == 80 within 1 s after 2", True,
         "80 already, since 1.00 s; never changed in [2.00, 3.00] s"),
        # values: step signals, tolerance, paths, strings
        ("measurement L < 50 within 0.5 s after k", True, "40 at 4.00 s (0.00 s after k)"),
        ("measurement L == 80 during [1, k]", True, "80 over [1.00, 4.00] s"),
        ("measurement L == 80 during [0.5, k]", False, "no value yet at 0.50 s"),
        ("measurement L > 90", False, "never in [0.00, 10.00] s: 40 .. 80 (last 40)"),
        ("measurement Loc == Corridor after k", True, "'Corridor' at 5.00 s"),
        ("cv V == 0.4 at 0", True, "0.4 at 0.00 s"),
        ("cv V == 0.4 at 1", False, "0.6 at 1.00 s"),
        ("cv V == 0.55 +- 0.05 from k + 0.1", True, "0.5 over [4.10, 10.00] s"),
        ("cv V in [0.4, 0.8] always", True, "0.4 .. 0.6 (last 0.5) over [0.00, 10.00] s"),
        ("param c.max_vel <= 0.5 from 5", True, "0.5 over [5.00, 10.00] s"),
        ("param c.roi[1] == 3 at end", True, "3 at 10.00 s"),
        ("data s.out.pos[2] > 0.5 during [2, 7]", False, "0.2 at 6.00 s"),
        ('implementation c == "pkg.Dwa" from 5', False, "'pkg.Vfh' at 5.00 s"),
        ("implementation c == \"pkg.Dwa\" within 1 s after 6", True, "'pkg.Dwa' at 6.20 s"),
        # events from plans, node states, selections, measurements, conflicts
        ("swap(a -> b) within 0.5 s after k", True, "at 4.35 s (0.35 s after k)"),
        ("swap(b -> a)", False, "never happened"),
        ("swap(* -> b) before 4", False, "not in [0.00, 4.00] s; happened at 4.35 s"),
        ("rewire(s.in) before k + 1", True, "at 4.35 s"),
        ("restart(c) within 1 s after crash(c)", True, "at 6.20 s (0.20 s after crash(c))"),
        ("restart(a)", False, "never happened"),
        ("no crash(*) during [0, 5]", True, "none in [0.00, 5.00] s"),
        ("no crash(*)", False, "crash(c) at 6.00 s"),
        ("select(B) within 0.1 s after k", True, "at 4.05 s"),
        ("deselect(A) after k", True, "at 4.05 s"),
        ("sample(L) within 0.1 s after k", True, "at 4.00 s"),
        ("injection(k) before 5", True, "at 4.00 s"),
        ("no failed adaptation", False, "rollback at 7.00 s"),
        ("no conflict before 7", True, "none in [0.00, 7.00] s"),
        ("no conflict", False, "conflict(X) at 8.00 s"),
        ("set_params(c)", False, "never happened"),  # only ok adaptations count
        ("adaptation within 1 s after k", True, "at 4.35 s"),
        ("stop(a) before start(b)", True, "at 4.20 s"),
        ("start(b) before stop(a)", False, "not in [0.00, 4.20] s; happened at 4.30 s"),
        ("deploy before 0.1", True, "deploy at 0.00 s"),
        # negatives over the run
        ("no node FATAL", True, "no node FATAL in [0.00, 10.00] s"),
        ("no node BACKOFF", False, "node c BACKOFF at 6.00 s"),
        ("no node d", True, "never seen"),
        ("no node b", False, "node b was part of the run (RUNNING at 4.30 s)"),
        ("no orphan process", True, "none"),
        # anchors that never happened
        ("feature B selected within 1 s after zz", False, "injection zz was never applied"),
        ("feature B selected within 1 s after start(zz)", False, "start(zz) never happened"),
        ("feature B selected at 12", False, "12 = 12.00 s is after the end of the run"),
    ],
)  # fmt: skip
def test_evaluation(text: str, passed: bool, observed: str) -> None:
    out = judge(text)
    assert (out.passed, observed in out.observed) == (passed, True), out


def test_swaps_follow_the_components_that_can_replace_each_other() -> None:
    plan = ("stop a,x (1.0 ms) ok", "start b,x (1.0 ms) ok")
    rec = recording(events=[adapt(1.0, *plan)])
    occ = {(o.kind, o.args) for o in x.Index(rec).occurrences}
    assert ("swap", ("a", "b")) in occ
    assert not any(k == "swap" and "x" in a for k, a in occ)  # x restarted: no swap
    rec = recording(events=[adapt(1.0, *plan)], swap_pairs=[])  # no pairing known: any pair
    assert ("swap", ("a", "b")) in {(o.kind, o.args) for o in x.Index(rec).occurrences}


def test_orphans_and_failed_injections() -> None:
    rec = recording(
        orphans=[123],
        injections=[x.Applied(name="k", at=4, stamp=T0 + 4, ok=False, detail="no reply")],
    )
    assert judge("no orphan process", rec) == x.Outcome(
        False, "still alive after the stop: pids [123]"
    )
    assert judge("no orphan process", recording(orphans=None)).observed.startswith("not checked")
    assert judge("node a RUNNING from k", rec).observed == "injection k failed: no reply"
    assert not judge("injection(k)", rec).passed


def test_a_recording_survives_msgpack_with_infinities() -> None:
    rec = recording(measurements=[meas(1.0, "ObstDist", math.inf)], events=REC.events)
    back = x.load_recording(x.save_recording(rec))
    assert back == rec and back.measurements[0].value == math.inf


# ---- the verdict -------------------------------------------------------------------------------
def relay_case(tmp_path: Path, extra: str = ""):
    p = write(
        tmp_path,
        "name: relay\nduration: 10\n"
        "timeline:\n  - {at: 4, name: k, set_params: {node: source, params: {value: 7.0}}}\n"
        "expect:\n  - feature Filtered selected within 1 s after k\n  - cv Gain == 9\n" + extra,
    )
    (case,) = load_scenario(p).cases
    return p, case


def test_rows_name_the_scenario_line_and_the_observed_value(tmp_path: Path) -> None:
    p, case = relay_case(tmp_path)
    rec = recording(
        selections=[sel(4.2, "Filtered", cv={"Gain": 7.0})],
        injections=[x.Applied(name="k", at=4.0, stamp=T0 + 4.0)],
    )
    rows = evaluate_case(case, rec)
    assert [(r.outcome.passed, r.where) for r in rows] == [
        (True, f"{p}:{located(p, 'feature Filtered').line}"),
        (False, f"{p}:{located(p, 'cv Gain').line}"),
    ]
    run = CaseRun(case, tmp_path, rows, seconds=12.5)
    (tmp_path / "events.jsonl").write_text("")
    text = describe_failure(run)
    assert f"{p}:{located(p, 'cv Gain').line}: expectation failed: cv Gain == 9" in text
    assert "observed: never in [0.00, 10.00] s: 7" in text
    assert f"kept: {tmp_path / 'events.jsonl'}" in text
    table = render_rows([run]).splitlines()
    assert table[0].split() == ["SCENARIO", "EXPECTATION", "OUTCOME", "OBSERVED"]
    assert table[2].startswith("relay") and "FAIL" in table[2] and table[2].endswith("s: 7")


def test_a_step_that_failed_is_a_failed_row(tmp_path: Path) -> None:
    p, case = relay_case(tmp_path)
    rec = recording(
        injections=[x.Applied(name="k", at=4.0, stamp=T0 + 4, ok=False, detail="no reply from x")]
    )
    row = evaluate_case(case, rec)[0]
    where = f"{p}:{located(p, '{at: 4').line}"
    assert row == Row("step k (set_params)", where, x.Outcome(False, "no reply from x", 4.0))


# ---- the runner's pure parts --------------------------------------------------------------------
def test_replacement_overrides_go_into_a_copy_of_the_package(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "name: s\nduration: 3\n"
        "replacement: {default: start-then-stop, components: {filtered: standby}}\n",
    )
    (case,) = load_scenario(p).cases
    pkg = prepare_package(case, tmp_path / "run")
    assert pkg == tmp_path / "run" / "package" and pkg != case.package
    runtime = yaml.safe_load((pkg / "runtime.yaml").read_text())
    assert runtime["replacement"] == {
        "default": "start-then-stop",
        "components": {"filtered": "standby"},
    }
    assert runtime["features"] == yaml.safe_load((RELAY / "runtime.yaml").read_text())["features"]
    assert not list(pkg.glob("*.scenario.yaml"))
    p = write(tmp_path, "name: s\nduration: 3\n")
    (case,) = load_scenario(p).cases
    assert prepare_package(case, tmp_path / "run2") == case.package


def test_publish_repeats_are_scheduled_until_their_end(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "name: s\nduration: 3\ntimeline:\n"
        "  - {at: 2.5, kill: sink}\n"
        "  - {at: 2.5, kill: source}\n"
        "  - {at: 1, publish: {port: source.out, data: {value: 1}, every: 0.5, until: 2}}\n"
        "  - {at: 2, publish: {port: source.out, data: {value: 1}, every: 0.4}}\n",
    )
    (case,) = load_scenario(p).cases
    plan = sorted(_Run(case, tmp_path, 1.0).schedule())
    assert [(round(t, 6), case.timeline[i].step.action) for t, i, _ in plan] == [
        (1.0, "publish"), (1.5, "publish"), (2.0, "publish"), (2.0, "publish"),
        (2.4, "publish"), (2.5, "kill"), (2.5, "kill"), (2.8, "publish"),
    ]  # fmt: skip
    assert [t.name for t in case.timeline if t.step.kill] == ["kill@2.5s", "kill@2.5s#2"]


def test_the_marker_finds_the_processes_of_a_run() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-c", "import time; time.sleep(30)"], env={MARKER_ENV: "test-marker-1"}
    )
    try:
        assert marked_pids("test-marker-1") == [proc.pid]
        assert marked_pids("another") == []
    finally:
        proc.kill()
        proc.wait()
    assert marked_pids("test-marker-1") == []


def test_find_scenarios_and_plugin_patterns(tmp_path: Path) -> None:
    with pytest.raises(RraError, match="no such file"):
        find_scenarios([str(tmp_path / "nope")])
    with pytest.raises(RraError, match=r"no \*\.scenario\.yaml"):
        find_scenarios([str(tmp_path)])
    assert matches("scenarios/object_storing/radio.scenario.yaml", "*.scenario.yaml")
    assert matches("scenarios/object_storing/radio.scenario.yaml", "scenarios/**/*.scenario.yaml")
    assert matches("scenarios/radio.scenario.yaml", "scenarios/**/*.scenario.yaml")
    assert not matches("tests/data/radio.scenario.yaml", "scenarios/**/*.scenario.yaml")
    assert not matches("scenarios/a/radio.yaml", "scenarios/**/*.scenario.yaml")
    assert not matches("scenarios/radio.scenario.yaml", "scenarios/?/*.scenario.yaml")


# ---- the schema -------------------------------------------------------------------------------
def test_the_json_schema_is_generated_from_the_structs() -> None:
    spec = importlib.util.spec_from_file_location("gen_schemas", ROOT / "tools" / "gen_schemas.py")
    assert spec is not None and spec.loader is not None
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    text = gen.render(gen.schema_for(Scenario, gen.MODELS["scenario"][1]))
    assert (ROOT / "schemas" / "scenario.schema.json").read_text() == text
    for f in find_scenarios([str(OBJECT_STORING)]):
        head = f.read_text().splitlines()[0]
        assert head == "# yaml-language-server: $schema=../../schemas/scenario.schema.json"


def test_error_group_for_several_problems(tmp_path: Path) -> None:
    p = write(
        tmp_path, "name: s\nduration: 3\nexpect: [feature Nope selected, node nope RUNNING]\n"
    )
    with pytest.raises(ErrorGroup):
        load_scenario(p)


def test_a_summary_shows_each_distinct_value_once() -> None:
    rec = recording(selections=[sel(1.0, "A", "X"), sel(2.0, "A", "Y"), sel(3.0, "B")])
    assert judge("feature A selected always", rec).observed == "not selected at 3.00 s"
    assert judge("feature A selected during [0, 3]", rec).observed == (
        "selected over [0.00, 3.00] s"
    )
    assert judge("feature B selected before 2.5", rec).observed == (
        "never in [0.00, 2.50] s: not selected"
    )


def test_a_shared_expectation_is_reported_once_for_all_cases(tmp_path: Path) -> None:
    p = write(
        tmp_path,
        "name: s\nduration: 3\nexpect: [node nope RUNNING]\n"
        "cases: [{name: a}, {name: b, adaptation: false}]\n",
    )
    (err,) = errors_of(p)
    assert err.location == located(p, "nope") and "unknown node 'nope'" in err.message


# ---- conflict targets and rewired ports are names of the package ------------------------------
ROVER = Path(__file__).parent / "data" / "rover"


def rover_scenario(tmp_path: Path, *expect: str, rules: str = "") -> Path:
    """A scenario of a copy of tests/data/rover, with ``rules`` added to its adaptation."""
    import shutil

    pkg = tmp_path / "rover"
    shutil.copytree(ROVER, pkg, ignore=shutil.ignore_patterns("__pycache__", "*.scenario.yaml"))
    (pkg / "adaptation.rra").write_text((pkg / "adaptation.rra").read_text() + rules)
    path = tmp_path / "c.scenario.yaml"
    lines = "".join(f"  - {e}\n" for e in expect)
    path.write_text(f"package: {pkg}\nname: c\nduration: 3\nexpect:\n{lines}")
    return path


#: A second rule that fights Localize over the choice of localization (rra check: conflict).
RECOVER = "\nrule Recover:\n    if (cdm.Satellites > 10) activate_feature(Gnss)\n"


def test_a_wrongly_named_conflict_is_a_located_error(tmp_path: Path) -> None:
    p = rover_scenario(
        tmp_path,
        "no conflict(Localisation)",
        "no conflict(Rover)",
        "no conflict(MaxSped)",
        "rewire(drive.inn) within 1 s",
        rules=RECOVER,
    )
    errs = {e.location: e.message for e in errors_of(p)}
    assert errs == {
        located(p, "Localisation"): "unknown conflict target 'Localisation' (did you mean"
        " 'Localization'? known: Driving, Gnss, Localization, MaxSpeed, Rover, VisualOdometry);"
        " a conflict is over a feature or a CV attribute",
        located(p, "Rover)"): "no rule claims 'Rover', so no conflict is ever over it (conflict"
        " targets of adaptation.rra: Driving.MaxSpeed, Gnss, Localization, VisualOdometry)",
        located(p, "MaxSped"): "unknown conflict target 'MaxSped' (did you mean 'MaxSpeed'? known:"
        " Driving, Gnss, Localization, MaxSpeed, Rover, VisualOdometry); a conflict is over a"
        " feature or a CV attribute",
        located(p, "inn"): "unknown port 'inn' of 'drive' (did you mean 'in'? known: in, out)",
    }


def test_a_conflict_named_by_its_feature_or_attribute_matches_the_reports(tmp_path: Path) -> None:
    """``conflict(Localization)`` is the conflict over the choice among Localization's
    alternatives (reported as "the alternatives of Localization"); ``conflict(MaxSpeed)``
    the one over the CV attribute Driving.MaxSpeed."""
    p = rover_scenario(
        tmp_path,
        "conflict(Localization) within 1 s",
        "conflict(MaxSpeed) within 1 s",
        "no conflict(Gnss)",
        rules=RECOVER,
    )
    (case,) = load_scenario(p).cases
    rec = recording(
        selections=[
            m.ConflictReport(stamp=T0 + 0.5, target="the alternatives of Localization",
                             rules=["Localize", "Recover"], resolution=""),
            m.ConflictReport(stamp=T0 + 0.7, target="Driving.MaxSpeed",
                             rules=["SpeedLimit", "Other"], resolution=""),
        ],
    )  # fmt: skip
    outcomes = [x.evaluate(e, x.Index(rec)) for e in case.expectations]
    assert [o.passed for o in outcomes] == [True, True, True]
    assert [str(e.event) for e in case.expectations if isinstance(e, x.EventExpectation)] == [
        "conflict(Localization)",
        "conflict(Driving.MaxSpeed)",
        "conflict(Gnss)",
    ]


def test_a_package_without_rules_has_no_conflicts_to_name(tmp_path: Path) -> None:
    p = rover_scenario(tmp_path, "no conflict(Gnss)")
    (tmp_path / "rover" / "rra.yaml").write_text("name: rover\nadaptation: null\n")
    (err,) = errors_of(p)
    assert err.message == "conflict(Gnss): the package has no adaptation rules"
