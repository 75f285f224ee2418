"""Which run-time configurations the rules can reach (issue 24, item 6): a static search over
the rules' actions with the conditions taken as free, per family of features."""

from __future__ import annotations

import random
from pathlib import Path

from rra_agent.core.adaptation import AdaptationEngine
from rra_agent.core.reachable import reachable, rule_requests
from rra_agent.dsl.rules import parse_rules
from rra_agent.dsl.uvl import parse_uvl
from rra_agent.package.loader import load_package

ROOT = Path(__file__).resolve().parents[1]

UVL = """namespace R
features
    R {abstract}
        mandatory
            Mode {binding 'runtime'}
                alternative
                    Eco {default}
                    Normal
                    Boost
        optional
            Light {binding 'runtime'}
            Horn {binding 'runtime'}
"""
RULES = """import m as cdm
rule M: if (cdm.x > 1) activate_feature(Normal) else activate_feature(Eco)
rule L: if (cdm.y) activate_feature(Light) else deactivate_feature(Light)
"""


def test_a_feature_no_rule_activates_and_no_default_is_never_reached():
    fm = parse_uvl(UVL, "r.uvl")
    model = parse_rules(RULES, "r.rra", fm, None)
    r = reachable(fm, (), model)
    assert r.complete and r.never == ("Boost", "Horn")
    assert r.count == 4  # {Eco, Normal} x {Light, no Light}
    configs = r.configurations()
    assert r.start in configs and len(configs) == 3  # one family varied at a time
    assert sorted(sorted(fs) for fs, _ in r.alternatives()) == [["Boost", "Eco", "Mode",
                                                                 "Normal"], ["Light"]]  # fmt: skip


def test_from_the_current_configuration_a_latch_reaches_nothing_else():
    pkg = load_package(ROOT / "scenarios" / "quadcopter")
    assert pkg.adaptation is not None
    start = reachable(pkg.features, {"Hover"}, pkg.adaptation)
    assert start.count == 2 and not start.never
    latched = reachable(pkg.features, {"Hover"}, pkg.adaptation, {"Controller", "Proploss"})
    assert latched.count == 1 and latched.never == ("Standard",)


def test_forced_and_unavailable_features_constrain_what_is_reachable():
    fm = parse_uvl(UVL, "r.uvl")
    model = parse_rules(RULES, "r.rra", fm, None)
    r = reachable(fm, (), model, forced={"Light": False})
    assert "Light" in r.never and r.count == 2
    r = reachable(fm, (), model, unavailable={"Normal"})
    assert "Normal" in r.never


def test_a_search_cut_short_claims_nothing_unreachable():
    fm = parse_uvl(UVL, "r.uvl")
    model = parse_rules(RULES, "r.rra", fm, None)
    r = reachable(fm, (), model, max_states=1)
    assert not r.complete
    assert r.never == ("Horn",)  # Boost's family was cut short: nothing said about it


def test_the_shipped_packages_reach_every_run_time_feature():
    for name, select in (("object_storing", {"Manipulation"}), ("quadcopter", {"Hover"})):
        pkg = load_package(ROOT / "scenarios" / name)
        assert pkg.adaptation is not None
        r = reachable(pkg.features, select, pkg.adaptation)
        assert r.complete and r.never == (), name


def test_every_selection_a_run_reaches_is_found():
    """Property: what the engine reaches on random measurements is within the search."""
    fm = parse_uvl(UVL, "r.uvl")
    model = parse_rules(
        RULES + "rule B: if (cdm.x > 5 AND cdm.y) activate_feature(Boost)\n", "r.rra", fm, None
    )
    r = reachable(fm, (), model)
    family = {frozenset(s) for fam in r.families for s in fam.states}
    assert r.never == ("Horn",)
    engine = AdaptationEngine(fm, (), model)
    rng = random.Random(4)
    for i in range(300):
        sel = engine.tick(i, {"x": (rng.uniform(0, 8), i), "y": (rng.random() < 0.5, i)}).selection
        for fam in r.families:
            assert sel & set(fam.features) in family
    assert ("activate", "Boost") in rule_requests(model, fm, r.selectable)
