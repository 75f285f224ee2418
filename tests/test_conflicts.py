"""Static conflict analysis: opposing actions that can fire in one tick, with both locations."""

from __future__ import annotations

from pathlib import Path

import pytest

from rra_agent.core.conflicts import Conflict, check_conflicts
from rra_agent.dsl.rules import load_rules, parse_rules
from rra_agent.dsl.uvl import load_uvl
from rra_agent.models.measurements import Measurement, MeasurementsModel
from rra_agent.package.yamlload import load_yaml

ROOT = Path(__file__).resolve().parents[1]
OS = ROOT / "scenarios" / "object_storing"


@pytest.fixture(scope="module")
def fm():
    return load_uvl(OS / "features.uvl")


@pytest.fixture(scope="module")
def meas():
    extra = [
        Measurement(name="Motors", type="int", source="q.telemetry"),
        Measurement(name="Docked", type="bool", source="r.dock"),
    ]
    base = load_yaml(OS / "measurements.yaml", MeasurementsModel)[0]
    return MeasurementsModel(measurements=[*base.measurements, *extra])


def conflicts(text, fm, meas) -> list[Conflict]:
    model = parse_rules("import m as cdm\n" + text, "c.rra", fm, meas)
    return check_conflicts(model, fm)


def summary(cs: list[Conflict]):
    return [(c.kind, c.target, c.first.rule, c.second.rule, c.certain) for c in cs]


def test_fig5_has_no_conflicts(fm, meas):
    model = load_rules(OS / "adaptation.rra", fm, meas)
    assert check_conflicts(model, fm) == []


def test_planted_conflict_is_reported_with_both_locations(fm, meas):
    text = (
        "rule Eco:\n"
        "    if (cdm.BattLev < 30) activate_feature(Static)\n"
        "rule Busy:\n"
        "    if (cdm.BattLev < 50 AND cdm.SemLoc == 'Corridor') activate_feature(Dynamic)\n"
    )
    (c,) = conflicts(text, fm, meas)
    assert (c.kind, c.target, c.certain) == ("alternative", "the alternatives of Environment", True)
    assert (c.first.rule, c.first.action) == ("Eco", "activate_feature(Static)")
    assert (c.second.rule, c.second.action) == ("Busy", "activate_feature(Dynamic)")
    assert (c.first.span.line, c.first.span.col) == (3, 27)
    assert (c.second.span.line, c.second.span.col) == (5, 56)
    assert c.render() == (
        "c.rra:3:27: conflict: rules Eco and Busy can fire in the same tick with opposite "
        "effects on the alternatives of Environment: activate_feature(Static) vs "
        "activate_feature(Dynamic)\n    c.rra:5:56: activate_feature(Dynamic)"
    )


@pytest.mark.parametrize(
    ("a", "b", "expect"),
    [
        ("cdm.BattLev < 30", "cdm.BattLev >= 30", None),
        ("cdm.BattLev < 30", "cdm.BattLev > 29.5", True),
        ("cdm.BattLev <= 30", "cdm.BattLev >= 30", True),
        ("cdm.BattLev < 30", "cdm.BattLev == 30", None),
        ("cdm.BattLev == 30", "cdm.BattLev != 30", None),
        ("30 > cdm.BattLev", "cdm.BattLev > 40", None),  # constant on the left
        ('cdm.BattLev > "50"', "cdm.BattLev < 50", None),  # quoted numbers are numbers
        ("cdm.Motors < 4", "cdm.Motors > 3", None),  # int: nothing strictly between 3 and 4
        ("cdm.Motors < 4", "cdm.Motors > 2", True),
        ("cdm.Motors > 2 AND cdm.Motors < 4", "cdm.Motors != 3", None),
        ("cdm.ObstDist < 4", "cdm.ObstDist > 3", True),  # float: 3.5
        ("cdm.SemLoc == 'RoomA'", "cdm.SemLoc == 'RoomB'", None),
        ("cdm.SemLoc == 'RoomA'", "cdm.SemLoc != 'RoomB'", True),
        ("cdm.SemLoc == 'RoomA' OR 'RoomB'", "cdm.SemLoc == 'Corridor'", None),
        ("cdm.SemLoc == 'RoomA' OR 'RoomB'", "cdm.SemLoc == 'RoomB'", True),
        ("NOT (cdm.SemLoc == 'RoomA')", "cdm.SemLoc == 'RoomA'", None),
        ("cdm.Docked", "NOT cdm.Docked", None),
        ("cdm.Docked == true", "cdm.Docked != false", True),
        ("MaxVel > 0.6", "MaxVel < 0.5", None),  # CV values are variables too
        ("MaxVel.max > 0.5", "true", True),  # constant conditions are folded
        ("MaxVel.max < 0.5", "true", None),
        ("1 / 0 > 0", "true", None),  # undefined: never fires
        ("cdm.BattLev * 2 > cdm.ObstDist", "cdm.BattLev < 10", False),  # not understood
        ("cdm.BattLev * 2 > cdm.ObstDist", "NOT (cdm.BattLev * 2 > cdm.ObstDist)", None),
        ("cdm.BattLev > 10 AND cdm.BattLev * 2 > 1", "cdm.BattLev < 5", None),
    ],
)
def test_interval_reasoning(fm, meas, a, b, expect):
    text = (
        f"rule A: if ({a}) activate_feature(Static)\nrule B: if ({b}) activate_feature(Dynamic)\n"
    )
    found = conflicts(text, fm, meas)
    assert [c.certain for c in found] == ([] if expect is None else [expect])


def test_if_else_branches_are_disjoint(fm, meas):
    text = (
        "rule A: if (cdm.SemLoc == 'RoomA') activate_feature(Small)\n"
        "rule B: if (cdm.SemLoc == 'RoomA') activate_feature(Small)\n"
        "        else if (cdm.BattLev > 50) deactivate_feature(Small)\n"
        "        else activate_feature(Large)\n"
    )
    assert conflicts(text, fm, meas) == []


def test_opposite_feature_actions(fm, meas):
    text = (
        "rule On: activate_feature(Small)\n"
        "rule Off: if (cdm.BattLev < 5) deactivate_feature(Small)\n"
        "rule Parent: if (cdm.SemLoc == 'x') deactivate_feature(RackSize)\n"
        "rule Child: if (cdm.SemLoc == 'y') activate_feature(Large)\n"
    )
    assert summary(conflicts(text, fm, meas)) == [
        ("feature", "Small", "On", "Off", True),
        ("feature", "RackSize", "On", "Parent", True),  # activating Small needs RackSize
        ("alternative", "the alternatives of RackSize", "On", "Child", True),
    ]  # Parent and Child never fire together (SemLoc cannot be both 'x' and 'y')


def test_two_set_attribute_of_one_cv(fm, meas):
    text = (
        "rule A: set_attribute(MaxVel) with_value(0.5)\n"
        "rule B: if (cdm.SemLoc == 'Corridor') set_attribute(MaxVel) with_value(0.4)\n"
        "ruleSet S:\n"
        "  rule c priority 2: set_attribute(MaxVel) with_value(0.6)\n"
        "  rule d priority 1: set_attribute(MaxVel) with_value(0.7)\n"
    )
    found = summary(conflicts(text, fm, meas))
    assert ("attribute", "Motion Behavior.MaxVel", "A", "B", True) in found
    assert not [f for f in found if {f[2], f[3]} == {"c", "d"}]  # one rule set: priorities
    assert len(found) == 5  # A-B, A-c, A-d, B-c, B-d


def test_actions_of_one_branch_are_compared(fm, meas):
    found = conflicts("rule R: activate_feature(Small AND Large)", fm, meas)
    assert summary(found) == [("alternative", "the alternatives of RackSize", "R", "R", True)]


def test_select_counts_as_activating_its_best_variant(fm, meas):
    best = "rule S: select_feature_from_variants_of(CommunicChannel) where_attribute MIN(Latency)\n"
    assert conflicts(best + "rule A: activate_feature(ChannelB)", fm, meas) == []
    (c,) = conflicts(best + "rule A: activate_feature(ChannelA)", fm, meas)
    assert (c.kind, c.first.rule, c.second.rule) == ("alternative", "S", "A")


def test_results_are_in_file_order(fm, meas):
    text = (
        "rule A: activate_feature(Fragile)\nrule B: activate_feature(Small)\n"
        "rule C: activate_feature(Large)\nrule D: activate_feature(Firm)\n"
    )
    assert [(c.first.rule, c.second.rule) for c in conflicts(text, fm, meas)] == [
        ("A", "D"),
        ("B", "C"),
    ]


def test_large_guards_degrade_to_may_conflict(fm, meas):
    big = " AND ".join(f"(cdm.BattLev > {i} OR cdm.ObstDist > {i})" for i in range(10))
    text = f"rule A: if ({big}) activate_feature(Static)\nrule B: activate_feature(Dynamic)\n"
    (c,) = conflicts(text, fm, meas)
    assert c.certain is False
    assert c.render().startswith("c.rra:2:")
    assert "may conflict" in c.message
