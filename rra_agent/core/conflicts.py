"""Conflicts between adaptation rules (the paper's open problem, Sec. III-D), found statically.

Two actions *oppose* when they claim the same thing differently (`action_claims`): one
activates a feature (and so its ancestors) that another deactivates; two activate different
alternatives of one group; two set the same Continuous Variability attribute. `check_conflicts`
reports every pair of opposing actions that may fire in the same tick, unless they are
ordered on purpose: rules of one rule set (priorities decide) and branches of one rule
(disjoint by construction). Actions of the same branch are compared too.

Whether two actions can fire together is decided on their guards (the branch's condition and
the negation of the earlier conditions of its if/else chain), put in disjunctive normal form:
numeric comparisons of one measurement against constants are intersected as intervals (with
integer rounding for ``int`` measurements), string and boolean equalities as value sets, and
a condition and its negation are disjoint. A pair whose combined guard is provably empty is
not reported; a satisfiable one made only of understood comparisons is ``certain``; anything
else (arithmetic over several measurements, a guard too large to expand) is reported as
*may conflict*. Measurements are treated as independent variables; feature availability under
a particular deployment selection is not considered (see docs/rules.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from itertools import product
from typing import Literal

import msgspec

from rra_agent.models.adaptation import (
    Action,
    Activate,
    AdaptationModel,
    Arith,
    AttrValue,
    Bool,
    Bound,
    Call,
    Compare,
    Const,
    Deactivate,
    Expr,
    Logic,
    Measure,
    Neg,
    Not,
    Num,
    Rule,
    SelectVariant,
    SetAttribute,
    Str,
    action_text,
    children,
)
from rra_agent.models.features import FeatureModel, Span

ClaimKey = tuple[str, str]
Claim = tuple[ClaimKey, str]
ConflictKind = Literal["feature", "alternative", "attribute"]

#: Expansion limits: guards with more DNF clauses become "may conflict".
MAX_CLAUSES = 64
MAX_PAIRS = 4096

_KIND: dict[str, ConflictKind] = {
    "feature": "feature",
    "group": "alternative",
    "attribute": "attribute",
}


class ConflictSide(msgspec.Struct, frozen=True, kw_only=True):
    """One of the two actions of a conflict, with where it is written."""

    rule: str
    action: str
    span: Span | None = None
    ruleset: str | None = None


class Conflict(msgspec.Struct, frozen=True, kw_only=True):
    """Two rules that can fire in one tick with opposite effects on ``target``."""

    kind: ConflictKind
    target: str
    first: ConflictSide
    second: ConflictSide
    #: True: some measurement values make both fire. False: "may conflict" (not disproved).
    certain: bool

    @property
    def message(self) -> str:
        what = "conflict" if self.certain else "may conflict"
        return (
            f"{what}: rules {self.first.rule} and {self.second.rule} can fire in the same tick "
            f"with opposite effects on {self.target}: {self.first.action} vs "
            f"{self.second.action}"
        )

    def render(self) -> str:
        """``file:line:col: message`` at the first rule, then the second rule's location."""
        head = f"{self.first.span.location()}: " if self.first.span else ""
        tail = (
            f"\n    {self.second.span.location()}: {self.second.action}" if self.second.span else ""
        )
        return head + self.message + tail


# ---- claims: what an action asserts about the selection -----------------------------------
def feature_claims(fm: FeatureModel, name: str, on: bool) -> list[Claim]:
    """Claims of (de)activating a feature: activation also claims its run-time ancestors on
    and, for each of them in an alternative group, that group's choice."""
    if not on:
        return [(("feature", name), "off")]
    out: list[Claim] = []
    a: str | None = name
    while a is not None and fm.binding.get(a) == "runtime":
        out.append((("feature", a), "on"))
        group = _exclusive_group(fm, a)
        if group is not None:
            out.append((("group", group), a))
        a = fm.parent.get(a)
    return out


def _exclusive_group(fm: FeatureModel, name: str) -> str | None:
    """``Parent#i`` for a feature in an alternative (or at-most-one) group, else None."""
    parent = fm.parent.get(name)
    if parent is None:
        return None
    for i, g in enumerate(fm.features[parent].groups):
        if any(c.name == name for c in g.children):
            exclusive = g.kind == "alternative" or (g.kind == "cardinality" and g.upper == 1)
            return f"{parent}#{i}" if exclusive else None
    return None  # pragma: no cover - every non-root feature is in a group


def ranked_variants(fm: FeatureModel, action: SelectVariant) -> list[str]:
    """The variants of the action's variation point, best first: by the CIM attribute's rank
    (its number, or its position in the attribute's ``scale``), ascending for MIN and
    descending for MAX; ties keep feature-model order. Variants without a rank are left out."""
    ranked: list[tuple[float, int, str]] = []
    for i, child in enumerate(fm.features[action.point.name].children):
        attr = child.attribute(action.attribute)
        rank = attr.rank if attr is not None else None
        if rank is not None:
            ranked.append((rank if action.extremum == "min" else -rank, i, child.name))
    return [name for _, _, name in sorted(ranked)]


def action_claims(fm: FeatureModel, action: Action, token: str = "") -> list[list[Claim]]:
    """The claims of each effect of an action (one per feature it names); a select counts
    as activating its best variant; a set claims its attribute with the unique ``token``."""
    match action:
        case Activate(features=fs):
            return [feature_claims(fm, f.name, True) for f in fs]
        case Deactivate(features=fs):
            return [feature_claims(fm, f.name, False) for f in fs]
        case SelectVariant():
            best = ranked_variants(fm, action)[:1]
            return [feature_claims(fm, b, True) for b in best]
        case SetAttribute(target=t):
            return [[(("attribute", f"{t.feature}.{t.name}"), token or action_text(action))]]
    raise TypeError(action)  # pragma: no cover


def opposing(a: Iterable[Claim], b: Iterable[Claim]) -> ClaimKey | None:
    """The first key two claim lists assert differently, or None if they agree."""
    mine = dict(a)
    for key, value in b:
        if key in mine and mine[key] != value:
            return key
    return None


_GROUP_TEXT = "the alternatives of "


def target_text(key: ClaimKey) -> str:
    kind, name = key
    if kind == "group":
        return f"{_GROUP_TEXT}{name.rsplit('#', 1)[0]}"
    return name


def target_name(text: str) -> str:
    """The name a conflict's target is known by: the feature (``Gnss``), the parent of the
    alternatives (``Localization`` for "the alternatives of Localization"), or the CV
    attribute ``Feature.Attr``."""
    return text.removeprefix(_GROUP_TEXT)


def conflict_targets(model: AdaptationModel, fm: FeatureModel) -> frozenset[str]:
    """The `target_name`s the actions of ``model`` claim: all a conflict can be over."""
    return frozenset(
        target_name(target_text(key))
        for rule in model.rules()
        for branch in rule.branches
        for action in branch.actions
        for claims in action_claims(fm, action)
        for key, _ in claims
    )


# ---- static analysis -----------------------------------------------------------------------
@dataclass
class _Effect:
    unit: int
    rule: Rule
    ruleset: str | None
    branch: int
    action: int
    text: str
    span: Span | None
    guard: list[tuple[Expr, bool]]
    claims: list[Claim]
    index: int = 0
    dnf: list[list[_Lit]] | None = field(default=None, repr=False)

    def side(self) -> ConflictSide:
        return ConflictSide(
            rule=self.rule.name, action=self.text, span=self.span, ruleset=self.ruleset
        )


def check_conflicts(model: AdaptationModel, fm: FeatureModel) -> list[Conflict]:
    """Every pair of rules that can fire in one tick with opposite effects (see module doc),
    in file order of the first rule; ``certain`` False marks "may conflict"."""
    effects = list(_effects(model, fm))
    by_key: dict[ClaimKey, list[_Effect]] = {}
    for e in effects:
        for key, _ in e.claims:
            bucket = by_key.setdefault(key, [])
            if not bucket or bucket[-1] is not e:
                bucket.append(e)
    seen: set[tuple[int, int]] = set()
    out: list[tuple[tuple[int, int], Conflict]] = []
    for key in by_key:
        bucket = by_key[key]
        for i, e1 in enumerate(bucket):
            for e2 in bucket[i + 1 :]:
                pair = (e1.index, e2.index)
                if pair in seen or not _comparable(e1, e2):
                    continue
                clash = opposing(e1.claims, e2.claims)
                if clash is None:
                    continue
                seen.add(pair)
                status = _joint(e1, e2, fm)
                if status != "unsat":
                    conflict = Conflict(
                        kind=_KIND[clash[0]],
                        target=target_text(clash),
                        first=e1.side(),
                        second=e2.side(),
                        certain=status == "sat",
                    )
                    out.append((pair, conflict))
    return [c for _, c in sorted(out, key=lambda pc: pc[0])]


def _effects(model: AdaptationModel, fm: FeatureModel) -> Iterator[_Effect]:
    count = 0
    for unit, (ruleset, rules) in enumerate(model.units()):
        for rule in rules:
            guard: list[tuple[Expr, bool]] = []
            for b, branch in enumerate(rule.branches):
                here = [*guard, (branch.condition, True)] if branch.condition else list(guard)
                for a, action in enumerate(branch.actions):
                    token = f"{rule.name}/{b}/{a}"
                    for claims in action_claims(fm, action, token):
                        yield _Effect(
                            unit, rule, ruleset.name if ruleset else None, b, a,
                            action_text(action), action.span, here, claims, count,
                        )  # fmt: skip
                        count += 1
                if branch.condition is not None:
                    guard.append((branch.condition, False))


def rule_effects(model: AdaptationModel, fm: FeatureModel) -> list[_Effect]:
    """Every effect of every action of ``model`` (one per feature an action names), each
    with its rule, rule set unit, branch, guard and claims: what `check_conflicts` compares
    (the reflexes' analysis asks the same questions about one rule, `rra_agent.core.reflex`)."""
    return list(_effects(model, fm))


def may_fire_together(e1: _Effect, e2: _Effect, fm: FeatureModel) -> bool:
    """Whether two effects' guards can hold in one tick (not proved disjoint)."""
    return _joint(e1, e2, fm) != "unsat"


def constant_value(expr: Expr, fm: FeatureModel) -> object:
    """The value of a constant expression (None: undefined), or `NOT_CONSTANT`."""
    return _const(expr, fm)


def compare_constants(op: str, a: object, b: object) -> bool | None:
    """``a op b`` as the engine decides it (None: undefined)."""
    return _evaluate_compare(op, a, b)


def _comparable(e1: _Effect, e2: _Effect) -> bool:
    """Different units, or the same branch of the same rule (ordered on purpose otherwise)."""
    if e1.unit != e2.unit:
        return True
    return e1.rule is e2.rule and e1.branch == e2.branch


# ---- guards as DNF over literals ------------------------------------------------------------
@dataclass(frozen=True)
class _Lit:
    """``var op value`` (kind num/str/bool) or an opaque condition with a polarity."""

    kind: Literal["num", "str", "bool", "opaque"]
    var: object
    op: str
    value: object


_NEGATE = {"==": "!=", "!=": "==", "<": ">=", ">=": "<", "<=": ">", ">": "<="}
_FLIP = {"==": "==", "!=": "!=", "<": ">", ">": "<", "<=": ">=", ">=": "<="}
_TRUE: list[list[_Lit]] = [[]]
_FALSE: list[list[_Lit]] = []


def _guard_dnf(guard: Sequence[tuple[Expr, bool]], fm: FeatureModel) -> list[list[_Lit]]:
    result = _TRUE
    for expr, positive in guard:
        result = _and(result, _dnf(expr, positive, fm), expr, positive)
    return result


def _and(a: list[list[_Lit]], b: list[list[_Lit]], expr: Expr, positive: bool) -> list[list[_Lit]]:
    if len(a) * len(b) > MAX_CLAUSES:
        return [[*clause, _opaque(expr, positive)] for clause in a]
    return [[*x, *y] for x in a for y in b]


def _dnf(expr: Expr, positive: bool, fm: FeatureModel) -> list[list[_Lit]]:
    match expr:
        case Not(operand=o):
            return _dnf(o, not positive, fm)
        case Logic(op=op, left=left, right=right):
            a, b = _dnf(left, positive, fm), _dnf(right, positive, fm)
            if (op == "and") == positive:
                return _and(a, b, expr, positive)
            return _or(a, b, expr, positive)
        case Compare():
            return _compare(expr, positive, fm)
        case Bool(value=v):
            return _TRUE if v == positive else _FALSE
        case Measure(type="bool" | None):
            return [[_Lit("bool", _var(expr), "==", positive)]]
    value = _const(expr, fm)
    if isinstance(value, bool):
        return _TRUE if value == positive else _FALSE
    return [[_opaque(expr, positive)]]


def _or(a: list[list[_Lit]], b: list[list[_Lit]], expr: Expr, positive: bool) -> list[list[_Lit]]:
    if len(a) + len(b) > MAX_CLAUSES:
        return [[_opaque(expr, positive)]]
    return a + b


def _compare(cmp: Compare, positive: bool, fm: FeatureModel) -> list[list[_Lit]]:
    left, right = _const(cmp.left, fm), _const(cmp.right, fm)
    if left is not _NOT_CONST and right is not _NOT_CONST:
        value = _evaluate_compare(cmp.op, left, right)
        # An undefined comparison fires neither its branch nor the ones after it.
        return _FALSE if value is None or value != positive else _TRUE
    op = cmp.op if positive else _NEGATE[cmp.op]
    var, const = cmp.left, right
    if left is not _NOT_CONST:
        var, const, op = cmp.right, left, _FLIP[op]
    if const is _NOT_CONST or const is None or _var(var) is None:
        return [[_opaque(cmp, positive)]]
    if isinstance(const, bool):
        if op not in ("==", "!="):  # pragma: no cover - rejected by the type checker
            return [[_opaque(cmp, positive)]]
        return [[_Lit("bool", _var(var), "==", const == (op == "=="))]]
    kind: Literal["str", "num"] = "str" if isinstance(const, str) else "num"
    return [[_Lit(kind, _var(var), op, const)]]


def _var(expr: Expr) -> tuple[str, str | None] | None:
    """A variable: (name, measurement type) for a measurement or the value of a CV."""
    match expr:
        case Measure(name=n, type=t):
            return (f"measurement {n}", t)
        case AttrValue(kind="cv", feature=f, attribute=a):
            return (f"attribute {f}.{a}", "float")
    return None


def _opaque(expr: Expr, positive: bool) -> _Lit:
    return _Lit("opaque", _shape(expr), "==", positive)


def _shape(node: object) -> object:
    """A hashable form of an expression that ignores where it is written."""
    if isinstance(node, tuple):
        return tuple(_shape(x) for x in node)
    if not isinstance(node, msgspec.Struct):
        return node
    fields = (_shape(getattr(node, f)) for f in node.__struct_fields__ if f != "span")
    return (type(node).__name__, *fields)


# ---- constant folding (conditions over CIM/NFR values, bounds and literals) -----------------
_NOT_CONST = object()
#: What `constant_value` returns for an expression that is not constant.
NOT_CONSTANT = _NOT_CONST


def _const(expr: Expr, fm: FeatureModel) -> object:
    """The value of a constant expression (None if undefined), or `_NOT_CONST`."""
    match expr:
        case Num(value=v) | Str(value=v) | Bool(value=v):
            return v
        case Const(name=n):
            return math.e if n == "e" else math.pi
        case AttrValue(kind="cim" | "nfr", feature=f, attribute=a):
            attr = fm.features[f].attribute(a)
            return attr.rra_value if attr is not None else None
        case Bound(feature=f, attribute=a, bound=b):
            attr = fm.features[f].attribute(a)
            return None if attr is None else attr.lower if b == "min" else attr.upper
        case Neg() | Arith() | Call():
            args = [_const(c, fm) for c in children(expr)]
            if any(a is _NOT_CONST for a in args):
                return _NOT_CONST
            return _arith(expr, args)
    return _NOT_CONST


def _arith(expr: Expr, args: list) -> float | None:
    if any(not isinstance(a, int | float) or isinstance(a, bool) for a in args):
        return None
    try:
        match expr:
            case Neg():
                value = -args[0]
            case Arith(op=op):
                value = _ARITH[op](args[0], args[1])
            case Call(func=f):
                value = _CALLS[f](*args)
            case _:  # pragma: no cover
                return None
    except (ArithmeticError, ValueError, TypeError):
        return None
    return float(value) if math.isfinite(value) else None


_ARITH = {
    "+": lambda a, b: a + b,
    "-": lambda a, b: a - b,
    "*": lambda a, b: a * b,
    "/": lambda a, b: a / b,
    "^": math.pow,
}
_CALLS: dict[str, Callable[..., float]] = {
    "exp": math.exp,
    "log": math.log,
    "sqrt": math.sqrt,
    "abs": abs,
    "min": min,
    "max": max,
}


def _evaluate_compare(op: str, a: object, b: object) -> bool | None:
    if a is None or b is None:
        return None
    try:
        return {
            "==": a == b,
            "!=": a != b,
            "<": a < b,  # type: ignore[operator]
            "<=": a <= b,  # type: ignore[operator]
            ">": a > b,  # type: ignore[operator]
            ">=": a >= b,  # type: ignore[operator]
        }[op]
    except TypeError:
        return None


# ---- satisfiability of a conjunction --------------------------------------------------------
Status = Literal["sat", "unknown", "unsat"]


def _joint(e1: _Effect, e2: _Effect, fm: FeatureModel) -> Status:
    """Whether both guards can hold in one tick: sat, unsat, or unknown."""
    d1 = e1.dnf if e1.dnf is not None else _guard_dnf(e1.guard, fm)
    d2 = e2.dnf if e2.dnf is not None else _guard_dnf(e2.guard, fm)
    e1.dnf, e2.dnf = d1, d2
    if len(d1) * len(d2) > MAX_PAIRS:
        return "unknown"
    best: Status = "unsat"
    for c1, c2 in product(d1, d2):
        status = _clause([*c1, *c2])
        if status == "sat":
            return "sat"
        if status == "unknown":
            best = "unknown"
    return best


def _clause(lits: Sequence[_Lit]) -> Status:
    opaque: set[tuple[object, object]] = set()
    by_var: dict[object, list[_Lit]] = {}
    for lit in lits:
        if lit.kind == "opaque":
            if (lit.var, not lit.value) in opaque:
                return "unsat"
            opaque.add((lit.var, lit.value))
        else:
            by_var.setdefault(lit.var, []).append(lit)
    unknown = bool(opaque)
    for var, group in by_var.items():
        status = _variable(var, group)  # type: ignore[arg-type]
        if status == "unsat":
            return "unsat"
        unknown = unknown or status == "unknown"
    return "unknown" if unknown else "sat"


def _variable(var: tuple[str, str | None], lits: list[_Lit]) -> Status:
    kinds = {lit.kind for lit in lits}
    if len(kinds) > 1:
        return "unknown"  # mixed types: only possible for untyped measurements
    kind = kinds.pop()
    if kind == "num":
        return _numeric(lits, integer=var[1] == "int")
    values = [(lit.op, lit.value) for lit in lits]
    equal = {v for op, v in values if op == "=="}
    differ = {v for op, v in values if op == "!="}
    if kind == "bool":
        return "unsat" if len(equal) > 1 else "sat"
    if len(equal) > 1 or equal & differ:
        return "unsat"
    return "sat"


def _numeric(lits: list[_Lit], *, integer: bool) -> Status:
    lo, lo_open, hi, hi_open = -math.inf, False, math.inf, False
    equal: set[float] = set()
    differ: set[float] = set()
    for lit in lits:
        v = float(lit.value)  # type: ignore[arg-type]
        if lit.op == "==":
            equal.add(v)
        elif lit.op == "!=":
            differ.add(v)
        elif lit.op in (">", ">=") and (v > lo or (v == lo and lit.op == ">")):
            lo, lo_open = v, lit.op == ">"
        elif lit.op in ("<", "<=") and (v < hi or (v == hi and lit.op == "<")):
            hi, hi_open = v, lit.op == "<"
    if integer:
        # An int is finite: an unbounded side stays unbounded (no rounding of infinity), a
        # bound at infinity admits no int at all.
        if lo == math.inf or hi == -math.inf:
            return "unsat"
        if math.isfinite(lo):
            lo = math.floor(lo) + 1 if lo_open and lo == math.floor(lo) else math.ceil(lo)
            lo_open = False
        if math.isfinite(hi):
            hi = math.ceil(hi) - 1 if hi_open and hi == math.ceil(hi) else math.floor(hi)
            hi_open = False
        if any(not v.is_integer() for v in equal):
            return "unsat"
    if len(equal) > 1:
        return "unsat"
    if equal:
        v = next(iter(equal))
        inside = (lo < v or (lo == v and not lo_open)) and (v < hi or (v == hi and not hi_open))
        return "sat" if inside and v not in differ else "unsat"
    if lo > hi or (lo == hi and (lo_open or hi_open)):
        return "unsat"
    if integer and math.isfinite(lo) and math.isfinite(hi) and hi - lo < len(differ) + 1:
        return (
            "sat" if any(float(k) not in differ for k in range(int(lo), int(hi) + 1)) else "unsat"
        )
    if lo == hi:
        return "unsat" if lo in differ else "sat"
    return "sat"
