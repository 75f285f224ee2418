"""Operators' overrides and run-time conflicts in the pure engine (issue 11, deliverable 3):
forced features the rules cannot change, refused overrides, and conflicts in force reported
once when they start and once when they end."""

from __future__ import annotations

import pytest

from rra_agent.core.live_conflicts import ConflictTracker
from rra_agent.core.overrides import OverrideError
from tests.test_rules_engine import engine_for, sample, small_fm


@pytest.fixture
def small():
    return small_fm()


# ---- overrides ---------------------------------------------------------------------------
def test_a_forced_feature_stays_whatever_the_rules_say(small):
    engine = engine_for(
        small, "rule L: if (cdm.x > 1) activate_feature(Light) else deactivate_feature(Light)"
    )
    assert "Light" not in engine.tick(0.0, sample(0.0, x=0.0)).selection
    engine.force({"Light": "on"})
    r = engine.tick(0.1, sample(0.1, x=0.0))  # the rule says off
    assert "Light" in r.selection and r.changed
    (rej,) = r.rejected
    assert rej.rule == "L" and "forced on by an operator" in rej.reason
    engine.force({"Light": "auto"})
    assert "Light" not in engine.tick(0.2, sample(0.2, x=0.0)).selection  # the rule again
    engine.force({"Light": "off"})
    r = engine.tick(0.3, sample(0.3, x=5.0))  # the rule says on
    assert "Light" not in r.selection and r.rejected


def test_forcing_one_alternative_holds_against_a_rule_choosing_another(small):
    engine = engine_for(small, "rule T: activate_feature(Turbo)")
    assert "Turbo" in engine.tick(0.0, {}).selection
    engine.force({"Eco": "on"})
    r = engine.tick(0.1, {})
    assert "Eco" in r.selection and "Turbo" not in r.selection
    assert any("forced" in x.reason for x in r.rejected)


def test_refused_overrides_change_nothing(small):
    engine = engine_for(small, "rule L: activate_feature(Light)")
    engine.tick(0.0, {})
    with pytest.raises(OverrideError, match="Arm: not a run-time feature"):
        engine.force({"Arm": "on"})
    with pytest.raises(OverrideError, match="Soft: cannot be forced on"):
        engine.force({"Soft": "on"})  # Gripper => Arm, Arm not deployed
    with pytest.raises(OverrideError, match="Nope: no such feature"):
        engine.force({"Nope": "on"})
    with pytest.raises(OverrideError, match="expected on, off or auto"):
        engine.force({"Light": "maybe"})
    with pytest.raises(OverrideError, match="cannot"):
        engine.force({"Mode": "off"})  # mandatory
    with pytest.raises(OverrideError):
        engine.force({"Eco": "on", "Turbo": "on"})  # alternatives
    assert engine.forced == {}
    message = _error(lambda: engine.force({"Mode": "off"}))
    assert "\n" not in message


def test_overrides_and_a_forbidding_constraint(small):
    engine = engine_for(small, "rule L: activate_feature(Light)", {"Arm"})
    engine.tick(0.0, {})
    engine.force({"R1": "on"})
    engine.tick(0.1, {})
    with pytest.raises(OverrideError):
        engine.force({"R1": "off", "R2": "off", "R3": "off"})  # a group needs one
    assert engine.forced == {"R1": True}


def _error(fn) -> str:
    try:
        fn()
    except OverrideError as e:
        return str(e)
    raise AssertionError("not refused")


# ---- conflicts in force ----------------------------------------------------------------------
RULES = (
    "rule A period 0 ms: if (cdm.x > 0) activate_feature(Light)\n"
    "rule B period 0 ms: if (cdm.y > 5) deactivate_feature(Light)\n"
)


def test_a_conflict_lasts_while_both_wishes_stand_not_only_in_the_tick_both_fire(small):
    engine = engine_for(small, RULES)
    tracker = ConflictTracker()
    r = engine.tick(0.0, {**sample(0.0, x=1.0), **sample(0.0, y=0.0)})
    assert not r.active
    r = engine.tick(0.1, {**sample(0.0, x=1.0), **sample(0.1, y=9.0)})  # only B runs
    (c,) = r.active
    assert (c.kind, c.target, c.winner.rule, c.loser.rule, c.values) == (
        "feature",
        "Light",
        "B",
        "A",
        ("off", "on"),
    )
    started, ended = tracker.update(r.active, 0.1, {"x": 1.0, "y": 9.0})
    assert [s.describe() for s in started] == [
        "rules B and A on Light: B wants off, A wants on (context x=1.0, y=9.0); "
        "B applies (written later)"
    ]
    assert not ended
    for i in range(2, 30):  # neither runs again: the conflict stands, reported once
        r = engine.tick(i / 10, {**sample(0.0, x=1.0), **sample(0.1, y=9.0)})
        assert r.active and tracker.update(r.active, i / 10, {}) == ([], [])
    r = engine.tick(3.0, {**sample(0.0, x=1.0), **sample(3.0, y=0.0)})  # B withdraws
    assert not r.active
    started, ended = tracker.update(r.active, 3.0, {})
    assert not started and [(c.id, round(d, 3)) for c, d in ended] == [("feature:Light:B|A", 2.9)]


def test_conflict_context_and_values_of_attributes(small):
    engine = engine_for(
        small,
        "rule C: set_attribute(Vel) with_value(1)\n"
        "rule D: if (cdm.x > 5) set_attribute(Vel) with_value(0.2)\n",
    )
    r = engine.tick(1.0, sample(1.0, x=9.0))
    (c,) = r.active
    assert (c.kind, c.target, c.values) == ("attribute", "Motion.Vel", ("0.2", "1"))
    (live,), _ = ConflictTracker().update(r.active, 1.0, {"x": 9.0, "y": 3.0})
    assert live.context == {"x": 9.0} and live.wants == {"D": "0.2", "C": "1"}
    assert live.where["D"] == "r.rra:3:24"
    assert not engine.tick(2.0, sample(2.0, x=1.0)).active  # D ran and withdrew


def test_a_tracker_adopting_the_leaders_set_does_not_announce_it_again(small):
    engine = engine_for(small, RULES)
    r = engine.tick(0.0, {**sample(0.0, x=1.0), **sample(0.0, y=9.0)})
    leader = ConflictTracker()
    started, _ = leader.update(r.active, 0.0, {})
    standby = ConflictTracker()
    standby.adopt(leader.current)
    assert standby.update(r.active, 0.5, {}) == ([], [])
    _, ended = standby.update([], 1.0, {})
    assert [(c.id, d) for c, d in ended] == [(started[0].id, 1.0)]


# ---- scenarios: conflict(t) is a conflict that starts ----------------------------------------
def test_a_scenario_counts_a_conflict_when_it_starts_not_when_it_ends() -> None:
    from rra_agent.bus import messages as m
    from rra_agent.scenario import expectations as x
    from tests.test_scenario_model import T0, recording

    def report(t: float, state: str) -> m.ConflictReport:
        return m.ConflictReport(
            stamp=T0 + t, target="X", rules=["r1", "r2"], resolution="", state=state
        )

    rec = recording(selections=[report(2.0, "started"), report(5.0, "ended")])
    occurrences = [(o.t, o.kind) for o in x.Index(rec).occurrences if o.kind == "conflict"]
    assert occurrences == [(2.0, "conflict")]
