"""The UVL parser and exporter: examples, round trips, located errors, and fuzzing."""

from __future__ import annotations

import logging
import re
import string
import threading
from pathlib import Path
from textwrap import dedent

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rra_agent.dsl.uvl import (
    KEYWORDS,
    MAX_DEPTH,
    build_parser,
    check_feature_model,
    load_uvl,
    parse_uvl,
    same_model,
    strip_spans,
    to_uvl,
    uvl_warnings,
)
from rra_agent.errors import (
    DslSyntaxError,
    ErrorGroup,
    LocatedError,
    Location,
    RraError,
    SemanticError,
)
from rra_agent.models.features import (
    Aggregate,
    And,
    Attribute,
    Cardinality,
    Compare,
    Constraint,
    ConstraintList,
    Equiv,
    Expr,
    Feature,
    FeatureModel,
    Group,
    Implies,
    Not,
    Num,
    Or,
    Ref,
    Span,
    Text,
)

ROOT = Path(__file__).resolve().parents[1]
OBJECT_STORING = ROOT / "scenarios/object_storing/features.uvl"
QUADCOPTER = ROOT / "scenarios/quadcopter/features.uvl"
FILE = "m.uvl"


# ---- helpers ------------------------------------------------------------------------------------


def uvl(text: str) -> str:
    return dedent(text).lstrip("\n")


def fails(text: str) -> list[LocatedError]:
    """The located errors ``text`` gives (one, or the members of an ErrorGroup)."""
    with pytest.raises(RraError) as info:
        parse_uvl(text, FILE)
    e = info.value
    found = e.errors if isinstance(e, ErrorGroup) else [e]
    assert all(isinstance(x, LocatedError) for x in found), found
    return found  # type: ignore[return-value]


def only(text: str, cls: type[LocatedError]) -> LocatedError:
    (e,) = fails(text)
    assert isinstance(e, cls), e
    return e


def assert_at(e: LocatedError, text: str, line: int, col: int, token: str) -> None:
    """``e`` is at line:col, and ``token`` really is written there."""
    assert e.location == Location(FILE, line, col), str(e)
    assert text.split("\n")[line - 1][col - 1 :].startswith(token), (text, line, col)
    assert str(e).startswith(f"{FILE}:{line}:{col}: ")


# ---- the examples -------------------------------------------------------------------------------


def test_object_storing_example_structure() -> None:
    fm = load_uvl(OBJECT_STORING)
    assert fm.namespace == "ObjectStoring"
    assert fm.source == str(OBJECT_STORING)
    assert fm.root.name == "ObjectStoring" and fm.root.abstract
    assert [g.kind for g in fm.root.groups] == ["mandatory", "optional"]
    assert [c.name for c in fm.root.groups[0].children] == [
        "Task",
        "Environment",
        "Communic. Channel",
        "Motion Behavior",
    ]
    assert fm.group_of["ChannelA"].kind == "alternative"
    assert fm.group_of["RackSize"].kind == "optional"
    # bindings, declared and inherited
    assert fm.binding["Task"] == "deployment" and fm.binding["Manipulation"] == "deployment"
    assert fm.binding["Environment"] == "runtime" and fm.binding["Dynamic"] == "runtime"
    assert fm.binding["ChannelB"] == "runtime"
    assert set(fm.runtime_features()) >= {"Communic. Channel", "Small", "Firm"}
    # alias
    assert fm.resolve_name("CommunicChannel") == "Communic. Channel"
    assert fm.resolve_name("MotionBehavior") == "Motion Behavior"
    assert fm.resolve_name("Nope") is None
    # attributes
    _, max_vel = fm.attributes["MaxVel"]
    assert (max_vel.kind, max_vel.lower, max_vel.upper, max_vel.unit) == ("cv", 0.4, 0.8, "m/s")
    owner, limit = fm.attributes["VelocityLimit"]
    assert owner == "Dynamic"
    assert (limit.kind, limit.tag, limit.rra_value, limit.constrains) == (
        "nfr",
        "max",
        0.5,
        "MaxVel",
    )
    latency_a = fm.features["ChannelA"].attribute("Latency")
    latency_b = fm.features["ChannelB"].attribute("Latency")
    assert latency_a is not None and latency_b is not None
    assert latency_a.kind == "cim" and latency_a.scale == ("Low", "High")
    assert (latency_a.rank, latency_b.rank) == (1.0, 0.0)
    power = fm.features["ChannelB"].attribute("PowerConsump")
    assert power is not None and (power.rank, power.unit) == (1.2, "%/min")
    assert latency_a.value == {"kind": "cim", "value": "High", "scale": ["Low", "High"]}
    assert list(latency_a.value) == ["kind", "value", "scale"]  # insertion order kept
    # the constraint, with its spans
    (c,) = fm.constraints
    assert c.expr == Implies(
        left=Ref(name="Material", span=Span(str(OBJECT_STORING), 32, 5)),
        right=Ref(name="Manipulation", span=Span(str(OBJECT_STORING), 32, 17)),
    )
    assert c.span == Span(str(OBJECT_STORING), 32, 5)
    # spans of features, groups and attributes
    env = fm.features["Environment"]
    assert env.span == Span(str(OBJECT_STORING), 12, 13)
    assert env.groups[0].span == Span(str(OBJECT_STORING), 13, 17)
    assert max_vel.span == Span(str(OBJECT_STORING), 20, 75)


def test_quadcopter_example_structure() -> None:
    fm = load_uvl(QUADCOPTER)
    assert fm.namespace == "Quadcopter"
    assert list(fm.features) == [
        "Quadcopter",
        "Flight",
        "Hover",
        "Waypoints",
        "Circle",
        "Controller",
        "Standard",
        "Proploss",
    ]
    assert fm.runtime_features() == ["Controller", "Standard", "Proploss"]
    standard = fm.features["Standard"].attribute("Motors")
    proploss = fm.features["Proploss"].attribute("Motors")
    assert standard is not None and proploss is not None
    assert (standard.kind, standard.rank, proploss.rank) == ("cim", 4.0, 2.0)
    assert fm.group_of["Hover"].bounds == (1, 1)
    assert fm.constraints == ()


@pytest.mark.parametrize("path", [OBJECT_STORING, QUADCOPTER], ids=lambda p: p.parent.name)
def test_examples_round_trip(path: Path) -> None:
    fm = load_uvl(path)
    text = to_uvl(fm)
    again = parse_uvl(text, str(path))
    assert same_model(again, fm)
    assert strip_spans(again) == strip_spans(fm)
    assert to_uvl(again) == text


def test_export_format() -> None:
    text = uvl("""
        namespace N
        features
            "A b" {abstract, x -1.5, y [1, 'two', true], z {k 'v', flag}}
                mandatory
                    B
                [1..*]
                    C
                    D
                [2]
                    E
                [0..1]
                    F
        constraints
            B & (C | D) => !E
            (B => C) => D
            B => (C => D)
            !(B & C) <=> "A b"
    """)
    assert to_uvl(parse_uvl(text)) == uvl("""
        namespace N

        features
            "A b" {abstract, x -1.5, y [1, 'two', true], z {k 'v', flag}}
                mandatory
                    B
                [1..*]
                    C
                    D
                [2]
                    E
                [0..1]
                    F

        constraints
            B & (C | D) => !E
            B => C => D
            B => (C => D)
            !(B & C) <=> "A b"
    """)


def test_precedence_and_left_associativity() -> None:
    text = uvl("""
        features
            A
                optional
                    B
                    C
                    D
        constraints
            !A & B | C => D <=> A
            A => B => C
            A | B & C
            !!A
    """)
    a, b, c, d = (Ref(name=n) for n in "ABCD")
    exprs = [strip_spans(parse_uvl(text)).constraints[i].expr for i in range(4)]
    assert exprs == [
        Equiv(
            left=Implies(left=Or(left=And(left=Not(operand=a), right=b), right=c), right=d), right=a
        ),
        Implies(left=Implies(left=a, right=b), right=c),
        Or(left=a, right=And(left=b, right=c)),
        Not(operand=Not(operand=a)),
    ]


def test_layout_comments_tabs_and_crlf() -> None:
    text = (
        "/* header\n   block */\r\n"
        "namespace  N // trailing\r\n"
        "\r\n"
        "features\r\n"
        "\tRoot {x 1, // inside braces\r\n"
        "\t      y [1,\r\n"
        "\t         2]}\r\n"
        "// a comment at column 1 inside the tree\r\n"
        "\t\toptional\r\n"
        "        /* spaces: 8 = two tabs */\r\n"
        '\t\t\t"Quoted Name" /* after */\r\n'
        "\t\t\tdotted.Name\r\n"
        "constraints\r\n"
        '\tdotted.Name => "Quoted Name"  // done'
    )
    fm = parse_uvl(text, FILE)
    assert fm.namespace == "N"
    assert [f.name for f in fm.root.children] == ["Quoted Name", "dotted.Name"]
    assert fm.root.attribute("y") == Attribute(name="y", value=[1, 2], span=Span(FILE, 7, 8))
    assert fm.constraints[0].span == Span(FILE, 15, 2)
    assert fm.features["dotted.Name"].span == Span(FILE, 13, 4)


def test_values() -> None:
    fm = parse_uvl(
        "features\n    A {i 42, n -7, f 2.5, e 1e-3, g -2.5E+2, s '', t true, u false,"
        " l [], m {}, q [[1], {a 1}], flag, \"quoted key\" 'x'}\n"
    )
    values = {a.name: a.value for a in fm.root.attributes}
    assert values == {
        "i": 42,
        "n": -7,
        "f": 2.5,
        "e": 0.001,
        "g": -250.0,
        "s": "",
        "t": True,
        "u": False,
        "l": [],
        "m": {},
        "q": [[1], {"a": 1}],
        "flag": None,
        "quoted key": "x",
    }
    assert [type(values[k]) for k in ("i", "f", "t")] == [int, float, bool]


def test_load_uvl_errors_name_the_path(tmp_path: Path) -> None:
    bad = tmp_path / "bad.uvl"
    bad.write_text("features\n    A {\n")
    with pytest.raises(DslSyntaxError) as info:
        load_uvl(bad)
    assert info.value.location == Location(str(bad), 2, 8)
    with pytest.raises(RraError, match="cannot read"):
        load_uvl(tmp_path / "missing.uvl")


def test_parses_concurrently() -> None:
    text = OBJECT_STORING.read_text()
    expected = parse_uvl(text)
    results: list[object] = []

    def work() -> None:
        for _ in range(20):
            try:
                results.append(parse_uvl(text))
            except Exception as e:  # collected, asserted below
                results.append(e)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 80 and all(r == expected for r in results)


# ---- the grammar --------------------------------------------------------------------------------


def test_grammar_has_no_conflicts(caplog: pytest.LogCaptureFixture) -> None:
    """lark resolves shift/reduce conflicts silently (as shift) unless strict: there are none."""
    lark_logger = logging.getLogger("lark")
    old = lark_logger.level
    lark_logger.setLevel(logging.DEBUG)
    try:
        with caplog.at_level(logging.DEBUG, logger="lark"):
            build_parser(strict=False)
    finally:
        lark_logger.setLevel(old)
    assert not [r for r in caplog.records if "conflict" in r.getMessage().lower()]
    assert not [r for r in caplog.records if "collision" in r.getMessage().lower()]


def test_every_rule_has_a_transformer_method() -> None:
    from rra_agent.dsl.uvl import _ToModel

    rules = build_parser().rules
    named = {
        str(r.alias or r.origin.name)
        for r in rules
        if not str(r.origin.name).startswith("_") and (r.alias or not r.options.expand1)
    }
    assert named and {n for n in named if not callable(getattr(_ToModel, n, None))} == set()


def test_grammar_builds_in_strict_mode() -> None:
    pytest.importorskip("interegular", reason="lark's strict mode needs interegular")
    parser = build_parser(strict=True)
    assert parser.options.strict


# ---- syntax errors ------------------------------------------------------------------------------

SYNTAX_CASES = [
    pytest.param(
        "features\n    A {x 1 y}\n",
        (2, 12, "y"),
        "unexpected name 'y', expected one of ',', '}'",
        id="token-in-attributes",
    ),
    pytest.param(
        "features\n    A $\n",
        (2, 7, "$"),
        "unexpected character '$', expected one of '.', 'cardinality', '{', end of line",
        id="bad-character",
    ),
    pytest.param(
        "features\n    A\n        B\n",
        (3, 9, "B"),
        "unexpected name 'B', expected one of '[', 'alternative', 'mandatory', 'optional', 'or'",
        id="feature-without-group",
    ),
    pytest.param(
        "namespace X\n    features\n",
        (2, 5, "features"),
        "unexpected indent, expected one of 'features', 'imports', 'include'",
        id="unexpected-indent",
    ),
    pytest.param(
        "features\n    A {x 1\n",
        (2, 11, ""),
        "unexpected end of input, expected one of ',', '}'",
        id="unclosed-brace",
    ),
    pytest.param(
        "features\n    A\n        [1..]\n            B\n",
        (3, 13, "]"),
        "unexpected ']', expected one of '*', integer",
        id="bad-cardinality",
    ),
    pytest.param(
        "features\n", (1, 9, ""), "unexpected end of input, expected indent", id="no-root"
    ),
    pytest.param(
        "features\n    A\n    B\n",
        (3, 5, "B"),
        "unexpected name 'B', expected dedent",
        id="two-roots",
    ),
    pytest.param(
        "features\n    A {x 'abc}\n",
        (2, 10, "'abc"),
        'unexpected character "\'", expected one of ',
        id="unterminated-string",
    ),
    pytest.param(
        "features\n    A\nconstraints\n    A & | A\n",
        (4, 9, "|"),
        "unexpected '|', expected one of '!', '(', '-', integer, name, number, quoted name, string",
        id="constraint-operator",
    ),
    pytest.param(
        "features\n    A\nconstraints\n    (A & A\n",
        (4, 11, ""),
        "unexpected end of input, expected one of '!=', '&', '(', ')', '*'",
        id="unclosed-paren",
    ),
    pytest.param(
        "features\n    A\n        optional\n            B {binding 'runtime'\n",
        (4, 33, ""),
        "unexpected end of input, expected one of ',', '}'",
        id="eof-in-nested-block",
    ),
    pytest.param(
        "features\n    A\n        optional\n        B\n",
        (4, 9, "B"),
        "unexpected name 'B', expected one of '[', 'alternative', 'mandatory', 'optional', 'or'",
        id="feature-at-group-level",
    ),
    pytest.param("", (1, 1, ""), "unexpected end of input, expected one of 'features'", id="empty"),
    pytest.param(
        "namespace {\n",
        (1, 11, "{"),
        "unexpected '{', expected one of name, quoted name",
        id="token-from-other-context",
    ),
    pytest.param(
        'features\n    ""\n', (2, 5, '""'), "unexpected character '\"'", id="empty-quoted-name"
    ),
]


@pytest.mark.parametrize(("text", "where", "message"), SYNTAX_CASES)
def test_syntax_errors(text: str, where: tuple[int, int, str], message: str) -> None:
    e = only(text, DslSyntaxError)
    assert isinstance(e, DslSyntaxError)
    line, col, token = where
    assert_at(e, text + "\n", line, col, token)
    assert e.message.startswith(message), e.message
    assert e.expected and all(name in e.message for name in e.expected)
    assert e.source_line == text.split("\n")[line - 1]


def test_syntax_error_renders_the_line_with_a_caret() -> None:
    e = only("features\n    A {x 1 y}\n", DslSyntaxError)
    assert str(e).splitlines() == [
        "m.uvl:2:12: unexpected name 'y', expected one of ',', '}'",
        "        A {x 1 y}",
        "               ^",
    ]


@pytest.mark.parametrize(
    ("text", "line", "col"),
    [
        ("features\n  A\n     mandatory\n    B\n", 4, 5),
        ("features\n    A\n        mandatory\n            B\n          C\n", 5, 11),
        ("features\n\tA\n\t\tmandatory\n\t\t\tB\n\t\t  C\n", 5, 5),
    ],
)
def test_inconsistent_dedent_is_located(text: str, line: int, col: int) -> None:
    e = only(text, DslSyntaxError)
    assert e.location == Location(FILE, line, col)
    assert e.message.startswith(f"inconsistent dedent to column {col}, which matches no")
    assert e.source_line == text.split("\n")[line - 1]
    assert e.expected and e.expected[0] == "indentation to column 1"


# ---- the rest of UVL: kept, exported, and warned about where reasoning ignores it -------------

FULL_UVL = uvl("""
    namespace N
    include
        Arithmetic.feature-cardinality
        Type.*
    imports
        other.Model as o
    features
        Root
            optional
                Integer price
                B cardinality [1..3]
                C {constraint B => C}
                D {x {constraints [B, C]}}
                String name
    constraints
        B & Root.price > 3
        sum(Root.price) < 10 | B
        len(name) == 3
        name == 'x'
        o.Thing => B
        B => C
""")


def test_full_uvl_constructs_are_kept_and_round_trip() -> None:
    fm = parse_uvl(FULL_UVL, FILE)
    assert fm.includes == ("Arithmetic.feature-cardinality", "Type.*")
    assert [(i.namespace, i.alias) for i in fm.imports] == [("other.Model", "o")]
    f = fm.features
    assert (f["price"].type, f["name"].type, f["B"].type) == ("Integer", "String", None)
    assert f["B"].cardinality == Cardinality(lower=1, upper=3)
    c_attr = f["C"].attributes[0]
    assert c_attr.name == "constraint"
    assert isinstance(c_attr.constraints, ConstraintList) and c_attr.constraints.single
    assert c_attr.value is None
    nested = f["D"].attributes[0].value
    assert isinstance(nested, dict) and isinstance(nested["constraints"], ConstraintList)
    first = fm.constraints[0].expr
    assert isinstance(first, And) and isinstance(first.right, Compare)
    assert first.right == Compare(
        op=">", left=Ref(name="Root.price", span=Span(FILE, 16, 9)), right=Num(value=3)
    )
    assert isinstance(fm.constraints[1].expr, Or)
    assert isinstance(fm.constraints[1].expr.left.left, Aggregate)  # type: ignore[attr-defined]
    assert fm.constraints[3].expr == Compare(
        op="==", left=Ref(name="name", span=Span(FILE, 19, 5)), right=Text(value="x")
    )
    # only the propositional constraint over this model's features is reasoned with
    assert [c.span.line for c in fm.boolean_constraints if c.span] == [21]
    again = parse_uvl(to_uvl(fm), FILE)
    assert same_model(again, fm)


def test_models_of_the_whole_language_decode_from_json() -> None:
    """The model types stay decodable with msgspec (packages ship feature models as JSON)."""
    import msgspec

    text = FULL_UVL.replace("            D {x {constraints [B, C]}}\n", "")
    fm = parse_uvl(text, FILE)
    assert msgspec.json.decode(msgspec.json.encode(fm), type=FeatureModel) == fm


def test_what_reasoning_ignores_is_warned_about_at_its_place() -> None:
    warnings = uvl_warnings(parse_uvl(FULL_UVL, FILE))
    expected = [
        (6, 5, "other.Model", "imported model 'other.Model' is not loaded"),
        (11, 13, "B cardinality", "feature 'B' has cardinality [1..3]"),
        (12, 16, "constraint", "constraint attribute of feature 'C' is kept"),
        (13, 16, "x {constraints", "constraint attribute of feature 'D' is kept"),
        (16, 5, "B & Root", "constraint uses a comparison"),
        (17, 5, "sum(", "constraint uses the aggregate function sum"),
        (18, 5, "len(", "constraint uses the aggregate function len"),
        (19, 5, "name ==", "constraint uses a string comparison"),
        (20, 5, "o.Thing", "constraint names 'o.Thing' of an imported model"),
    ]
    assert len(warnings) == len(expected), warnings
    for w, (line, col, token, start) in zip(warnings, expected, strict=True):
        assert w.location == Location(FILE, line, col), w
        assert FULL_UVL.split("\n")[line - 1][col - 1 :].startswith(token)
        assert w.message.startswith(start), w
        assert str(w).startswith(f"{FILE}:{line}:{col}: warning: ")
    assert uvl_warnings(load_uvl(OBJECT_STORING)) == []
    assert uvl_warnings(load_uvl(QUADCOPTER)) == []


def test_reasoning_ignores_constraints_it_cannot_evaluate() -> None:
    """A comparison never blocks a selection; the propositional constraint still does."""
    from rra_agent.core.features import check_selection

    fm = parse_uvl(FULL_UVL, FILE)
    assert check_selection(fm, {"Root", "B"}) != []  # B => C
    assert check_selection(fm, {"Root", "B", "C"}) == []  # Root.price > 3 is not evaluated


def test_imported_root_placed_in_the_tree_is_reasoned_about() -> None:
    """``e.Engine`` (an imported model's root put in the tree) is a feature of this model, so
    a constraint over it is enforced; one naming a feature inside the imported model is not."""
    fm = parse_uvl(
        uvl("""
            imports
                sub.Engine as e
            features
                Car
                    optional
                        e.Engine
                        Turbo
            constraints
                Turbo => e.Engine
                e.Engine.Big => Turbo
        """),
        FILE,
    )
    assert [c.span.line for c in fm.boolean_constraints if c.span] == [9]
    warnings = [w.message for w in uvl_warnings(fm)]
    assert warnings[-1].startswith("constraint names 'e.Engine.Big' of an imported model")


MISPLACED = uvl("""
    features
        Root
            optional
                B
                Integer n
    constraints
        (B | n) & 2 + 3
        'text'
        n > (B & n)
        -B > 1
        B & max(n) > 1
        sum(n, n, n) > 1
        len(3) == 1
""")


def test_misplaced_expressions_are_located_errors() -> None:
    found = fails(MISPLACED)
    assert all(isinstance(e, SemanticError) for e in found)
    expected = [
        (7, 15, "2 + 3", "expected a condition (a feature, a comparison, or ! & | => <=>), "
         "not an arithmetic term"),
        (8, 5, "'text'", "expected a condition (a feature, a comparison, or ! & | => <=>), "
         "not a string"),
        (9, 10, "B & n", "expected a value (a number, a string, a reference or a function), "
         "not a condition"),
        (10, 5, "-B", "a minus sign applies to numbers only, not to a condition (write 0 - x)"),
        (11, 9, "max", "unknown function max() (UVL has sum(), avg(), len(), floor(), ceil())"),
        (12, 5, "sum", "sum() takes 1 or 2 reference(s), not 3"),
        (13, 5, "len", "len() takes feature or attribute references, not a number"),
    ]  # fmt: skip
    assert len(found) == len(expected), found
    for e, (line, col, token, message) in zip(found, expected, strict=True):
        assert_at(e, MISPLACED, line, col, token)
        assert e.message == message


# ---- semantic errors ----------------------------------------------------------------------------

SEMANTIC_CASES = [
    pytest.param(
        """
        features
            A
                optional
                    B
                    B
        """,
        (5, 13, "B"),
        "duplicate feature name 'B' (first declared at 4:13)",
        id="duplicate-feature",
    ),
    pytest.param(
        """
        features
            A
                optional
                    B
        constraints
            B => (A | Ghost)
        """,
        (6, 15, "Ghost"),
        "constraint refers to unknown feature 'Ghost'",
        id="unknown-feature",
    ),
    pytest.param(
        """
        features
            A
                optional
                    "B b" {alias 'Bb'}
        constraints
            A => Bb
        """,
        (6, 10, "Bb"),
        "constraint refers to unknown feature 'Bb' ('Bb' is the alias of 'B b'; UVL",
        id="alias-in-constraint",
    ),
    pytest.param(
        """
        features
            A {binding 'sometimes'}
        """,
        (2, 8, "binding"),
        "binding must be 'deployment' or 'runtime', not 'sometimes'",
        id="bad-binding",
    ),
    pytest.param(
        """
        features
            A {binding}
        """,
        (2, 8, "binding"),
        "binding must be 'deployment' or 'runtime', not nothing",
        id="binding-flag",
    ),
    pytest.param(
        """
        features
            A
                optional
                    B {binding 'runtime'}
                        mandatory
                            C
                                optional
                                    D {x 1, binding 'deployment'}
        """,
        (8, 37, "binding"),
        "feature 'D' is bound at deployment time but its parent 'C' is bound at run time",
        id="deployment-under-runtime",
    ),
    pytest.param(
        """
        features
            A
                optional
                    B {alias 'Same'}
                    C {alias 'Same'}
        """,
        (5, 16, "alias"),
        "alias 'Same' is already used by 'B'",
        id="duplicate-alias",
    ),
    pytest.param(
        """
        features
            A
                optional
                    B {alias 'A'}
        """,
        (4, 16, "alias"),
        "alias 'A' of 'B' is the name of another feature",
        id="alias-is-a-feature-name",
    ),
    pytest.param(
        """
        features
            A {alias 'two words'}
        """,
        (2, 8, "alias"),
        "alias must be a string holding a plain identifier, not 'two words'",
        id="alias-not-identifier",
    ),
    pytest.param(
        """
        features
            A {Lat {kind 'cmi', value 1}}
        """,
        (2, 13, "kind"),
        "attribute 'Lat': kind must be 'cim', 'nfr' or 'cv', not 'cmi'",
        id="bad-kind",
    ),
    pytest.param(
        """
        features
            A {Lat {kind 'cim', unit 'ms'}}
        """,
        (2, 8, "Lat"),
        "cim attribute 'Lat' needs value (a number or a string)",
        id="cim-without-value",
    ),
    pytest.param(
        """
        features
            A {Lat {kind 'cim', value true}}
        """,
        (2, 25, "value"),
        "cim attribute 'Lat': value must be a number or a string, not true",
        id="cim-bool-value",
    ),
    pytest.param(
        """
        features
            A {Lat {kind 'cim', value 'High'}}
        """,
        (2, 8, "Lat"),
        "cim attribute 'Lat' needs scale (a list of distinct strings, lowest first)",
        id="cim-string-without-scale",
    ),
    pytest.param(
        """
        features
            A {Lat {kind 'cim', value 'Mid', scale ['Low', 'High']}}
        """,
        (2, 25, "value"),
        "cim attribute 'Lat': value must be one of the scale ['Low', 'High'], not 'Mid'",
        id="cim-value-not-in-scale",
    ),
    pytest.param(
        """
        features
            A {Lat {kind 'cim', value 'Low', scale ['Low', 1]}}
        """,
        (2, 38, "scale"),
        "cim attribute 'Lat': scale must be a list of distinct strings, lowest first, "
        "not ['Low', 1]",
        id="cim-bad-scale",
    ),
    pytest.param(
        """
        features
            A {Lim {kind 'nfr', tag 'maximum', value 1}}
        """,
        (2, 25, "tag"),
        "nfr attribute 'Lim': tag must be 'min', 'max', 'avg' or 'count', not 'maximum'",
        id="nfr-bad-tag",
    ),
    pytest.param(
        """
        features
            A {Lim {kind 'nfr', tag 'max', value 'fast'}}
        """,
        (2, 36, "value"),
        "nfr attribute 'Lim': value must be a number, not 'fast'",
        id="nfr-string-value",
    ),
    pytest.param(
        """
        features
            A {Lim {kind 'nfr', tag 'max'}}
        """,
        (2, 8, "Lim"),
        "nfr attribute 'Lim' needs value (a number)",
        id="nfr-without-value",
    ),
    pytest.param(
        """
        features
            A {Vel {kind 'cv', lower 0, upper 1},
               Lim {kind 'nfr', tag 'max', value 1, constrains 'Vell'}}
        """,
        (3, 45, "constrains"),
        "nfr attribute 'Lim': constrains must be the name of a cv attribute (known: Vel), "
        "not 'Vell'",
        id="nfr-constrains-unknown",
    ),
    pytest.param(
        """
        features
            A {Vel {kind 'cv', lower 2, upper 1.5}}
        """,
        (2, 24, "lower"),
        "cv attribute 'Vel': lower 2 exceeds upper 1.5",
        id="cv-lower-above-upper",
    ),
    pytest.param(
        """
        features
            A {Vel {kind 'cv', lower 0}}
        """,
        (2, 8, "Vel"),
        "cv attribute 'Vel' needs upper (a number)",
        id="cv-without-upper",
    ),
    pytest.param(
        """
        features
            A {Vel {kind 'cv', lower 0, upper 1, colour 'red'}}
        """,
        (2, 42, "colour"),
        "attribute 'Vel': unknown key 'colour' (allowed: constrains, description, kind, lower,",
        id="unknown-key",
    ),
    pytest.param(
        """
        features
            A {Vel {kind 'cv', lower 0, upper 1, unit 3}}
        """,
        (2, 42, "unit"),
        "attribute 'Vel': unit must be a string",
        id="unit-not-string",
    ),
    pytest.param(
        """
        features
            A {Vel {kind 'cv', lower 0, upper 1}}
                optional
                    B {Vel {kind 'cv', lower 0, upper 2}}
        """,
        (4, 16, "Vel"),
        "attribute name 'Vel' is used twice (first at 2:8); rules refer to attributes by name",
        id="duplicate-cv-name",
    ),
    pytest.param(
        """
        features
            A {Lat {kind 'cim', value 1}}
                optional
                    B {Lat {kind 'nfr', tag 'max', value 2}}
        """,
        (4, 16, "Lat"),
        "attribute name 'Lat' is used twice (first at 2:8)",
        id="cim-name-reused-by-nfr",
    ),
    pytest.param(
        """
        features
            A
                alternative
                    B {Lat {kind 'cim', value 'Low', scale ['Low', 'High']}}
                    C {Lat {kind 'cim', value 'Low', scale ['High', 'Low']}}
        """,
        (5, 46, "scale"),
        "cim attribute 'Lat' has a different scale than its first use (at 4:16)",
        id="cim-scales-differ",
    ),
    pytest.param(
        """
        features
            A {x 1, y 2, x 3}
        """,
        (2, 18, "x"),
        "feature 'A' has attribute 'x' twice (first at 2:8)",
        id="duplicate-attribute",
    ),
    pytest.param(
        """
        features
            A {Vel {kind 'cv', lower 0, upper 1, lower 2}}
        """,
        (2, 42, "lower"),
        "duplicate key 'lower' (first given at 2:24)",
        id="duplicate-key",
    ),
    pytest.param(
        """
        features
            A
                [3..1]
                    B
        """,
        (3, 9, "[3..1]"),
        "group cardinality lower bound 3 exceeds upper bound 1",
        id="cardinality-bounds",
    ),
    pytest.param(
        """
        features
            A {abstract 'yes'}
        """,
        (2, 8, "abstract"),
        "abstract must be a flag or true/false, not 'yes'",
        id="abstract-value",
    ),
    pytest.param(
        """
        features
            A {x 99999999999999999999999999999999999999999999999999e999}
        """,
        (2, 10, "9999"),
        "number out of range",
        id="float-overflow",
    ),
    pytest.param(
        """
        features
            A {Vel {kind 'cv', lower 0, upper 1}, Lim {kind 'nfr', tag 'min', value 0,
               constrains ['Vel']}}
        """,
        (3, 8, "constrains"),
        "nfr attribute 'Lim': constrains must be the name of a cv attribute (known: Vel), "
        "not ['Vel']",
        id="nfr-constrains-list",
    ),
]


@pytest.mark.parametrize(("text", "where", "message"), SEMANTIC_CASES)
def test_semantic_errors(text: str, where: tuple[int, int, str], message: str) -> None:
    source = uvl(text)
    e = only(source, SemanticError)
    assert_at(e, source, *where)
    assert e.message.startswith(message), e.message


def test_semantic_errors_are_all_collected_in_source_order() -> None:
    source = uvl("""
        features
            A {binding 'never'}
                optional
                    A
                    B {Vel {kind 'cv', lower 1, upper 0}}
        constraints
            Ghost | B
    """)
    found = fails(source)
    assert [(e.location.line, e.location.col) for e in found if e.location] == [
        (2, 8),
        (4, 13),
        (5, 32),
        (7, 5),
    ]
    assert all(isinstance(e, SemanticError) for e in found)


def test_valid_rra_attributes_pass() -> None:
    source = uvl("""
        features
            A {binding 'deployment', alias 'AA', abstract true}
                alternative
                    B {binding 'runtime',
                       Lat {kind 'cim', value 'Low', scale ['Low', 'High'], description 'ok'}}
                        optional
                            B1 {binding 'runtime'}
                    C {Lat {kind 'cim', value 'High', scale ['Low', 'High']},
                       Cost {kind 'cim', value -3}}
                optional
                    D {Vel {kind 'cv', lower -1, upper 2.5, unit 'm/s'},
                       Lim {kind 'nfr', tag 'count', value 3, constrains 'Vel'}}
                    E {plain {kind2 'whatever', nested {kind 'not checked here'}}}
    """)
    fm = parse_uvl(source)
    assert fm.root.abstract and fm.aliases == {"AA": "A"}
    assert fm.features["D"].attribute("Lim").constrains == "Vel"  # type: ignore[union-attr]


def test_check_feature_model_works_on_models_built_in_code() -> None:
    fm = FeatureModel(
        root=Feature(
            name="R",
            attributes=(Attribute(name="binding", value="runtime"),),
            groups=(
                Group(
                    kind="optional",
                    children=(
                        Feature(
                            name="X", attributes=(Attribute(name="binding", value="deployment"),)
                        ),
                    ),
                ),
            ),
        ),
        constraints=(Constraint(expr=Ref(name="Y")),),
    )
    found = check_feature_model(fm)
    assert [e.message for e in found] == [
        "feature 'X' is bound at deployment time but its parent 'R' is bound at run time",
        "constraint refers to unknown feature 'Y'",
    ]
    assert all(e.location is None for e in found)


def test_overlong_integer_is_located() -> None:
    text = "features\n    A {x 1, y " + "9" * 5000 + "}\n"
    e = only(text, SemanticError)
    assert_at(e, text, 2, 15, "9999")
    assert e.message == "number too long"


def test_nesting_depth_is_limited() -> None:
    deep = "features\n    A\nconstraints\n    " + "!" * (MAX_DEPTH + 10) + "A\n"
    e = only(deep, DslSyntaxError)
    assert e.location is not None and e.location.line == 4
    assert f"nested more than {MAX_DEPTH} levels deep" in e.message
    ok = "features\n    A\nconstraints\n    " + "(" * 100 + "!" * 100 + "A" + ")" * 100 + "\n"
    assert len(parse_uvl(ok).constraints) == 1


# ---- export of what UVL cannot hold -------------------------------------------------------------


@pytest.mark.parametrize(
    "fm",
    [
        FeatureModel(root=Feature(name='say "hi"')),
        FeatureModel(root=Feature(name="")),
        FeatureModel(root=Feature(name="line\nbreak")),
        FeatureModel(root=Feature(name="A", attributes=(Attribute(name="s", value="it's"),))),
        FeatureModel(root=Feature(name="A", attributes=(Attribute(name="f", value=float("nan")),))),
        FeatureModel(root=Feature(name="A", attributes=(Attribute(name="f", value=[None]),))),
        FeatureModel(root=Feature(name="A", attributes=(Attribute(name="f", value={1: 2}),))),
    ],
    ids=["quote", "empty", "newline", "apostrophe", "nan", "none-in-list", "int-key"],
)
def test_export_rejects_what_uvl_cannot_write(fm: FeatureModel) -> None:
    with pytest.raises(RraError, match=r"cannot be written in UVL|UVL names are strings"):
        to_uvl(fm)


def test_keywords_and_odd_names_are_quoted() -> None:
    names = [*sorted(KEYWORDS), "1st", "a b", "x.", "ünï", "_x", "a.b.c", "-"]
    root = Feature(
        name="Root",
        groups=(Group(kind="optional", children=tuple(Feature(name=n) for n in names)),),
    )
    fm = FeatureModel(
        root=root,
        constraints=tuple(Constraint(expr=Ref(name=n)) for n in names),
        source=FILE,
    )
    text = to_uvl(fm)
    assert '"or"' in text and '"1st"' in text and "a.b.c\n" in text
    # plain only where the reference grammar reads a plain name too (ASCII letter first)
    assert '    "ünï"\n' in text and '    "_x"\n' in text
    assert same_model(parse_uvl(text, FILE), fm)


# ---- round trips of generated models ------------------------------------------------------------

PLAIN = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,6}(\.[A-Za-z_][A-Za-z0-9_]{0,3})?", fullmatch=True)
QUOTABLE = st.text(
    st.characters(exclude_characters='"\r\n', exclude_categories=["Cs"]), min_size=1, max_size=8
)
NAMES = st.one_of(PLAIN, QUOTABLE, st.sampled_from(sorted(KEYWORDS)))
RESERVED = {"binding", "alias", "abstract"}
TEXT = st.text(st.characters(exclude_characters="'\r\n", exclude_categories=["Cs"]), max_size=8)
SCALARS = st.one_of(
    st.booleans(),
    st.integers(),
    st.floats(allow_nan=False, allow_infinity=False),
    TEXT,
)


def _maps(values: st.SearchStrategy) -> st.SearchStrategy:
    keys = NAMES.filter(lambda k: k != "kind")
    return st.dictionaries(keys, st.one_of(st.none(), values), max_size=3)


VALUES = st.recursive(
    SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=3), _maps(inner)), max_leaves=6
)
ATTRIBUTE_VALUES = st.one_of(st.none(), VALUES)
GROUP_KINDS = st.sampled_from(["mandatory", "optional", "alternative", "or", "cardinality"])


@st.composite
def kinded_attributes(draw: st.DrawFn, index: int) -> Attribute:
    kind = draw(st.sampled_from(["cim", "nfr", "cv"]))
    name = f"{kind}{index}"
    number = st.one_of(st.integers(-1000, 1000), st.floats(-1e6, 1e6))
    if kind == "cim":
        scale = draw(st.lists(TEXT, min_size=1, max_size=3, unique=True))
        value = draw(st.one_of(number, st.sampled_from(scale)))
        body = {"kind": "cim", "value": value}
        if isinstance(value, str):
            body["scale"] = scale
    elif kind == "nfr":
        tag = draw(st.sampled_from(["min", "max", "avg", "count"]))
        body = {"kind": "nfr", "tag": tag, "value": draw(number), "unit": draw(TEXT)}
    else:
        low, high = sorted([draw(number), draw(number)])
        body = {"kind": "cv", "lower": low, "upper": high}
    return Attribute(name=name, value=body)


@st.composite
def attributes(draw: st.DrawFn, counter: list[int]) -> tuple[Attribute, ...]:
    names = draw(st.lists(NAMES.filter(lambda n: n not in RESERVED), max_size=3, unique=True))
    out = [Attribute(name=n, value=draw(ATTRIBUTE_VALUES)) for n in names]
    if draw(st.booleans()):
        counter[0] += 1
        out.append(draw(kinded_attributes(counter[0])))
    if draw(st.booleans()):
        out.insert(0, Attribute(name="abstract"))
    return tuple(out)


@st.composite
def groups(draw: st.DrawFn, children: list[Feature]) -> tuple[Group, ...]:
    n_groups = draw(st.integers(1 if children else 0, 3))
    slots: list[list[Feature]] = [[] for _ in range(n_groups)]
    for child in children:
        slots[draw(st.integers(0, n_groups - 1))].append(child)
    out = []
    for members in slots:
        kind = draw(GROUP_KINDS)
        lower = upper = None
        if kind == "cardinality":
            lower = draw(st.integers(0, 5))
            upper = draw(st.one_of(st.none(), st.integers(lower, 9)))
        out.append(Group(kind=kind, children=tuple(members), lower=lower, upper=upper))
    return tuple(out)


@st.composite
def feature_models(draw: st.DrawFn) -> FeatureModel:
    names = draw(st.lists(NAMES, min_size=1, max_size=10, unique=True))
    parent_of = [draw(st.integers(0, i - 1)) for i in range(1, len(names))]
    runtime = draw(st.sets(st.sampled_from(names)))
    counter = [0]

    def build(i: int) -> Feature:
        kids = [build(j + 1) for j, p in enumerate(parent_of) if p == i]
        attrs = draw(attributes(counter))
        if names[i] in runtime:
            attrs = (Attribute(name="binding", value="runtime"), *attrs)
        return Feature(name=names[i], attributes=attrs, groups=draw(groups(kids)))

    root = build(0)
    refs = st.sampled_from(names).map(lambda n: Ref(name=n))
    exprs: st.SearchStrategy[Expr] = st.recursive(
        refs,
        lambda e: st.one_of(
            e.map(lambda x: Not(operand=x)),
            *(st.builds(op, left=e, right=e) for op in (And, Or, Implies, Equiv)),
        ),
        max_leaves=8,
    )
    constraints = tuple(Constraint(expr=x) for x in draw(st.lists(exprs, max_size=4)))
    namespace = draw(st.one_of(st.none(), NAMES))
    return FeatureModel(root=root, constraints=constraints, namespace=namespace, source=FILE)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(feature_models())
def test_generated_models_round_trip(fm: FeatureModel) -> None:
    assert check_feature_model(fm) == []
    text = to_uvl(fm)
    again = parse_uvl(text, FILE)
    assert same_model(again, fm), text
    assert strip_spans(again) == fm
    assert to_uvl(again) == text


KINDED_VALUES = st.one_of(st.sampled_from(["cim", "nfr", "cv", "min", "max", "Low", "x"]), VALUES)


@st.composite
def odd_kinded_models(draw: st.DrawFn) -> FeatureModel:
    keys = ["kind", "value", "unit", "tag", "lower", "upper", "scale", "constrains", "odd"]
    attrs = []
    for i in range(draw(st.integers(1, 4))):
        body = {k: draw(KINDED_VALUES) for k in draw(st.lists(st.sampled_from(keys), unique=True))}
        body["kind"] = draw(st.one_of(st.sampled_from(["cim", "nfr", "cv"]), KINDED_VALUES))
        attrs.append(Attribute(name=draw(st.sampled_from(["x", "y", f"a{i}"])), value=body))
    specials = st.sampled_from(["binding", "alias", "abstract"])
    attrs += [Attribute(name=n, value=draw(ATTRIBUTE_VALUES)) for n in draw(st.sets(specials))]
    child = Feature(name="C", attributes=tuple(attrs[::2]))
    root = Feature(
        name="R", attributes=tuple(attrs[1::2]), groups=(Group(kind="or", children=(child,)),)
    )
    return FeatureModel(root=root, source=FILE)


def unplaced(message: str) -> str:
    """A message without the ``(first at line:col)`` that only parsed models can give."""
    return re.sub(r" \((first (declared )?)?at \d+:\d+\)", "", message)


@settings(max_examples=200, deadline=None)
@given(odd_kinded_models())
def test_checks_never_crash_on_odd_attribute_values(fm: FeatureModel) -> None:
    found = check_feature_model(fm)
    assert all(isinstance(e, SemanticError) for e in found)
    try:
        text = to_uvl(fm)
    except RraError:
        return
    try:
        again = parse_uvl(text, FILE)
    except RraError as e:
        located = e.errors if isinstance(e, ErrorGroup) else [e]
        parsed_messages = sorted(unplaced(x.message) for x in located)
        assert parsed_messages == sorted(unplaced(x.message) for x in found)
        return
    assert found == [] and same_model(again, fm)


def test_same_model_tells_true_from_one() -> None:
    one = FeatureModel(root=Feature(name="A", attributes=(Attribute(name="x", value=1),)))
    true = FeatureModel(root=Feature(name="A", attributes=(Attribute(name="x", value=True),)))
    assert one == true  # Python's 1 == True ...
    assert not same_model(one, true)  # ... which the round trip must not blur


# ---- fuzzing: any text is a model or an RraError ------------------------------------------------


def parses_or_fails_cleanly(text: str) -> None:
    try:
        fm = parse_uvl(text, FILE)
    except RraError as e:
        located = e.errors if isinstance(e, ErrorGroup) else [e]
        for err in located:
            assert isinstance(err, LocatedError) and err.location is not None
            assert err.location.file == FILE and err.location.line >= 1
        return
    again = parse_uvl(to_uvl(fm), FILE)  # whatever parses also exports and round-trips
    assert same_model(again, fm)


EXAMPLE = OBJECT_STORING.read_text()
SIGNIFICANT = '{}[]()\'",.!&|=<>-*/\n\t "' + string.ascii_letters[:6] + "0123456789"


@settings(max_examples=300, deadline=None)
@given(st.text())
def test_any_text_parses_or_raises_rra_error(text: str) -> None:
    parses_or_fails_cleanly(text)


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet=SIGNIFICANT + "ab\n    ", max_size=80))
def test_uvl_like_text_parses_or_raises_rra_error(text: str) -> None:
    parses_or_fails_cleanly("features\n    R\n" + text)


@st.composite
def mutated_example(draw: st.DrawFn) -> str:
    text = EXAMPLE
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(text)))
        if draw(st.booleans()):
            j = draw(st.integers(i, min(len(text), i + 12)))
            text = text[:i] + text[j:]
        else:
            text = text[:i] + draw(st.text(alphabet=SIGNIFICANT, min_size=1, max_size=4)) + text[i:]
    return text


@settings(max_examples=400, deadline=None)
@given(mutated_example())
def test_mutated_example_parses_or_raises_rra_error(text: str) -> None:
    parses_or_fails_cleanly(text)


def test_rra_validate_prints_the_warnings(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A package whose UVL uses what the reasoning ignores validates, with located warnings."""
    import shutil

    from rra_agent.cli.commands import main

    pkg = tmp_path / "pkg"
    shutil.copytree(ROOT / "scenarios/base_station", pkg)
    uvl_file = pkg / "features.uvl"
    text = uvl_file.read_text(encoding="utf-8").replace(
        "RemotePlanning {default}", "RemotePlanning {default, latency 5}"
    )
    uvl_file.write_text(text + "\nconstraints\n    RemotePlanning.latency < 10\n")
    assert main(["validate", str(pkg)]) == 0
    out = capsys.readouterr().out.splitlines()
    line = len(text.splitlines()) + 3
    assert out[0] == (
        f"{uvl_file}:{line}:5: warning: constraint uses a comparison: "
        "rra-agent's feature reasoning ignores it"
    )
    assert out[1].startswith(f"{pkg}: ok (")
