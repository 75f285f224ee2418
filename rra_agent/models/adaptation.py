"""The Adaptation Model (paper Sec. III-D, Fig. 5): rules, rule sets, priorities, as an AST.

`rra_agent.dsl.rules` parses ``adaptation.rra`` into these Structs and resolves every name
against the feature model and the measurements model, so a loaded `AdaptationModel` holds
canonical feature names, measurement names and owner-qualified attributes. Every node keeps
the `Span` it was written at. Expressions and actions are tagged unions, dispatched with
``match``; the language itself is documented in ``docs/rules.md``.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Literal

import msgspec

from rra_agent.models.base import FrozenModel
from rra_agent.models.features import Span
from rra_agent.models.measurements import MeasurementType

CompareOp = Literal["==", "!=", "<", "<=", ">", ">="]
ArithOp = Literal["+", "-", "*", "/", "^"]
Function = Literal["exp", "log", "sqrt", "abs", "min", "max"]
Extremum = Literal["min", "max"]

#: Functions of the expression language and how many arguments each takes (min, max).
FUNCTIONS: dict[str, tuple[int, int | None]] = {
    "exp": (1, 1),
    "log": (1, 1),
    "sqrt": (1, 1),
    "abs": (1, 1),
    "min": (1, None),
    "max": (1, None),
}


class Node(FrozenModel, frozen=True, tag_field="node"):
    """Base of the AST's tagged unions (the tag field is ``node``: ``type`` is a field name)."""


# ---- expressions -------------------------------------------------------------------------
class Num(Node, frozen=True, tag="num"):
    """A number; ``quoted`` when written as a string (``"50"``), which still means 50."""

    value: float
    span: Span | None = None
    quoted: bool = False


class Str(Node, frozen=True, tag="str"):
    value: str
    span: Span | None = None


class Bool(Node, frozen=True, tag="bool"):
    """A boolean; ``quoted`` when written as a string (``"false"``) compared with a bool."""

    value: bool
    span: Span | None = None
    quoted: bool = False


class Const(Node, frozen=True, tag="const"):
    """A mathematical constant: ``e`` (so ``e^x`` is the exponential) or ``pi``."""

    name: Literal["e", "pi"]
    span: Span | None = None


class Name(Node, frozen=True, tag="name"):
    """A reference as written (``cdm.SemLoc``, ``MaxVel.min``); only before name resolution."""

    parts: tuple[str, ...]
    span: Span | None = None


class Measure(Node, frozen=True, tag="measure"):
    """A Context Dependent Measurement, with its type and staleness limit from the measurements
    model (both None when the rules were loaded without one)."""

    name: str
    type: MeasurementType | None = None
    max_age_ms: float | None = None
    span: Span | None = None


class AttrValue(Node, frozen=True, tag="attr"):
    """An attribute's value: a CIM/NFR constant, or the current value of a CV attribute."""

    feature: str
    attribute: str
    kind: Literal["cim", "nfr", "cv"]
    span: Span | None = None


class Bound(Node, frozen=True, tag="bound"):
    """A Continuous Variability bound: ``MaxVel.min`` / ``MaxVel.max``."""

    feature: str
    attribute: str
    bound: Extremum
    span: Span | None = None


class Neg(Node, frozen=True, tag="neg"):
    operand: Expr
    span: Span | None = None


class Arith(Node, frozen=True, tag="arith"):
    op: ArithOp
    left: Expr
    right: Expr
    span: Span | None = None


class Call(Node, frozen=True, tag="call"):
    func: Function
    args: tuple[Expr, ...]
    span: Span | None = None


class Compare(Node, frozen=True, tag="compare"):
    op: CompareOp
    left: Expr
    right: Expr
    span: Span | None = None


class Logic(Node, frozen=True, tag="logic"):
    op: Literal["and", "or"]
    left: Expr
    right: Expr
    span: Span | None = None


class Not(Node, frozen=True, tag="not"):
    operand: Expr
    span: Span | None = None


Expr = (
    Num
    | Str
    | Bool
    | Const
    | Name
    | Measure
    | AttrValue
    | Bound
    | Neg
    | Arith
    | Call
    | Compare
    | Logic
    | Not
)


# ---- actions -----------------------------------------------------------------------------
class FeatureRef(FrozenModel, frozen=True):
    """A feature named in an action: canonical name once resolved (written name before)."""

    name: str
    span: Span | None = None


class AttrRef(FrozenModel, frozen=True):
    """An attribute named in an action; ``feature`` is its owner (None only before resolution)."""

    name: str
    feature: str | None = None
    span: Span | None = None


class Activate(Node, frozen=True, tag="activate"):
    features: tuple[FeatureRef, ...]
    span: Span | None = None


class Deactivate(Node, frozen=True, tag="deactivate"):
    features: tuple[FeatureRef, ...]
    span: Span | None = None


class SelectVariant(Node, frozen=True, tag="select"):
    """``select_feature_from_variants_of(point) where_attribute MIN|MAX(attribute)``."""

    point: FeatureRef
    attribute: str
    extremum: Extremum
    span: Span | None = None


class SetAttribute(Node, frozen=True, tag="set"):
    """``set_attribute(target) with_value(value)``; target is a CV attribute."""

    target: AttrRef
    value: Expr
    span: Span | None = None


Action = Activate | Deactivate | SelectVariant | SetAttribute


# ---- rules -------------------------------------------------------------------------------
class Branch(FrozenModel, frozen=True):
    """One arm of a rule: ``if (condition)``/``else if (condition)``, or ``else`` (None)."""

    condition: Expr | None
    actions: tuple[Action, ...]
    span: Span | None = None


class Rule(Node, frozen=True, tag="rule"):
    """An atomic rule. ``period_ms`` None: every tick; 0: on new measurements it reads."""

    name: str
    branches: tuple[Branch, ...]
    priority: int | None = None
    period_ms: float | None = None
    #: False (``reflex off``): the decision is never delegated to a node as a reflex.
    reflex: bool = True
    span: Span | None = None


class RuleSet(Node, frozen=True, tag="ruleSet"):
    """Rules over the same features/attribute; ``rules`` as written (see `by_evaluation`)."""

    name: str
    rules: tuple[Rule, ...]
    span: Span | None = None

    def by_evaluation(self) -> tuple[Rule, ...]:
        """Evaluation order: lowest priority (highest number) first, so priority 1 wins."""
        return tuple(sorted(self.rules, key=lambda r: -(r.priority or 0)))


class Import(FrozenModel, frozen=True):
    """``import caseStudy.contextDepMeasModel as cdm``: ``cdm.X`` names measurement X."""

    module: str
    alias: str
    span: Span | None = None


class AdaptationModel(FrozenModel, frozen=True):
    imports: tuple[Import, ...] = ()
    items: tuple[Rule | RuleSet, ...] = ()
    source: str = "<rules>"

    def units(self) -> Iterator[tuple[RuleSet | None, tuple[Rule, ...]]]:
        """Evaluation units in file order: a lone rule, or a rule set in priority order."""
        for item in self.items:
            if isinstance(item, RuleSet):
                yield item, item.by_evaluation()
            else:
                yield None, (item,)

    def rules(self) -> Iterator[Rule]:
        """Every atomic rule, in file order."""
        for item in self.items:
            if isinstance(item, RuleSet):
                yield from item.rules
            else:
                yield item


# ---- helpers -----------------------------------------------------------------------------
def children(expr: Expr) -> tuple[Expr, ...]:
    """The direct sub-expressions of an expression."""
    match expr:
        case Neg(operand=o) | Not(operand=o):
            return (o,)
        case Arith(left=a, right=b) | Compare(left=a, right=b) | Logic(left=a, right=b):
            return (a, b)
        case Call(args=args):
            return args
        case _:
            return ()


def walk(expr: Expr) -> Iterator[Expr]:
    """Every node of an expression, pre-order, without recursion (deep trees are fine)."""
    stack = [expr]
    while stack:
        node = stack.pop()
        yield node
        stack.extend(reversed(children(node)))


def depth(expr: Expr) -> int:
    """Nesting depth of an expression (a leaf is 1), computed without recursion."""
    best = 0
    stack = [(expr, 1)]
    while stack:
        node, d = stack.pop()
        best = max(best, d)
        stack.extend((c, d + 1) for c in children(node))
    return best


def measures_read(expr: Expr | None) -> tuple[str, ...]:
    """Names of the measurements an expression reads, in order of first appearance."""
    if expr is None:
        return ()
    return tuple(dict.fromkeys(n.name for n in walk(expr) if isinstance(n, Measure)))


def action_text(action: Action) -> str:
    """An action the way it is written in the DSL (without the value expression)."""
    match action:
        case Activate(features=fs):
            return f"activate_feature({' AND '.join(f.name for f in fs)})"
        case Deactivate(features=fs):
            return f"deactivate_feature({' AND '.join(f.name for f in fs)})"
        case SelectVariant(point=p, attribute=a, extremum=x):
            return f"select_feature_from_variants_of({p.name}) where_attribute {x.upper()}({a})"
        case SetAttribute(target=t):
            return f"set_attribute({t.name})"
    raise TypeError(action)  # pragma: no cover


def encode(model: AdaptationModel) -> bytes:
    """The model as JSON (e.g. for ``rra validate --json`` or caching)."""
    return msgspec.json.encode(model)
