"""The Adaptation Engine core (paper Sec. III-D): compiled rules evaluated one `tick` at a time.

`AdaptationEngine` compiles an `AdaptationModel` once into Python code objects (the evaluation
units, a lone rule or a rule set in priority order, become straight-line code: one function per
scheduled unit, one per run of every-tick units) and then, for each tick, takes the current
measurements and produces the run-time feature selection and the values of the Continuous
Variability attributes. Pure: no I/O, no clock (``now`` is a parameter).

Semantics (docs/rules.md has the full text):

- Conditions use Kleene logic. A measurement that was never received, or is older than its
  ``max_age_ms``, is undefined, and so is every comparison or arithmetic that reads it (and
  division by zero, overflow, a non-finite result). An ``if`` whose condition is undefined
  fires no branch (not even ``else``); a ``set_attribute`` whose value is undefined leaves the
  attribute as it was.
- All conditions of a tick read the same inputs: this tick's measurements and the CV values
  and selection of the previous tick. Fired actions are then applied in evaluation order: file
  order, a rule set's rules from the lowest priority (highest number) to the highest. So the
  later action wins: priority 1 inside a rule set, the rule written later between units.
- Two opposing actions of different units in one tick yield a `ConflictRecord` (winner: the
  later one). Within a rule set, priorities decide and no record is made.
- Feature actions become `apply_requests` requests, so the selection stays valid; features
  no rule touches keep their state; impossible requests are `Rejected` with the reason.
  ``select_feature_from_variants_of`` activates the best selectable variant (`ranked_variants`).
- ``set_attribute`` stores the requested value; the published value is it clamped into the
  CV bounds and then into every active NFR that ``constrains`` the CV (on a selected feature;
  ``min`` raises, ``max`` lowers, the ``max`` is applied last).
- Scheduling: a rule without ``period`` runs every tick; ``period N ms`` at the first tick
  at least N ms after its last run; ``period 0 ms`` on ticks where a measurement it reads is
  new (its stamp changed, or it is named in ``changed``). A rule set runs as a whole when any
  of its rules is due. Every rule runs on the first tick.
- Explanation (``tick(..., explain=True)``, `why`): each change of the selection and of a CV
  value names the action that made it (`apply_requests` traces which request switched which
  feature), the values it read, and the fired actions that wanted otherwise and why they did
  not prevail (`Overruled`). Computed only for ticks that change something; `why` answers
  for the current state (the last change, and what the rules want now).
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Collection, Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from types import CodeType
from typing import Any, Literal

import msgspec

from rra_agent import _compat
from rra_agent.core import overrides
from rra_agent.core.conflicts import (
    ClaimKey,
    action_claims,
    feature_claims,
    ranked_variants,
    target_text,
)
from rra_agent.core.cv import CvAttribute, clamp, cv_table, limiting
from rra_agent.core.features import (
    Request,
    apply_requests,
    check_selection,
    complete_deployment,
    default_runtime_selection,
    selectable_runtime,
)
from rra_agent.errors import SelectionError
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
    measures_read,
    walk,
)
from rra_agent.models.features import Constraint, FeatureModel, Span, refs

__all__ = [
    "AdaptationEngine",
    "ConflictRecord",
    "FiredRule",
    "Overruled",
    "Rejected",
    "TickResult",
    "Why",
]

#: (value, stamp): a measurement sample as the engine receives it; stamps in seconds.
Sample = tuple[Any, float]


class FiredRule(msgspec.Struct, frozen=True, kw_only=True):
    """An action that fired in a tick: the cause of an adaptation."""

    rule: str
    action: str
    span: Span | None = None
    ruleset: str | None = None
    #: The measurements the conditions that led here and the action's value read.
    reads: tuple[str, ...] = ()
    #: For set_attribute: the value computed (before clamping).
    value: float | None = None


class Rejected(msgspec.Struct, frozen=True, kw_only=True):
    """A fired action the engine could not honour, and why (the selection stayed valid)."""

    rule: str
    action: str
    reason: str
    span: Span | None = None
    #: The feature it asked for is unavailable (an implementation it needs cannot run).
    unavailable: str = ""
    #: It would have changed this feature, which an operator forced (``rra select``).
    forced: str = ""


class ConflictRecord(msgspec.Struct, frozen=True, kw_only=True):
    """Opposing actions of two units fired in one tick; the later one (``winner``) applied."""

    kind: str
    target: str
    winner: FiredRule
    loser: FiredRule
    #: What the winner and the loser want (``on``/``off``, an alternative, a CV value);
    #: filled in for the conflicts in force (`TickResult.active`).
    values: tuple[str, ...] = ()


#: Why a fired action did not prevail on a target (`Overruled.why`).
OverruleReason = Literal[
    "priority", "later_rule", "operator", "nfr", "bounds", "unavailable", "refused", "waiting"
]
#: What put a target in its state (`Why.reason`).
WhyReason = Literal["rule", "nfr", "operator", "unavailable", "model", "default", "resumed"]


class Overruled(msgspec.Struct, frozen=True, kw_only=True):
    """A fired action that wanted something else for a target and did not prevail.

    ``why``: ``priority`` (a rule of higher priority in its rule set), ``later_rule`` (a rule
    written later: a run-time conflict), ``operator`` (a feature an operator forced),
    ``nfr`` / ``bounds`` (the CV value it computed was clamped by an active NFR / into the
    attribute's bounds), ``unavailable`` (an implementation the feature needs cannot run),
    ``refused`` (the feature model does not allow it), ``waiting`` (it wants a change its
    rule has not applied yet: not due, see `why`)."""

    rule: str
    action: str
    span: Span | None = None
    ruleset: str | None = None
    #: What it wants: ``on``/``off``, an alternative, or the CV value it computed.
    wants: str
    why: OverruleReason
    #: The same, for people (names the rule or NFR that prevailed).
    detail: str = ""


class Why(msgspec.Struct, frozen=True, kw_only=True):
    """Why a run-time feature or a CV attribute has its value: what changed it last.

    ``reason``: ``rule`` (the actions in ``by``), ``nfr`` (an NFR began or ceased to clamp a
    CV: ``by`` names what selected or deselected its feature), ``operator`` (an operator's
    forced feature), ``unavailable`` (left, or put in place of, an unavailable feature),
    ``model`` (the feature model completed a change), ``default`` (so since the engine
    started), ``resumed`` (so when the engine resumed from the running system)."""

    #: The feature, or the CV attribute's key.
    target: str
    kind: Literal["feature", "cv"]
    #: ``on``/``off``, or the CV value.
    value: str
    #: The tick that put it there (None: before this engine's first change of it).
    since: float | None = None
    reason: WhyReason
    by: tuple[FiredRule, ...] = ()
    #: The measurements ``by`` read: name -> (value, stamp), as the tick saw them.
    reads: dict[str, tuple[Any, float]] = {}
    detail: str = ""
    #: The fired actions that wanted otherwise, and why they did not prevail.
    overruled: tuple[Overruled, ...] = ()


class TickResult(msgspec.Struct, kw_only=True):
    """What one tick produced. ``selection`` holds run-time features only."""

    now: float
    selection: frozenset[str]
    cv: dict[str, float]
    #: Whether the selection or a CV value differs from the previous tick's.
    changed: bool
    fired: list[FiredRule] = []
    rejected: list[Rejected] = []
    conflicts: list[ConflictRecord] = []
    #: The conflicts in force: two units whose latest wishes on one target differ (a unit's
    #: wish lasts until it runs again), whether or not both fired in this tick.
    active: list[ConflictRecord] = []
    #: Measurements the rules read that were missing or stale in this tick.
    undefined: list[str] = []
    #: With ``tick(..., explain=True)``: why each feature and CV value that changed did.
    why: list[Why] = []


# ---- runtime helpers used by the generated code ------------------------------------------------
_ERRS = (TypeError, ValueError, ArithmeticError)
_isfinite = math.isfinite


def _fin(x: float) -> float:
    """``x`` if it is a number other than NaN; raises (-> undefined) for None and NaN.

    Infinities are values: a distance with nothing in sight is ``inf``, and comparisons and
    ``e^(-inf) = 0`` are well defined on it."""
    if x is None or x != x:
        raise ValueError(x)
    return x


def _num(x: Any) -> float:
    """A float (infinities included) from a number or a numeric string; raises otherwise."""
    v = float(x)
    if v == v and not isinstance(x, bool):
        return v
    raise ValueError(x)


def _fnum(x: Any) -> float:
    """A *finite* float: the value a CV attribute can take; raises otherwise."""
    v = float(x)
    if _isfinite(v) and not isinstance(x, bool):
        return v
    raise ValueError(x)


def _truth(x: Any) -> bool | None:
    return x if x is True or x is False else None


_BOOL_TEXT = {"true": True, "false": False}


def _dyn(op: str, a: Any, b: Any) -> bool | None:
    """Compare values of statically unknown type: numbers and numeric strings as numbers,
    booleans and the strings ``"true"``/``"false"`` (any case) as booleans."""
    if a is None or b is None:
        return None
    if isinstance(a, bool) and isinstance(b, str):
        b = _BOOL_TEXT.get(b.strip().lower(), b)
    elif isinstance(b, bool) and isinstance(a, str):
        a = _BOOL_TEXT.get(a.strip().lower(), a)
    if isinstance(a, bool) and isinstance(b, bool):
        return _COMPARE[op](a, b) if op in ("==", "!=") else None
    if isinstance(a, str) != isinstance(b, str):
        try:
            a, b = _num(a), _num(b)
        except _ERRS:
            return None
    try:
        return _COMPARE[op](a, b)
    except TypeError:
        return None


_COMPARE: dict[str, Callable[[Any, Any], bool]] = {
    "==": lambda a, b: a == b,
    "!=": lambda a, b: a != b,
    "<": lambda a, b: a < b,
    "<=": lambda a, b: a <= b,
    ">": lambda a, b: a > b,
    ">=": lambda a, b: a >= b,
}

_RUNTIME: dict[str, Any] = {
    "_ERRS": _ERRS,
    "_fin": _fin,
    "_fnum": _fnum,
    "_num": _num,
    "_truth": _truth,
    "_dyn": _dyn,
    "_pow": math.pow,
    "_exp": math.exp,
    "_log": math.log,
    "_sqrt": math.sqrt,
}


# ---- measurement coercion ----------------------------------------------------------------
def _as_float(v: Any) -> float | None:
    if isinstance(v, bool):
        return None
    if isinstance(v, int | float):
        return float(v) if v == v else None  # NaN is undefined, infinities are values
    if isinstance(v, str):
        try:
            return _num(v)
        except _ERRS:
            return None
    return None


def _as_int(v: Any) -> int | None:
    f = _as_float(v)
    return int(f) if f is not None and f.is_integer() else None


def _as_bool(v: Any) -> bool | None:
    return v if isinstance(v, bool) else None


def _as_str(v: Any) -> str | None:
    return v if isinstance(v, str) else None


def _as_any(v: Any) -> Any:
    if isinstance(v, float) and v != v:
        return None
    return v if isinstance(v, bool | int | float | str) else None


_COERCE: dict[str | None, Callable[[Any], Any]] = {
    "float": _as_float,
    "int": _as_int,
    "bool": _as_bool,
    "str": _as_str,
    None: _as_any,
}


# ---- compilation -------------------------------------------------------------------------------
_ActionKind = Literal["activate", "deactivate", "set", "reject"]


@dataclass(slots=True)
class _ActionInfo:
    """A compiled action: what it does, its report template and its contested claims."""

    index: int
    unit: int
    branch: tuple[int, int]  # (rule number, branch number): same-branch conflicts
    fired: FiredRule
    kind: _ActionKind
    features: tuple[str, ...] = ()
    cv: int = -1
    reason: str = ""
    claims: list[tuple[ClaimKey, str]] = field(default_factory=list)
    #: Every claim (`claims` keeps only the contested ones): what it wants, to explain.
    wants: list[tuple[ClaimKey, str]] = field(default_factory=list)
    requests: list[Request] = field(default_factory=list)
    #: select_feature_from_variants_of: the selectable variants, best first (the first
    #: available one is activated).
    variants: tuple[str, ...] = ()


@dataclass(slots=True)
class _RuleSchedule:
    period: float | None  # seconds; None: every tick
    reads: tuple[int, ...]  # measurement slots
    last: float | None = None


@dataclass(slots=True)
class _Unit:
    name: str
    rules: list[_RuleSchedule]
    fn: Callable[..., None] | None = None  # None: runs every tick, inside a merged function

    @property
    def always(self) -> bool:
        return any(r.period is None for r in self.rules)


@lru_cache(maxsize=16)
def _compiled(source: str, filename: str) -> CodeType:
    """The rules' Python source compiled, once per process and source: a code object is
    immutable, and an engine forked after its fork server compiled it (which the fork server
    does for the Resolution Engine's initial values, `rra_agent.deployment`) runs Python's
    compiler no more (it wrote to ~1 MiB of the fork server's pages in each)."""
    return compile(source, filename, "exec")


class _Compiler:
    """AdaptationModel -> Python source of one function per unit, plus the action table."""

    def __init__(self, model: AdaptationModel, fm: FeatureModel, selectable: frozenset[str]):
        self.fm, self.model, self.selectable = fm, model, selectable
        self.slots: dict[str, int] = {}
        self.types: dict[str, str | None] = {}
        self.max_age: dict[str, float | None] = {}
        self.cvs = cv_table(fm)
        self.cv_index = {(c.feature, c.attribute): i for i, c in enumerate(self.cvs)}
        self.actions: list[_ActionInfo] = []
        self.units: list[tuple[str, list[_RuleSchedule]]] = []
        self.lines: list[str] = []
        self.tmp = 0
        self.rule_no = 0

    def compile(self) -> tuple[list[_Unit], list[tuple[Callable[..., None], int]], str]:
        """The units, the plan (function, unit index or -1 for every tick) and the source.

        Consecutive units that run on every tick share one function (fewer calls per tick);
        a scheduled unit gets its own, called when due.
        """
        bodies = []
        for u, (ruleset, rules) in enumerate(self.model.units()):
            start = len(self.lines)
            self._unit(u, ruleset.name if ruleset else None, rules)
            bodies.append(self.lines[start:])
            del self.lines[start:]
        units = [_Unit(name, schedules) for name, schedules in self.units]
        plan_names: list[tuple[str, int]] = []
        for u, unit in enumerate(units):
            if unit.always and plan_names and plan_names[-1][1] < 0:
                self.lines.extend(bodies[u])
                continue
            name = f"_g{u}" if unit.always else f"_u{u}"
            plan_names.append((name, -1 if unit.always else u))
            self.lines.append(f"def {name}(M, CV, out, V):")
            self.lines.extend(bodies[u])
        source = "\n".join(self.lines) + "\n"
        namespace = dict(_RUNTIME)
        exec(_compiled(source, f"<rules {self.model.source}>"), namespace)
        plan = [(namespace[name], u) for name, u in plan_names]
        for fn, u in plan:
            if u >= 0:
                units[u].fn = fn
        _mark_contested(self.actions)
        return units, plan, source

    # measurement slots
    def slot(self, m: Measure) -> int:
        if m.name not in self.slots:
            self.slots[m.name] = len(self.slots)
            self.types[m.name] = m.type
            self.max_age[m.name] = m.max_age_ms
        return self.slots[m.name]

    def emit(self, indent: int, text: str) -> None:
        self.lines.append("    " * indent + text)

    def temp(self) -> str:
        self.tmp += 1
        return f"_t{self.tmp}"

    # units, rules, branches
    def _unit(self, u: int, ruleset: str | None, rules: tuple[Rule, ...]) -> None:
        self.tmp = 0
        schedules = []
        for rule in rules:
            reads = [self.slot(m) for m in _rule_measures(rule)]
            period = None if rule.period_ms is None else rule.period_ms / 1000.0
            schedules.append(_RuleSchedule(period, tuple(reads)))
            self.emit(1, f"# rule {rule.name}")
            self._rule(u, ruleset, rule)
        self.units.append((ruleset or rules[0].name, schedules))

    def _rule(self, u: int, ruleset: str | None, rule: Rule) -> None:
        self.rule_no += 1
        branches = rule.branches
        if len(branches) == 1 and branches[0].condition is None:
            self._actions(1, u, ruleset, rule, 0, ())
            return
        self.emit(1, "while True:")
        reads: tuple[str, ...] = ()
        for b, branch in enumerate(branches):
            if branch.condition is None:
                self._actions(2, u, ruleset, rule, b, reads)
                break
            reads = tuple(dict.fromkeys((*reads, *measures_read(branch.condition))))
            t = self.condition(2, branch.condition)
            self.emit(2, f"if {t} is True:")
            self._actions(3, u, ruleset, rule, b, reads)
            self.emit(3, "break")
            self.emit(2, f"if {t} is None:")
            self.emit(3, "break")
        self.emit(2, "break")

    def _actions(
        self,
        indent: int,
        u: int,
        ruleset: str | None,
        rule: Rule,
        b: int,
        reads: tuple[str, ...],
    ) -> None:
        for action in rule.branches[b].actions:
            k = len(self.actions)
            extra = measures_read(action.value) if isinstance(action, SetAttribute) else ()
            fired = FiredRule(
                rule=rule.name,
                action=action_text(action),
                span=action.span,
                ruleset=ruleset,
                reads=tuple(dict.fromkeys((*reads, *extra))),
            )
            self.actions.append(self._info(k, u, (self.rule_no, b), fired, action))
            if isinstance(action, SetAttribute):
                self._set(indent, k, action)
            else:
                self.emit(indent, f"out.append({k})")

    def _info(
        self, k: int, u: int, branch: tuple[int, int], fired: FiredRule, action: Action
    ) -> _ActionInfo:
        info = _ActionInfo(k, u, branch, fired, "activate")
        claims = [c for group in action_claims(self.fm, action, str(k)) for c in group]
        match action:
            case Activate(features=fs):
                info.features = tuple(f.name for f in fs)
            case Deactivate(features=fs):
                info.kind, info.features = "deactivate", tuple(f.name for f in fs)
            case SelectVariant():
                best = [v for v in ranked_variants(self.fm, action) if v in self.selectable]
                if best:
                    info.features, info.variants = (best[0],), tuple(best)
                    claims = feature_claims(self.fm, best[0], True)
                else:
                    info.kind = "reject"
                    info.reason = (
                        f"no variant of {action.point.name} with attribute {action.attribute} "
                        f"is selectable with the deployment-time selection"
                    )
            case SetAttribute(target=t):
                if t.feature is None:  # pragma: no cover - the resolver names every owner
                    raise ValueError(
                        f"set_attribute({t.name}): the attribute's owner is unresolved"
                    )
                info.kind, info.cv = "set", self.cv_index[(t.feature, t.name)]
        info.claims = claims
        info.wants = list(claims)
        kind = info.kind
        if kind == "activate" or kind == "deactivate":
            info.requests = [(kind, f) for f in info.features]
        return info

    def _set(self, indent: int, k: int, action: SetAttribute) -> None:
        code, _ty, _simple = self.value(action.value, numeric=True)
        self.emit(indent, "try:")
        self.emit(indent + 1, f"V[{k}] = _fnum({code})")
        self.emit(indent, "except _ERRS:")
        self.emit(indent + 1, "pass")
        self.emit(indent, "else:")
        self.emit(indent + 1, f"out.append({k})")

    # conditions: straight-line code leaving True/False/None in a temporary
    def condition(self, indent: int, expr: Expr) -> str:
        match expr:
            case Logic(op=op, left=a, right=b):
                ta, tb = self.condition(indent, a), self.condition(indent, b)
                t = self.temp()
                decisive = "False" if op == "and" else "True"  # one such operand decides
                other = "True" if op == "and" else "False"
                self.emit(
                    indent,
                    f"{t} = {decisive} if {ta} is {decisive} or {tb} is {decisive} else "
                    f"(None if {ta} is None or {tb} is None else {other})",
                )
                return t
            case Not(operand=o):
                to = self.condition(indent, o)
                t = self.temp()
                self.emit(indent, f"{t} = None if {to} is None else not {to}")
                return t
            case Compare():
                return self._compare(indent, expr)
        code, ty, _simple = self.value(expr, numeric=False)
        t = self.temp()
        self.emit(indent, f"{t} = {code}" if ty == "bool" else f"{t} = _truth({code})")
        return t

    def _compare(self, indent: int, cmp: Compare) -> str:
        lc, lt, ls = self.value(cmp.left, numeric=False)
        rc, rt, rs = self.value(cmp.right, numeric=False)
        t = self.temp()
        dynamic = "any" in (lt, rt)
        if not ls:
            lc = f"_fin({lc})"
        if not rs:
            rc = f"_fin({rc})"
        sides = ((lc, _literal(cmp.left)), (rc, _literal(cmp.right)))
        checks = [code for code, literal in sides if not literal]
        if ls and rs:
            if dynamic:
                self.emit(indent, f"{t} = _dyn({cmp.op!r}, {lc}, {rc})")
                return t
            guard = " or ".join(f"{x} is None" for x in checks)
            body = f"{lc} {cmp.op} {rc}"
            self.emit(indent, f"{t} = None if {guard} else ({body})" if guard else f"{t} = {body}")
            return t
        self.emit(indent, "try:")
        self.emit(indent + 1, f"_a = {lc}")
        self.emit(indent + 1, f"_b = {rc}")
        self.emit(indent, "except _ERRS:")
        self.emit(indent + 1, f"{t} = None")
        self.emit(indent, "else:")
        if dynamic:
            self.emit(indent + 1, f"{t} = _dyn({cmp.op!r}, _a, _b)")
        else:
            self.emit(indent + 1, f"{t} = None if _a is None or _b is None else (_a {cmp.op} _b)")
        return t

    # values: one Python expression; `simple` when it cannot raise (no arithmetic)
    def value(self, expr: Expr, *, numeric: bool) -> tuple[str, str, bool]:
        match expr:
            case Num(value=v):
                return repr(float(v)), "num", True
            case Str(value=v):
                return repr(v), "str", True
            case Bool(value=v):
                return repr(v), "bool", True
            case Const(name=n):
                return repr(math.e if n == "e" else math.pi), "num", True
            case Measure(type=t):
                code = f"M[{self.slot(expr)}]"
                if t is None:
                    return (f"_num({code})", "num", False) if numeric else (code, "any", True)
                return code, _TYPES[t], True
            case AttrValue(kind="cv", feature=f, attribute=a):
                return f"CV[{self.cv_index[(f, a)]}]", "num", True
            case AttrValue(feature=f, attribute=a):
                value = self.fm.features[f].attribute(a).rra_value  # type: ignore[union-attr]
                return _constant(value)
            case Bound(feature=f, attribute=a, bound=b):
                attr = self.fm.features[f].attribute(a)
                bound = attr.lower if b == "min" else attr.upper  # type: ignore[union-attr]
                return repr(float(bound)), "num", True  # type: ignore[arg-type]
        return self._arith(expr), "num", False

    def _arith(self, expr: Expr) -> str:
        match expr:
            case Neg(operand=o):
                return f"(-{self.value(o, numeric=True)[0]})"
            case Arith(op="^", left=Const(name="e"), right=b):
                return f"_exp({self.value(b, numeric=True)[0]})"
            case Arith(op="^", left=a, right=b):
                return f"_pow({self.value(a, numeric=True)[0]}, {self.value(b, numeric=True)[0]})"
            case Arith(op=op, left=a, right=b):
                return f"({self.value(a, numeric=True)[0]} {op} {self.value(b, numeric=True)[0]})"
            case Call(func=f, args=args):
                codes = [self.value(a, numeric=True)[0] for a in args]
                if f in ("min", "max") and len(codes) == 1:
                    return f"({codes[0]})"
                name = {"abs": "abs", "min": "min", "max": "max"}.get(f, f"_{f}")
                return f"{name}({', '.join(codes)})"
        raise TypeError(f"cannot compile {expr!r}")  # pragma: no cover - resolver guarantees


_TYPES = {"float": "num", "int": "num", "str": "str", "bool": "bool"}


def _literal(expr: Expr) -> bool:
    return isinstance(expr, Num | Str | Bool | Const | Bound) or (
        isinstance(expr, AttrValue) and expr.kind != "cv"
    )


def _constant(value: object) -> tuple[str, str, bool]:
    if isinstance(value, bool):
        return repr(value), "bool", True
    if isinstance(value, int | float):
        return repr(float(value)), "num", True
    return repr(str(value)), "str", True


def _rule_measures(rule: Rule) -> list[Measure]:
    """The measurements a rule reads (conditions and values), in order of appearance."""
    out: dict[str, Measure] = {}
    for branch in rule.branches:
        values = [a.value for a in branch.actions if isinstance(a, SetAttribute)]
        for expr in (branch.condition, *values):
            for node in walk(expr) if expr is not None else ():
                if isinstance(node, Measure):
                    out.setdefault(node.name, node)
    return list(out.values())


def _mark_contested(actions: list[_ActionInfo]) -> None:
    """Keep only claims another unit (or the same branch) also makes: the rest cannot clash."""
    claimants: dict[ClaimKey, list[_ActionInfo]] = {}
    for info in actions:
        for key, _ in info.claims:
            claimants.setdefault(key, []).append(info)
    for info in actions:
        info.claims = [
            (key, value)
            for key, value in info.claims
            if any(
                other is not info and (other.unit != info.unit or other.branch == info.branch)
                for other in claimants[key]
            )
        ]


# ---- the engine ----------------------------------------------------------------------------------
class AdaptationEngine:
    """Evaluates an Adaptation Model against measurements, one `tick` at a time.

    ``deployment_selection`` may be partial; it is completed with `complete_deployment`. The
    run-time selection starts at `default_runtime_selection` (or ``initial``). ``verify``
    re-checks every new selection with `check_selection` (for tests and debugging; the
    selection `apply_requests` returns is valid by construction).
    """

    def __init__(
        self,
        fm: FeatureModel,
        deployment_selection: Collection[str],
        model: AdaptationModel,
        *,
        initial: Collection[str] | None = None,
        verify: bool = False,
    ) -> None:
        self.fm = fm
        self.model = model
        self.deployment = complete_deployment(fm, deployment_selection)
        self.selectable = selectable_runtime(fm, self.deployment)
        compiler = _Compiler(model, fm, self.selectable)
        self._units, self._plan, self.source = compiler.compile()
        self._timed = [[r for r in u.rules if r.period] for u in self._units]
        slot_units: list[set[int]] = [set() for _ in compiler.slots]
        for u, unit in enumerate(self._units):
            for r in unit.rules:
                if r.period == 0 and not unit.always:
                    for i in r.reads:
                        slot_units[i].add(u)
        self._slot_units = [tuple(sorted(s)) for s in slot_units]
        self._family = request_families(fm)
        self._leaf_group = _leaf_groups(fm)
        self._free_leaf = _free_leaves(fm)
        self.verify = verify
        self._actions = compiler.actions
        self._cvs = compiler.cvs
        self._slot_names = list(compiler.slots)
        self._slot_of = dict(compiler.slots)
        self._slots = [
            (name, _COERCE[compiler.types[name]], compiler.max_age[name])
            for name in self._slot_names
        ]
        self._M: list[Any] = [None] * len(self._slots)
        self._V: list[Any] = [None] * len(self._actions)
        self._raw: list[Any] = [_UNSEEN] * len(self._slots)
        self._stamps: list[Any] = [_UNSEEN] * len(self._slots)
        self._requested: list[float | None] = [c.initial for c in self._cvs]
        self._effective: list[float | None] = []
        if initial is None:
            self.selection = default_runtime_selection(fm, self.deployment)
        else:
            self.selection = frozenset(initial)
            problems = check_selection(fm, self.deployment | self.selection)
            if problems:
                raise SelectionError(
                    "the initial run-time selection is invalid", [p.message for p in problems]
                )
        self._effective = self._clamp_all(self.selection)
        self._unselectable: dict[str, str] = {}
        #: Run-time features that need an unavailable implementation, and why (see
        #: `set_unavailable`).
        self.unavailable: dict[str, str] = {}
        self._full = False
        self.ticks = 0
        #: Run-time features an operator forced on (True) or off (False): see `force`.
        self.forced: dict[str, bool] = {}
        #: The latest wish of each unit on each contested claim (conflicts in force).
        self._wishes: dict[ClaimKey, dict[int, tuple[str, FiredRule]]] = {}
        self._held: dict[int, set[ClaimKey]] = {}
        self._always = [u for u, unit in enumerate(self._units) if unit.always]
        #: Why each feature and CV value is as it is: its last explained change (`why`).
        self.provenance: dict[str, Why] = {}
        #: What a target no explained change touched owes its state to.
        self._origin: WhyReason = "default"
        self._priority = {
            (ruleset.name, rule.name): rule.priority
            for ruleset, rules in model.units()
            if ruleset is not None
            for rule in rules
        }
        self._groups: dict[str, ClaimKey | None] = {}
        self._wanting: dict[str, tuple[list[tuple[int, str]], list[tuple[int, str]]]] = {}
        self._lost: dict[tuple[int, int], tuple[OverruleReason, str]] = {}
        #: Static indexes: who claims what (feature actions), which actions set each CV.
        self._claimants: dict[ClaimKey, list[tuple[int, str]]] = {}
        self._cv_actions: list[list[int]] = [[] for _ in self._cvs]
        for info in self._actions:
            if info.cv >= 0:
                self._cv_actions[info.cv].append(info.index)
            elif info.requests:
                for key, value in info.wants:
                    self._claimants.setdefault(key, []).append((info.index, value))

    @property
    def cv(self) -> dict[str, float]:
        return {c.key: v for c, v in zip(self._cvs, self._effective, strict=True) if v is not None}

    def adopt(self, selection: Collection[str], cv: Mapping[str, float]) -> None:
        """Continue from this run-time selection and these CV values (a replica taking over
        from another, an engine resuming over a running system). Raises `SelectionError` if
        the selection is not valid; CV values are clamped as the engine's own are."""
        chosen = frozenset(selection)
        problems = check_selection(self.fm, self.deployment | chosen)
        if problems:
            raise SelectionError(
                "cannot adopt the run-time selection", [p.message for p in problems]
            )
        self._origin = "resumed" if chosen != self.selection or self.ticks else self._origin
        self.selection = chosen
        self._requested = [
            float(cv[c.key]) if c.key in cv else r
            for c, r in zip(self._cvs, self._requested, strict=True)
        ]
        self._effective = self._clamp_all(chosen)

    def force(self, choices: Mapping[str, str]) -> frozenset[str]:
        """Force run-time features ``on`` or ``off`` (``auto`` releases them): from the next
        tick the rules cannot change them. Returns the selection that tick will reach;
        raises `OverrideError` (nothing changed) if the feature model does not allow it."""
        selection, self.forced = overrides.change(
            self.fm, self.deployment, self.selectable, self.selection, self.forced, choices
        )
        return selection

    def outcome(self, rule: str, branch: int) -> frozenset[str]:
        """The run-time selection the next tick reaches if, of all the rules, only branch
        ``branch`` of rule ``rule`` fires: its feature actions applied as a tick applies
        them, from the current selection, the forced and the unavailable features (a
        ``set_attribute`` is left out). The current selection if it changes nothing. A
        reflex's switch is compiled for this outcome (`rra_agent.core.reflex`)."""
        fired: list[FiredRule] = []
        requests: list[Request] = []
        sources: list[int] = []
        rejected: list[Rejected] = []
        for info in self._actions:
            if info.fired.rule != rule or info.branch[1] != branch or info.cv >= 0:
                continue
            wanted = info.requests
            if info.variants and self.unavailable:
                wanted = self._available_variant(info, rejected)
            requests += wanted
            sources += [len(fired)] * len(wanted)
            fired.append(info.fired)
        return self._select(requests, sources, fired, rejected)

    def set_unavailable(self, features: Mapping[str, str]) -> bool:
        """Features that need an unavailable implementation (feature -> why): from the next
        tick they cannot be activated (the request is rejected as ``unavailable``), a
        ``select_feature_from_variants_of`` picks the best variant still available, and a
        selected one is left for another where the feature model allows. That tick runs
        every rule, as the first does. Returns whether anything changed."""
        features = dict(features)
        if features == self.unavailable:
            return False
        self.unavailable, self._full = features, True
        return True

    def tick(
        self,
        now: float,
        measurements: Mapping[str, Sample],
        *,
        changed: Collection[str] = (),
        explain: bool = False,
    ) -> TickResult:
        """Evaluate the due rules on ``measurements`` (name -> (value, stamp)) at ``now`` (s).
        ``explain``: fill `TickResult.why` for what changed, and keep it for `why`."""
        requested_before = self._requested.copy() if explain else None
        fresh = self._prepare(now, measurements, changed)
        out: list[int] = []
        cv_before = self._effective
        first, self._full = self.ticks == 0 or self._full, False
        M, V, timed = self._M, self._V, self._timed
        woken = {u for i in fresh for u in self._slot_units[i]}
        ran = list(self._always)
        for fn, u in self._plan:
            if u < 0:
                fn(M, cv_before, out, V)
            elif first or u in woken or (timed[u] and _due(timed[u], now)):
                for r in timed[u]:
                    r.last = now
                fn(M, cv_before, out, V)
                ran.append(u)
        self.ticks += 1
        fired, rejected, conflicts, requests, sources = self._collect(out)
        active = self._in_force(out, fired, ran)
        trace: list[tuple[int, list[str]]] | None = [] if explain else None
        selection = self._select(requests, sources, fired, rejected, trace)
        self._effective = self._clamp_all(selection)
        changed_any = selection != self.selection or self._effective != cv_before
        before, self.selection = self.selection, selection
        undefined = [n for n, v in zip(self._slot_names, self._M, strict=True) if v is None]
        why: list[Why] = []
        if changed_any and trace is not None and requested_before is not None:
            tick = _Tick(now, measurements, before, cv_before, requested_before, frozenset(out), V)
            why = self._explain(tick, out, rejected, trace)
        return TickResult(
            now=now,
            selection=selection,
            cv=self.cv,
            changed=changed_any,
            fired=fired,
            rejected=rejected,
            conflicts=conflicts,
            active=active,
            undefined=undefined,
            why=why,
        )

    # steps of a tick
    def _prepare(
        self, now: float, measurements: Mapping[str, Sample], changed: Collection[str]
    ) -> list[int]:
        """Fill M with this tick's values (None: missing or stale); the slots that are new."""
        M, raw, stamps = self._M, self._raw, self._stamps
        fresh: list[int] = []
        for i, (name, coerce, max_age) in enumerate(self._slots):
            sample = measurements.get(name)
            if sample is None:
                M[i] = None
                continue
            value, stamp = sample
            if stamp != stamps[i]:
                stamps[i] = stamp
                fresh.append(i)
            if max_age is not None and not _recent(now, stamp, max_age):
                M[i] = None
            elif value is raw[i] and M[i] is not None:
                pass
            else:
                raw[i] = value
                M[i] = coerce(value)
        for name in changed:
            slot = self._slot_of.get(name)
            if slot is not None:
                fresh.append(slot)
        return fresh

    def _collect(self, out: list[int]):
        fired: list[FiredRule] = []
        rejected: list[Rejected] = []
        conflicts: list[ConflictRecord] = []
        requests: list[Request] = []
        sources: list[int] = []
        owners: dict[ClaimKey, tuple[str, int, _ActionInfo]] = {}
        requested = self._requested
        V = self._V
        actions = self._actions
        for k in out:
            info = actions[k]
            position = len(fired)
            if info.cv >= 0:
                value = V[k]
                requested[info.cv] = value
                fired.append(msgspec.structs.replace(info.fired, value=value))
            else:
                fired.append(info.fired)
            for key, value in info.claims:
                previous = owners.get(key)
                if previous is not None and previous[0] != value:
                    self._conflict(key, previous, info, position, fired, conflicts)
                owners[key] = (value, position, info)
            wanted = info.requests
            if info.variants and self.unavailable:
                wanted = self._available_variant(info, rejected)
            if wanted:
                requests += wanted
                sources += [position] * len(wanted)
            elif info.reason:
                rejected.append(_rejected(info.fired, info.reason))
        return fired, rejected, conflicts, requests, sources

    def _available_variant(self, info: _ActionInfo, rejected: list[Rejected]) -> list[Request]:
        """The best variant of a select that is available (none: rejected as such)."""
        best = next((v for v in info.variants if v not in self.unavailable), None)
        if best is not None:
            return [("activate", best)]
        why = "; ".join(self.unavailable[v] for v in info.variants)
        reason = f"no variant is available: {why}"
        rejected.append(_rejected(info.fired, reason, info.variants[0]))
        return []

    def _in_force(
        self, out: list[int], fired: list[FiredRule], ran: list[int]
    ) -> list[ConflictRecord]:
        """Update each unit's latest wishes (the units that ran drop theirs, then the fired
        actions state theirs) and return the conflicts in force, later unit as winner."""
        wishes, held = self._wishes, self._held
        for u in ran:
            for key in held.pop(u, ()):
                mine = wishes[key]
                mine.pop(u, None)
                if not mine:
                    del wishes[key]
        for k, f in zip(out, fired, strict=True):
            info = self._actions[k]
            for key, value in info.claims:
                wishes.setdefault(key, {})[info.unit] = (value, f)
                held.setdefault(info.unit, set()).add(key)
        active: list[ConflictRecord] = []
        for key, by_unit in wishes.items():
            if len(by_unit) < 2:
                continue
            units = sorted(by_unit)
            for i, a in enumerate(units):
                for b in units[i + 1 :]:
                    (va, fa), (vb, fb) = by_unit[a], by_unit[b]
                    if va != vb:
                        active.append(
                            ConflictRecord(
                                kind=_RECORD_KIND[key[0]],
                                target=target_text(key),
                                winner=fb,
                                loser=fa,
                                values=(_wanted(key, vb, fb), _wanted(key, va, fa)),
                            )
                        )
        return active

    @staticmethod
    def _conflict(
        key: ClaimKey,
        previous: tuple[str, int, _ActionInfo],
        info: _ActionInfo,
        position: int,
        fired: list[FiredRule],
        conflicts: list[ConflictRecord],
    ) -> None:
        """Record a clash of two fired actions (once per pair; not inside one rule set)."""
        _, ppos, pinfo = previous
        if ppos == position or (pinfo.unit == info.unit and pinfo.branch != info.branch):
            return
        for earlier in reversed(conflicts):  # one record per pair of actions
            if earlier.winner is not fired[position]:
                break
            if earlier.loser is fired[ppos]:
                return
        conflicts.append(
            ConflictRecord(
                kind=_RECORD_KIND[key[0]],
                target=target_text(key),
                winner=fired[position],
                loser=fired[ppos],
            )
        )

    def _select(
        self,
        requests: list[Request],
        sources: list[int],
        fired: list[FiredRule],
        rejected: list[Rejected],
        trace: list[tuple[int, list[str]]] | None = None,
    ) -> frozenset[str]:
        """Apply the feature requests; the selection stays valid (else the previous one).
        ``trace`` gets (the fired action's position, or `_OPERATOR` / `_UNAVAILABLE`, the
        features it switched) for each change, in order."""
        current = self.selection
        live: list[Request] = []
        live_sources: list[int] = []
        if self.forced:  # newly forced features first: the rules' requests apply on top
            enforced = overrides.enforce(self.fm, self.deployment, current, self.forced)
            current = _traced(trace, _OPERATOR, current, enforced or current)
            keep, blocked = overrides.split(requests, self.forced)
            for i, reason in blocked:
                f = requests[i][1]
                rejected.append(_rejected(fired[sources[i]], reason, forced=f))
            requests, sources = [requests[i] for i in keep], [sources[i] for i in keep]
        for (kind, f), src in zip(requests, sources, strict=True):
            if kind == "activate" and f in self.unavailable and not self.forced.get(f):
                rejected.append(_rejected(fired[src], self.unavailable[f], f))
            elif kind == "activate" and f not in self.selectable:
                rejected.append(_rejected(fired[src], self._why_unavailable(f)))
            elif kind == "deactivate" and f not in self.selectable:
                continue  # never selected under this deployment: nothing to do
            else:
                live.append((kind, f))
                live_sources.append(src)
        live, live_sources = self._reduce(live, live_sources, current)
        if not live:
            return _traced(trace, _UNAVAILABLE, current, self._leave_unavailable(current))
        steps: list[tuple[int, list[str]]] | None = None if trace is None else []
        selection, refused = apply_requests(self.fm, self.deployment, current, live, steps)
        if trace is not None and steps:
            trace += [(live_sources[i], names) for i, names in steps]
        for i, reason in refused:
            rejected.append(_rejected(fired[live_sources[i]], reason))
        if self.forced:
            enforced = self._enforce(selection, current, live, live_sources, fired, rejected)
            selection = _traced(trace, _OPERATOR, selection, enforced)
        selection = _traced(trace, _UNAVAILABLE, selection, self._leave_unavailable(selection))
        if self.verify and selection != current:
            problems = check_selection(self.fm, self.deployment | selection)
            if problems:  # pragma: no cover - apply_requests keeps selections valid
                reason = "; ".join(p.message for p in problems)
                for src in dict.fromkeys(live_sources):
                    rejected.append(_rejected(fired[src], f"invalid selection: {reason}"))
                return current
        return selection

    def _enforce(
        self,
        selection: frozenset[str],
        before: frozenset[str],
        live: list[Request],
        sources: list[int],
        fired: list[FiredRule],
        rejected: list[Rejected],
    ) -> frozenset[str]:
        """The forced features back in their state; a request it undoes is reported."""
        if not self.forced or overrides.holds(selection, self.forced):
            return selection
        enforced = overrides.enforce(self.fm, self.deployment, selection, self.forced)
        result = before if enforced is None else enforced
        forced = ", ".join(f for f, on in sorted(self.forced.items()) if on)
        for (kind, f), src in zip(live, sources, strict=True):
            if (f in result) != (kind == "activate"):
                reason = f"cannot {kind} {f}: it would change an operator's forced feature"
                reason += f" ({forced})" if forced else ""
                rejected.append(_rejected(fired[src], reason, forced=f))
        return result

    def _reduce(
        self, live: list[Request], sources: list[int], current: frozenset[str]
    ) -> tuple[list[Request], list[int]]:
        """Drop the requests that cannot change the outcome of `apply_requests`.

        A request only changes features of its own family (`request_families`). Within a family, a
        request repeating the one before it is a no-op; and while a family has one surviving
        request, which therefore runs on ``current``, a request that supersedes it
        (`_supersedes`) replaces it: so a rule set's overridden defaults cost nothing. Then
        every family whose remaining requests already hold in ``current`` is left out.
        """
        family, leaf_group, free = self._family, self._leaf_group, self._free_leaf
        active = (current, self.deployment)
        last: dict[object, int] = {}  # family -> its latest surviving request
        alone: dict[object, bool] = {}  # ... and whether it is the family's only one
        dropped: set[int] = set()
        for i, (kind, f) in enumerate(live):
            fam = family[f]
            j = last.get(fam)
            if j is None:
                alone[fam] = True
            elif live[j] == (kind, f):
                dropped.add(i)
                continue
            elif alone[fam] and _supersedes((kind, f), live[j], leaf_group, free, active):
                dropped.add(j)  # it ran on `current`, so the check above was exact
            else:
                alone[fam] = False
            last[fam] = i
        dirty = {
            family[f]
            for i, (kind, f) in enumerate(live)
            if i not in dropped and (f in current) != (kind == "activate")
        }
        keep = [i for i, (_, f) in enumerate(live) if i not in dropped and family[f] in dirty]
        return [live[i] for i in keep], [sources[i] for i in keep]

    def _leave_unavailable(self, selection: frozenset[str]) -> frozenset[str]:
        """Leave the selected features that are unavailable (unless an operator forced them
        on) where the feature model allows: deselect one, or else activate the first
        available selectable sibling of its group (model order)."""
        unavailable = self.unavailable.keys() - {f for f, on in self.forced.items() if on}
        for f in sorted(selection & unavailable):
            if f not in selection:
                continue
            parent = self.fm.parent.get(f)
            siblings = [c.name for c in self.fm.features[parent].children] if parent else []
            tries: list[list[Request]] = [[("deactivate", f)]]
            tries += [[("activate", s)] for s in siblings
                      if s != f and s in self.selectable and s not in unavailable]  # fmt: skip
            for requests in tries:
                after, refused = apply_requests(self.fm, self.deployment, selection, requests)
                if not refused and f not in after and not (after - selection) & unavailable:
                    selection = after
                    break
        return selection

    def _why_unavailable(self, feature: str) -> str:
        reason = self._unselectable.get(feature)
        if reason is None:
            _, refused = apply_requests(
                self.fm, self.deployment, self.selection, [("activate", feature)]
            )
            reason = refused[0][1] if refused else f"{feature} is not selectable"
            self._unselectable[feature] = reason
        return reason

    def _clamp_all(self, selection: frozenset[str]) -> list[float | None]:
        active = self.deployment | selection
        return [clamp(c, v, active) for c, v in zip(self._cvs, self._requested, strict=True)]

    # ---- explanation: what changed each target, and what was overruled --------------------
    # Fired actions are told apart by their index in the action table: the compiler numbers
    # them in evaluation order, so a larger index acted later in the tick.
    def _explain(
        self,
        t: _Tick,
        out: list[int],
        rejected: list[Rejected],
        trace: list[tuple[int, list[str]]],
    ) -> list[Why]:
        """Why each feature and CV value that changed in tick ``t`` did (kept for `why`)."""
        cause: dict[str, int] = {}
        for pos, names in trace:
            k = out[pos] if pos >= 0 else pos
            for name in names:
                cause[name] = k
        if rejected:
            t.refused = {_key(r): r for r in rejected}
        why = [self._why_feature(t, f, cause.get(f)) for f in sorted(t.before ^ self.selection)]
        effective, before = self._effective, t.cv_before
        why += [self._why_cv(t, i) for i in range(len(effective)) if effective[i] != before[i]]
        return why

    def _report(self, t: _Tick | _Now, k: int) -> FiredRule:
        """The report of fired action ``k``, with the value it computed if it sets a CV."""
        info = self._actions[k]
        return info.fired if info.cv < 0 else msgspec.structs.replace(info.fired, value=t.V[k])

    def _why_feature(self, t: _Tick, f: str, k: int | None) -> Why:
        on = f in self.selection
        by: tuple[FiredRule, ...] = ()
        reason: WhyReason = "rule"
        detail = ""
        if k is None:
            reason, detail = "model", "the feature model, completing another change"
        elif k == _OPERATOR:
            reason, detail = "operator", self._forced_text(f)
        elif k == _UNAVAILABLE:
            reason, detail = "unavailable", self._unavailable_text(f, t.before)
        else:
            by = (self._report(t, k),)
            best = self._actions[k].variants[:1]
            if best and best[0] in self.unavailable:
                detail = f"its best variant, {best[0]}, is unavailable: {self.unavailable[best[0]]}"
        opposing = self._opposing(t.fired, f, on)
        overruled = (
            tuple(
                _overruled(self._report(t, j), wants, *self._beaten(t, j, k, f))
                for j, wants in opposing
                if j != k
            )
            if opposing
            else ()
        )
        why = Why(
            target=f,
            kind="feature",
            value="on" if on else "off",
            since=t.now,
            reason=reason,
            by=by,
            reads=_reads(by, t.measurements),
            detail=detail,
            overruled=overruled,
        )
        self.provenance[f] = why
        return why

    def _why_cv(self, t: _Tick, i: int) -> Why:
        c, requested = self._cvs[i], self._requested[i]
        sets = [k for k in self._cv_actions[i] if k in t.fired]
        winner = sets[-1] if sets else None
        by: tuple[FiredRule, ...] = ()
        reason: WhyReason = "model"
        detail = ""
        owner = self._nfr_changed(c, t.before)
        if winner is not None and requested != t.requested_before[i]:
            by, reason = (self._report(t, winner),), "rule"
        elif owner is not None:
            state = "selected" if owner in self.selection else "deselected"
            cause = self.provenance.get(owner)
            by, reason = (cause.by if cause else ()), "nfr"
            detail = f"{owner} was {state}: its NFR {self._nfr_name(owner, c)} " + (
                "applies" if state == "selected" else "no longer applies"
            )
        elif winner is not None:
            by, reason = (self._report(t, winner),), "rule"
        overruled = [
            _overruled(f, _value_text(f.value), *self._beaten(t, k, winner))
            for k in sets[:-1]
            if (f := self._report(t, k)) is not None
        ]
        limit = limiting(c, requested, self.deployment | self.selection)
        if limit is not None and requested is not None:
            text = self._limit_text(c, requested, limit)
            detail = f"{detail}; {text}" if detail else text
            standing = self._report(t, winner) if winner is not None else self._standing(c.key)
            if standing is not None:
                kind: OverruleReason = "bounds" if limit[0] in ("lower", "upper") else "nfr"
                overruled.append(_overruled(standing, _value_text(requested), kind, text))
        new = self._effective[i]
        why = Why(
            target=c.key,
            kind="cv",
            value="-" if new is None else f"{new:g}",
            since=t.now,
            reason=reason,
            by=by,
            reads=_reads(by, t.measurements),
            detail=detail,
            overruled=tuple(overruled),
        )
        self.provenance[c.key] = why
        return why

    def _beaten(
        self, t: _Tick, k: int, winner: int | None, target: str = ""
    ) -> tuple[OverruleReason, str]:
        """Why fired action ``k`` did not prevail over ``winner`` (an action, `_OPERATOR`,
        `_UNAVAILABLE`)."""
        rejection = t.refused.get(_key(self._actions[k].fired)) if t.refused else None
        if rejection is not None:
            if rejection.forced:
                return "operator", self._forced_text(rejection.forced)
            if rejection.unavailable:
                return "unavailable", rejection.reason
            return "refused", rejection.reason
        if winner == _OPERATOR:
            return "operator", self._forced_text(target)
        if winner == _UNAVAILABLE:
            return "unavailable", self._unavailable_text(target, t.before)
        if winner is not None and winner > k:
            return self._later(k, winner)
        return "refused", "its request changed nothing"

    def _later(self, k: int, winner: int) -> tuple[OverruleReason, str]:
        """Action ``k`` lost to action ``winner``, evaluated after it."""
        found = self._lost.get((k, winner))
        if found is not None:
            return found
        w = self._actions[winner].fired
        reason: OverruleReason = "later_rule"
        text = f"rule {_rule_name(w)}, written later, wins (a run-time conflict)"
        if self._actions[k].unit == self._actions[winner].unit and w.ruleset is not None:
            p = self._priority.get((w.ruleset, w.rule))
            prio = f" (priority {p})" if p is not None else ""
            reason = "priority"
            text = f"rule {w.rule}{prio} has a higher priority in rule set {w.ruleset}"
        self._lost[(k, winner)] = (reason, text)
        return reason, text

    def _opposing(self, fired: Collection[int], f: str, on: bool) -> list[tuple[int, str]]:
        """The fired actions that want feature ``f`` otherwise than ``on``: (action, what it
        wants: on, off or another alternative), in evaluation order."""
        return [kw for kw in self._against(f)[on] if kw[0] in fired]

    def _agreeing(self, fired: Collection[int], f: str, on: bool) -> int | None:
        """The last fired action that wants feature ``f`` as it is (``on``), if any."""
        return max((k for k, _ in self._against(f)[not on] if k in fired), default=None)

    def _against(self, f: str) -> tuple[list[tuple[int, str]], list[tuple[int, str]]]:
        """The actions that want ``f`` on (first) and off (second), with what they want:
        ``on``, ``off`` or the alternative they choose instead; in evaluation order."""
        table = self._wanting.get(f)
        if table is None:
            want: tuple[dict[int, str], dict[int, str]] = ({}, {})
            for k, value in self._claimants.get(("feature", f), ()):
                want[value != "on"].setdefault(k, value)
            group = self._group_key(f)
            for k, member in self._claimants.get(group, ()) if group is not None else ():
                want[member != f].setdefault(k, "on" if member == f else member)
            table = self._wanting[f] = (sorted(want[0].items()), sorted(want[1].items()))
        return table

    def _group_key(self, f: str) -> ClaimKey | None:
        """The claim of ``f``'s alternative group (None: not in one)."""
        if f not in self._groups:
            claims = feature_claims(self.fm, f, True) if f in self.fm.features else []
            self._groups[f] = next(
                (key for key, value in claims if key[0] == "group" and value == f), None
            )
        return self._groups[f]

    def _forced_text(self, f: str) -> str:
        if f in self.forced:
            return f"an operator forced {f} {'on' if self.forced[f] else 'off'}"
        forced = ", ".join(f"{g} {'on' if on else 'off'}" for g, on in sorted(self.forced.items()))
        return f"the features an operator forced ({forced or 'none now'})"

    def _unavailable_text(self, f: str, before: frozenset[str]) -> str:
        if f in self.unavailable:
            return f"{f} is unavailable: {self.unavailable[f]}"
        gone = sorted(g for g in self.unavailable if g in before and g not in self.selection)
        return f"in place of {', '.join(gone)} (unavailable)" if gone else "an unavailable feature"

    def _nfr_changed(self, c: CvAttribute, before: frozenset[str]) -> str | None:
        """An owner of an NFR on ``c`` that was selected or deselected since ``before``."""
        for owner, _ in (*c.nfr_max, *c.nfr_min):
            if (owner in before) != (owner in self.selection) and owner not in self.deployment:
                return owner
        return None

    def _nfr_name(self, owner: str, c: CvAttribute) -> str:
        names = [
            a.name
            for a in self.fm.features[owner].attributes
            if a.kind == "nfr" and a.constrains in (c.attribute, f"{c.feature}.{c.attribute}")
        ]
        return names[0] if names else "?"

    def _limit_text(self, c: CvAttribute, requested: float, limit: tuple[str, str, float]) -> str:
        kind, owner, bound = limit
        if kind in ("lower", "upper"):
            return f"{requested:g} clamped into its bounds [{c.lower:g}, {c.upper:g}]"
        name = self._nfr_name(owner, c)
        return f"{requested:g} clamped to {bound:g} by the NFR {name} of {owner} ({kind} {bound:g})"

    def _standing(self, key: str) -> FiredRule | None:
        """The rule whose value a CV holds (its last change), if a rule set it."""
        why = self.provenance.get(key)
        return why.by[0] if why is not None and why.reason == "rule" and why.by else None

    # ---- why: the current state, for people (rra why) -----------------------------------
    def note(self, why: Iterable[Why]) -> None:
        """Take these explanations as the provenance of their targets (a replica following
        its leader's selections)."""
        for w in why:
            self.provenance[w.target] = w

    def targets(self) -> list[tuple[str, str]]:
        """(kind, name) of everything `why` explains: the run-time features selectable under
        the deployment, in model order, then the CV attributes."""
        features = [("feature", f) for f in self.fm.features if f in self.selectable]
        return features + [("cv", c.key) for c in self._cvs]

    def target(self, name: str) -> tuple[str, str]:
        """(kind, canonical name) of a run-time feature or CV attribute named ``name`` (a
        feature's alias, a CV's ``Feature.Attr`` or attribute name); KeyError saying what
        there is otherwise."""
        feature = self.fm.resolve_name(name)
        if feature is not None and feature in self.selectable:
            return "feature", feature
        for c in self._cvs:
            if name in (c.key, f"{c.feature}.{c.attribute}", c.attribute):
                return "cv", c.key
        if feature is not None:
            raise KeyError(f"{feature} is not a run-time feature selectable in this deployment")
        known = [n for _, n in self.targets()]
        close = difflib.get_close_matches(name, known, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise KeyError(f"no run-time feature or CV attribute named {name!r}{hint}")

    def why(self, names: Iterable[str] | None = None) -> list[Why]:
        """The current state of each named run-time feature or CV attribute (default: every
        one, `targets`) and why: the change that put it there and, evaluated now on the
        latest measurements, the actions that want otherwise and why they do not prevail.
        Raises KeyError for a name that is neither."""
        chosen = self.targets() if names is None else [self.target(n) for n in names]
        out: list[int] = []
        values: list[Any] = [None] * len(self._actions)
        for fn, _ in self._plan:  # every unit, due or not, on the latest tick's inputs
            fn(self._M, self._effective, out, values)
        now = _Now(frozenset(out), values)
        return [
            self._feature_now(now, name) if kind == "feature" else self._cv_now(now, name)
            for kind, name in chosen
        ]

    def _feature_now(self, now: _Now, f: str) -> Why:
        on = f in self.selection
        base = self._standing_why(f, "feature", "on" if on else "off")
        if f in self.forced and base.reason != "operator":
            base = msgspec.structs.replace(
                base, reason="operator", by=(), reads={}, detail=self._forced_text(f)
            )
        agree = self._agreeing(now.fired, f, on)
        overruled = tuple(
            _overruled(self._report(now, k), wants, *self._beaten_now(k, agree, f, wants))
            for k, wants in self._opposing(now.fired, f, on)
        )
        return msgspec.structs.replace(base, overruled=overruled)

    def _beaten_now(
        self, k: int, agree: int | None, f: str, wants: str
    ) -> tuple[OverruleReason, str]:
        """Why action ``k``, which wants ``f`` otherwise, does not prevail now."""
        info = self._actions[k]
        forced = next((g for g in (f, *(g for _, g in info.requests)) if g in self.forced), None)
        if forced is not None:
            return "operator", self._forced_text(forced)
        wanted = f if wants == "on" else wants if wants != "off" else None
        if wanted is not None and wanted in self.unavailable:
            return "unavailable", f"{wanted} is unavailable: {self.unavailable[wanted]}"
        if agree is not None and agree > k:
            return self._later(k, agree)
        _, refusals = apply_requests(self.fm, self.deployment, self.selection, info.requests)
        if refusals:
            return "refused", refusals[0][1]
        return "waiting", _WAITING

    def _cv_now(self, now: _Now, key: str) -> Why:
        i = next(i for i, c in enumerate(self._cvs) if c.key == key)
        c, requested, value = self._cvs[i], self._requested[i], self._effective[i]
        base = self._standing_why(key, "cv", "-" if value is None else f"{value:g}")
        sets = [k for k in self._cv_actions[i] if k in now.fired]
        reports = [self._report(now, k) for k in sets]
        overruled = [
            _overruled(f, _value_text(f.value), *self._later(k, sets[-1]))
            for k, f in zip(sets[:-1], reports, strict=False)
        ]
        if reports and reports[-1].value != requested:
            last = reports[-1]
            overruled.append(_overruled(last, _value_text(last.value), "waiting", _WAITING))
        limit = limiting(c, requested, self.deployment | self.selection)
        standing = reports[-1] if reports else self._standing(key)
        if limit is not None and requested is not None and standing is not None:
            kind: OverruleReason = "bounds" if limit[0] in ("lower", "upper") else "nfr"
            text = self._limit_text(c, requested, limit)
            overruled.append(_overruled(standing, _value_text(requested), kind, text))
        return msgspec.structs.replace(base, overruled=tuple(overruled))

    def _standing_why(self, target: str, kind: Literal["feature", "cv"], value: str) -> Why:
        """The provenance of ``target`` if it still holds, else since the engine began."""
        why = self.provenance.get(target)
        if why is not None and why.value == value:
            return why
        return Why(target=target, kind=kind, value=value, reason=self._origin)


_UNSEEN = object()
_RECORD_KIND = {"feature": "feature", "group": "alternative", "attribute": "attribute"}


def feature_families(fm: FeatureModel) -> dict[str, object]:
    """Run-time feature -> its family: the features one request on it can change (see
    `request_families`); requests on different families never interact."""
    return request_families(fm)


def request_families(fm: FeatureModel) -> dict[str, object]:
    """Run-time features grouped so that requests in different groups cannot interact.

    `apply_requests` changes the requested feature, its subtree, its run-time ancestors and
    their siblings in groups with bounds; constraints only reject, never add. So a request
    changes only its family: the topmost run-time ancestor T, or T's group when that group
    has bounds between its children (alternative, or, cardinality); mandatory and optional
    siblings of T never change. Whether a request is accepted also depends on the features
    its constraints name, so families linked by a constraint are merged.
    """
    out: dict[str, object] = {}
    for name in fm.features:
        if fm.binding[name] != "runtime":
            continue
        top = name
        while (p := fm.parent[top]) is not None and fm.binding[p] == "runtime":
            top = p
        group = fm.group_of.get(top)
        independent = group is None or group.kind in ("mandatory", "optional")
        out[name] = top if independent else ("group", fm.parent[top], id(group))
    merged: dict[object, object] = {}

    def find(x: object) -> object:
        while merged.get(x, x) != x:
            x = merged[x]
        return x

    for c in fm.constraints:
        linked = {find(out[n]) for n in _constrained([c], fm) if n in out}
        first, *rest = sorted(linked, key=repr) or [None]
        for other in rest:
            merged[other] = first
    return {name: find(fam) for name, fam in out.items()}


def _constrained(constraints: Iterable[Constraint], fm: FeatureModel) -> set[str]:
    """The features the given cross-tree constraints name (canonical names)."""
    return {
        name
        for c in constraints
        for r in refs(c.expr)
        if (name := fm.resolve_name(r.name)) is not None
    }


def _leaf_groups(fm: FeatureModel) -> dict[str, tuple[int, str]]:
    """Run-time leaves of exclusive (alternative, at-most-one) groups none of whose members a
    constraint names (so switching among them is never rejected): (group id, parent)."""
    constrained = _constrained(fm.constraints, fm)
    out: dict[str, tuple[int, str]] = {}
    for name, feature in fm.features.items():
        group, parent = fm.group_of.get(name), fm.parent[name]
        if fm.binding[name] != "runtime" or feature.groups or group is None or parent is None:
            continue
        exclusive = group.kind == "alternative" or (
            group.kind == "cardinality" and group.upper == 1
        )
        if exclusive and not any(c.name in constrained for c in group.children):
            out[name] = (id(group), parent)
    return out


def _free_leaves(fm: FeatureModel) -> dict[str, str]:
    """Run-time leaves of optional groups that no constraint names -> their parent (so
    (de)activating them under a selected parent is never rejected)."""
    constrained = _constrained(fm.constraints, fm)
    return {
        name: fm.parent[name]  # type: ignore[misc]
        for name, feature in fm.features.items()
        if fm.binding[name] == "runtime"
        and not feature.groups
        and name not in constrained
        and (g := fm.group_of.get(name)) is not None
        and g.kind == "optional"
    }


def _supersedes(
    request: Request,
    earlier: Request,
    leaf_group: dict[str, tuple[int, str]],
    free: dict[str, str],
    active: tuple[frozenset[str], frozenset[str]],
) -> bool:
    """Whether ``request`` makes ``earlier`` (the one before it, run on the current state)
    irrelevant to the final selection.

    Both act on unconstrained leaves under a selected parent, so neither selects ancestors,
    completes subtrees or can be rejected: ``activate A; activate B`` on leaves of one
    exclusive group ends exactly as ``activate B``, and a request on a leaf of an optional
    group is undone or repeated by a later one on the same leaf.
    """
    (kind, f), (pkind, pf) = request, earlier
    runtime, deployment = active
    if f == pf:
        parent = free.get(f)
        return parent is not None and (parent in runtime or parent in deployment)
    g = leaf_group.get(f)
    return (
        kind == pkind == "activate"
        and g is not None
        and g == leaf_group.get(pf)
        and (g[1] in runtime or g[1] in deployment)
    )


def _recent(now: float, stamp: Any, max_age_ms: float) -> bool:
    """Whether a sample stamped ``stamp`` (s) is at most ``max_age_ms`` old at ``now``."""
    try:
        return (now - stamp) * 1000.0 <= max_age_ms
    except TypeError:  # not a time: treat the sample as unusable
        return False


def _wanted(key: ClaimKey, value: str, f: FiredRule) -> str:
    """What a claim wants, for people: on/off, an alternative, or the CV value computed."""
    if key[0] == "attribute":
        return "undefined" if f.value is None else f"{f.value:g}"
    return value


def _rejected(
    report: FiredRule, reason: str, unavailable: str = "", *, forced: str = ""
) -> Rejected:
    return Rejected(
        rule=report.rule,
        action=report.action,
        reason=reason,
        span=report.span,
        unavailable=unavailable,
        forced=forced,
    )


#: `_select`'s trace: a change made by enforcing operators' forced features, or by leaving
#: unavailable features (the others are fired actions' positions).
_OPERATOR = -1
_UNAVAILABLE = -2


@dataclass(slots=True)
class _Tick:
    """What `AdaptationEngine._explain` needs of one tick."""

    now: float
    measurements: Mapping[str, Sample]
    before: frozenset[str]
    cv_before: list[float | None]
    requested_before: list[float | None]
    #: The fired actions (their indices) and the values the set actions computed.
    fired: frozenset[int]
    V: list[Any]
    refused: dict[tuple[str, str, Span | None], Rejected] | None = None


@dataclass(slots=True)
class _Now:
    """A dry evaluation for `AdaptationEngine.why`: the actions that fire, their values."""

    fired: frozenset[int]
    V: list[Any]


_WAITING = "not applied yet: its rule runs on its period or on new measurements"


def _traced(
    trace: list[tuple[int, list[str]]] | None,
    who: int,
    before: frozenset[str],
    after: frozenset[str],
) -> frozenset[str]:
    """``after``; the features that differ from ``before`` go to ``trace`` as ``who``'s."""
    if trace is not None and after != before:
        trace.append((who, sorted(after ^ before)))
    return after


def _key(r: FiredRule | Rejected) -> tuple[str, str, Span | None]:
    return (r.rule, r.action, r.span)


def _reads(by: Iterable[FiredRule], measurements: Mapping[str, Sample]) -> dict[str, Any]:
    """The samples (value, stamp) the actions ``by`` read."""
    return {n: tuple(measurements[n]) for f in by for n in f.reads if n in measurements}


def _value_text(value: float | None) -> str:
    return "undefined" if value is None else f"{value:g}"


def _rule_name(f: FiredRule) -> str:
    return f.rule if f.ruleset is None else f"{f.ruleset}.{f.rule}"


def _overruled(f: FiredRule, wants: str, why: OverruleReason, detail: str) -> Overruled:
    return Overruled(
        rule=f.rule,
        action=f.action,
        span=f.span,
        ruleset=f.ruleset,
        wants=wants,
        why=why,
        detail=detail,
    )


def _due(timed: list[_RuleSchedule], now: float) -> bool:
    """Whether a rule with ``period N ms`` (N > 0) is due: N ms after its last run."""
    return any(r.last is None or now - r.last >= r.period - 1e-9 for r in timed)  # type: ignore[operator]


__getattr__ = _compat.renamed(__name__)  # old names, for one release (docs/api.md)
