"""The rule DSL: Fig. 5 notation, name resolution, types, located errors, robustness."""

from __future__ import annotations

import math
from pathlib import Path

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rra_agent.dsl.rules import MAX_DEPTH, load_rules, parse_rules
from rra_agent.dsl.uvl import load_uvl, parse_uvl
from rra_agent.errors import DslSyntaxError, ErrorGroup, RraError, SemanticError
from rra_agent.models.adaptation import (
    Activate,
    AdaptationModel,
    Arith,
    AttrValue,
    Bool,
    Bound,
    Compare,
    Const,
    Deactivate,
    Logic,
    Measure,
    Num,
    RuleSet,
    SelectVariant,
    SetAttribute,
    Str,
    measures_read,
)
from rra_agent.models.features import Attribute, Feature, FeatureModel, Group
from rra_agent.models.measurements import Measurement, MeasurementsModel
from rra_agent.package.yamlload import load_yaml

ROOT = Path(__file__).resolve().parents[1]
OS = ROOT / "scenarios" / "object_storing"
QC = ROOT / "scenarios" / "quadcopter"


@pytest.fixture(scope="module")
def fm():
    return load_uvl(OS / "features.uvl")


@pytest.fixture(scope="module")
def meas():
    return load_yaml(OS / "measurements.yaml", MeasurementsModel)[0]


def parse(text, fm, meas, file="t.rra"):
    return parse_rules(text, file, fm, meas)


def error_of(text, fm, meas) -> RraError:
    with pytest.raises(RraError) as info:
        parse(text, fm, meas)
    return info.value


def messages(err: RraError) -> list[str]:
    errs = err.errors if isinstance(err, ErrorGroup) else [err]
    return [e.headline for e in errs]  # type: ignore[attr-defined]


IMPORT = "import caseStudy.contextDepMeasModel as cdm\n"


# ---- the grammar -------------------------------------------------------------------------
def test_grammar_is_strict_lalr():
    from rra_agent.dsl.rules import _parser

    parser = _parser()
    assert parser.options.parser == "lalr" and parser.options.strict


# ---- Fig. 5 --------------------------------------------------------------------------------
def test_fig5_parses_into_the_papers_structure(fm, meas):
    model = load_rules(OS / "adaptation.rra", fm, meas)
    assert [i.name for i in model.items] == [
        "Location",
        "RackSize",
        "Radio",
        "MaxVelocity",
        "ObjMaterial",
    ]
    assert model.imports[0].alias == "cdm"
    assert model.imports[0].module == "caseStudy.contextDepMeasModel"
    location, racksize, radio, maxvel, material = model.items

    # `cdm.SemLoc == "RoomA" OR "RoomB"` means SemLoc == RoomA OR SemLoc == RoomB.
    cond = location.branches[0].condition
    assert isinstance(cond, Logic) and cond.op == "or"
    for side, room in ((cond.left, "RoomA"), (cond.right, "RoomB")):
        assert side.op == "=="
        assert side.left == Measure(name="SemLoc", type="str", max_age_ms=2000, span=side.left.span)
        assert isinstance(side.right, Str) and side.right.value == room
    assert location.branches[1].condition is None

    assert len(racksize.branches) == 3
    last = racksize.branches[2].actions[0]
    assert isinstance(last, Deactivate)
    assert [f.name for f in last.features] == ["Large", "Small"]

    # "50" is the number 50; the variation point's quoted name is the canonical feature.
    gt = radio.branches[0].condition
    assert gt.op == ">" and gt.right == Num(value=50.0, span=gt.right.span, quoted=True)
    sel = radio.branches[0].actions[0]
    assert isinstance(sel, SelectVariant)
    assert (sel.point.name, sel.attribute, sel.extremum) == ("Communic. Channel", "Latency", "min")
    assert radio.branches[1].actions[0].attribute == "PowerConsump"

    assert isinstance(maxvel, RuleSet)
    assert [(r.name, r.priority) for r in maxvel.rules] == [
        ("maxVelBattObst", 2),
        ("maxVelCorridor", 1),
    ]
    assert [r.name for r in maxvel.by_evaluation()] == ["maxVelBattObst", "maxVelCorridor"]
    formula = maxvel.rules[0].branches[0].actions[0]
    assert isinstance(formula, SetAttribute)
    assert (formula.target.feature, formula.target.name) == ("Motion Behavior", "MaxVel")
    assert measures_read(formula.value) == ("BattLev", "ObstDist")  # bare names resolved
    nodes = _nodes(formula.value)
    assert Bound(feature="Motion Behavior", attribute="MaxVel", bound="min") in nodes
    assert Bound(feature="Motion Behavior", attribute="MaxVel", bound="max") in nodes
    power = next(n for n in nodes if isinstance(n, Arith) and n.op == "^")
    assert isinstance(power.left, Const) and power.left.name == "e"
    cap = maxvel.rules[1].branches[0].actions[0]
    assert cap.value == AttrValue(
        feature="Dynamic", attribute="VelocityLimit", kind="nfr", span=cap.value.span
    )
    fragile = material.branches[0].actions[0]
    assert isinstance(fragile, Activate) and fragile.features[0].name == "Fragile"


def _nodes(expr):
    """Every node with all spans removed, for structural comparison."""
    from rra_agent.models.adaptation import walk

    return [_strip(n) for n in walk(expr)]


def _strip(x):
    if isinstance(x, tuple):
        return tuple(_strip(v) for v in x)
    if isinstance(x, msgspec.Struct):
        fields = {f: _strip(getattr(x, f)) for f in x.__struct_fields__ if f != "span"}
        return type(x)(**fields)
    return x


def test_fig5_as_printed_character_for_character(fm, meas):
    """The figure's own spelling: U+02C6 as the power sign, a line break inside
    `MaxVel.\\nmax`, bare measurement names."""
    text = (
        IMPORT + "ruleSet MaxVelocity:\nrule maxVelBattObst priority 2:\n"
        "set_attribute(MaxVel) with_value(MaxVel.min + (MaxVel.\n"
        "max-MaxVel.min)*(BattLev/100)*[1-e\u02c6(-ObstDist)])\n"
        'rule maxVelCorridor priority 1:\nif( cdm.SemLoc == "Corridor" )\n'
        "set_attribute(MaxVel) with_value(VelocityLimit)\n"
    )
    model = parse(text, fm, meas)
    assert [r.name for r in model.items[0].by_evaluation()] == ["maxVelBattObst", "maxVelCorridor"]


def test_multiword_feature_unquoted_is_a_syntax_error_with_a_hint(fm, meas):
    err = error_of(
        "rule Radio: select_feature_from_variants_of(Communic. Channel) where_attribute "
        "MIN(Latency)",
        fm,
        meas,
    )
    assert isinstance(err, DslSyntaxError)
    assert err.headline == (
        "t.rra:1:53: unexpected '.', expected ')' (multi-word feature names are written "
        "quoted or by their alias)"
    )


def test_alias_and_quoted_name_are_the_same_feature(fm, meas):
    a = parse("rule R: activate_feature(CommunicChannel)", fm, meas)
    b = parse('rule R: activate_feature("Communic. Channel")', fm, meas)
    assert a.items[0].branches[0].actions[0].features[0].name == "Communic. Channel"
    assert b.items[0].branches[0].actions[0].features[0].name == "Communic. Channel"


# ---- measurement names: prefix, bare, case ----------------------------------------------
def test_measurement_case_insensitive_match(fm, meas):
    model = parse(
        IMPORT + 'rule R: if (cdm.material == "Glass") activate_feature(Fragile)', fm, meas
    )
    assert model.items[0].branches[0].condition.left.name == "Material"


def test_unknown_measurement_suggests_the_model_name(fm, meas):
    err = error_of(IMPORT + "rule R: if (cdm.batteryLevel > 50) activate_feature(Static)", fm, meas)
    assert err.headline == "t.rra:2:13: unknown measurement batteryLevel (did you mean BattLev?)"
    assert err.source_line == "rule R: if (cdm.batteryLevel > 50) activate_feature(Static)"
    assert str(err).endswith("\n                ^")


def test_prefix_without_import_is_reported(fm, meas):
    err = error_of('rule R: if (cdm.SemLoc == "A") activate_feature(Static)', fm, meas)
    assert "no import declares cdm" in err.headline


def test_case_insensitive_ambiguity_is_a_located_error(fm):
    two = MeasurementsModel(
        measurements=[
            Measurement(name="Speed", type="float", source="a.b"),
            Measurement(name="speed", type="float", source="a.c"),
        ]
    )
    err = error_of(IMPORT + "rule R: if (cdm.SPEED > 1) activate_feature(Static)", fm, two)
    assert (
        err.headline
        == "t.rra:2:13: measurement SPEED is ambiguous: it matches Speed, speed ignoring case"
    )
    bare = error_of("rule R: if (SPEED > 1) activate_feature(Static)", fm, two)
    assert messages(bare) == [
        "t.rra:1:13: measurement SPEED is ambiguous: it matches Speed, speed ignoring case"
    ]
    # exact names still work
    parse(IMPORT + "rule R: if (cdm.speed > 1 AND Speed < 3) activate_feature(Static)", fm, two)


def test_bare_name_both_measurement_and_attribute_is_ambiguous(fm):
    clash = MeasurementsModel(measurements=[Measurement(name="MaxVel", type="float", source="a.b")])
    err = error_of("rule R: if (MaxVel > 1) activate_feature(Static)", fm, clash)
    assert "MaxVel is both a measurement and an attribute" in err.headline
    parse(IMPORT + "rule R: if (cdm.MaxVel > 1) activate_feature(Static)", fm, clash)


def test_without_a_measurements_model_names_are_unchecked(fm):
    text = "rule R: if (cdm.Anything > 1 AND Other == 'x') activate_feature(Static)"
    model = parse(IMPORT + text, fm, None)
    cond = model.items[0].branches[0].condition
    assert cond.left.left == Measure(name="Anything", type=None, span=cond.left.left.span)
    assert cond.right.left.name == "Other"


# ---- attributes -----------------------------------------------------------------------------
def test_attribute_names_qualified_bounds_and_ambiguity(fm, meas):
    ok = parse(
        'rule R: if (ChannelA.Latency == "High" AND MotionBehavior.MaxVel.max > 0.5 '
        "AND MaxVel < 0.6) activate_feature(Static)",
        fm,
        meas,
    )
    cond = ok.items[0].branches[0].condition
    bound = cond.left.right.left
    assert bound == Bound(
        feature="Motion Behavior", attribute="MaxVel", bound="max", span=bound.span
    )
    assert cond.right.left.kind == "cv"
    err = error_of('rule R: if (Latency == "High") activate_feature(Static)', fm, meas)
    assert "attribute Latency is ambiguous: write one of ChannelA.Latency, ChannelB.Latency" in (
        err.headline
    )


ROBOT_UVL = """features
    Robot {abstract}
        mandatory
            Localization {binding 'runtime'}
                alternative
                    LidarSlam {Accuracy {kind 'cim', value 0.05, unit 'm'}}
                    Gnss {Accuracy {kind 'cim', value 2.0, unit 'm'}}
            Planner {binding 'runtime', Tolerance {kind 'cv', lower 0.1, upper 1.0, unit 'm'}}
"""


def test_an_ambiguous_attribute_to_set_suggests_nothing_that_cannot_be_set():
    """The first message says what can be written; only CIM attributes of different features
    may share a name (UVL), and a CIM attribute cannot be set: so it says that, instead of
    "write one of LidarSlam.Accuracy, ..." and a second error once the user did."""
    fm = parse_uvl(ROBOT_UVL, "robot.uvl")
    err = error_of("rule R: set_attribute(Accuracy) with_value(0.5)", fm, None)
    (message,) = messages(err)
    assert message == (
        "t.rra:1:23: attribute Accuracy cannot be set: LidarSlam.Accuracy (CIM), Gnss.Accuracy "
        "(CIM) (only run-time Continuous Variability (cv) attributes can be set)"
    )
    ok = parse("rule R: set_attribute(Tolerance) with_value(0.5)", fm, None)
    assert ok.items[0].branches[0].actions[0].target.feature == "Planner"
    # Read, it stays ambiguous among all of them (a CIM attribute can be read).
    err = error_of("rule R: if (Accuracy > 1) activate_feature(Gnss)", fm, None)
    assert "write one of LidarSlam.Accuracy, Gnss.Accuracy" in err.headline


def test_an_attribute_none_of_whose_owners_can_be_set(fm, meas):
    err = error_of("rule R: set_attribute(Latency) with_value(1)", fm, meas)
    (message,) = messages(err)
    assert message == (
        "t.rra:1:23: attribute Latency cannot be set: ChannelA.Latency (CIM), ChannelB.Latency "
        "(CIM) (only run-time Continuous Variability (cv) attributes can be set)"
    )


# ---- shorthand and literals ---------------------------------------------------------------
def test_or_shorthand_extends_to_every_literal(fm, meas):
    model = parse(
        IMPORT + 'rule R: if (cdm.SemLoc == "A" OR "B" OR "C") activate_feature(Static)', fm, meas
    )
    cond = model.items[0].branches[0].condition
    leaves = [n for n in _nodes(cond) if isinstance(n, Compare)]
    assert [(c.op, c.left.name, c.right.value) for c in leaves] == [
        ("==", "SemLoc", "A"),
        ("==", "SemLoc", "B"),
        ("==", "SemLoc", "C"),
    ]


@pytest.mark.parametrize(
    ("cond", "message"),
    [
        ('cdm.SemLoc != "A" OR "B"', 'the shorthand only extends ==; write x != "A" AND x != "B"'),
        (
            'cdm.BattLev > 1 OR "B"',
            "a bare value after OR needs a comparison `x == value` before it",
        ),
    ],
)
def test_or_shorthand_misuse(fm, meas, cond, message):
    err = error_of(IMPORT + f"rule R: if ({cond}) activate_feature(Static)", fm, meas)
    assert messages(err) == [f"t.rra:2:{13 + cond.index(' OR ') + 4}: {message}"]


def test_quoted_numbers_are_numbers_and_strings_stay_strings(fm, meas):
    model = parse(
        IMPORT + 'rule R: if ("5" > "3" AND cdm.SemLoc == "50" AND cdm.BattLev == "1e2") '
        "activate_feature(Static)",
        fm,
        meas,
    )
    nodes = _nodes(model.items[0].branches[0].condition)
    cmps = [n for n in nodes if isinstance(n, Compare)]
    assert cmps[0].left == Num(value=5.0, quoted=True) and cmps[0].right == Num(
        value=3.0, quoted=True
    )
    assert cmps[1].right == Str(value="50")  # SemLoc is a string measurement
    assert cmps[2].right == Num(value=100.0, quoted=True)


BOOL_MEAS = MeasurementsModel(
    measurements=[
        Measurement(name="Indoor", type="bool", source="gnss.fix"),
        Measurement(name="SemLoc", type="str", source="nav.loc"),
    ]
)


@pytest.mark.parametrize(
    ("written", "value"),
    [('"false"', False), ('"true"', True), ("'False'", False), ('"TRUE"', True)],
)
def test_quoted_booleans_compare_as_booleans(fm, written, value):
    """As "50" counts as 50 against a number, "false" counts as false against a bool."""
    model = parse(
        IMPORT + f"rule R: if (cdm.Indoor == {written}) activate_feature(Static)", fm, BOOL_MEAS
    )
    (cmp,) = [n for n in _nodes(model.items[0].branches[0].condition) if isinstance(n, Compare)]
    assert cmp.right == Bool(value=value, quoted=True)
    swapped = parse(
        IMPORT + f"rule R: if ({written} != cdm.Indoor) activate_feature(Static)", fm, BOOL_MEAS
    )
    (cmp,) = [n for n in _nodes(swapped.items[0].branches[0].condition) if isinstance(n, Compare)]
    assert cmp.left == Bool(value=value, quoted=True)


def test_a_quoted_boolean_fires_like_the_keyword(fm):
    from rra_agent.core.adaptation import AdaptationEngine

    for cond in ('cdm.Indoor == "false"', "cdm.Indoor == false"):
        model = parse(
            IMPORT + f"rule R: if ({cond}) activate_feature(Dynamic) else activate_feature(Static)",
            fm,
            BOOL_MEAS,
        )
        engine = AdaptationEngine(fm, {"Manipulation"}, model)
        assert "Dynamic" in engine.tick(1.0, {"Indoor": (False, 1.0)}).selection
        assert "Static" in engine.tick(2.0, {"Indoor": (True, 2.0)}).selection


def test_a_string_that_is_no_boolean_against_a_bool_is_a_located_error(fm):
    text = IMPORT + 'rule R: if (cdm.Indoor == "no") activate_feature(Static)'
    assert messages(error_of(text, fm, BOOL_MEAS)) == [
        't.rra:2:27: "no" is not a boolean: measurement Indoor (bool) is true or false'
        ' (write true, false, "true" or "false")'
    ]


def test_a_quoted_boolean_against_a_string_measurement_stays_a_string(fm):
    model = parse(
        IMPORT + 'rule R: if (cdm.SemLoc == "true") activate_feature(Static)', fm, BOOL_MEAS
    )
    (cmp,) = [n for n in _nodes(model.items[0].branches[0].condition) if isinstance(n, Compare)]
    assert cmp.right == Str(value="true")


def test_quoted_booleans_of_untyped_measurements_compare_at_run_time(fm):
    """Without a measurements model the type is known only at run time: a bool value and
    "true"/"false" compare as booleans, like a number and a numeric string."""
    from rra_agent.core.adaptation import AdaptationEngine

    model = parse(
        IMPORT + 'rule R: if (cdm.Indoor == "false") activate_feature(Dynamic)'
        " else activate_feature(Static)",
        fm,
        None,
    )
    engine = AdaptationEngine(fm, {"Manipulation"}, model)
    assert "Dynamic" in engine.tick(1.0, {"Indoor": (False, 1.0)}).selection
    assert "Static" in engine.tick(2.0, {"Indoor": (True, 2.0)}).selection


def test_keywords_are_case_insensitive_and_comments_ignored(fm, meas):
    model = parse(
        IMPORT + "// a comment\n/* block\ncomment */ rule R: # trailing\n"
        'if (cdm.BattLev > 1 and not cdm.SemLoc == "A" Or cdm.BattLev < max(1, 2, 3)) '
        "activate_feature(Static, Small)",
        fm,
        meas,
    )
    action = model.items[0].branches[0].actions[0]
    assert [f.name for f in action.features] == ["Static", "Small"]


def test_periods_and_multiple_actions(fm, meas):
    model = parse(
        "rule A period 250 ms: activate_feature(Static) deactivate_feature(Small)\n"
        "rule B period 2 s: activate_feature(Dynamic)\nrule C period 0 ms: activate_feature(Large)",
        fm,
        meas,
    )
    a, b, c = model.items
    assert (a.period_ms, b.period_ms, c.period_ms) == (250.0, 2000.0, 0.0)
    assert [type(x) for x in a.branches[0].actions] == [Activate, Deactivate]


# ---- located errors ---------------------------------------------------------------------------
def test_syntax_error_format(fm, meas):
    err = error_of("rule R:\n    if (cdm.X > ) activate_feature(Static)", fm, meas)
    assert isinstance(err, DslSyntaxError)
    assert str(err) == (
        "t.rra:2:17: unexpected ')', expected one of '(', '+' or '-', 'MAX', 'MIN', '[', "
        "'false', 'true', name, number, string\n"
        "        if (cdm.X > ) activate_feature(Static)\n"
        "                    ^"
    )
    assert "number" in err.expected


def test_syntax_error_at_end_of_input(fm, meas):
    err = error_of("rule R: if (cdm.BattLev > 1)", fm, meas)
    assert err.headline.startswith("t.rra:1:29: unexpected end of input, expected one of ")
    assert "'activate_feature'" in err.headline


def test_unexpected_character(fm, meas):
    err = error_of("rule R: activate_feature(Static) $", fm, meas)
    assert err.headline.startswith("t.rra:1:34: unexpected character '$', expected one of")


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("rule R: activate_feature(Statc)", "1:26: unknown feature 'Statc' (did you mean Static?)"),
        (
            "rule R: activate_feature(Manipulation)",
            "1:26: feature Manipulation is bound at deployment time; rules act only on run-time "
            "features",
        ),
        (
            "rule R: set_attribute(MaxVell) with_value(1)",
            "1:23: unknown attribute MaxVell (did you mean MaxVel?)",
        ),
        (
            "rule R: set_attribute(ChannelA.PowerConsump) with_value(1)",
            "1:23: PowerConsump is a CIM attribute; only Continuous Variability (cv) attributes "
            "can be set",
        ),
        (
            'rule R: if (cdm.SemLoc > "A") activate_feature(Static)',
            "1:24: > orders numbers; a string compares only with == and !=",
        ),
        (
            "rule R: if (cdm.SemLoc == 3) activate_feature(Static)",
            "1:24: cannot compare a string to a number",
        ),
        (
            'rule R: if (cdm.BattLev == "high") activate_feature(Static)',
            "1:25: cannot compare a number to a string",
        ),
        (
            "rule R: if (cdm.BattLev) activate_feature(Static)",
            "1:13: a condition must be true or false, not a number",
        ),
        (
            'rule R: if (cdm.BattLev + "x" > 1) activate_feature(Static)',
            "1:27: + needs numbers, not a string",
        ),
        (
            "rule R: set_attribute(MaxVel) with_value(cdm.SemLoc)",
            "1:9: set_attribute needs a number, not a string",
        ),
        (
            "rule R: set_attribute(MaxVel) with_value(foo(1))",
            "1:42: unknown function foo (functions: exp, log, sqrt, abs, min, max)",
        ),
        (
            "rule R: set_attribute(MaxVel) with_value(exp(1, 2))",
            "1:42: exp takes 1 argument(s), got 2",
        ),
        (
            "rule R: set_attribute(MaxVel) with_value(Latency.min)",
            "1:42: attribute Latency is ambiguous: write one of ChannelA.Latency, ChannelB.Latency",
        ),
        (
            "rule R: set_attribute(MaxVel) with_value(Dynamic.VelocityLimit.max)",
            "1:42: VelocityLimit is not a Continuous Variability attribute: it has no max",
        ),
        (
            "rule R: set_attribute(MaxVel) with_value(Static.Nope)",
            "1:42: feature Static has no attribute Nope",
        ),
        (
            "rule R period 5 h: activate_feature(Static)",
            "1:17: unknown period unit h (use ms or s)",
        ),
        (
            "rule R priority 1: activate_feature(Static)",
            "1:1: rule R has a priority but belongs to no rule set",
        ),
        (
            "ruleSet S:\nrule R: activate_feature(Static)",
            "1:1: rule set S has no rules (its rules are written 'rule NAME priority N: ...' "
            "right after it)",
        ),
        (
            "rule R: activate_feature(Static)\nrule R: activate_feature(Dynamic)",
            "2:1: name R is already used (first at t.rra:2:1)",
        ),
        (
            "rule R: select_feature_from_variants_of(Environment) where_attribute MIN(Latency)",
            "1:9: variant Static has no CIM attribute Latency",
        ),
        (
            "rule R: if (cdm.BattLev > 1 AND 3) activate_feature(Static)",
            "1:33: AND needs conditions, not a number",
        ),
        (
            "rule R: if (NOT cdm.SemLoc) activate_feature(Static)",
            "1:17: NOT needs conditions, not a string",
        ),
        ("rule R: if (pie > 1) activate_feature(Static)", "1:13: unknown name pie"),
        (
            "rule R: if (a.b.c.d > 1) activate_feature(Static)",
            "1:13: unknown name a.b.c.d (imports: cdm)",
        ),
    ],
)
def test_semantic_errors_are_located(fm, meas, text, message):
    err = error_of(IMPORT + text, fm, meas)
    assert isinstance(err, SemanticError | ErrorGroup)
    line, rest = message.split(":", 1)
    expected = f"t.rra:{int(line) + 1}:{rest}"
    assert messages(err)[0] == expected
    first = err.errors[0] if isinstance(err, ErrorGroup) else err
    assert first.source_line == (IMPORT + text).split("\n")[int(line)]


def test_equal_priorities_are_an_error_naming_both_rules(fm, meas):
    text = (
        "ruleSet S:\n  rule a priority 1: activate_feature(Static)\n"
        "  rule b priority 2: activate_feature(Static)\n"
        "  rule c priority 1: activate_feature(Dynamic)\n"
    )
    err = error_of(text, fm, meas)
    assert messages(err) == [
        "t.rra:4:3: rules a (t.rra:2:3) and c of rule set S have the same priority 1: "
        "priorities inside a rule set must differ"
    ]


def test_all_semantic_errors_of_a_file_are_reported_in_order(fm, meas):
    text = "rule A: activate_feature(Nope)\nrule B: activate_feature(Manipulation)\n"
    err = error_of(text, fm, meas)
    assert isinstance(err, ErrorGroup)
    assert [e.location.line for e in err.errors] == [1, 2]


def test_unorderable_cim_values_need_a_scale():
    # The UVL loader already demands a scale; a model built in code may still lack one.
    def variant(name, value):
        return Feature(
            name=name, attributes=(Attribute(name="Q", value={"kind": "cim", "value": value}),)
        )

    point = Feature(
        name="P",
        attributes=(Attribute(name="binding", value="runtime"),),
        groups=(Group(kind="alternative", children=(variant("A", "good"), variant("B", "bad"))),),
    )
    fm = FeatureModel(root=Feature(name="R", groups=(Group(kind="mandatory", children=(point,)),)))
    err = error_of("rule R: select_feature_from_variants_of(P) where_attribute MAX(Q)", fm, None)
    assert messages(err)[0] == (
        "t.rra:1:9: A.Q = 'good' cannot be ordered: give the attribute a number or a scale "
        "listing its values"
    )


def test_too_deep_expressions_are_rejected_not_crashing(fm, meas):
    deep = "(" * 300 + "1" + ")" * 300  # redundant parentheses are fine
    parse(f"rule R: set_attribute(MaxVel) with_value({deep})", fm, meas)
    nested = "1" + "".join(" + (1 * (2" for _ in range(MAX_DEPTH)) + "))" * MAX_DEPTH
    err = error_of(f"rule R: set_attribute(MaxVel) with_value({nested})", fm, meas)
    assert "nested too deeply" in err.headline
    long_chain = " + ".join(["cdm.BattLev"] * 5000)
    err = error_of(IMPORT + f"rule R: set_attribute(MaxVel) with_value({long_chain})", fm, meas)
    assert "nested too deeply" in err.headline


def test_load_rules_missing_file(fm, meas, tmp_path):
    with pytest.raises(RraError, match="cannot read rules"):
        load_rules(tmp_path / "nope.rra", fm, meas)


def test_model_round_trips_through_json(fm, meas):
    model = load_rules(OS / "adaptation.rra", fm, meas)
    back = msgspec.json.decode(msgspec.json.encode(model), type=AdaptationModel)
    assert back == model


def test_quadcopter_rules(fm):
    qfm = load_uvl(QC / "features.uvl")
    qmeas = load_yaml(QC / "measurements.yaml", MeasurementsModel)[0]
    model = load_rules(QC / "adaptation.rra", qfm, qmeas)
    (rule,) = model.items
    assert rule.period_ms == 0.0
    assert len(rule.branches) == 1  # latched: no else branch, see the file's comment
    cond = rule.branches[0].condition
    assert cond.left.name == "WorkingMotors" and cond.left.type == "int"


# ---- robustness -------------------------------------------------------------------------------
VOCAB = [
    "import", "as", "rule", "ruleSet", "priority", "period", "ms", "if", "else", "(", ")", "[",
    "]", ":", ",", ".", "activate_feature", "deactivate_feature",
    "select_feature_from_variants_of", "where_attribute", "MIN", "MAX", "set_attribute",
    "with_value", "AND", "OR", "NOT", "==", "!=", "<", "<=", ">", ">=", "+", "-", "*", "/", "^",
    "e", "exp", "abs", "min", "cdm", "cdm.SemLoc", "cdm.BattLev", "BattLev", "ObstDist", "MaxVel",
    "MaxVel.min", "Static", "Dynamic", "Small", "Large", "CommunicChannel", '"Communic. Channel"',
    "Latency", "PowerConsump", "VelocityLimit", "ChannelA.Latency", '"RoomA"', '"50"', "0", "1",
    "2.5", "1e400", "true", "\n", "R", "S",
]  # fmt: skip


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=st.text(max_size=200))
def test_any_text_gives_a_model_or_a_located_error(fm, meas, text):
    _model_or_located_error(text, fm, meas)


@settings(max_examples=600, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(tokens=st.lists(st.sampled_from(VOCAB), max_size=40), prefix=st.booleans())
def test_token_soup_gives_a_model_or_a_located_error(fm, meas, tokens, prefix):
    head = IMPORT + "rule R: if (" if prefix else ""
    _model_or_located_error(head + " ".join(tokens), fm, meas)


def _model_or_located_error(text, fm, meas):
    try:
        model = parse(text, fm, meas)
    except ErrorGroup as e:
        assert all(err.location is not None for err in e.errors)  # type: ignore[attr-defined]
    except RraError as e:
        assert e.location is not None  # type: ignore[attr-defined]
        assert e.location.line >= 1 and e.location.col >= 1
    else:
        assert isinstance(model, AdaptationModel)


def test_numbers_out_of_range_are_errors(fm, meas):
    err = error_of("rule R: set_attribute(MaxVel) with_value(1e400)", fm, meas)
    assert "out of range" in err.headline
    assert math.isfinite(parse("rule R: set_attribute(MaxVel) with_value(1e300)", fm, meas)
                         .items[0].branches[0].actions[0].value.value)  # fmt: skip
