"""Failure as context: features that need an unavailable implementation (the rule engine's
side, `Engine.set_unavailable`, and the feature -> implementation map of
`rra_agent.core.availability`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rra_agent.core.adaptation import AdaptationEngine
from rra_agent.core.availability import (
    implementation_key,
    requirements,
    unavailable_features,
)
from rra_agent.dsl.rules import parse_rules
from rra_agent.package.loader import load_package

ROOT = Path(__file__).resolve().parents[1]
OS = ROOT / "scenarios" / "object_storing"


@pytest.fixture(scope="module")
def pkg():
    return load_package(OS)


def ctx(now: float, **values):
    return {name: (value, now) for name, value in values.items()}


def engine(pkg) -> AdaptationEngine:
    assert pkg.adaptation is not None
    return AdaptationEngine(pkg.features, pkg.manifest.default_selection, pkg.adaptation)


CONTEXT = {"SemLoc": "RoomA", "BattLev": 80.0, "ObstDist": 2.0, "Material": "Glass"}


def test_requirements_name_what_each_feature_launches(pkg):
    needs = requirements(pkg.features, pkg.runtime)
    assert needs["ChannelB"] == {("radio_driver_b", "")}
    assert needs["Dynamic"] == {("local_navigation", "dynamic")}
    assert "Small" not in needs  # only parameters
    why = unavailable_features(needs, {("radio_driver_b", ""): "RuntimeError: no antenna"})
    assert why == {"ChannelB": "radio_driver_b is unavailable: RuntimeError: no antenna"}
    nav = pkg.system.component("local_navigation")
    assert implementation_key(nav, nav.implementations["dynamic"]) == "dynamic"
    assert implementation_key(nav, nav.implementation) == ""


def test_a_select_picks_the_best_variant_still_available(pkg):
    e = engine(pkg)
    assert "ChannelB" in e.tick(1.0, ctx(1.0, **CONTEXT)).selection  # MIN(Latency)
    assert e.set_unavailable({"ChannelB": "radio_driver_b is unavailable: no antenna"})
    result = e.tick(2.0, ctx(1.0, **CONTEXT))  # nothing new: every rule runs again
    assert "ChannelA" in result.selection and "ChannelB" not in result.selection
    assert result.changed
    # re-admitted: the rules pick ChannelB again
    assert e.set_unavailable({})
    assert "ChannelB" in e.tick(3.0, ctx(1.0, **CONTEXT)).selection
    assert not e.set_unavailable({})  # no change, no full tick


def test_activating_an_unavailable_feature_is_rejected_as_unavailable(pkg):
    e = engine(pkg)
    e.tick(1.0, ctx(1.0, **CONTEXT))
    e.set_unavailable({"Dynamic": "local_navigation (dynamic) is unavailable: crashed"})
    result = e.tick(2.0, ctx(2.0, **{**CONTEXT, "SemLoc": "Corridor"}))
    assert "Static" in result.selection and "Dynamic" not in result.selection
    [rejected] = [r for r in result.rejected if r.unavailable]
    assert rejected.rule == "Location" and rejected.unavailable == "Dynamic"
    assert "crashed" in rejected.reason


def test_a_selected_feature_that_becomes_unavailable_is_left_where_the_model_allows(pkg):
    """No rule asks for it any more: the engine itself moves to an available sibling."""
    fm = pkg.features
    rules = parse_rules(
        "import c.m as cdm\nrule Once period 100000 ms:\n"
        "    if (cdm.BattLev > 0) activate_feature(ChannelB)\n",
        "once.rra",
        fm,
        pkg.measurements,
    )
    e = AdaptationEngine(fm, pkg.manifest.default_selection, rules)
    assert "ChannelB" in e.tick(1.0, ctx(1.0, BattLev=80.0)).selection
    e.set_unavailable({"ChannelB": "radio_driver_b is unavailable: gone"})
    assert "ChannelA" in e.tick(2.0, ctx(1.0, BattLev=80.0)).selection


def test_an_operator_forcing_an_unavailable_feature_on_wins(pkg):
    e = engine(pkg)
    e.set_unavailable({"ChannelB": "radio_driver_b is unavailable: gone"})
    e.force({"ChannelB": "on"})
    assert "ChannelB" in e.tick(1.0, ctx(1.0, **CONTEXT)).selection
