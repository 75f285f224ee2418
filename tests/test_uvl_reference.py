"""rra-agent's UVL parser against the reference parser ``uvlparser`` (ANTLR, the UVL project's).

Both parse trees are brought to one normal form (`norm_model` for rra-agent's `FeatureModel`,
`norm_reference` for the reference's ANTLR tree): namespace, include levels, imports, every
feature with its type, cardinality and parent, every group with its kind, cardinality and
members, every attribute value (constraint attributes included), and every constraint as a
tree. A property-based test generates models over the whole language, exports them with
`to_uvl`, and asserts that both parsers read the text alike and that rra-agent reads back the
model it exported; hand-written cases cover each construct of the UVL language reference in
the ways people write it (tabs, comments, blank lines, parentheses, quoting).

Two quirks of the reference lexer shape the generator, not the language: it lexes ``[1]``
inside a vector as a cardinality and ``a-1`` as ``a`` followed by the number ``-1``; the
exporter writes spaces around operators, and generated vectors never hold one integer alone.
"""

from __future__ import annotations

import string
from textwrap import dedent
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytest.importorskip("uvl.UVLPythonParser", reason="uvlparser (the test extra) is not installed")

from antlr4 import CommonTokenStream, InputStream
from antlr4.error.ErrorListener import ErrorListener
from uvl.UVLCustomLexer import UVLCustomLexer
from uvl.UVLPythonParser import UVLPythonParser

from rra_agent.dsl.uvl import KEYWORDS, parse_uvl, same_model, to_uvl
from rra_agent.models.features import (
    Aggregate,
    And,
    Arith,
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
    Import,
    Not,
    Num,
    Or,
    Ref,
    Text,
)

# ---- the reference parser and its normal form ---------------------------------------------------


class _Raise(ErrorListener):
    def syntaxError(self, recognizer: Any, symbol: Any, line: int, col: int, msg: str, e: Any):
        raise SyntaxError(f"reference parser: {line}:{col}: {msg}")


def parse_reference(text: str) -> Any:
    """The reference parser's tree of ``text`` (a SyntaxError when it refuses it)."""
    lexer = UVLCustomLexer(InputStream(text))
    lexer.removeErrorListeners()
    lexer.addErrorListener(_Raise())
    parser = UVLPythonParser(CommonTokenStream(lexer))
    parser.removeErrorListeners()
    parser.addErrorListener(_Raise())
    return parser.featureModel()


def _kind(ctx: Any) -> str:
    return type(ctx).__name__.removesuffix("Context")


def _unquote(text: str) -> str:
    return text[1:-1] if text.startswith('"') else text


def _ref_name(ctx: Any) -> str:
    return ".".join(_unquote(i.getText()) for i in ctx.id_())


def _cardinality(text: str) -> tuple[int, int | None]:
    low, _, high = text[1:-1].partition("..")
    if not high:
        return int(low), int(low)
    return int(low), None if high == "*" else int(high)


_COMPARE = {
    "EqualEquation": "==",
    "NotEqualsEquation": "!=",
    "LowerEquation": "<",
    "LowerEqualsEquation": "<=",
    "GreaterEquation": ">",
    "GreaterEqualsEquation": ">=",
}
_LOGIC = {
    "AndConstraint": "and",
    "OrConstraint": "or",
    "ImplicationConstraint": "implies",
    "EquivalenceConstraint": "equiv",
}


def _ref_constraint(ctx: Any) -> tuple:
    kind = _kind(ctx)
    if kind == "ParenthesisConstraint":
        return _ref_constraint(ctx.constraint())
    if kind == "LiteralConstraint":
        return ("ref", _ref_name(ctx.reference()))
    if kind == "NotConstraint":
        return ("not", _ref_constraint(ctx.constraint()))
    if kind in _LOGIC:
        return (
            _LOGIC[kind],
            _ref_constraint(ctx.constraint(0)),
            _ref_constraint(ctx.constraint(1)),
        )
    assert kind == "EquationConstraint", kind
    eq = ctx.equation()
    op = _COMPARE[_kind(eq)]
    return ("cmp", op, _ref_term(eq.expression(0)), _ref_term(eq.expression(1)))


def _ref_term(ctx: Any) -> tuple:
    kind = _kind(ctx)
    match kind:
        case "Expression":
            return _ref_term(ctx.additiveExpression())
        case "MultiplicativeExpr":
            return _ref_term(ctx.multiplicativeExpression())
        case "AddExpression" | "SubExpression":
            op = "+" if kind == "AddExpression" else "-"
            left, right = ctx.additiveExpression(), ctx.multiplicativeExpression()
            return ("arith", op, _ref_term(left), _ref_term(right))
        case "MulExpression" | "DivExpression":
            op = "*" if kind == "MulExpression" else "/"
            left, right = ctx.multiplicativeExpression(), ctx.primaryExpression()
            return ("arith", op, _ref_term(left), _ref_term(right))
        case "PrimaryExpressionExpression":
            return _ref_term(ctx.primaryExpression())
        case "FloatLiteralExpression":
            return ("num", ("float", float(ctx.getText())))
        case "IntegerLiteralExpression":
            return ("num", ("int", int(ctx.getText())))
        case "StringLiteralExpression":
            return ("str", ctx.getText()[1:-1])
        case "LiteralExpression":
            return ("ref", _ref_name(ctx.reference()))
        case "BracketExpression":
            return _ref_term(ctx.expression())
        case "AggregateFunctionExpression":
            return _ref_aggregate(ctx.aggregateFunction())
    raise AssertionError(kind)


def _ref_aggregate(ctx: Any) -> tuple:
    kind = _kind(ctx)
    inner = {
        "SumAggregateFunctionExpression": lambda: ("sum", ctx.sumAggregateFunction()),
        "AvgAggregateFunctionExpression": lambda: ("avg", ctx.avgAggregateFunction()),
        "StringAggregateFunctionExpression": lambda: ("len", ctx.stringAggregateFunction()),
        "NumericAggregateFunctionExpression": lambda: (None, ctx.numericAggregateFunction()),
    }[kind]()
    name, node = inner
    if name is None:
        name = "floor" if _kind(node) == "FloorAggregateFunction" else "ceil"
    refs = node.reference()
    refs = refs if isinstance(refs, list) else [refs]
    return ("agg", name, tuple(_ref_name(r) for r in refs))


def _ref_value(ctx: Any) -> Any:
    if ctx.BOOLEAN() is not None:
        return ("bool", ctx.getText() == "true")
    if ctx.FLOAT() is not None:
        return ("float", float(ctx.getText()))
    if ctx.INTEGER() is not None:
        return ("int", int(ctx.getText()))
    if ctx.STRING() is not None:
        return ("str", ctx.getText()[1:-1])
    if ctx.attributes() is not None:
        return ("map", _ref_attributes(ctx.attributes()))
    return ("list", tuple(_ref_value(v) for v in ctx.vector().value()))


def _ref_attributes(ctx: Any) -> tuple:
    out = []
    for a in ctx.attribute():
        if a.valueAttribute() is not None:
            va = a.valueAttribute()
            value = _ref_value(va.value()) if va.value() is not None else None
            out.append((_unquote(va.key().getText()), value))
            continue
        ca = a.constraintAttribute()
        if _kind(ca) == "SingleConstraintAttribute":
            out.append(("constraint", ("constraint", _ref_constraint(ca.constraint()))))
        else:
            exprs = tuple(_ref_constraint(c) for c in ca.constraintList().constraint())
            out.append(("constraints", ("constraints", exprs)))
    return tuple(out)


def norm_reference(tree: Any) -> dict[str, Any]:
    """The normal form of the reference parser's tree."""
    features: list[tuple] = []
    groups: list[tuple] = []
    attributes: dict[str, tuple] = {}

    def feature(ctx: Any, parent: str | None) -> None:
        name = _ref_name(ctx.reference())
        ftype = ctx.featureType().getText() if ctx.featureType() is not None else None
        card = ctx.featureCardinality()
        card_n = _cardinality(card.CARDINALITY().getText()) if card is not None else None
        features.append((name, ftype, parent, card_n))
        attributes[name] = _ref_attributes(ctx.attributes()) if ctx.attributes() else ()
        for g in ctx.group():
            kind = _kind(g).removesuffix("Group").lower()
            bounds = _cardinality(g.CARDINALITY().getText()) if kind == "cardinality" else None
            members = g.groupSpec().feature()
            groups.append((name, kind, bounds, tuple(_ref_name(m.reference()) for m in members)))
            for m in members:
                feature(m, name)

    feature(tree.features().feature(), None)
    includes = tree.includes()
    imports = tree.imports()
    constraints = tree.constraints()
    return {
        "namespace": _ref_name(tree.namespace().reference()) if tree.namespace() else None,
        "includes": tuple(i.languageLevel().getText() for i in includes.includeLine())
        if includes
        else (),
        "imports": tuple(
            (_ref_name(i.reference(0)), _ref_name(i.reference(1)) if i.reference(1) else None)
            for i in imports.importLine()
        )
        if imports
        else (),
        "features": tuple(features),
        "groups": tuple(groups),
        "attributes": attributes,
        "constraints": tuple(_ref_constraint(c.constraint()) for c in constraints.constraintLine())
        if constraints
        else (),
    }


# ---- rra-agent's model in the same normal form --------------------------------------------------

_OPS = {And: "and", Or: "or", Implies: "implies", Equiv: "equiv"}


def _norm_expr(e: Expr) -> tuple:
    match e:
        case Ref(name=name):
            return ("ref", name)
        case Not(operand=o):
            return ("not", _norm_expr(o))
        case And() | Or() | Implies() | Equiv():
            return (_OPS[type(e)], _norm_expr(e.left), _norm_expr(e.right))
        case Compare(op=op, left=a, right=b):
            return ("cmp", op, _norm_expr(a), _norm_expr(b))
        case Arith(op=op, left=a, right=b):
            return ("arith", op, _norm_expr(a), _norm_expr(b))
        case Num(value=v):
            return ("num", (type(v).__name__, v))
        case Text(value=v):
            return ("str", v)
        case Aggregate(function=fn, args=args):
            return ("agg", fn, tuple(a.name for a in args))
    raise AssertionError(e)


def _norm_value(v: Any) -> Any:
    match v:
        case None:
            return None
        case ConstraintList(exprs=exprs, single=True):
            return ("constraint", _norm_expr(exprs[0]))
        case ConstraintList(exprs=exprs):
            return ("constraints", tuple(map(_norm_expr, exprs)))
        case dict():
            return ("map", tuple((k, _norm_value(x)) for k, x in v.items()))
        case list():
            return ("list", tuple(map(_norm_value, v)))
    return (type(v).__name__, v)


def norm_model(fm: FeatureModel) -> dict[str, Any]:
    """The normal form of an rra-agent `FeatureModel`."""
    features: list[tuple] = []
    groups: list[tuple] = []
    attributes: dict[str, tuple] = {}

    def feature(f: Feature, parent: str | None) -> None:
        card = (f.cardinality.lower, f.cardinality.upper) if f.cardinality else None
        features.append((f.name, f.type, parent, card))
        attributes[f.name] = tuple(
            (a.name, _norm_value(a.constraints or a.value)) for a in f.attributes
        )
        for g in f.groups:
            bounds = (g.lower or 0, g.upper) if g.kind == "cardinality" else None
            groups.append((f.name, g.kind, bounds, tuple(c.name for c in g.children)))
            for c in g.children:
                feature(c, f.name)

    feature(fm.root, None)
    return {
        "namespace": fm.namespace,
        "includes": fm.includes,
        "imports": tuple((i.namespace, i.alias) for i in fm.imports),
        "features": tuple(features),
        "groups": tuple(groups),
        "attributes": attributes,
        "constraints": tuple(_norm_expr(c.expr) for c in fm.constraints),
    }


def assert_parsers_agree(text: str) -> FeatureModel:
    """Both parsers read ``text`` alike, and rra-agent reads its own export back."""
    ours = parse_uvl(text)
    assert norm_model(ours) == norm_reference(parse_reference(text))
    exported = to_uvl(ours)
    again = parse_uvl(exported)
    assert same_model(again, ours), exported
    assert norm_reference(parse_reference(exported)) == norm_model(ours), exported
    return ours


# ---- generated models over the whole language ---------------------------------------------------

RESERVED = KEYWORDS | {"abstract", "alias", "binding", "default", "kind", "as"}
_plain = st.builds(
    str.__add__,
    st.sampled_from(string.ascii_letters),
    st.text(string.ascii_letters + string.digits + "_", max_size=4),
).filter(lambda s: s not in RESERVED)
_quoted = st.text(string.ascii_letters + string.digits + " -äß", min_size=1, max_size=6).filter(
    lambda s: s.strip() == s and s not in RESERVED
)
_part = st.one_of(_plain, _plain, _quoted)
_name = st.one_of(_part, _part, st.lists(_part, min_size=2, max_size=3).map(".".join))
_key = _plain  # attribute keys are single names in the reference grammar
_float = (
    st.floats(-1e4, 1e4, allow_nan=False)
    .map(lambda x: round(x, 3))
    .filter(lambda x: "e" not in repr(x))
)
_text = st.text(string.ascii_letters + string.digits + " _-.äß!", min_size=1, max_size=8)
_scalar = st.one_of(st.booleans(), st.integers(-(10**6), 10**6), _float, _text)
LEVELS = [
    "Boolean",
    "Arithmetic",
    "Type",
    "Boolean.group-cardinality",
    "Boolean.feature-cardinality",
    "Arithmetic.aggregate-function",
    "Type.string-constraints",
    "Arithmetic.*",
    "Type.*",
]


def _vector(values: list[Any]) -> list[Any]:
    if len(values) == 1 and isinstance(values[0], int) and not isinstance(values[0], bool):
        return [*values, "x"]  # the reference lexes [1] as a cardinality
    return values


@st.composite
def _terms(draw: st.DrawFn, refs: list[str]) -> Expr:
    ref = st.sampled_from(refs).map(lambda n: Ref(name=n))
    leaf = st.one_of(
        ref,
        st.integers(-999, 999).map(lambda v: Num(value=v)),
        _float.map(lambda v: Num(value=v)),
        _text.map(lambda v: Text(value=v)),
        st.tuples(st.sampled_from(["sum", "avg"]), st.lists(ref, min_size=1, max_size=2)).map(
            lambda t: Aggregate(function=t[0], args=tuple(t[1]))
        ),
        st.tuples(st.sampled_from(["len", "floor", "ceil"]), ref).map(
            lambda t: Aggregate(function=t[0], args=(t[1],))
        ),
    )
    return draw(
        st.recursive(
            leaf,
            lambda inner: st.builds(
                lambda op, a, b: Arith(op=op, left=a, right=b),
                st.sampled_from(["+", "-", "*", "/"]),
                inner,
                inner,
            ),
            max_leaves=2,
        )
    )


@st.composite
def _conditions(draw: st.DrawFn, features: list[str], terms_refs: list[str]) -> Expr:
    compare = st.builds(
        lambda op, a, b: Compare(op=op, left=a, right=b),
        st.sampled_from(["==", "!=", "<", "<=", ">", ">="]),
        _terms(terms_refs),
        _terms(terms_refs),
    )
    leaf = st.one_of(st.sampled_from(features).map(lambda n: Ref(name=n)), compare)

    def extend(inner: st.SearchStrategy[Expr]) -> st.SearchStrategy[Expr]:
        binary = st.builds(
            lambda cls, a, b: cls(left=a, right=b),
            st.sampled_from([And, Or, Implies, Equiv]),
            inner,
            inner,
        )
        return st.one_of(inner.map(lambda e: Not(operand=e)), binary)

    return draw(st.recursive(leaf, extend, max_leaves=3))


@st.composite
def _values(draw: st.DrawFn, conditions: st.SearchStrategy[Expr], depth: int = 0) -> Any:
    choice = draw(st.integers(0, 9 if depth == 0 else 6))
    if choice <= 4:
        return draw(_scalar)
    if choice == 5:
        return None
    if choice == 6:
        return _vector(draw(st.lists(_scalar, max_size=3)))
    if choice == 7 and depth < 1:
        keys = draw(st.lists(_key, max_size=2, unique=True))
        out: dict[str, Any] = {k: draw(_values(conditions, depth + 1)) for k in keys}
        if draw(st.booleans()):
            out["constraint"] = ConstraintList(exprs=(draw(conditions),), single=True)
        return out
    return draw(_scalar)


@st.composite
def models(draw: st.DrawFn) -> FeatureModel:
    """A feature model using any construct of UVL, valid for rra-agent's checks."""
    names = draw(st.lists(_name, min_size=1, max_size=5, unique=True))
    imports = tuple(
        Import(namespace=ns, alias=alias)
        for ns, alias in draw(
            st.lists(st.tuples(_name, st.none() | _plain), max_size=2, unique_by=lambda t: t[1])
        )
    )
    prefixes = [i.prefix for i in imports]
    condition_refs = names + [f"{p}.Ext" for p in prefixes]
    attr_keys = draw(st.lists(_key, min_size=1, max_size=3, unique=True))
    term_refs = names + [f"{n}.{k}" for n in names[:3] for k in attr_keys]
    conditions = _conditions(condition_refs, term_refs)

    parents = [None] + [draw(st.integers(0, i - 1)) for i in range(1, len(names))]
    kids: dict[int, list[int]] = {i: [] for i in range(len(names))}
    for i, p in enumerate(parents):
        if p is not None:
            kids[p].append(i)

    def group(members: tuple[Feature, ...]) -> Group:
        kind = draw(st.sampled_from(["mandatory", "optional", "alternative", "or", "cardinality"]))
        if kind != "cardinality":
            return Group(kind=kind, children=members)
        lower = draw(st.integers(0, 3))
        upper = draw(st.none() | st.integers(lower, lower + 3))
        return Group(kind="cardinality", children=members, lower=lower, upper=upper)

    def build(i: int) -> Feature:
        children = tuple(build(k) for k in kids[i])
        groups: list[Group] = []
        while children:
            n = draw(st.integers(1, len(children)))
            groups.append(group(children[:n]))
            children = children[n:]
        attrs = [
            Attribute(name=k, value=draw(_values(conditions)))
            for k in draw(st.lists(st.sampled_from(attr_keys), max_size=1, unique=True))
        ]
        if draw(st.integers(0, 4)) == 0:
            attrs.append(
                Attribute(
                    name="constraint",
                    constraints=ConstraintList(exprs=(draw(conditions),), single=True),
                )
            )
        if draw(st.integers(0, 6)) == 0:
            exprs = tuple(draw(st.lists(conditions, max_size=2)))
            attrs.append(Attribute(name="constraints", constraints=ConstraintList(exprs=exprs)))
        card = None
        if draw(st.integers(0, 3)) == 0:
            lower = draw(st.integers(0, 3))
            card = Cardinality(lower=lower, upper=draw(st.none() | st.integers(lower, lower + 2)))
        return Feature(
            name=names[i],
            attributes=tuple(draw(st.permutations(attrs))),
            groups=tuple(groups),
            type=draw(st.sampled_from([None, None, "Boolean", "Integer", "Real", "String"])),
            cardinality=card,
        )

    return FeatureModel(
        root=build(0),
        constraints=tuple(Constraint(expr=e) for e in draw(st.lists(conditions, max_size=2))),
        namespace=draw(st.none() | _name),
        includes=tuple(draw(st.lists(st.sampled_from(LEVELS), max_size=3))),
        imports=imports,
        source="<uvl>",
    )


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fm=models())
def test_both_parsers_read_generated_models_alike(fm: FeatureModel) -> None:
    text = to_uvl(fm)
    ours = parse_uvl(text)
    assert same_model(ours, fm), text  # export, then parse: the same model
    assert norm_model(ours) == norm_model(fm)
    assert norm_reference(parse_reference(text)) == norm_model(fm), text


# ---- hand-written cases: every construct of the UVL language reference --------------------------

CASES = {
    "boolean-groups": """
        features
            Car
                mandatory
                    Engine
                optional
                    Radio
                alternative
                    Petrol
                    Electric
                or
                    GPS
                    Bluetooth
        """,
    "group-cardinalities": """
        features
            Pizza
                [1..3]
                    Salami
                    Ham
                    Mozzarella
                [2]
                    Thin
                    Thick
                [0..*]
                    Basil
        """,
    "namespace-and-comments": """
        namespace Pizzas
        // a comment line
        features
            /* a block
               comment */
            Pizza {abstract} // trailing comment

                optional

                    Extra
        """,
    "tabs": "features\n\tA\n\t\toptional\n\t\t\tB\n\t\t\tC\nconstraints\n\tB => C\n",
    "attributes-all-values": """
        features
            Server {cores 8, load -0.25, ratio .5, name 'web 1', on true, off false, \
tags ['a', 'b'], limits [1, 2.5, -3], spec {ram 16, disk {size 512, kind2 'ssd'}}, flag}
        """,
    "multi-line-attributes": """
        features
            A {
                x 1,
                y [1, 2,
                   3]
            }
        """,
    "typed-features": """
        features
            Product
                mandatory
                    Integer Quantity {default2 1}
                    Real Price
                    String Label
                    Boolean Gift
        """,
    "feature-cardinality": """
        features
            Robot
                optional
                    Wheel cardinality [2..6]
                    Arm cardinality [0..*]
                    Head cardinality [1]
        """,
    "quoted-and-dotted-names": """
        features
            "My Root"
                optional
                    "with space"
                    plain.dotted
                    "quoted part".tail
        constraints
            "with space" => plain.dotted
            "quoted part".tail | !"with space"
        """,
    "boolean-constraints-precedence": """
        features
            R
                optional
                    A
                    B
                    C
                    D
        constraints
            A & B | C => D <=> A
            !(A | B) & (C => D)
            A => B => C
            (A <=> B) <=> C
            !!A
        """,
    "comparisons-and-arithmetic": """
        features
            Shop
                optional
                    Integer Items {cost 3}
                    Real Budget
                    String Code
        constraints
            Items > 0
            Items * Shop.cost <= Budget
            Budget - 10 / 2 != (Items + 1) * 2
            Items >= -5 & Budget < 1.5
            Code == 'ABC' | Items == 0
            !Items < 3
        """,
    "aggregate-functions": """
        include
            Arithmetic.aggregate-function
            Type.string-constraints
        features
            Shop {price 1}
                optional
                    Item {price 2}
                    String Name
                    Real Weight
        constraints
            sum(price) < 10
            sum(Shop, price) > avg(Shop, price)
            avg(price) == 1.5
            len(Name) <= 8
            floor(Weight) + ceil(Weight) > 2
        """,
    "constraint-attributes": """
        features
            Root
                optional
                    A {constraint A => Root}
                    B {constraints [B => A, !A | B], note 'x'}
                    C {meta {constraint C => A}}
        """,
    "include-levels": """
        include
            Boolean
            Boolean.group-cardinality
            Boolean.feature-cardinality
            Arithmetic
            Arithmetic.*
            Type.string-constraints
            Type.*
        features
            A
        """,
    "imports": """
        namespace Main
        include
            Boolean.*
        imports
            sub.Engine as e
            Gearbox
        features
            Car
                mandatory
                    e.Engine
                    Gearbox.Root
        constraints
            e.Engine.Turbo => Gearbox.Root.Manual
        """,
    "empty-attributes": """
        features
            A {}
                optional
                    B {empty {}, list []}
        """,
}


@pytest.mark.parametrize("text", list(CASES.values()), ids=list(CASES))
def test_both_parsers_read_every_construct_alike(text: str) -> None:
    assert_parsers_agree(dedent(text).lstrip("\n"))


def test_the_reference_refuses_what_the_generator_avoids() -> None:
    """The two quirks the generator steers clear of are the reference's, not rra-agent's."""
    with pytest.raises(SyntaxError):
        parse_reference("features\n    A {x [1]}\n")
    with pytest.raises(SyntaxError):
        parse_reference("features\n    Integer a\nconstraints\n    a-1 > 0\n")
    assert parse_uvl("features\n    A {x [1]}\n").root.attributes[0].value == [1]
    assert isinstance(parse_uvl("features\n    Integer a\nconstraints\n    a-1 > 0\n")
                      .constraints[0].expr, Compare)  # fmt: skip
