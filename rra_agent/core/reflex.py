"""Reflexes, the pure part: which decisions of the rules a node may take ahead of the engines.

A *reflex* is a decision the engines have already planned, compiled into the node that has
to switch: a condition over measurements computed from one node's output, evaluated by the
node on each sample, and the switch it makes (rewires, activations). The engines stay the
authority: they decide on the same context as always, find the switch done and confirm it,
or roll it back (`rra_agent.engines.reflexes`). This module answers the static questions:

- `condition_of`: a branch's guard (its condition and the negation of the conditions before
  it in its if/else chain) as a disjunction of conjunctions of `Test`s ``measurement op
  constant``, or `NotEligible` when it reads anything else (a CV value, arithmetic over a
  measurement). CIM/NFR values, bounds and literals are folded as the engine folds them.
- `holds`: the condition on computed values. A measurement that is missing or NaN makes it
  false: where the engine's Kleene logic is undefined, the reflex never fires (the engines
  still decide; the reflex only ever does less than they would).
- `candidates`: the branches of the Adaptation Model whose decision may be delegated: the rule
  is not ``reflex off``, is evaluated on every new sample (no ``period`` > 0), its branch
  only (de)activates features, its guard reads measurements of one source interface only
  (each computed from that one interface), and the static conflict analysis
  (`rra_agent.core.conflicts`) shows that no other rule whose guard can hold together with
  it acts on the features of its family (the features one request can change, linked by
  constraints): no other rule, and no other priority of its rule set, can overturn it.

What the branch would change in the *current* configuration (operators' overrides,
unavailable implementations, NFRs, the resulting plan) is the engines' question, asked each
time the configuration changes. Pure: no I/O, no clock.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from rra_agent.core.conflicts import (
    NOT_CONSTANT,
    compare_constants,
    constant_value,
    may_fire_together,
    rule_effects,
)
from rra_agent.models.adaptation import (
    Activate,
    AdaptationModel,
    Bool,
    Compare,
    Deactivate,
    Expr,
    Logic,
    Measure,
    Not,
    Rule,
    SelectVariant,
)
from rra_agent.models.features import FeatureModel
from rra_agent.models.measurements import MeasurementsModel

#: Guards larger than this (clauses of the disjunction) are not compiled.
MAX_CLAUSES = 64

_NEGATE = {"==": "!=", "!=": "==", "<": ">=", ">=": "<", "<=": ">", ">": "<="}
_FLIP = {"==": "==", "!=": "!=", "<": ">", ">": "<", "<=": ">=", ">=": "<="}
_OPS: dict[str, Callable[[Any, Any], bool]] = {
    "==": operator.eq,
    "!=": operator.ne,
    "<": operator.lt,
    "<=": operator.le,
    ">": operator.gt,
    ">=": operator.ge,
}


class NotEligible(Exception):
    """Why a rule's decision cannot be a reflex (the message says it)."""


@dataclass(frozen=True)
class Test:
    """``measurement op value``."""

    measurement: str
    op: str
    value: bool | int | float | str


#: A disjunction of conjunctions: it holds when every test of some clause holds.
Condition = tuple[tuple[Test, ...], ...]
TRUE: Condition = ((),)
FALSE: Condition = ()


# ---- the condition ---------------------------------------------------------------------------
def condition_of(guard: Sequence[tuple[Expr, bool]], fm: FeatureModel) -> Condition:
    """The guard (conditions with their polarity, all of which must hold) as a `Condition`;
    `NotEligible` when it reads more than measurements compared with constants."""
    result = TRUE
    for expr, positive in guard:
        result = _and(result, _dnf(expr, positive, fm))
    return result


def _and(a: Condition, b: Condition) -> Condition:
    if len(a) * len(b) > MAX_CLAUSES:
        raise NotEligible(f"its condition has more than {MAX_CLAUSES} cases")
    return tuple((*x, *y) for x in a for y in b)


def _or(a: Condition, b: Condition) -> Condition:
    if len(a) + len(b) > MAX_CLAUSES:
        raise NotEligible(f"its condition has more than {MAX_CLAUSES} cases")
    return a + b


def _dnf(expr: Expr, positive: bool, fm: FeatureModel) -> Condition:
    match expr:
        case Not(operand=o):
            return _dnf(o, not positive, fm)
        case Logic(op=op, left=left, right=right):
            a, b = _dnf(left, positive, fm), _dnf(right, positive, fm)
            return _and(a, b) if (op == "and") == positive else _or(a, b)
        case Compare():
            return _compare(expr, positive, fm)
        case Bool(value=v):
            return TRUE if v == positive else FALSE
        case Measure(name=n, type="bool"):
            return ((Test(n, "==", positive),),)
    value = constant_value(expr, fm)
    if isinstance(value, bool):
        return TRUE if value == positive else FALSE
    raise NotEligible(f"its condition reads {_what(expr)}")


def _compare(cmp: Compare, positive: bool, fm: FeatureModel) -> Condition:
    left, right = constant_value(cmp.left, fm), constant_value(cmp.right, fm)
    if left is not NOT_CONSTANT and right is not NOT_CONSTANT:
        value = compare_constants(cmp.op, left, right)
        # Undefined: the engine fires neither this branch nor the ones after it.
        return FALSE if value is None or value != positive else TRUE
    op = cmp.op if positive else _NEGATE[cmp.op]
    var, const = cmp.left, right
    if left is not NOT_CONSTANT:
        var, const, op = cmp.right, left, _FLIP[op]
    if not isinstance(var, Measure) or var.type is None:
        raise NotEligible(f"its condition reads {_what(var)}")
    if const is NOT_CONSTANT:
        raise NotEligible(f"its condition compares {var.name} with {_what(cmp.right)}")
    if const is None:
        return FALSE  # compared with something undefined: never fires
    assert isinstance(const, bool | int | float | str)
    return ((Test(var.name, op, const),),)


def _what(expr: Expr) -> str:
    """An expression, for a reason: what it reads."""
    name = type(expr).__name__.lower()
    labels = {
        "attrvalue": "an attribute's value (a CV changes at run time)",
        "arith": "arithmetic",
        "call": "a function call",
        "neg": "arithmetic",
        "measure": "a measurement of unknown type",
    }
    return labels.get(name, name)


def reads(condition: Condition) -> tuple[str, ...]:
    """The measurements a condition reads, in order."""
    return tuple(dict.fromkeys(t.measurement for clause in condition for t in clause))


def holds(condition: Condition, values: Mapping[str, Any]) -> bool:
    """Whether ``condition`` holds for these measurement values; false when one it reads is
    missing or NaN (where the engine's logic would be undefined, the reflex stays put)."""
    for name in reads(condition):
        v = values.get(name)
        if v is None or (isinstance(v, float) and math.isnan(v)):
            return False
    return any(all(_test(t, values[t.measurement]) for t in clause) for clause in condition)


def _test(t: Test, value: Any) -> bool:
    try:
        return bool(_OPS[t.op](value, t.value))
    except TypeError:
        return False


# ---- which branches may be reflexes ----------------------------------------------------------
@dataclass(frozen=True)
class Candidate:
    """A branch whose decision may be delegated, with its compiled condition."""

    rule: Rule
    ruleset: str | None
    branch: int
    condition: Condition
    #: The source interface (``component.port``) its measurements are computed from.
    source: str
    measurements: tuple[str, ...]

    @property
    def label(self) -> str:
        return self.rule.name if self.ruleset is None else f"{self.ruleset}.{self.rule.name}"


def candidates(
    model: AdaptationModel,
    fm: FeatureModel,
    measurements: MeasurementsModel,
    families: Mapping[str, object],
) -> tuple[list[Candidate], dict[str, str]]:
    """The branches that may be reflexes, and why each other rule (``rule`` or
    ``rule[branch]``) may not. ``families``: run-time feature -> its family (the features a
    request on it can change, `rra_agent.core.adaptation`)."""
    effects = rule_effects(model, fm)
    out: list[Candidate] = []
    why: dict[str, str] = {}
    for ruleset, rules in model.units():
        for rule in rules:
            for b in range(len(rule.branches)):
                key = rule.name if len(rule.branches) == 1 else f"{rule.name}[{b}]"
                try:
                    out.append(_candidate(rule, ruleset.name if ruleset else None, b, fm,
                                          measurements, effects, families))  # fmt: skip
                except NotEligible as e:
                    why[key] = str(e)
    return out, why


def _candidate(
    rule: Rule,
    ruleset: str | None,
    b: int,
    fm: FeatureModel,
    measurements: MeasurementsModel,
    effects: list[Any],
    families: Mapping[str, object],
) -> Candidate:
    if not rule.reflex:
        raise NotEligible("reflex off")
    if rule.period_ms:
        raise NotEligible(f"evaluated every {rule.period_ms:g} ms, not on each new sample")
    branch = rule.branches[b]
    if not branch.actions or not all(
        isinstance(a, Activate | Deactivate | SelectVariant) for a in branch.actions
    ):
        raise NotEligible("it sets an attribute (only feature changes are reflexes)")
    guard = [(c.condition, False) for c in rule.branches[:b] if c.condition is not None]
    if branch.condition is not None:
        guard.append((branch.condition, True))
    condition = condition_of(guard, fm)
    names = reads(condition)
    if not names:
        raise NotEligible("its condition reads no measurement")
    source = _one_source(names, measurements)
    _not_overturned(rule, b, fm, effects, families)
    return Candidate(rule, ruleset, b, condition, source, names)


def _one_source(names: tuple[str, ...], model: MeasurementsModel) -> str:
    """The one interface every measurement of ``names`` is computed from."""
    sources = set()
    for name in names:
        meas = next((x for x in model.measurements if x.name == name), None)
        if meas is None or len(meas.inputs) != 1:
            raise NotEligible(f"measurement {name} is not computed from one node's output")
        sources.add(meas.inputs[0])
    if len(sources) != 1:
        outputs = ", ".join(sorted(sources))
        raise NotEligible(f"its measurements come from several outputs ({outputs})")
    return sources.pop()


def _not_overturned(
    rule: Rule, b: int, fm: FeatureModel, effects: list[Any], families: Mapping[str, object]
) -> None:
    """`NotEligible` naming a rule that may act on the family of this branch's features in
    the same tick (its guard not proved disjoint from this one's)."""
    ours = [e for e in effects if e.rule is rule and e.branch == b]
    mine = {families[name] for e in ours for (kind, name), _ in e.claims if kind == "feature"}
    for other in effects:
        if other.rule is rule:
            continue  # its other branches are disjoint from this one by construction
        theirs = {families[n] for (kind, n), _ in other.claims if kind == "feature"}
        if not theirs & mine:
            continue
        if any(may_fire_together(o, other, fm) for o in ours):
            who = other.rule.name if other.ruleset is None else f"{other.ruleset}.{other.rule.name}"
            raise NotEligible(f"rule {who} may overturn it ({other.text})")
