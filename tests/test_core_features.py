"""Feature-model semantics (rra_agent.core.features): the paper's case study, then properties
checked against a brute-force enumeration of every selection of small random models."""

from __future__ import annotations

import itertools
from collections.abc import Iterable
from dataclasses import FrozenInstanceError
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rra_agent.core.features import (
    Violation,
    apply_requests,
    check_selection,
    complete_deployment,
    default_runtime_selection,
    selectable_runtime,
)
from rra_agent.errors import SelectionError
from rra_agent.models.features import (
    And,
    Attribute,
    Constraint,
    Equiv,
    Expr,
    Feature,
    FeatureModel,
    Group,
    Implies,
    Not,
    Or,
    Ref,
)

ROOT = Path(__file__).resolve().parents[1]
CASE_STUDY_UVL = ROOT / "scenarios" / "object_storing" / "features.uvl"

# ---- builders ---------------------------------------------------------------------------------

RUNTIME = Attribute(name="binding", value="runtime")


def feat(name: str, *groups: Group, runtime: bool = False, **attrs: object) -> Feature:
    attributes = [RUNTIME] if runtime else []
    attributes += [Attribute(name=k, value=v) for k, v in attrs.items()]  # type: ignore[arg-type]
    return Feature(name=name, groups=groups, attributes=tuple(attributes))


def grp(kind: str, *children: Feature, lower: int | None = None, upper: int | None = None) -> Group:
    return Group(kind=kind, children=children, lower=lower, upper=upper)  # type: ignore[arg-type]


def implies(a: str, b: str) -> Constraint:
    return Constraint(expr=Implies(left=Ref(name=a), right=Ref(name=b)))


def case_study(*, default_channel_b: bool = False) -> FeatureModel:
    """The paper's Fig. 3 model, as in scenarios/object_storing/features.uvl."""
    channel_b = feat("ChannelB", default=True) if default_channel_b else feat("ChannelB")
    return FeatureModel(
        root=feat(
            "ObjectStoring",
            grp(
                "mandatory",
                feat("Task", grp("alternative", feat("Detection"), feat("Manipulation"))),
                feat(
                    "Environment", grp("alternative", feat("Static"), feat("Dynamic")), runtime=True
                ),
                feat(
                    "Communic. Channel",
                    grp("alternative", feat("ChannelA"), channel_b),
                    runtime=True,
                    alias="CommunicChannel",
                ),
                feat("Motion Behavior", runtime=True, alias="MotionBehavior"),
            ),
            grp(
                "optional",
                feat("RackSize", grp("alternative", feat("Small"), feat("Large")), runtime=True),
                feat("Material", grp("alternative", feat("Fragile"), feat("Firm")), runtime=True),
            ),
            abstract=None,
        ),
        constraints=(implies("Material", "Manipulation"),),
    )


FM = case_study()
DETECTION = frozenset({"ObjectStoring", "Task", "Detection"})
MANIPULATION = frozenset({"ObjectStoring", "Task", "Manipulation"})
DEFAULT_RT = frozenset(
    {"Environment", "Static", "Communic. Channel", "ChannelA", "Motion Behavior"}
)


# ---- case study: check_selection --------------------------------------------------------------


def test_violation_is_a_frozen_record() -> None:
    v = Violation("Task", "oops")
    assert (v.feature, v.message, str(v)) == ("Task", "oops", "oops")
    with pytest.raises(FrozenInstanceError):
        v.message = "other"  # type: ignore[misc]


def test_valid_full_selection_has_no_violations() -> None:
    assert check_selection(FM, DETECTION | DEFAULT_RT) == []
    assert check_selection(FM, MANIPULATION | DEFAULT_RT | {"Material", "Firm"}) == []


@pytest.mark.parametrize(
    ("selection", "expected"),
    [
        (
            MANIPULATION | {"Detection"} | DEFAULT_RT,
            [
                (
                    "Task",
                    "alternative group of Task has 2 selected children (Detection, "
                    "Manipulation); exactly 1 allowed",
                )
            ],
        ),
        (
            DETECTION | DEFAULT_RT | {"Material", "Fragile"},
            [
                (
                    None,
                    "constraint Material => Manipulation is violated (Material selected, "
                    "Manipulation not selected)",
                )
            ],
        ),
        (
            DETECTION | DEFAULT_RT - {"Environment", "Static"},
            [
                (
                    "Environment",
                    "mandatory feature Environment is not selected though its parent "
                    "ObjectStoring is",
                )
            ],
        ),
        (
            DETECTION | DEFAULT_RT | {"Small"},
            [("Small", "Small is selected but its parent RackSize is not")],
        ),
        (
            DETECTION | DEFAULT_RT | {"RackSize"},
            [
                (
                    "RackSize",
                    "alternative group of RackSize has 0 selected children; exactly 1 required",
                )
            ],
        ),
        (
            {"Task", "Detection", "Motion Behavior"},
            [
                ("ObjectStoring", "root feature ObjectStoring must always be selected"),
                ("Task", "Task is selected but its parent ObjectStoring is not"),
                (
                    "Motion Behavior",
                    "Motion Behavior is selected but its parent ObjectStoring is not",
                ),
            ],
        ),
        (DETECTION | DEFAULT_RT | {"Nope"}, [(None, "unknown feature 'Nope'")]),
    ],
)
def test_check_selection_explains_every_violation(
    selection: frozenset[str], expected: list[tuple[str | None, str]]
) -> None:
    got = [(v.feature, v.message) for v in check_selection(FM, selection)]
    assert sorted(got, key=str) == sorted(expected, key=str)


def test_check_selection_accepts_aliases() -> None:
    sel = (DETECTION | DEFAULT_RT) - {"Communic. Channel"} | {"CommunicChannel"}
    assert check_selection(FM, sel) == []


def test_undecided_features_only_yield_certain_violations() -> None:
    runtime = FM.runtime_features()
    assert check_selection(FM, DETECTION, undecided=runtime) == []
    assert check_selection(FM, {"ObjectStoring"}, undecided=runtime) != []  # Task missing
    # Material is undecided, so `Material => Manipulation` is not certainly violated ...
    assert check_selection(FM, DETECTION | DEFAULT_RT | {"Fragile"}, undecided=["Material"]) == []
    # ... but a selected Material is.
    with_material = DETECTION | DEFAULT_RT | {"Material"}
    [violation] = check_selection(FM, with_material, undecided=["Fragile", "Firm"])
    assert violation.message.startswith("constraint Material => Manipulation is violated")
    only = check_selection(FM, {"ObjectStoring", "Task"}, undecided=runtime)
    assert [v.message for v in only] == [
        "alternative group of Task has 0 selected children; exactly 1 required"
    ]
    nothing = check_selection(FM, DETECTION | {"RackSize"}, undecided=["Environment"])
    assert "alternative group of RackSize has 0 selected children; exactly 1 required" in [
        v.message for v in nothing
    ]


def test_group_messages_for_cardinalities() -> None:
    fm = FeatureModel(
        root=feat(
            "R", grp("cardinality", feat("A"), feat("B"), feat("C"), feat("D"), lower=2, upper=3)
        )
    )
    [too_many] = check_selection(fm, {"R", "A", "B", "C", "D"})
    assert too_many.message == (
        "[2..3] group of R has 4 selected children (A, B, C, D); between 2 and 3 allowed"
    )
    [too_few] = check_selection(fm, {"R"}, undecided=["A"])
    assert too_few.message == (
        "[2..3] group of R has 0 selected children and 1 undecided; between 2 and 3 required"
    )
    assert check_selection(fm, {"R"}, undecided=["A", "B"]) == []
    assert check_selection(fm, {"R", "A"}, undecided=["B", "C", "D"]) == []


def test_constraint_text_keeps_the_needed_parentheses() -> None:
    expr = Equiv(
        left=Not(operand=And(left=Ref(name="A"), right=Ref(name="My B"))),
        right=Or(left=Ref(name="A"), right=Implies(left=Ref(name="A"), right=Ref(name="A"))),
    )
    fm = FeatureModel(
        root=feat("R", grp("optional", feat("A"), feat("My B"))),
        constraints=(Constraint(expr=expr),),
    )
    [v] = check_selection(fm, {"R", "A", "My B"})
    assert v.message.startswith('constraint !(A & "My B") <=> A | (A => A) is violated')


# ---- case study: deployment time --------------------------------------------------------------


@pytest.mark.parametrize(
    ("partial", "expected"),
    [
        ({"Manipulation"}, MANIPULATION),
        ({"Detection"}, DETECTION),
        ({"Task", "Detection"}, DETECTION),
        (set(), DETECTION),  # the first child of the alternative group
        ({"ObjectStoring"}, DETECTION),
    ],
)
def test_complete_deployment(partial: set[str], expected: frozenset[str]) -> None:
    assert complete_deployment(FM, partial) == expected


def test_complete_deployment_rejects_both_tasks_with_the_reason() -> None:
    with pytest.raises(SelectionError) as err:
        complete_deployment(FM, ["Detection", "Manipulation"])
    assert err.value.reasons == (
        "alternative group of Task has 2 selected children (Detection, Manipulation); "
        "exactly 1 allowed",
    )


@pytest.mark.parametrize("bad", ["Static", "CommunicChannel", "Nope"])
def test_complete_deployment_rejects_unknown_and_runtime_features(bad: str) -> None:
    with pytest.raises(SelectionError) as err:
        complete_deployment(FM, ["Detection", bad])
    assert bad in err.value.reasons[0]


def test_complete_deployment_skips_choices_that_break_constraints() -> None:
    fm = FeatureModel(
        root=feat(
            "R",
            grp("mandatory", feat("X", grp("alternative", feat("A"), feat("B")))),
            grp("optional", feat("C")),
        ),
        constraints=(
            Constraint(expr=Implies(left=Ref(name="C"), right=Not(operand=Ref(name="A")))),
        ),
    )
    assert complete_deployment(fm, ["C"]) == {"R", "X", "B", "C"}
    assert complete_deployment(fm, []) == {"R", "X", "A"}


# ---- case study: run time ---------------------------------------------------------------------


def test_selectable_runtime_follows_the_deployment_selection() -> None:
    under_detection = selectable_runtime(FM, DETECTION)
    assert {"Material", "Fragile", "Firm"}.isdisjoint(under_detection)
    assert {
        "ChannelA",
        "ChannelB",
        "Static",
        "Dynamic",
        "RackSize",
        "Small",
        "Large",
        "Environment",
        "Motion Behavior",
        "Communic. Channel",
    } <= under_detection
    assert {"Material", "Fragile", "Firm"} <= selectable_runtime(FM, MANIPULATION)
    assert selectable_runtime(FM, MANIPULATION) == set(FM.runtime_features())


def test_selectable_runtime_is_empty_for_an_inconsistent_deployment() -> None:
    assert selectable_runtime(FM, DETECTION | {"Manipulation"}) == frozenset()
    with pytest.raises(SelectionError):
        selectable_runtime(FM, DETECTION | {"Static"})


def test_runtime_features_below_unselected_deployment_features_are_not_selectable() -> None:
    fm = FeatureModel(
        root=feat(
            "R", grp("alternative", feat("A", grp("optional", feat("RA", runtime=True))), feat("B"))
        )
    )
    assert selectable_runtime(fm, {"R", "B"}) == frozenset()
    assert selectable_runtime(fm, {"R", "A"}) == {"RA"}
    _, rejected = apply_requests(fm, {"R", "B"}, set(), [("activate", "RA")])
    assert rejected == [(0, "cannot activate RA: its deployment-time ancestor A is not selected")]


def test_default_runtime_selection() -> None:
    assert default_runtime_selection(FM, DETECTION) == DEFAULT_RT
    assert default_runtime_selection(FM, MANIPULATION) == DEFAULT_RT
    with_default = default_runtime_selection(case_study(default_channel_b=True), DETECTION)
    assert with_default == DEFAULT_RT - {"ChannelA"} | {"ChannelB"}
    with pytest.raises(SelectionError):
        default_runtime_selection(FM, DETECTION | {"Manipulation"})


def test_default_runtime_selection_avoids_choices_that_break_constraints() -> None:
    fm = FeatureModel(
        root=feat(
            "R",
            grp(
                "mandatory",
                feat("X", grp("alternative", feat("X1"), feat("X2")), runtime=True),
                feat("Y", grp("alternative", feat("Y1"), feat("Y2")), runtime=True),
            ),
        ),
        constraints=(implies("Y1", "X2"),),
    )
    assert default_runtime_selection(fm, {"R"}) == {"X", "X1", "Y", "Y2"}


def test_default_runtime_selection_raises_when_no_selection_exists() -> None:
    fm = FeatureModel(
        root=feat("R", grp("mandatory", feat("X", runtime=True), feat("Y", runtime=True))),
        constraints=(
            Constraint(expr=Implies(left=Ref(name="X"), right=Not(operand=Ref(name="Y")))),
        ),
    )
    with pytest.raises(SelectionError) as err:
        default_runtime_selection(fm, {"R"})
    assert any("X => !Y" in r for r in err.value.reasons)
    assert selectable_runtime(fm, {"R"}) == frozenset()


def run(
    requests: list[tuple[str, str]],
    *,
    deployment: frozenset[str] = DETECTION,
    previous: Iterable[str] = DEFAULT_RT,
) -> tuple[frozenset[str], list[tuple[int, str]]]:
    result, rejected = apply_requests(FM, deployment, frozenset(previous), requests)  # type: ignore[arg-type]
    assert check_selection(FM, deployment | result) == [], "apply_requests broke the model"
    return result, rejected


def test_activate_dynamic_deselects_static() -> None:
    assert run([("activate", "Dynamic")]) == (DEFAULT_RT - {"Static"} | {"Dynamic"}, [])


def test_activate_fragile_under_detection_is_rejected_with_the_constraint() -> None:
    result, [(index, reason)] = run([("activate", "Fragile")])
    assert result == DEFAULT_RT and index == 0
    assert "Fragile" in reason and "Material => Manipulation" in reason


def test_activate_fragile_under_manipulation_selects_material() -> None:
    result, rejected = run([("activate", "Fragile")], deployment=MANIPULATION)
    assert (result, rejected) == (DEFAULT_RT | {"Material", "Fragile"}, [])
    result, rejected = run([("activate", "Firm")], deployment=MANIPULATION, previous=result)
    assert (result, rejected) == (DEFAULT_RT | {"Material", "Firm"}, [])


@pytest.mark.parametrize("size", ["Small", "Large"])
def test_deactivate_large_then_small_deselects_rack_size(size: str) -> None:
    """The paper's ``deactivate_feature(Large AND Small)``, whichever size is selected."""
    result, rejected = run(
        [("deactivate", "Large"), ("deactivate", "Small")], previous=DEFAULT_RT | {"RackSize", size}
    )
    assert (result, rejected) == (DEFAULT_RT, [])


def test_activate_channel_b_then_channel_a() -> None:
    result, rejected = run([("activate", "ChannelB"), ("activate", "ChannelA")])
    assert (result, rejected) == (DEFAULT_RT, [])
    result, rejected = run([("activate", "ChannelB")])
    assert (result, rejected) == (DEFAULT_RT - {"ChannelA"} | {"ChannelB"}, [])


def test_activate_completes_new_features_with_defaults() -> None:
    assert run([("activate", "RackSize")]) == (DEFAULT_RT | {"RackSize", "Small"}, [])
    assert run([("activate", "Large")]) == (DEFAULT_RT | {"RackSize", "Large"}, [])


def test_activating_a_selected_feature_is_a_no_op() -> None:
    assert run([("activate", "Static"), ("activate", "CommunicChannel")]) == (DEFAULT_RT, [])


def test_deactivating_an_alternative_selects_the_next_sibling() -> None:
    assert run([("deactivate", "Static")]) == (DEFAULT_RT - {"Static"} | {"Dynamic"}, [])
    assert run([("deactivate", "Dynamic")]) == (DEFAULT_RT, [])  # not selected: a no-op


def test_mandatory_features_cannot_be_deactivated() -> None:
    result, [(index, reason)] = run([("deactivate", "CommunicChannel")])
    assert (result, index) == (DEFAULT_RT, 0)
    assert "mandatory feature Communic. Channel is not selected" in reason


def test_bad_requests_are_rejected_and_the_rest_applied() -> None:
    result, rejected = run(
        [
            ("activate", "Manipulation"),
            ("activate", "Nope"),
            ("explode", "Static"),  # type: ignore[list-item]
            ("activate", "Dynamic"),
        ]
    )
    assert result == DEFAULT_RT - {"Static"} | {"Dynamic"}
    assert [i for i, _ in rejected] == [0, 1, 2]
    assert "deployment-time" in rejected[0][1] and "Nope" in rejected[1][1]


def test_apply_requests_refuses_a_previous_selection_with_deployment_features() -> None:
    with pytest.raises(SelectionError):
        apply_requests(FM, DETECTION, DEFAULT_RT | {"Task"}, [])


def test_apply_requests_rejects_what_breaks_a_constraint_elsewhere() -> None:
    fm = FeatureModel(
        root=feat(
            "R",
            grp("mandatory", feat("E", grp("alternative", feat("S"), feat("D")), runtime=True)),
            grp("optional", feat("Fast", runtime=True)),
        ),
        constraints=(implies("Fast", "D"),),
    )
    base = default_runtime_selection(fm, {"R"})
    assert base == {"E", "S"}
    result, [(index, reason)] = apply_requests(fm, {"R"}, base, [("activate", "Fast")])
    assert (result, index) == (base, 0) and "Fast => D" in reason
    result, rejected = apply_requests(fm, {"R"}, base, [("activate", "D"), ("activate", "Fast")])
    assert (result, rejected) == ({"E", "D", "Fast"}, [])
    result, [(index, reason)] = apply_requests(fm, {"R"}, result, [("activate", "S")])
    assert (result, index) == ({"E", "D", "Fast"}, 0) and "Fast => D" in reason


def test_cardinality_groups_drop_the_last_selected_child() -> None:
    fm = FeatureModel(
        root=feat(
            "R",
            grp(
                "cardinality",
                feat("A"),
                feat("B"),
                feat("C"),
                lower=1,
                upper=2,
            ),
            runtime=True,
        )
    )
    result, rejected = apply_requests(fm, set(), {"R", "A", "B"}, [("activate", "C")])
    assert (result, rejected) == ({"R", "A", "C"}, [])


def test_uvl_case_study_gives_the_same_answers() -> None:
    uvl = pytest.importorskip("rra_agent.dsl.uvl")
    fm = uvl.load_uvl(CASE_STUDY_UVL)
    assert list(fm.features) == list(FM.features)
    assert complete_deployment(fm, {"Detection"}) == DETECTION
    assert selectable_runtime(fm, DETECTION) == selectable_runtime(FM, DETECTION)
    assert default_runtime_selection(fm, DETECTION) == DEFAULT_RT
    result, rejected = apply_requests(fm, DETECTION, DEFAULT_RT, [("activate", "Fragile")])
    assert result == DEFAULT_RT and "Material => Manipulation" in rejected[0][1]


def test_large_models_stay_fast() -> None:
    """Linear work per request: would time out (pytest-timeout) if it were exponential."""
    points = [
        feat(f"P{i}", grp("alternative", *(feat(f"P{i}V{j}") for j in range(3))), runtime=True)
        for i in range(300)
    ]
    fm = FeatureModel(
        root=feat("R", grp("mandatory", *points[:200]), grp("optional", *points[200:])),
        constraints=tuple(implies(f"P{i}V2", f"P{i + 1}V0") for i in range(0, 298, 2)),
    )
    default = default_runtime_selection(fm, {"R"})
    assert len(selectable_runtime(fm, {"R"})) == 1200
    requests = [("activate" if k % 3 else "deactivate", f"P{k % 300}V{k % 3}") for k in range(3000)]
    result, rejected = apply_requests(fm, {"R"}, default, requests)  # type: ignore[arg-type]
    assert check_selection(fm, {"R"} | result) == []
    assert all(0 <= i < len(requests) for i, _ in rejected)


# ---- properties against brute force ----------------------------------------------------------

KINDS = ["mandatory", "optional", "optional", "alternative", "alternative", "or", "cardinality"]


@st.composite
def feature_models(draw: st.DrawFn, max_features: int = 8) -> FeatureModel:
    """Random trees with mixed groups, binding times (no deployment under run-time),
    `default` marks and random cross-tree constraints."""
    n = draw(st.integers(2, max_features))
    parent = [-1] + [draw(st.integers(0, i - 1)) for i in range(1, n)]
    slot = [0] + [draw(st.integers(0, 1)) for _ in range(1, n)]
    runtime = [draw(st.integers(0, 5)) == 0]
    for i in range(1, n):
        runtime.append(runtime[parent[i]] or draw(st.integers(0, 2)) > 0)
    default = [draw(st.integers(0, 4)) == 0 for _ in range(n)]
    features: list[Feature] = []
    for i in reversed(range(n)):  # children (higher indexes) first
        groups = []
        for s in (0, 1):
            kids = [features[n - 1 - c] for c in range(i + 1, n) if parent[c] == i and slot[c] == s]
            if not kids:
                continue
            kind = draw(st.sampled_from(KINDS))
            lower = upper = None
            if kind == "cardinality":
                lower = draw(st.integers(0, len(kids)))
                upper = draw(st.one_of(st.none(), st.integers(max(lower, 1), len(kids))))
            groups.append(grp(kind, *kids, lower=lower, upper=upper))
        attrs = {"default": True} if default[i] else {}
        declared = runtime[i] and (i == 0 or not runtime[parent[i]])  # children inherit it
        features.append(feat(f"F{i}", *groups, runtime=declared, **attrs))
    names = [f"F{i}" for i in range(n)]
    constraints = draw(st.lists(_constraints(names), max_size=3))
    return FeatureModel(root=features[-1], constraints=tuple(constraints))


def _constraints(names: list[str]) -> st.SearchStrategy[Constraint]:
    ref = st.sampled_from(names).map(lambda n: Ref(name=n))
    pair = st.tuples(ref, ref)
    simple = st.one_of(
        pair.map(lambda p: Implies(left=p[0], right=p[1])),
        pair.map(lambda p: Implies(left=p[0], right=Not(operand=p[1]))),
    )
    exprs = st.recursive(
        ref,
        lambda e: st.one_of(
            e.map(lambda x: Not(operand=x)),
            st.tuples(e, e).map(lambda p: And(left=p[0], right=p[1])),
            st.tuples(e, e).map(lambda p: Or(left=p[0], right=p[1])),
            st.tuples(e, e).map(lambda p: Equiv(left=p[0], right=p[1])),
        ),
        max_leaves=3,
    )
    return st.one_of(simple, simple, exprs).map(lambda e: Constraint(expr=e))


def evaluate(expr: Expr, sel: frozenset[str]) -> bool:
    match expr:
        case Ref(name=n):
            return n in sel
        case Not(operand=o):
            return not evaluate(o, sel)
        case And(left=a, right=b):
            return evaluate(a, sel) and evaluate(b, sel)
        case Or(left=a, right=b):
            return evaluate(a, sel) or evaluate(b, sel)
        case Implies(left=a, right=b):
            return not evaluate(a, sel) or evaluate(b, sel)
        case Equiv(left=a, right=b):
            return evaluate(a, sel) == evaluate(b, sel)
    raise AssertionError(expr)


def brute_valid(fm: FeatureModel, sel: frozenset[str]) -> bool:
    """The definition of a valid selection, written out independently."""
    if fm.root.name not in sel:
        return False
    for name, f in fm.features.items():
        p = fm.parent[name]
        if name in sel and p is not None and p not in sel:
            return False
        if name in sel:
            for g in f.groups:
                lo, hi = g.bounds
                k = sum(c.name in sel for c in g.children)
                if k < lo or (hi is not None and k > hi):
                    return False
    return all(evaluate(c.expr, sel) for c in fm.constraints)


def all_selections(names: list[str]) -> Iterable[frozenset[str]]:
    for bits in itertools.product((False, True), repeat=len(names)):
        yield frozenset(n for n, b in zip(names, bits, strict=True) if b)


def valid_selections(fm: FeatureModel) -> list[frozenset[str]]:
    return [s for s in all_selections(list(fm.features)) if brute_valid(fm, s)]


def subtree(fm: FeatureModel, name: str) -> set[str]:
    out, stack = set(), [fm.features[name]]
    while stack:
        f = stack.pop()
        out.add(f.name)
        stack.extend(f.children)
    return out


SETTINGS = settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)


@SETTINGS
@given(feature_models())
def test_check_selection_agrees_with_brute_force(fm: FeatureModel) -> None:
    for sel in all_selections(list(fm.features)):
        violations = check_selection(fm, sel)
        assert (violations == []) == brute_valid(fm, sel), (sorted(sel), violations)
        assert all(isinstance(v, Violation) and v.message for v in violations)


@SETTINGS
@given(feature_models(), st.data())
def test_undecided_violations_are_certain(fm: FeatureModel, data: st.DataObject) -> None:
    names = list(fm.features)
    selected = frozenset(data.draw(st.sets(st.sampled_from(names))))
    undecided = data.draw(st.sets(st.sampled_from(names))) - selected
    if check_selection(fm, selected, undecided=undecided):
        for extra in all_selections(sorted(undecided)):
            assert not brute_valid(fm, selected | extra)


@SETTINGS
@given(feature_models(), st.data())
def test_complete_deployment_is_consistent(fm: FeatureModel, data: st.DataObject) -> None:
    deployment_features = fm.deployment_features()
    partial = (
        data.draw(st.sets(st.sampled_from(deployment_features))) if deployment_features else set()
    )
    try:
        result = complete_deployment(fm, partial)
    except SelectionError as e:
        assert e.reasons
        return
    assert partial <= result <= set(deployment_features)
    assert fm.binding[fm.root.name] == "runtime" or fm.root.name in result
    assert check_selection(fm, result, undecided=fm.runtime_features()) == []


def deployment_of(fm: FeatureModel, data: st.DataObject) -> frozenset[str] | None:
    deployment_features = fm.deployment_features()
    partial = (
        data.draw(st.sets(st.sampled_from(deployment_features))) if deployment_features else set()
    )
    try:
        return complete_deployment(fm, partial)
    except SelectionError:
        return None


def runtime_parts(fm: FeatureModel, deployment: frozenset[str]) -> list[frozenset[str]]:
    """Every valid full selection with this deployment part (brute force)."""
    dep = set(fm.deployment_features())
    return [s for s in valid_selections(fm) if s & dep == deployment]


@SETTINGS
@given(feature_models(), st.data())
def test_selectable_runtime_matches_brute_force(fm: FeatureModel, data: st.DataObject) -> None:
    deployment = deployment_of(fm, data)
    if deployment is None:
        return
    valid = runtime_parts(fm, deployment)
    runtime = set(fm.runtime_features())
    possible = set().union(*valid) & runtime if valid else set()
    selectable = selectable_runtime(fm, deployment)
    assert selectable <= possible  # sound: a valid selection contains each
    assert selectable == possible  # exact on small models (and complete without constraints)


@SETTINGS
@given(feature_models(), st.data())
def test_default_runtime_selection_is_valid(fm: FeatureModel, data: st.DataObject) -> None:
    deployment = deployment_of(fm, data)
    if deployment is None:
        return
    valid = runtime_parts(fm, deployment)
    if not valid:
        with pytest.raises(SelectionError):
            default_runtime_selection(fm, deployment)
        return
    default = default_runtime_selection(fm, deployment)
    assert default <= set(fm.runtime_features())
    assert deployment | default in valid
    assert check_selection(fm, deployment | default) == []


def activation_solutions(
    fm: FeatureModel, valid: list[frozenset[str]], state: frozenset[str], f: str
) -> list[frozenset[str]]:
    """Valid selections an activation of `f` may produce from `state`: `f` and its unselected
    ancestors on, the siblings they displace (all in an alternative group, the last ones
    over an upper bound) off, free inside the new subtree, everything else as it was."""
    chain = [f]
    while (p := fm.parent[chain[-1]]) is not None and p not in state:
        chain.append(p)
    off: set[str] = set()
    for x in chain:
        p = fm.parent[x]
        if p is None:
            continue
        g = fm.group_of[x]
        chosen = [c.name for c in g.children if c.name in state or c.name == x]
        _, hi = g.bounds
        excess = len(chosen) - (len(g.children) if hi is None else hi)
        for c in reversed(chosen):
            if excess > 0 and c != x and fm.binding[c] == "runtime":
                off |= subtree(fm, c)
                excess -= 1
    region = subtree(fm, chain[-1]) | off
    return [s for s in valid if set(chain) <= s and not s & off and s - region == state - region]


def expected_outcomes(
    fm: FeatureModel,
    valid: list[frozenset[str]],
    selectable: frozenset[str],
    state: frozenset[str],
    action: str,
    f: str,
) -> list[frozenset[str]]:
    """The selections a request may lead to (empty: it must be rejected)."""
    if f not in fm.features or fm.binding[f] != "runtime":
        return []
    if action == "activate":
        return [state] if f in state else activation_solutions(fm, valid, state, f)
    if f not in state:
        return [state]
    after = state - subtree(fm, f)
    p = fm.parent[f]
    if p is None:
        return [s for s in valid if s == after]
    g = fm.group_of[f]
    if sum(c.name in after for c in g.children) >= g.bounds[0]:
        return [s for s in valid if s == after]
    pp = fm.parent[p]
    if fm.binding[p] == "runtime" and pp is not None:
        pg = fm.group_of[p]
        if sum(c.name in after for c in pg.children) - 1 >= pg.bounds[0]:
            return [s for s in valid if s == after - subtree(fm, p)]
    for s in g.children:
        if s.name != f and s.name not in after and s.name in selectable:
            found = activation_solutions(fm, valid, after, s.name)
            if found:
                return found
    return []


@settings(SETTINGS, max_examples=300)
@given(feature_models(), st.data())
def test_apply_requests_against_brute_force(fm: FeatureModel, data: st.DataObject) -> None:
    deployment = deployment_of(fm, data)
    if deployment is None:
        return
    valid = runtime_parts(fm, deployment)
    if not valid:
        return
    runtime = fm.runtime_features()
    names = [*runtime, *runtime, *runtime, *fm.features, "Unknown"]  # mostly run-time ones
    requests = data.draw(
        st.lists(
            st.tuples(st.sampled_from(["activate", "deactivate"]), st.sampled_from(names)),
            min_size=3,
            max_size=12,
        )
    )
    previous = data.draw(st.sampled_from(valid)) - deployment
    selectable = selectable_runtime(fm, deployment)
    final, rejected = apply_requests(fm, deployment, previous, requests)
    assert check_selection(fm, deployment | final) == []
    state = previous
    for i, (action, f) in enumerate(requests):
        new, rej = apply_requests(fm, deployment, state, [(action, f)])
        expected = expected_outcomes(fm, valid, selectable, deployment | state, action, f)
        if rej:
            [(index, reason)] = rej
            assert index == 0 and reason
            assert not expected, f"{action} {f} was rejected ({reason}) but could be honoured"
            assert new == state
            assert (i, reason) in rejected
        else:
            assert deployment | new in expected, f"{action} {f} gave {sorted(new)}"
            assert all(j != i for j, _ in rejected)
        state = new
    assert state == final
