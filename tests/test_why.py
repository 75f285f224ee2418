"""Why a selection is what it is (issue 24, item 3), in the pure engine: each change names the
action that made it (not every rule that fired), the values it read with their stamps, and
the fired actions that wanted otherwise with the reason they lost: a higher priority in the
rule set, a later rule in a run-time conflict, an operator's override, an NFR clamp of a CV,
an unavailable feature. `why` answers for the current state."""

from __future__ import annotations

from pathlib import Path

import pytest

from rra_agent.core.adaptation import AdaptationEngine, Why
from rra_agent.dsl.rules import load_rules, parse_rules
from rra_agent.dsl.uvl import load_uvl
from rra_agent.models.measurements import MeasurementsModel
from rra_agent.package.yamlload import load_yaml

ROOT = Path(__file__).resolve().parents[1]
AGV = ROOT / "tests" / "data" / "agv"
OS = ROOT / "scenarios" / "object_storing"

#: The issue's case: Zone would keep NormalZone for "near", but SafetyZone (written later)
#: selects HumanZone; Sensor, Signal and Speed fire on every tick and change nothing.
SAFETY = """
rule SafetyZone:
    if (cdm.Zone == "human" OR "near")
        activate_feature(HumanZone)
"""


def agv(extra: str = SAFETY) -> AdaptationEngine:
    fm = load_uvl(AGV / "features.uvl")
    meas = load_yaml(AGV / "measurements.yaml", MeasurementsModel)[0]
    text = (AGV / "adaptation.rra").read_text() + extra
    return AdaptationEngine(fm, (), parse_rules(text, "agv.rra", fm, meas))


def fig5() -> AdaptationEngine:
    fm = load_uvl(OS / "features.uvl")
    meas = load_yaml(OS / "measurements.yaml", MeasurementsModel)[0]
    return AdaptationEngine(fm, {"Manipulation"}, load_rules(OS / "adaptation.rra", fm, meas))


def by_target(whys: list[Why]) -> dict[str, Why]:
    return {w.target: w for w in whys}


def os_sample(now: float, loc: str, batt: float = 80.0) -> dict:
    values = {"SemLoc": loc, "BattLev": batt, "ObstDist": 3.0, "Material": "Glass"}
    return {k: (v, now - 0.01) for k, v in values.items()}


def test_the_rule_that_changed_the_selection_is_named_not_the_first_that_fired():
    engine = agv()
    engine.tick(1.0, {"Zone": ("normal", 0.9)}, explain=True)
    r = engine.tick(2.0, {"Zone": ("near", 1.95)}, explain=True)
    assert {"HumanZone"} <= r.selection
    why = by_target(r.why)
    assert set(why) == {"HumanZone", "NormalZone", "MaxSpeed"}  # only what changed
    for target in ("HumanZone", "NormalZone"):
        w = why[target]
        assert w.reason == "rule" and [f.rule for f in w.by] == ["SafetyZone"]
        assert w.reads == {"Zone": ("near", 1.95)}  # the value it read, with its stamp
        assert w.since == 2.0
        (lost,) = w.overruled  # Zone wanted NormalZone: a later rule won
        assert lost.rule == "Zone" and lost.why == "later_rule"
        assert "SafetyZone" in lost.detail
    assert why["HumanZone"].value == "on" and why["NormalZone"].value == "off"
    # Sensor, Signal and Speed fired too, but changed nothing: no explanation names them
    named = {f.rule for w in r.why for f in w.by} | {o.rule for w in r.why for o in w.overruled}
    assert {"Sensor", "Signal"}.isdisjoint(named)
    assert {f.rule for f in r.fired} >= {"Zone", "Sensor", "Signal", "Speed", "SafetyZone"}


def test_a_cv_clamped_by_an_nfr_names_the_change_that_made_the_nfr_apply():
    engine = agv()
    engine.tick(1.0, {"Zone": ("normal", 0.9)}, explain=True)
    r = engine.tick(2.0, {"Zone": ("near", 1.95)}, explain=True)
    w = by_target(r.why)["MaxSpeed"]
    assert (w.value, w.reason) == ("0.5", "nfr")
    assert [f.rule for f in w.by] == ["SafetyZone"]  # it selected HumanZone, whose NFR applies
    assert "SpeedLimit" in w.detail and "HumanZone" in w.detail
    (lost,) = w.overruled
    assert (lost.rule, lost.wants, lost.why) == ("Speed", "1.4", "nfr")
    r = engine.tick(3.0, {"Zone": ("normal", 2.95)}, explain=True)
    w = by_target(r.why)["MaxSpeed"]
    assert (w.value, w.reason) == ("1.4", "nfr") and "no longer applies" in w.detail
    assert [f.rule for f in w.by] == ["Zone"]


def test_a_higher_priority_in_the_rule_set_overrules():
    engine = fig5()
    engine.tick(1.0, os_sample(1.0, "RoomA"), explain=True)
    r = engine.tick(2.0, os_sample(2.0, "Corridor"), explain=True)
    w = by_target(r.why)["MaxVel"]
    assert w.reason == "rule" and [f.rule for f in w.by] == ["maxVelCorridor"]
    assert w.by[0].ruleset == "MaxVelocity" and w.value == "0.5"
    assert w.reads["SemLoc"] == ("Corridor", 1.99)
    (lost,) = w.overruled
    assert (lost.rule, lost.why) == ("maxVelBattObst", "priority")
    assert "priority 1" in lost.detail and "MaxVelocity" in lost.detail


def test_an_operator_override_overrules_the_rules():
    engine = fig5()
    engine.tick(1.0, os_sample(1.0, "RoomA", batt=80.0), explain=True)  # ChannelB: low latency
    engine.force({"ChannelA": "on"})
    r = engine.tick(2.0, os_sample(2.0, "RoomA", batt=80.0), explain=True)
    why = by_target(r.why)
    assert why["ChannelA"].reason == "operator" and "forced ChannelA on" in why["ChannelA"].detail
    (lost,) = why["ChannelA"].overruled  # Radio wants ChannelB
    assert (lost.rule, lost.wants, lost.why) == ("Radio", "ChannelB", "operator")
    # and now, on the current state
    (now,) = engine.why(["ChannelA"])
    assert now.reason == "operator" and [o.why for o in now.overruled] == ["operator"]


def test_an_unavailable_feature_overrules_the_rule_that_wants_it():
    engine = agv(extra="")
    engine.tick(1.0, {"Zone": ("normal", 0.9)}, explain=True)
    engine.set_unavailable({"HumanZone": "zone_driver: exited with status 1"})
    r = engine.tick(2.0, {"Zone": ("human", 1.95)}, explain=True)
    assert "HumanZone" not in r.selection
    (now,) = engine.why(["HumanZone"])
    assert now.value == "off"
    (lost,) = now.overruled
    assert (lost.rule, lost.why) == ("Zone", "unavailable") and "exited" in lost.detail
    assert any(w.target == "DepthCamera" and w.by[0].rule == "Sensor" for w in r.why)


def test_leaving_an_unavailable_feature_is_explained_as_such():
    engine = agv(extra="")
    engine.tick(1.0, {"Zone": ("human", 0.9)}, explain=True)
    engine.set_unavailable({"DepthCamera": "no camera"})
    r = engine.tick(2.0, {"Zone": ("human", 1.9)}, explain=True)
    why = by_target(r.why)
    camera = why["DepthCamera"]  # Sensor's select takes the best variant still available
    assert why["Lidar"].value == "on" and camera.value == "off"
    assert [f.rule for f in camera.by] == ["Sensor"]
    assert "DepthCamera, is unavailable: no camera" in camera.detail


def test_a_selected_feature_left_for_an_unavailable_one_says_so():
    engine = agv(extra="")
    engine.tick(1.0, {"Zone": ("human", 0.9)}, explain=True)
    engine.set_unavailable({"HumanZone": "zone driver crashed"})
    r = engine.tick(2.0, {}, explain=True)  # no measurement: no rule fires on Zone
    why = by_target(r.why)
    assert why["HumanZone"].reason == "unavailable" and "crashed" in why["HumanZone"].detail
    assert why["NormalZone"].reason == "unavailable" and "in place of HumanZone" in (
        why["NormalZone"].detail
    )


def test_why_answers_for_the_current_state():
    engine = agv()
    engine.tick(1.0, {"Zone": ("near", 0.9)}, explain=True)
    for _ in range(3):  # ticks that change nothing keep the explanation of the change
        engine.tick(1.5, {"Zone": ("near", 1.4)}, explain=True)
    human, normal, speed = engine.why(["HumanZone", "NormalZone", "MaxSpeed"])
    assert human.value == "on" and [f.rule for f in human.by] == ["SafetyZone"]
    assert human.since == 1.0 and human.reads == {"Zone": ("near", 0.9)}
    assert [(o.rule, o.why) for o in human.overruled] == [("Zone", "later_rule")]
    assert normal.value == "off"
    assert [(o.rule, o.why) for o in speed.overruled] == [("Speed", "nfr")]
    (beacon,) = engine.why(["Beacon"])  # never changed: the default
    assert (beacon.value, beacon.reason, beacon.since) == ("off", "default", None)
    assert [w.target for w in engine.why()] == [n for _, n in engine.targets()]


def test_why_refuses_unknown_names_with_a_suggestion():
    engine = agv()
    with pytest.raises(KeyError, match="did you mean HumanZone"):
        engine.why(["HumanZon"])
    assert engine.target("Motion.MaxSpeed") == ("cv", "MaxSpeed")
    assert engine.target("MaxSpeed") == ("cv", "MaxSpeed")


def test_explaining_changes_nothing_decided():
    plain, explained = fig5(), fig5()
    rooms = ("RoomA", "RoomB", "Corridor")
    previous = explained.selection
    for i in range(60):
        s = os_sample(i * 0.1 + 0.1, rooms[i % 3], batt=(20.0, 80.0)[i // 3 % 2])
        a = plain.tick(i * 0.1 + 0.1, s)
        b = explained.tick(i * 0.1 + 0.1, s, explain=True)
        assert (a.selection, a.cv, a.changed) == (b.selection, b.cv, b.changed)
        assert not a.why
        assert bool(b.why) == b.changed
        assert {w.target for w in b.why if w.kind == "feature"} == previous ^ b.selection
        previous = b.selection


def test_adopting_a_leaders_explanations():
    leader, standby = agv(), agv()
    leader.tick(1.0, {"Zone": ("near", 0.9)}, explain=True)
    r = leader.tick(2.0, {"Zone": ("near", 1.9)}, explain=True)
    standby.adopt(leader.selection, leader.cv)
    (before,) = standby.why(["HumanZone"])
    assert before.reason == "resumed"
    standby.note(leader.provenance.values())
    (after,) = standby.why(["HumanZone"])
    assert [f.rule for f in after.by] == ["SafetyZone"] and not r.why
