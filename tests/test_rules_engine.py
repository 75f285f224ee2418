"""The Adaptation Engine core: Fig. 5 end to end, priorities, selection validity, Kleene
logic, clamping, scheduling, run-time conflicts, and the compiler against an interpreter."""

from __future__ import annotations

import functools
import math
from pathlib import Path

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rra_agent.core.adaptation import AdaptationEngine, TickResult
from rra_agent.core.features import check_selection, complete_deployment
from rra_agent.dsl.rules import load_rules, parse_rules
from rra_agent.dsl.uvl import load_uvl, parse_uvl
from rra_agent.models.adaptation import (
    Arith,
    AttrValue,
    Bool,
    Bound,
    Call,
    Compare,
    Const,
    Logic,
    Measure,
    Neg,
    Not,
    Num,
    Str,
)
from rra_agent.models.measurements import Measurement, MeasurementsModel
from rra_agent.package.yamlload import load_yaml

ROOT = Path(__file__).resolve().parents[1]
OS = ROOT / "scenarios" / "object_storing"
QC = ROOT / "scenarios" / "quadcopter"


# ---- Fig. 5 ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def fig5():
    fm = load_uvl(OS / "features.uvl")
    meas = load_yaml(OS / "measurements.yaml", MeasurementsModel)[0]
    return fm, load_rules(OS / "adaptation.rra", fm, meas)


def _line_of(text: str) -> int:
    lines = (OS / "adaptation.rra").read_text().split("\n")
    return next(i for i, line in enumerate(lines, 1) if text in line)


def sample(now, **values):
    return {name: (value, now) for name, value in values.items()}


def fig5_maxvel(loc: str, batt: float, dist: float) -> float:
    """Fig. 5 by hand: the formula clamped into [0.4, 0.8]; 0.5 in the corridor."""
    lo, hi = 0.4, 0.8
    value = lo + (hi - lo) * (batt / 100) * (1 - math.e ** (-dist))
    value = min(max(value, lo), hi)
    return 0.5 if loc == "Corridor" else value


def fig5_selection(loc: str, batt: float, material: str) -> set[str]:
    sel = {"Environment", "Communic. Channel", "Motion Behavior", "Material"}
    sel.add("Static" if loc in ("RoomA", "RoomB") else "Dynamic")
    if loc == "RoomA":
        sel |= {"RackSize", "Small"}
    elif loc == "RoomB":
        sel |= {"RackSize", "Large"}
    sel.add("ChannelB" if batt > 50 else "ChannelA")  # MIN(Latency): Low; MIN(PowerConsump)
    sel.add("Fragile" if material == "Glass" else "Firm")
    return sel


CONTEXTS = [
    (loc, batt, dist, mat)
    for loc in ("RoomA", "RoomB", "Corridor")
    for batt in (20.0, 80.0)
    for dist in (0.3, 3.0)
    for mat in ("Glass", "Wood")
]


@pytest.mark.parametrize(("loc", "batt", "dist", "mat"), CONTEXTS)
def test_fig5_table(fig5, loc, batt, dist, mat):
    fm, model = fig5
    engine = AdaptationEngine(fm, {"Manipulation"}, model)
    r = engine.tick(1.0, sample(1.0, SemLoc=loc, BattLev=batt, ObstDist=dist, Material=mat))
    assert r.selection == fig5_selection(loc, batt, mat)
    assert r.cv == {"MaxVel": pytest.approx(fig5_maxvel(loc, batt, dist), abs=1e-12)}
    assert not r.rejected and not r.conflicts and not r.undefined
    assert check_selection(fm, engine.deployment | r.selection) == []


def test_fig5_sequence_does_not_depend_on_history(fig5):
    """One engine walked through every context, back and forth, gives the table's answers."""
    fm, model = fig5
    engine = AdaptationEngine(fm, {"Manipulation"}, model)
    now = 0.0
    for loc, batt, dist, mat in CONTEXTS + CONTEXTS[::-1]:
        now += 0.1
        r = engine.tick(now, sample(now, SemLoc=loc, BattLev=batt, ObstDist=dist, Material=mat))
        assert r.selection == fig5_selection(loc, batt, mat)
        assert r.cv["MaxVel"] == pytest.approx(fig5_maxvel(loc, batt, dist), abs=1e-12)


def test_fig5_corridor_cap_comes_from_the_priority_1_rule(fig5):
    fm, model = fig5
    r = AdaptationEngine(fm, {"Manipulation"}, model).tick(
        0.0, sample(0.0, SemLoc="Corridor", BattLev=100.0, ObstDist=50.0, Material="Wood")
    )
    fired = [(f.rule, f.value) for f in r.fired if f.ruleset == "MaxVelocity"]
    assert fired == [("maxVelBattObst", pytest.approx(0.8)), ("maxVelCorridor", 0.5)]
    assert r.cv["MaxVel"] == 0.5
    assert not r.conflicts  # ordered by priority inside the rule set: no conflict


def test_fig5_velocity_limit_nfr_applies_only_while_dynamic(fig5):
    """Outside the rooms but not in the corridor (the corridor rule does not fire), the
    VelocityLimit NFR of Dynamic still caps MaxVel at 0.5; back in a room it is lifted."""
    fm, model = fig5
    engine = AdaptationEngine(fm, {"Manipulation"}, model)
    r = engine.tick(0.0, sample(0.0, SemLoc="Lab", BattLev=80.0, ObstDist=3.0, Material="Wood"))
    assert "Dynamic" in r.selection
    assert [f.value for f in r.fired if f.rule == "maxVelBattObst"] == [
        pytest.approx(fig5_maxvel("RoomA", 80.0, 3.0))
    ]
    assert r.cv["MaxVel"] == 0.5
    r = engine.tick(1.0, sample(1.0, SemLoc="RoomA", BattLev=80.0, ObstDist=3.0, Material="Wood"))
    assert "Static" in r.selection
    assert r.cv["MaxVel"] == pytest.approx(fig5_maxvel("RoomA", 80.0, 3.0))
    assert r.cv["MaxVel"] > 0.5


def test_fig5_clamps_into_the_cv_bounds(fig5):
    fm, model = fig5
    engine = AdaptationEngine(fm, {"Manipulation"}, model)
    high = engine.tick(0.0, sample(0.0, SemLoc="RoomA", BattLev=150.0, ObstDist=9.0))
    assert high.cv["MaxVel"] == 0.8
    low = engine.tick(1.0, sample(1.0, SemLoc="RoomA", BattLev=-50.0, ObstDist=9.0))
    assert low.cv["MaxVel"] == 0.4


def test_fig5_detection_deployment_never_selects_material(fig5):
    """Material requires Manipulation: with Detection, ObjMaterial's requests are rejected."""
    fm, model = fig5
    engine = AdaptationEngine(fm, {"Detection"}, model)
    r = engine.tick(0.0, sample(0.0, SemLoc="RoomA", BattLev=80.0, ObstDist=1.0, Material="Glass"))
    assert not {"Material", "Fragile", "Firm"} & r.selection
    (rej,) = r.rejected
    assert rej.rule == "ObjMaterial" and rej.action == "activate_feature(Fragile)"
    assert "Manipulation" in rej.reason
    assert rej.span is not None and rej.span.line == _line_of("activate_feature(Fragile)")
    assert check_selection(fm, engine.deployment | r.selection) == []


def test_fig5_fired_rules_name_the_cause(fig5):
    fm, model = fig5
    r = AdaptationEngine(fm, {"Manipulation"}, model).tick(
        0.0, sample(0.0, SemLoc="RoomB", BattLev=80.0, ObstDist=1.0, Material="Wood")
    )
    by_rule = {f.rule: f for f in r.fired}
    assert by_rule["RackSize"].action == "activate_feature(Large)"
    assert by_rule["RackSize"].reads == ("SemLoc",)
    assert (by_rule["RackSize"].span.line, by_rule["RackSize"].span.col) == (
        _line_of("activate_feature(Large)"),
        9,
    )
    assert by_rule["maxVelBattObst"].reads == ("BattLev", "ObstDist")
    assert by_rule["Radio"].action.startswith("select_feature_from_variants_of(Communic. Channel)")


def test_fig5_missing_measurements_change_nothing(fig5):
    fm, model = fig5
    engine = AdaptationEngine(fm, {"Manipulation"}, model)
    first = engine.tick(
        0.0, sample(0.0, SemLoc="RoomA", BattLev=80.0, ObstDist=1.0, Material="Glass")
    )
    later = engine.tick(10.0, {})
    assert later.selection == first.selection and later.cv == first.cv
    assert later.fired == [] and not later.changed
    assert set(later.undefined) == {"SemLoc", "BattLev", "ObstDist", "Material"}


def test_fig5_stale_measurements_are_undefined(fig5):
    """ObstDist has max_age_ms 500: older samples make the MaxVel formula undefined."""
    fm, model = fig5
    engine = AdaptationEngine(fm, {"Manipulation"}, model)
    engine.tick(0.0, sample(0.0, SemLoc="RoomA", BattLev=80.0, ObstDist=3.0))
    before = engine.cv["MaxVel"]
    stale = {**sample(1.0, SemLoc="RoomA", BattLev=20.0, Material="Wood"), "ObstDist": (0.3, 0.4)}
    r = engine.tick(1.0, stale)
    assert r.undefined == ["ObstDist"]
    assert r.cv["MaxVel"] == before  # unchanged
    fresh = {**stale, "ObstDist": (0.3, 0.6)}
    assert engine.tick(1.0, fresh).cv["MaxVel"] == pytest.approx(fig5_maxvel("RoomA", 20, 0.3))


def test_rules_are_compiled_once_not_walked(fig5):
    fm, model = fig5
    engine = AdaptationEngine(fm, {"Manipulation"}, model)
    assert "def _g0(M, CV, out, V):" in engine.source
    engine.model = None  # the tick never looks at the AST again
    r = engine.tick(0.0, sample(0.0, SemLoc="RoomB", BattLev=80.0, ObstDist=1.0))
    assert "Large" in r.selection


def test_tick_result_goes_on_the_bus(fig5):
    fm, model = fig5
    r = AdaptationEngine(fm, {"Manipulation"}, model).tick(
        0.0, sample(0.0, SemLoc="Corridor", BattLev=80.0, ObstDist=1.0, Material="Glass")
    )
    assert isinstance(r, msgspec.Struct)
    for codec in (msgspec.msgpack, msgspec.json):
        assert codec.decode(codec.encode(r), type=TickResult) == r


# ---- a small model for the rest ----------------------------------------------------------------
SMALL_UVL = """features
    Robot {abstract}
        mandatory
            Mode {binding 'runtime'}
                alternative
                    Eco {Cost {kind 'cim', value 'Low', scale ['Low', 'Mid', 'High']}}
                    Normal {Cost {kind 'cim', value 'Mid', scale ['Low', 'Mid', 'High']}}
                    Turbo {Cost {kind 'cim', value 'High', scale ['Low', 'Mid', 'High']}}
            Radio {binding 'runtime'}
                alternative
                    R1 {Lat {kind 'cim', value 2}}
                    R2 {Lat {kind 'cim', value 1}}
                    R3 {Lat {kind 'cim', value 1}}
            Motion {binding 'runtime', Vel {kind 'cv', lower 0.0, upper 2.0}, Free {kind 'cv', lower -1000000000, upper 1000000000}}
        optional
            Arm
            Light {binding 'runtime'}
            Safe {binding 'runtime', Cap {kind 'nfr', tag 'max', value 1.0, constrains 'Vel'}, Floor {kind 'nfr', tag 'min', value 0.5, constrains 'Vel'}}
            Gripper {binding 'runtime'}
                alternative
                    Soft
                    Hard
constraints
    Gripper => Arm
    R2 => Arm
"""  # noqa: E501

SMALL_MEAS = MeasurementsModel(
    measurements=[
        Measurement(name="x", type="float", source="c.x", max_age_ms=1000),
        Measurement(name="y", type="float", source="c.y"),
        Measurement(name="s", type="str", source="c.s"),
        Measurement(name="n", type="int", source="c.n"),
        Measurement(name="b", type="bool", source="c.b"),
    ]
)


@functools.cache
def small_fm():
    return parse_uvl(SMALL_UVL, "small.uvl")


@pytest.fixture
def small():
    return small_fm()


def engine_for(fm, rules, deployment=(), **kw):
    model = parse_rules("import m as cdm\n" + rules, "r.rra", fm, SMALL_MEAS)
    return AdaptationEngine(fm, deployment, model, **kw)


def test_rule_set_highest_priority_has_the_last_word(small):
    text = (
        "ruleSet S:\n"
        "  rule a priority {a}: set_attribute(Vel) with_value(0.3)\n"
        "  rule b priority {b}: set_attribute(Vel) with_value(0.6)\n"
        "  rule c priority {c}: set_attribute(Vel) with_value(0.9)\n"
    )
    for prios, winner in (((3, 1, 2), 0.6), ((1, 2, 3), 0.3), ((2, 3, 1), 0.9)):
        engine = engine_for(small, text.format(a=prios[0], b=prios[1], c=prios[2]))
        r = engine.tick(0.0, {})
        assert r.cv["Vel"] == winner
        assert [f.rule for f in r.fired][-1] == "abc"[prios.index(1)]
        assert not r.conflicts


def test_rule_set_on_features_priority_wins_without_conflict(small):
    engine = engine_for(
        small,
        "ruleSet S:\n  rule on priority 1: deactivate_feature(Light)\n"
        "  rule off priority 2: activate_feature(Light)\n",
    )
    r = engine.tick(0.0, {})
    assert "Light" not in r.selection and not r.conflicts


def test_select_by_ordinal_scale_and_numbers(small):
    engine = engine_for(
        small,
        "rule A: select_feature_from_variants_of(Mode) where_attribute MAX(Cost)\n"
        "rule B: select_feature_from_variants_of(Radio) where_attribute MAX(Lat)\n",
    )
    assert {"Turbo", "R1"} <= engine.tick(0.0, {}).selection
    engine = engine_for(
        small, "rule A: select_feature_from_variants_of(Mode) where_attribute MIN(Cost)"
    )
    engine.selection = engine.selection - {"Eco"} | {"Turbo"}
    assert "Eco" in engine.tick(0.0, {}).selection  # 'Low' < 'Mid' < 'High' by the scale


def test_select_ties_break_by_model_order_among_selectable_variants(small):
    rules = "rule A: select_feature_from_variants_of(Radio) where_attribute MIN(Lat)"
    with_arm = engine_for(small, rules, {"Arm"}).tick(0.0, {})
    assert "R2" in with_arm.selection  # R2 and R3 tie at 1: R2 comes first
    without_arm = engine_for(small, rules).tick(0.0, {})
    assert "R3" in without_arm.selection  # R2 => Arm: R2 is not selectable
    assert not without_arm.rejected


def test_set_attribute_clamps_into_bounds_and_active_nfrs(small):
    engine = engine_for(
        small,
        "rule V: set_attribute(Vel) with_value(cdm.x)\n"
        "rule S: if (cdm.b) activate_feature(Safe) else deactivate_feature(Safe)\n",
    )
    assert engine.tick(0.0, sample(0.0, x=5.0, b=False)).cv["Vel"] == 2.0
    assert engine.tick(0.1, sample(0.1, x=-3.0, b=False)).cv["Vel"] == 0.0
    assert engine.tick(0.2, sample(0.2, x=5.0, b=True)).cv["Vel"] == 1.0  # Cap (max)
    assert engine.tick(0.3, sample(0.3, x=0.1, b=True)).cv["Vel"] == 0.5  # Floor (min)
    assert engine.tick(0.4, sample(0.4, x=1.5, b=False)).cv["Vel"] == 1.5


def test_nfr_follows_the_selection_without_a_new_set(small):
    engine = engine_for(
        small,
        "rule V period 0 ms: set_attribute(Vel) with_value(cdm.x)\n"
        "rule S: if (cdm.b) activate_feature(Safe) else deactivate_feature(Safe)\n",
    )
    engine.tick(0.0, {**sample(0.0, x=1.8), "b": (False, 0.0)})
    r = engine.tick(0.1, {**sample(0.0, x=1.8), "b": (True, 0.1)})
    assert not any(f.rule == "V" for f in r.fired)
    assert r.cv["Vel"] == 1.0
    r = engine.tick(0.2, {**sample(0.0, x=1.8), "b": (False, 0.2)})
    assert r.cv["Vel"] == 1.8  # the requested value comes back once the NFR is inactive


def test_untouched_features_keep_their_state(small):
    engine = engine_for(small, "rule L: if (cdm.x > 1) activate_feature(Light)")
    assert "Light" not in engine.tick(0.0, {}).selection
    assert "Light" in engine.tick(1.0, sample(1.0, x=2.0)).selection
    assert "Light" in engine.tick(2.0, sample(2.0, x=0.0)).selection  # no else: stays
    assert "Light" in engine.tick(3.0, {}).selection


def test_alternatives_stay_alternatives_and_the_later_unit_wins(small):
    engine = engine_for(
        small, "rule A: activate_feature(Turbo)\nrule B: activate_feature(Normal)\n"
    )
    r = engine.tick(0.0, {})
    assert "Normal" in r.selection and not {"Turbo", "Eco"} & r.selection
    (c,) = r.conflicts
    assert (c.kind, c.target) == ("alternative", "the alternatives of Mode")
    assert (c.winner.rule, c.loser.rule) == ("B", "A")
    assert (c.winner.span.line, c.loser.span.line) == (3, 2)


def test_runtime_conflicts_on_features_and_attributes(small):
    engine = engine_for(
        small,
        "rule A: if (cdm.x > 0) activate_feature(Light)\n"
        "rule B: if (cdm.x > 5) deactivate_feature(Light)\n"
        "rule C: set_attribute(Vel) with_value(1)\n"
        "rule D: if (cdm.x > 5) set_attribute(Vel) with_value(0.2)\n",
    )
    calm = engine.tick(0.0, sample(0.0, x=1.0))
    assert "Light" in calm.selection and calm.cv["Vel"] == 1.0 and not calm.conflicts
    r = engine.tick(1.0, sample(1.0, x=9.0))
    assert "Light" not in r.selection and r.cv["Vel"] == 0.2
    assert [(c.kind, c.target, c.winner.rule, c.loser.rule) for c in r.conflicts] == [
        ("feature", "Light", "B", "A"),
        ("attribute", "Motion.Vel", "D", "C"),
    ]


def test_unavailable_features_are_never_selected(small):
    engine = engine_for(small, "rule G: activate_feature(Soft)")
    r = engine.tick(0.0, {})
    assert not {"Soft", "Gripper"} & r.selection
    (rej,) = r.rejected
    assert rej.rule == "G" and "Arm" in rej.reason
    assert (
        "Soft" in engine_for(small, "rule G: activate_feature(Soft)", {"Arm"}).tick(0, {}).selection
    )


def test_impossible_requests_keep_the_last_valid_selection(small):
    engine = engine_for(
        small, "rule L: activate_feature(Light)\nrule M: deactivate_feature(Mode)\n"
    )
    before = engine.selection
    r = engine.tick(0.0, {})
    assert r.selection == before | {"Light"}
    (rej,) = r.rejected
    assert rej.rule == "M" and "mandatory" in rej.reason
    assert check_selection(small, engine.deployment | r.selection) == []


# ---- undefined values (Kleene logic) ------------------------------------------------------------
@pytest.mark.parametrize(
    ("cond", "values", "expect"),
    [
        ("cdm.x > 1", {}, None),  # missing: no branch, not even else
        ("cdm.x > 1 OR cdm.s == 'go'", {"s": "go"}, True),
        ("cdm.x > 1 OR cdm.s == 'go'", {"s": "stop"}, None),
        ("cdm.x > 1 AND cdm.s == 'go'", {"s": "stop"}, False),
        ("cdm.x > 1 AND cdm.s == 'go'", {"s": "go"}, None),
        ("NOT (cdm.x > 1)", {}, None),
        ("cdm.y / cdm.x > 1", {"x": 0.0, "y": 1.0}, None),  # division by zero
        ("log(cdm.x) > 0", {"x": -1.0}, None),  # domain error
        ("cdm.x ^ 0.5 > 0", {"x": -4.0}, None),  # no real root
        ("e ^ cdm.x > 0", {"x": 1e6}, None),  # overflow
        ("cdm.x == 2.5", {"x": "2.5"}, True),  # numeric strings are numbers for float
        ("cdm.x == 2.5", {"x": "fast"}, None),  # anything else is undefined
        ("cdm.x > 1", {"x": float("nan")}, None),
        ("cdm.x > 1", {"x": float("inf")}, True),  # nothing in sight is far away
        ("e ^ (-cdm.x) == 0", {"x": float("inf")}, True),
        ("cdm.n == 3", {"n": 3.0}, True),
        ("cdm.n == 3", {"n": 3.5}, None),
        ("cdm.b", {"b": 1}, None),  # not a boolean
        ("cdm.b == false", {"b": False}, True),
    ],
)
def test_kleene_conditions(small, cond, values, expect):
    engine = engine_for(
        small,
        f"rule K: if ({cond}) activate_feature(Turbo) else activate_feature(Normal)",
        initial={"Mode", "Eco", "Radio", "R1", "Motion"},
    )
    r = engine.tick(0.0, sample(0.0, **values))
    chosen = {"Turbo": True, "Normal": False, "Eco": None}
    assert [chosen[m] for m in ("Turbo", "Normal", "Eco") if m in r.selection] == [expect]
    assert len(r.fired) == (0 if expect is None else 1)


def test_undefined_value_leaves_the_attribute_unchanged(small):
    engine = engine_for(small, "rule V: set_attribute(Vel) with_value(2 / cdm.x)")
    assert engine.tick(0.0, sample(0.0, x=4.0)).cv["Vel"] == 0.5
    r = engine.tick(0.1, sample(0.1, x=0.0))
    assert r.cv["Vel"] == 0.5 and r.fired == [] and not r.changed
    assert engine.tick(2.0, {"x": (4.0, 0.5)}).undefined == ["x"]  # stale after 1000 ms


def test_cv_initial_value_and_previous_tick_reads(small):
    engine = engine_for(
        small,
        "rule A: set_attribute(Vel) with_value(cdm.x)\n"
        "rule B: if (Vel > 1) activate_feature(Light) else deactivate_feature(Light)\n",
    )
    assert engine.cv == {"Vel": 0.0, "Free": -1e9}  # no declared value: the lower bound
    r = engine.tick(0.0, sample(0.0, x=1.5))
    assert "Light" not in r.selection  # B read the value of the previous tick
    assert "Light" in engine.tick(0.1, sample(0.1, x=1.5)).selection


def test_changed_flag(small):
    engine = engine_for(small, "rule L: if (cdm.x > 1) activate_feature(Light)")
    assert engine.tick(0.0, sample(0.0, x=2.0)).changed
    assert not engine.tick(0.1, sample(0.1, x=2.0)).changed


# ---- scheduling ----------------------------------------------------------------------------------
def test_period_rules_run_only_when_due(small):
    engine = engine_for(small, "rule P period 100 ms: set_attribute(Free) with_value(cdm.y)")
    values = []
    for now in (0.0, 0.05, 0.099, 0.1, 0.15, 0.2, 0.35):
        values.append(engine.tick(now, sample(now, y=now)).cv["Free"])
    assert values == [0.0, 0.0, 0.0, 0.1, 0.1, 0.2, 0.35]


def test_period_zero_runs_on_new_measurements_it_reads(small):
    engine = engine_for(
        small,
        "rule Q period 0 ms: set_attribute(Free) with_value(cdm.y)\n"
        "rule Always: set_attribute(Vel) with_value(cdm.x)\n",
    )
    assert engine.tick(0.0, {"y": (1.0, 5.0), "x": (1.0, 0.0)}).cv["Free"] == 1.0  # first tick
    r = engine.tick(0.1, {"y": (2.0, 5.0), "x": (1.5, 0.0)})  # same stamp: not new
    assert r.cv == {"Free": 1.0, "Vel": 1.5}
    assert engine.tick(0.2, {"y": (2.0, 5.0), "x": (1.0, 0.0)}, changed=["y"]).cv["Free"] == 2.0
    assert engine.tick(0.3, {"y": (3.0, 6.0), "x": (1.0, 0.0)}).cv["Free"] == 3.0  # new stamp
    assert engine.tick(0.4, {"x": (1.0, 0.0)}).cv["Free"] == 3.0  # gone: not new


def test_a_rule_set_runs_whole_when_any_rule_is_due(small):
    engine = engine_for(
        small,
        "ruleSet S:\n"
        "  rule a priority 2 period 1000 ms: set_attribute(Vel) with_value(cdm.x)\n"
        "  rule b priority 1 period 0 ms:\n"
        "    if (cdm.s == 'slow') set_attribute(Vel) with_value(0.25)\n",
    )
    assert engine.tick(0.0, {"x": (1.0, 0.0), "s": ("fast", 0.0)}).cv["Vel"] == 1.0
    r = engine.tick(0.1, {"x": (1.5, 0.1), "s": ("slow", 0.1)})
    assert [f.rule for f in r.fired] == ["a", "b"] and r.cv["Vel"] == 0.25
    assert engine.tick(0.2, {"x": (1.8, 0.2), "s": ("slow", 0.1)}).fired == []


# ---- the quadcopter ----------------------------------------------------------------------------
def test_quadcopter_switches_to_proploss_and_latches():
    fm = load_uvl(QC / "features.uvl")
    meas = load_yaml(QC / "measurements.yaml", MeasurementsModel)[0]
    engine = AdaptationEngine(fm, {"Hover"}, load_rules(QC / "adaptation.rra", fm, meas))
    assert "Standard" in engine.tick(0.0, {"WorkingMotors": (4, 0.0)}).selection
    assert "Standard" in engine.tick(0.01, {}).selection  # missing: nothing changes
    r = engine.tick(0.02, {"WorkingMotors": (3, 0.02)})
    assert "Proploss" in r.selection and "Standard" not in r.selection and r.changed
    assert r.fired[0].reads == ("WorkingMotors",)
    assert "Proploss" in engine.tick(0.03, {"WorkingMotors": (4, 0.03)}).selection  # latched
    assert "Proploss" in engine.tick(1.0, {"WorkingMotors": (4, 0.5)}).selection  # stale


# ---- properties ---------------------------------------------------------------------------------
SEMLOC = st.one_of(st.sampled_from(["RoomA", "RoomB", "Corridor", "Lab", ""]), st.text(max_size=5))
ANY = st.one_of(
    st.none(),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(10**6), 10**6),
    st.booleans(),
    st.text(max_size=4),
    st.sampled_from(["50", "Glass", "Wood", "1e3"]),
)


def _vector(value_strategy):
    return st.fixed_dictionaries(
        {},
        optional={
            "SemLoc": st.tuples(st.one_of(SEMLOC, ANY), st.floats(0, 3)),
            "BattLev": st.tuples(st.one_of(st.floats(-50, 150), ANY), st.floats(0, 3)),
            "ObstDist": st.tuples(st.one_of(st.floats(0, 10), ANY), st.floats(0, 3)),
            "Material": st.tuples(
                st.one_of(st.sampled_from(["Glass", "Wood"]), ANY), st.floats(0, 3)
            ),
        },
    )


@settings(
    max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    vectors=st.lists(_vector(ANY), min_size=1, max_size=6),
    deployment=st.sampled_from([("Manipulation",), ("Detection",)]),
)
def test_any_measurements_give_a_valid_selection(fig5, vectors, deployment):
    fm, model = fig5
    engine = AdaptationEngine(fm, deployment, model)
    for i, vector in enumerate(vectors):
        r = engine.tick(3.0 + i * 0.1, vector)
        assert check_selection(fm, engine.deployment | r.selection) == []
        assert 0.4 <= r.cv["MaxVel"] <= 0.8
        if "Dynamic" in r.selection:
            assert r.cv["MaxVel"] <= 0.5
        if deployment == ("Detection",):
            assert "Material" not in r.selection


FEATURES = ["Eco", "Normal", "Turbo", "R1", "R2", "R3", "Light", "Safe", "Soft", "Hard", "Gripper"]
CONDS = ["cdm.x > 1", "cdm.x <= 0.5", "cdm.s == 'a'", "cdm.b", "NOT cdm.b", "cdm.n != 2", "true"]


@st.composite
def random_rules(draw):
    lines = []
    for i in range(draw(st.integers(1, 6))):
        action = draw(st.sampled_from(["activate_feature", "deactivate_feature"]))
        feats = " AND ".join(draw(st.lists(st.sampled_from(FEATURES), min_size=1, max_size=2)))
        body = f"{action}({feats})"
        if draw(st.booleans()):
            cond = draw(st.sampled_from(CONDS))
            other = draw(st.sampled_from(FEATURES))
            body = f"if ({cond}) {body} else activate_feature({other})"
        lines.append(f"rule r{i}: {body}")
    return "\n".join(lines)


@settings(
    max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    rules=random_rules(),
    deployment=st.sampled_from([(), ("Arm",)]),
    ticks=st.lists(
        st.fixed_dictionaries(
            {},
            optional={
                "x": st.tuples(st.floats(-2, 3), st.just(0.0)),
                "s": st.tuples(st.sampled_from(["a", "b"]), st.just(0.0)),
                "b": st.tuples(st.booleans(), st.just(0.0)),
                "n": st.tuples(st.integers(0, 3), st.just(0.0)),
            },
        ),
        min_size=1,
        max_size=4,
    ),
)
def test_random_rules_never_break_the_feature_model(rules, deployment, ticks):
    small = small_fm()
    engine = engine_for(small, rules, deployment)
    for vector in ticks:
        r = engine.tick(0.0, vector)
        assert check_selection(small, complete_deployment(small, deployment) | r.selection) == []


# ---- the compiler agrees with a straightforward interpreter ----------------------------------
def interpret(expr, env, fm, cv):
    """Reference semantics, written independently of the compiler: None is undefined."""
    match expr:
        case Num(value=v) | Str(value=v) | Bool(value=v):
            return v
        case Const(name=n):
            return math.e if n == "e" else math.pi
        case Measure(name=n):
            return env.get(n)
        case AttrValue(kind="cv", attribute=a):
            return cv[a]
        case AttrValue(feature=f, attribute=a):
            return fm.features[f].attribute(a).rra_value
        case Bound(feature=f, attribute=a, bound=b):
            attr = fm.features[f].attribute(a)
            return attr.lower if b == "min" else attr.upper
        case Not(operand=o):
            v = interpret(o, env, fm, cv)
            return None if v is None else not v
        case Logic(op=op, left=a, right=b):
            x, y = interpret(a, env, fm, cv), interpret(b, env, fm, cv)
            decisive = op == "or"
            if x is decisive or y is decisive:
                return decisive
            return None if x is None or y is None else not decisive
        case Compare(op=op, left=a, right=b):
            x, y = _not_nan(interpret(a, env, fm, cv)), _not_nan(interpret(b, env, fm, cv))
            if x is None or y is None:
                return None
            return {"==": x == y, "!=": x != y, "<": x < y, "<=": x <= y, ">": x > y, ">=": x >= y}[
                op
            ]
    args = [interpret(c, env, fm, cv) for c in _operands(expr)]
    if any(a is None for a in args):
        return None
    try:
        match expr:
            case Neg():
                return -args[0]
            case Arith(op="^", left=Const(name="e")):
                return math.exp(args[1])
            case Arith(op="+"):
                return args[0] + args[1]
            case Arith(op="-"):
                return args[0] - args[1]
            case Arith(op="*"):
                return args[0] * args[1]
            case Arith(op="/"):
                return args[0] / args[1]
            case Arith(op="^"):
                return math.pow(args[0], args[1])
            case Call(func=f):
                if f in ("min", "max") and len(args) == 1:
                    return args[0]
                fn = {"exp": math.exp, "log": math.log, "sqrt": math.sqrt, "abs": abs,
                      "min": min, "max": max}[f]  # fmt: skip
                return fn(*args)
    except (ArithmeticError, ValueError):
        return None
    raise AssertionError(expr)


def _operands(expr):
    match expr:
        case Neg(operand=o):
            return [o]
        case Arith(left=a, right=b):
            return [a, b]
        case Call(args=args):
            return list(args)
    raise AssertionError(expr)


def _finite(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def _not_nan(v):
    """Comparisons: NaN is undefined; infinities compare as numbers."""
    if isinstance(v, float) and v != v:
        return None
    return v


LEAVES = st.sampled_from(
    ["cdm.x", "cdm.y", "cdm.n", "0", "1", "2", "0.5", "-1", '"3"', "e", "pi", "Vel", "Vel.max"]
)


def _num_expr():
    def extend(inner):
        return st.one_of(
            st.tuples(inner, st.sampled_from(["+", "-", "*", "/", "^"]), inner).map(
                lambda t: f"({t[0]} {t[1]} {t[2]})"
            ),
            inner.map(lambda a: f"-({a})"),
            inner.map(lambda a: f"[{a}]"),
            st.tuples(st.sampled_from(["exp", "log", "sqrt", "abs"]), inner).map(
                lambda t: f"{t[0]}({t[1]})"
            ),
            st.tuples(st.sampled_from(["min", "max"]), st.lists(inner, min_size=1, max_size=3)).map(
                lambda t: f"{t[0]}({', '.join(t[1])})"
            ),
        )

    return st.recursive(LEAVES, extend, max_leaves=8)


def _cond_expr():
    num = _num_expr()
    atoms = st.one_of(
        st.tuples(num, st.sampled_from(["==", "!=", "<", "<=", ">", ">="]), num).map(" ".join),
        st.sampled_from(["cdm.b", "cdm.s == 'A'", "cdm.s != 'B'", "true", "false"]),
    )

    def extend(inner):
        return st.one_of(
            st.tuples(inner, st.sampled_from(["AND", "OR"]), inner).map(
                lambda t: f"({t[0]} {t[1]} {t[2]})"
            ),
            inner.map(lambda a: f"NOT ({a})"),
        )

    return st.recursive(atoms, extend, max_leaves=6)


VALUES = st.one_of(
    st.none(),
    st.sampled_from([-2.0, -0.5, 0.0, 0.5, 1.0, 3.0, 700.0, 1e300, math.inf, -math.inf]),
)


@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    value=_num_expr(),
    cond=_cond_expr(),
    x=VALUES,
    y=VALUES,
    n=st.one_of(st.none(), st.integers(-2, 3)),
    s=st.one_of(st.none(), st.sampled_from(["A", "B"])),
    b=st.one_of(st.none(), st.booleans()),
)
def test_compiled_rules_match_the_interpreter(value, cond, x, y, n, s, b):
    small = small_fm()
    rules = (
        f"rule V: set_attribute(Free) with_value({value})\n"
        f"rule C: if ({cond}) activate_feature(Light) else deactivate_feature(Light)\n"
    )
    engine = engine_for(small, rules, initial={"Mode", "Eco", "Radio", "R1", "Motion", "Light"})
    env = {k: v for k, v in {"x": x, "y": y, "n": n, "s": s, "b": b}.items() if v is not None}
    r = engine.tick(0.0, {k: (v, 0.0) for k, v in env.items()})
    cv = {"Vel": 0.0, "Free": -1e9}
    v_rule, c_rule = engine.model.items
    want_value = interpret(v_rule.branches[0].actions[0].value, env, small, cv)
    want_value = _finite(float(want_value)) if want_value is not None else None
    if want_value is None:
        assert r.cv["Free"] == -1e9
    else:
        assert r.cv["Free"] == min(max(want_value, -1e9), 1e9)
    want_cond = interpret(c_rule.branches[0].condition, env, small, cv)
    assert ("Light" in r.selection) == (want_cond is not False)
    assert len([f for f in r.fired if f.rule == "C"]) == (want_cond is not None)


# ---- request reduction is invisible --------------------------------------------------------------
REDUCE_UVL = """features
    Root {abstract}
        mandatory
            A {binding 'runtime'}
                alternative
                    A1
                    A2
                    A3
                        alternative
                            A3x
                            A3y
            B {binding 'runtime'}
                or
                    B1
                    B2
        optional
            C {binding 'runtime'}
                optional
                    C1
                    C2
                alternative
                    C3
                    C4
            D {binding 'runtime'}
            E {binding 'runtime'}
constraints
    A2 => C1
    C2 => !A1
    D => B2
    A3y => !C4
"""
REDUCE_FEATURES = ["A1", "A2", "A3", "A3x", "A3y", "B1", "B2"]
REDUCE_FEATURES += ["C", "C1", "C2", "C3", "C4", "D", "E"]
REQUESTS = st.lists(
    st.tuples(st.sampled_from(["activate", "deactivate"]), st.sampled_from(REDUCE_FEATURES)),
    max_size=10,
)


@functools.cache
def reduce_engine(constraints: bool):
    text = REDUCE_UVL if constraints else REDUCE_UVL.split("constraints")[0]
    fm = parse_uvl(text, "reduce.uvl")
    return AdaptationEngine(fm, (), parse_rules("", "empty.rra", fm, None))


@settings(max_examples=300, deadline=None)
@given(setup=REQUESTS, requests=REQUESTS, constraints=st.booleans())
def test_dropped_requests_never_change_the_selection(setup, requests, constraints):
    """What the engine leaves out before apply_requests makes no difference to its result
    (with constraints linking families, and without, where more requests are dropped)."""
    from rra_agent.core.features import apply_requests

    engine = reduce_engine(constraints)
    fm, dep = engine.fm, engine.deployment
    start = frozenset({"A", "A1", "B", "B1"})
    current, _ = apply_requests(fm, dep, start, setup)
    kept, _ = engine._reduce(list(requests), list(range(len(requests))), current)
    full, _ = apply_requests(fm, dep, current, requests)
    reduced, _ = apply_requests(fm, dep, current, kept)
    assert reduced == full
    assert len(kept) <= len(requests)


def test_overridden_defaults_do_not_reach_apply_requests(small, monkeypatch):
    """A rule set's default followed by an override of the same group is one request."""
    import rra_agent.core.adaptation as core

    calls = []
    real = core.apply_requests
    monkeypatch.setattr(core, "apply_requests", lambda *a: calls.append(list(a[3])) or real(*a))
    engine = engine_for(
        small,
        "ruleSet M:\n  rule d priority 2: activate_feature(Eco)\n"
        "  rule o priority 1: if (cdm.x > 1) activate_feature(Turbo)\n",
    )
    engine.tick(0.0, sample(0.0, x=2.0))
    assert calls == [[("activate", "Turbo")]]
    engine.tick(0.1, sample(0.1, x=2.0))
    assert len(calls) == 1  # Eco then Turbo while Turbo is selected: nothing to do
    assert "Turbo" in engine.tick(0.2, sample(0.2, x=2.0)).selection


def test_nothing_in_sight_gives_the_formulas_speed(fig5):
    """ObstDist = inf (no obstacle in the scan): 1 - e^(-inf) = 1, MaxVel follows the battery."""
    fm, model = fig5
    engine = AdaptationEngine(fm, ("Manipulation",), model)
    r = engine.tick(
        1.0,
        {"SemLoc": ("RoomA", 1.0), "BattLev": (80.0, 1.0), "ObstDist": (math.inf, 1.0)},
    )
    assert r.cv["MaxVel"] == pytest.approx(0.4 + 0.4 * 0.8)
    assert "ObstDist" not in r.undefined
