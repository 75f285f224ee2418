"""Feature-model semantics (paper Sec. II, III-B and III-D), pure and deterministic.

A *selection* is a set of feature names. It is valid when the root is selected, every selected
feature's parent is selected (so unselected features have no selected children), every group
of a selected feature has a number of selected children within `Group.bounds`, and every
propositional cross-tree constraint holds (a reference is true iff selected; constraints with
comparisons, arithmetic or imported names are kept in the model but not enforced, see
`FeatureModel.boolean_constraints`).

Binding times split the selection in two. *Deployment-time* features are fixed once by the
deployment-time selection (`complete_deployment`); *run-time* features are chosen by the
Adaptation Engine while the system runs, and only those whose deployment-time ancestors are
selected and that the constraints allow can be (`selectable_runtime`). The engine starts from
`default_runtime_selection` and turns its rules' ``activate_feature`` / ``deactivate_feature``
actions into a new valid selection with `apply_requests`, rejecting (with a reason) every
request that would break the model.

Internally features are numbered in the model's depth-first pre-order, so a subtree is a
contiguous range. Selections with unknowns use Kleene three-valued logic (True, False, None).
Searches for a valid completion are a small DPLL (unit propagation over parent/child rules,
group bounds and constraints, then chronological backtracking in model order) capped at
`SEARCH_BUDGET` conflicts: exact for every model of practical size, and when a search hits the
cap the answer is the safe one (a feature is reported not selectable, a request is rejected).
Everything derived from a model or a deployment selection is computed once and cached.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Collection, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Literal

from rra_agent.errors import SelectionError
from rra_agent.models.features import And, Equiv, Expr, FeatureModel, Implies, Not, Or, Ref

__all__ = [
    "SEARCH_BUDGET",
    "Request",
    "Violation",
    "apply_requests",
    "check_selection",
    "complete_deployment",
    "default_runtime_selection",
    "selectable_runtime",
]

Request = tuple[Literal["activate", "deactivate"], str]
Tri = bool | None

#: Conflicts a completion search may hit before it gives up (and answers the safe way).
SEARCH_BUDGET = 10_000


@dataclass(frozen=True)
class Violation:
    """One broken rule of the feature model, as a human sentence.

    `feature` is the feature the problem is about (the child for a parent rule, the parent for
    a group bound, the missing feature for a mandatory child); None for cross-tree constraints
    and unknown names.
    """

    feature: str | None
    message: str

    def __str__(self) -> str:
        return self.message


# ---- compiled model ------------------------------------------------------------------------

_REF, _NOT, _AND, _OR, _IMP, _EQV, _FALSE = range(7)
_PREC: dict[type, int] = {Equiv: 1, Implies: 2, Or: 3, And: 4, Not: 5, Ref: 6}
_OPS: dict[type, str] = {Equiv: "<=>", Implies: "=>", Or: "|", And: "&"}
_IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


@dataclass(frozen=True, slots=True)
class _Group:
    parent: int
    label: str  # "alternative group", "[1..2] group", ...
    mandatory: bool
    lo: int
    hi: int  # an unbounded upper bound is the number of children
    upper: int | None
    children: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class _Constraint:
    expr: tuple
    refs: tuple[int, ...]  # distinct, in order of appearance
    text: str
    where: str
    unknown: tuple[str, ...]  # references to features the model does not have


def _quote(name: str) -> str:
    return name if _IDENT.fullmatch(name) else f'"{name}"'


def _format(expr: Expr) -> str:
    """UVL text of a constraint, with only the parentheses precedence needs."""
    match expr:
        case Ref(name=n):
            return _quote(n)
        case Not(operand=o):
            inner = _format(o)
            return "!" + (inner if _PREC[type(o)] >= _PREC[Not] else f"({inner})")
        case (
            And(left=a, right=b)
            | Or(left=a, right=b)
            | Implies(left=a, right=b)
            | Equiv(left=a, right=b)
        ):
            op = type(expr)
            return f"{_operand(a, op)} {_OPS[op]} {_operand(b, op)}"
    raise TypeError(f"not a constraint expression: {expr!r}")


def _operand(e: Expr, op: type) -> str:
    """An operand of a binary operator, parenthesised unless precedence makes it unambiguous
    (``&`` and ``|`` chain with themselves)."""
    text = _format(e)
    inner, outer = _PREC[type(e)], _PREC[op]
    bare = inner > outer or (inner == outer and op in (And, Or))
    return text if bare else f"({text})"


def _compile(expr: Expr, lookup: Callable[[str], int | None], unknown: list[str]) -> tuple:
    match expr:
        case Ref(name=n):
            i = lookup(n)
            if i is None:
                unknown.append(n)
                return (_FALSE,)
            return (_REF, i)
        case Not(operand=o):
            return (_NOT, _compile(o, lookup, unknown))
        case And(left=a, right=b):
            return (_AND, _compile(a, lookup, unknown), _compile(b, lookup, unknown))
        case Or(left=a, right=b):
            return (_OR, _compile(a, lookup, unknown), _compile(b, lookup, unknown))
        case Implies(left=a, right=b):
            return (_IMP, _compile(a, lookup, unknown), _compile(b, lookup, unknown))
        case Equiv(left=a, right=b):
            return (_EQV, _compile(a, lookup, unknown), _compile(b, lookup, unknown))
    raise TypeError(f"not a constraint expression: {expr!r}")


def _compiled_refs(e: tuple) -> Iterable[int]:
    if e[0] == _REF:
        yield e[1]
    else:
        for sub in e[1:]:
            yield from _compiled_refs(sub)


def _kleene(e: tuple, val: Sequence[Tri]) -> Tri:
    """Kleene three-valued value of a compiled expression (None: cannot tell yet)."""
    op = e[0]
    if op == _REF:
        return val[e[1]]
    if op == _FALSE:
        return False
    a = _kleene(e[1], val)
    if op == _NOT:
        return None if a is None else not a
    if op == _AND:
        if a is False:
            return False
        b = _kleene(e[2], val)
        return False if b is False else (True if a and b else None)
    if op == _OR:
        if a is True:
            return True
        b = _kleene(e[2], val)
        return True if b is True else (False if a is False and b is False else None)
    if op == _IMP:
        if a is False:
            return True
        b = _kleene(e[2], val)
        return True if b is True else (False if a is True and b is False else None)
    b = _kleene(e[2], val)
    return None if a is None or b is None else a == b


def _group_label(kind: str, lo: int, upper: int | None) -> str:
    if kind == "cardinality":
        return f"[{lo}..{'*' if upper is None else upper}] group"
    return f"{kind} group"


class _Index:
    """A feature model numbered in pre-order, with the relations the algorithms walk."""

    def __init__(self, fm: FeatureModel) -> None:
        self.fm = fm
        self.names: tuple[str, ...] = tuple(fm.features)
        n = len(self.names)
        pos = {name: i for i, name in enumerate(self.names)}
        self.lookup_table = {**{a: pos[t] for a, t in fm.aliases.items() if t in pos}, **pos}
        self.parent = tuple(pos[p] if (p := fm.parent[m]) is not None else -1 for m in self.names)
        self.runtime = tuple(fm.binding[m] == "runtime" for m in self.names)
        self.default = tuple(fm.features[m].default for m in self.names)
        self.children = tuple(
            tuple(pos[c.name] for c in fm.features[m].children) for m in self.names
        )
        self.end = self._subtree_ends(n)
        self.groups, self.group_of, self.child_groups = self._groups(fm, pos)
        self.constraints = tuple(self._constraint(c.expr, c.span) for c in fm.boolean_constraints)
        cons_of: list[list[int]] = [[] for _ in range(n)]
        for k, c in enumerate(self.constraints):
            for r in c.refs:
                cons_of[r].append(k)
        self.cons_of = tuple(tuple(k) for k in cons_of)
        self.contexts: dict[frozenset[str], _Context] = {}

    def _groups(
        self, fm: FeatureModel, pos: dict[str, int]
    ) -> tuple[tuple[_Group, ...], tuple[int, ...], tuple[tuple[int, ...], ...]]:
        """Every group; the group each feature is in (-1: root); each feature's groups."""
        groups: list[_Group] = []
        group_of = [-1] * len(self.names)
        child_groups: list[tuple[int, ...]] = []
        for i, m in enumerate(self.names):
            mine = []
            for g in fm.features[m].groups:
                lo, upper = g.bounds
                kids = tuple(pos[c.name] for c in g.children)
                hi = len(kids) if upper is None else upper
                for c in kids:
                    group_of[c] = len(groups)
                mine.append(len(groups))
                label = _group_label(g.kind, lo, upper)
                groups.append(_Group(i, label, g.kind == "mandatory", lo, hi, upper, kids))
            child_groups.append(tuple(mine))
        return tuple(groups), tuple(group_of), tuple(child_groups)

    def _subtree_ends(self, n: int) -> tuple[int, ...]:
        end = list(range(1, n + 1))
        for i in range(n - 1, 0, -1):
            p = self.parent[i]
            end[p] = max(end[p], end[i])
        return tuple(end)

    def _constraint(self, expr: Expr, span: object) -> _Constraint:
        unknown: list[str] = []
        compiled = _compile(expr, self.lookup, unknown)
        refs = tuple(dict.fromkeys(_compiled_refs(compiled)))
        where = f" [{span.location()}]" if span is not None else ""  # type: ignore[attr-defined]
        return _Constraint(compiled, refs, _format(expr), where, tuple(dict.fromkeys(unknown)))

    def lookup(self, name: str) -> int | None:
        return self.lookup_table.get(name)

    def subtree(self, v: int) -> range:
        return range(v, self.end[v])


_INDEXES: dict[int, tuple[FeatureModel, _Index]] = {}
_CACHE_SIZE = 32


def _index(fm: FeatureModel) -> _Index:
    """The compiled form of `fm`, cached (the entry keeps `fm` alive, so its id stays unique)."""
    hit = _INDEXES.get(id(fm))
    if hit is not None and hit[0] is fm:
        return hit[1]
    idx = _Index(fm)
    if len(_INDEXES) >= _CACHE_SIZE:
        _INDEXES.clear()
    _INDEXES[id(fm)] = (fm, idx)
    return idx


def _names(value: Iterable[str], what: str) -> Iterable[str]:
    if isinstance(value, str):
        raise TypeError(f"{what} must be a collection of feature names, not a string")
    return value


# ---- violations -------------------------------------------------------------------------------


def _bound_text(g: _Group) -> str:
    if g.upper is not None and g.lo == g.upper:
        return f"exactly {g.lo}"
    if g.upper is None or g.upper >= len(g.children):
        return f"at least {g.lo}"
    if g.lo == 0:
        return f"at most {g.upper}"
    return f"between {g.lo} and {g.upper}"


def _group_violations(idx: _Index, g: _Group, val: Sequence[Tri]) -> Iterable[Violation]:
    parent = idx.names[g.parent]
    if g.mandatory:
        for c in g.children:
            if val[c] is False:
                missing = idx.names[c]
                msg = f"mandatory feature {missing} is not selected though its parent {parent} is"
                yield Violation(missing, msg)
        return
    chosen = [idx.names[c] for c in g.children if val[c] is True]
    undecided = sum(val[c] is None for c in g.children)
    t = len(chosen)
    listed = f" ({', '.join(chosen)})" if chosen else ""
    head = f"{g.label} of {parent} has {t} selected children{listed}"
    if t > g.hi:
        yield Violation(parent, f"{head}; {_bound_text(g)} allowed")
    elif t + undecided < g.lo:
        more = f" and {undecided} undecided" if undecided else ""
        yield Violation(parent, f"{head}{more}; {_bound_text(g)} required")


def _constraint_violation(idx: _Index, c: _Constraint, val: Sequence[Tri]) -> Violation:
    state = {True: "selected", False: "not selected", None: "undecided"}
    details = ", ".join(f"{idx.names[r]} {state[val[r]]}" for r in c.refs)
    return Violation(None, f"constraint {c.text} is violated ({details}){c.where}")


def _violations(idx: _Index, val: Sequence[Tri], unknown: Iterable[str] = ()) -> list[Violation]:
    """Every rule of the model `val` certainly breaks (None values are undecided)."""
    out = [Violation(None, f"unknown feature {name!r}") for name in dict.fromkeys(unknown)]
    for c in idx.constraints:
        if c.unknown:
            names = ", ".join(repr(u) for u in c.unknown)
            out.append(Violation(None, f"constraint {c.text} refers to unknown feature {names}"))
    if val[0] is False:
        out.append(_unrooted(idx))
    for v, x in enumerate(val):
        if x is not True:
            continue
        p = idx.parent[v]
        if p >= 0 and val[p] is False:
            out.append(_orphan(idx, v))
        for g in idx.child_groups[v]:
            out.extend(_group_violations(idx, idx.groups[g], val))
    for c in idx.constraints:
        if _kleene(c.expr, val) is False:
            out.append(_constraint_violation(idx, c, val))
    return out


def _local_violations(idx: _Index, val: Sequence[Tri], changed: Iterable[int]) -> list[Violation]:
    """The violations of the rules touching `changed` (all of them, if the rest was valid)."""
    out: list[Violation] = []
    groups: dict[int, None] = {}
    cons: dict[int, None] = {}
    for c in sorted(changed):
        p = idx.parent[c]
        if val[c] and p >= 0 and not val[p]:
            out.append(_orphan(idx, c))
        if not val[c]:
            if p < 0:
                out.append(_unrooted(idx))
            out.extend(_orphan(idx, k) for k in idx.children[c] if val[k])
        if p >= 0:
            groups[idx.group_of[c]] = None
        groups.update(dict.fromkeys(idx.child_groups[c]))
        cons.update(dict.fromkeys(idx.cons_of[c]))
    for g in groups:
        if val[idx.groups[g].parent]:
            out.extend(_group_violations(idx, idx.groups[g], val))
    for k in cons:
        if _kleene(idx.constraints[k].expr, val) is False:
            out.append(_constraint_violation(idx, idx.constraints[k], val))
    return out


def _unrooted(idx: _Index) -> Violation:
    return Violation(idx.names[0], f"root feature {idx.names[0]} must always be selected")


def _orphan(idx: _Index, v: int) -> Violation:
    p = idx.names[idx.parent[v]]
    return Violation(idx.names[v], f"{idx.names[v]} is selected but its parent {p} is not")


def check_selection(
    fm: FeatureModel, selected: Collection[str], *, undecided: Collection[str] = ()
) -> list[Violation]:
    """Every way `selected` breaks the feature model, explained (empty: the selection is valid).

    Names may be aliases; unknown names are reported. Features in `undecided` may still go
    either way (a name in both sets counts as selected): constraints are evaluated with Kleene
    three-valued logic and group sizes as intervals, and only certain violations are reported,
    one rule at a time. So a deployment-time selection is checked with ``undecided`` = the
    run-time features.
    """
    idx = _index(fm)
    val: list[Tri] = [False] * len(idx.names)
    unknown: list[str] = []
    for names, value in ((undecided, None), (selected, True)):
        for name in _names(names, "a selection"):
            i = idx.lookup(name)
            if i is None:
                unknown.append(name)
            else:
                val[i] = value
    return _violations(idx, val, unknown)


# ---- completion search --------------------------------------------------------------------


class _BudgetExceeded(Exception):
    """A completion search hit `SEARCH_BUDGET`."""


Prefer = Callable[[_Index, Sequence[Tri], int], bool]


def _prefer_default(idx: _Index, val: Sequence[Tri], v: int) -> bool:
    """Select `v` only if its group still needs children: defaults first, then model order."""
    g = idx.groups[idx.group_of[v]]
    chosen = open_defaults = 0
    for c in g.children:
        x = val[c]
        if x:
            chosen += 1
        elif x is None and c != v and idx.default[c]:
            open_defaults += 1
    need = g.lo - chosen
    return need > 0 and (idx.default[v] or need > open_defaults)


class _Search:
    """DPLL over the `free` features (pre-order); every other value in `val` is fixed.

    Every rule that mentions a free feature is enforced (parent rule, group bounds,
    constraints); rules among fixed features only are the caller's business.
    """

    def __init__(self, idx: _Index, val: list[Tri], free: Sequence[int]) -> None:
        self.idx, self.val, self.free = idx, val, free
        self.trail: list[int] = []
        self.queue: list[int] = []

    def assign(self, v: int, value: bool) -> bool:
        current = self.val[v]
        if current is None:
            self.val[v] = value
            self.trail.append(v)
            self.queue.append(v)
            return True
        return current == value

    def group(self, gi: int) -> bool:
        g, val = self.idx.groups[gi], self.val
        chosen = sum(val[c] is True for c in g.children)
        open_ = sum(val[c] is None for c in g.children)
        feasible = chosen <= g.hi and chosen + open_ >= g.lo
        if val[g.parent] is None:
            return feasible or self.assign(g.parent, False)
        if not val[g.parent] or not open_:
            return feasible or not val[g.parent]
        if not feasible:
            return False
        if chosen == g.hi or chosen + open_ == g.lo:
            fill = chosen < g.hi
            return all(self.assign(c, fill) for c in g.children if val[c] is None)
        return True

    def constraint(self, k: int) -> bool:
        c, val = self.idx.constraints[k], self.val
        result = _kleene(c.expr, val)
        if result is not None:
            return result
        for r in c.refs:  # failed-literal lookahead on each undecided reference
            if val[r] is not None:
                continue
            val[r] = True
            if_true = _kleene(c.expr, val)
            val[r] = False
            if_false = _kleene(c.expr, val)
            val[r] = None
            if if_true is False and if_false is False:
                return False
            if (if_true is False or if_false is False) and not self.assign(r, if_true is not False):
                return False
        return True

    def touch(self, v: int) -> bool:
        """Enforce every rule around `v` (assigned or not)."""
        idx, val = self.idx, self.val
        p, x = idx.parent[v], val[v]
        if x is True and p >= 0 and not self.assign(p, True):
            return False
        if x is False and not all(self.assign(c, False) for c in idx.children[v]):
            return False
        if x is None and p >= 0 and val[p] is False and not self.assign(v, False):
            return False
        if x is None and any(val[c] for c in idx.children[v]) and not self.assign(v, True):
            return False
        groups = idx.child_groups[v] if p < 0 else (idx.group_of[v], *idx.child_groups[v])
        return all(self.group(g) for g in groups) and all(
            self.constraint(k) for k in idx.cons_of[v]
        )

    def seed(self) -> bool:
        """Enforce every rule around the free features once, then propagate."""
        idx, val = self.idx, self.val
        groups: set[int] = set()
        cons: set[int] = set()
        for v in self.free:
            if val[v] is None:
                p = idx.parent[v]
                if p >= 0 and val[p] is False and not self.assign(v, False):
                    return False
                if any(val[c] for c in idx.children[v]) and not self.assign(v, True):
                    return False
            if idx.parent[v] >= 0:
                groups.add(idx.group_of[v])
            groups.update(idx.child_groups[v])
            cons.update(idx.cons_of[v])
        ok = all(self.group(g) for g in groups) and all(self.constraint(k) for k in cons)
        return ok and self.propagate()

    def propagate(self) -> bool:
        while self.queue:
            if not self.touch(self.queue.pop()):
                self.queue.clear()
                return False
        return True

    def undo(self, mark: int) -> None:
        for v in self.trail[mark:]:
            self.val[v] = None
        del self.trail[mark:]
        self.queue.clear()

    def run(self, prefer: Prefer, assume: Iterable[int] = ()) -> bool:
        """Complete `val`; False when no completion exists. Raises `_BudgetExceeded`."""
        if not all(self.assign(v, True) for v in assume) or not self.seed():
            return False
        decisions: list[tuple[int, int, bool | None, int]] = []
        ptr, conflicts, val, free = 0, 0, self.val, self.free
        while True:
            while ptr < len(free) and val[free[ptr]] is not None:
                ptr += 1
            if ptr == len(free):
                return True
            v = free[ptr]
            first = prefer(self.idx, val, v)
            decisions.append((len(self.trail), v, not first, ptr))
            self.assign(v, first)
            while not self.propagate():
                conflicts += 1
                if conflicts > SEARCH_BUDGET:
                    raise _BudgetExceeded
                while True:
                    if not decisions:
                        return False
                    mark, dv, alt, dptr = decisions.pop()
                    self.undo(mark)
                    if alt is not None:
                        decisions.append((mark, dv, None, dptr))
                        self.assign(dv, alt)
                        ptr = dptr
                        break


def _greedy_fill(idx: _Index, val: list[Tri], free: Iterable[int]) -> None:
    """Default choices ignoring constraints: the attempt whose violations explain a failure."""
    for v in free:
        if val[v] is None:
            p = idx.parent[v]
            val[v] = p < 0 or (bool(val[p]) and _prefer_default(idx, val, v))


def _explain(idx: _Index, val: list[Tri], free: Sequence[int]) -> list[str]:
    _greedy_fill(idx, val, free)
    return [v.message for v in _violations(idx, val)]


# ---- per deployment selection -------------------------------------------------------------


_VALID_CACHE = 256


@dataclass
class _Context:
    """What a deployment-time selection fixes, and what follows from it (computed lazily)."""

    idx: _Index
    deployment: frozenset[int]
    base: list[Tri]  # deployment features fixed, free run-time features None
    free: tuple[int, ...]  # run-time features below selected deployment-time ancestors
    problems: list[Violation]  # certain violations of the deployment selection itself
    _selectable: frozenset[int] | None = None
    _default: frozenset[int] | SelectionError | None = None
    free_set: frozenset[int] = field(init=False)
    #: Run-time selections (canonical names) known to be valid under this deployment.
    _valid: dict[frozenset[str], None] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.free_set = frozenset(self.free)

    def known_valid(self, selection: frozenset[str]) -> bool:
        return selection in self._valid

    def remember_valid(self, selection: frozenset[str]) -> None:
        if len(self._valid) >= _VALID_CACHE:
            self._valid.pop(next(iter(self._valid)))  # forget the oldest
        self._valid[selection] = None

    @property
    def selectable(self) -> frozenset[int]:
        if self._selectable is None:
            self._selectable = _compute_selectable(self)
        return self._selectable

    @property
    def default(self) -> frozenset[int]:
        if self._default is None:
            try:
                self._default = _compute_default(self)
            except SelectionError as e:
                self._default = e
        if isinstance(self._default, SelectionError):
            err = self._default
            raise SelectionError(err.args[0].split("\n", 1)[0], err.reasons)
        return self._default

    def names(self, ints: Iterable[int]) -> frozenset[str]:
        return frozenset(self.idx.names[i] for i in ints)


def _context(fm: FeatureModel, deployment: Collection[str]) -> _Context:
    idx = _index(fm)
    key = frozenset(_names(deployment, "a deployment selection"))
    ctx = idx.contexts.get(key)
    if ctx is None:
        ctx = _new_context(idx, key)
        if len(idx.contexts) >= _CACHE_SIZE:
            idx.contexts.clear()
        idx.contexts[key] = ctx
    return ctx


def _resolve_all(idx: _Index, names: Iterable[str], binding: str, what: str) -> list[int]:
    """Names or aliases to indexes; SelectionError if any is unknown or of the wrong binding."""
    out: list[int] = []
    bad: list[str] = []
    for name in names:
        i = idx.lookup(name)
        if i is None:
            bad.append(f"unknown feature {name!r}")
        elif idx.runtime[i] != (binding == "runtime"):
            bad.append(f"{name} is a {'run' if idx.runtime[i] else 'deployment'}-time feature")
        else:
            out.append(i)
    if bad:
        raise SelectionError(f"{what} must name known {binding}-time features", bad)
    return out


def _new_context(idx: _Index, names: frozenset[str]) -> _Context:
    dep = frozenset(_resolve_all(idx, sorted(names), "deployment", "a deployment selection"))
    n = len(idx.names)
    base: list[Tri] = [i in dep for i in range(n)]
    available = [False] * n
    for v in range(n):
        p = idx.parent[v]
        if idx.runtime[v]:
            available[v] = p < 0 or (available[p] if idx.runtime[p] else p in dep)
            base[v] = None if available[v] else False
    base[0] = True  # the root is always selected, whatever its binding
    free = tuple(v for v in range(1, n) if base[v] is None)
    checked: list[Tri] = [i in dep if not idx.runtime[i] else base[i] for i in range(n)]
    problems = _violations(idx, checked)
    return _Context(idx, dep, base, free, problems)


def _compute_selectable(ctx: _Context) -> frozenset[int]:
    """Run-time features some valid full selection contains, each shown by a witness.

    Witness searches prefer the features no earlier witness contained, so a few untargeted
    ones cover most features (one per alternative); every feature still unseen then gets a
    search that assumes it. Exact unless a search exceeds `SEARCH_BUDGET`, in which case its
    target is left out: the answer is always sound.
    """
    if ctx.problems:
        return frozenset()
    seen: set[int] = set()
    witness = _witness(ctx, seen, None)
    if witness is None:  # no valid selection (or none found within the budget)
        return frozenset()
    while witness is not None and not witness <= seen:
        seen |= witness
        witness = _witness(ctx, seen, None)
    for f in ctx.free:
        if f not in seen:
            seen |= _witness(ctx, seen, f) or set()
    return frozenset(seen)


def _witness(ctx: _Context, seen: set[int], target: int | None) -> set[int] | None:
    """The run-time features of a valid full selection (containing `target`), or None."""
    idx = ctx.idx
    wanted = [v in ctx.free_set and v not in seen for v in range(len(idx.names))]
    for v in range(len(wanted) - 1, 0, -1):  # children before parents
        wanted[idx.parent[v]] = wanted[idx.parent[v]] or wanted[v]

    def prefer(idx: _Index, val: Sequence[Tri], v: int) -> bool:
        if wanted[v]:
            return True
        siblings = idx.groups[idx.group_of[v]].children
        if any(wanted[c] and val[c] is None for c in siblings):
            return False  # leave room for a sibling no witness has shown yet
        return _prefer_default(idx, val, v)

    search = _Search(idx, list(ctx.base), ctx.free)
    try:
        found = search.run(prefer, () if target is None else (target,))
    except _BudgetExceeded:
        return None
    if not found:
        return None
    return {v for v, x in enumerate(search.val) if x and idx.runtime[v]}


def _compute_default(ctx: _Context) -> frozenset[int]:
    idx = ctx.idx
    if ctx.problems:
        raise SelectionError(
            "the deployment-time selection is inconsistent", [v.message for v in ctx.problems]
        )
    search = _Search(idx, list(ctx.base), ctx.free)
    try:
        found = search.run(_prefer_default)
    except _BudgetExceeded:
        raise SelectionError(
            f"no default run-time selection found within {SEARCH_BUDGET} search conflicts"
        ) from None
    if not found:
        raise SelectionError(
            "no run-time selection satisfies the feature model with this deployment selection",
            _explain(idx, list(ctx.base), ctx.free),
        )
    problems = _violations(idx, search.val)
    if problems:  # only rules among fixed features can remain, and `ctx.problems` had them
        raise SelectionError(
            "the default run-time selection is invalid", [str(p) for p in problems]
        )
    return frozenset(v for v in range(len(search.val)) if idx.runtime[v] and search.val[v])


def complete_deployment(fm: FeatureModel, partial: Iterable[str]) -> frozenset[str]:
    """Complete a deployment-time selection deterministically (run-time features stay open).

    Adds the root, the ancestors of the given features and, walking the tree in model order,
    every mandatory child and, for a group whose lower bound cannot be met otherwise (run-time
    children count as possibly selected), the first deployment-time children in model order
    whose constraints are not certainly violated. Constraints do not add features.

    Names may be aliases. Raises `SelectionError` for unknown names and run-time features, and,
    with every violation as a reason, when the completed selection is inconsistent (checked
    with the run-time features undecided).
    """
    idx = _index(fm)
    given = _resolve_all(
        idx, _names(partial, "a deployment selection"), "deployment", "a deployment-time selection"
    )
    n = len(idx.names)
    val: list[Tri] = [None] * n
    val[0] = True
    for v in given:
        a = v
        while a >= 0 and val[a] is not True:
            if idx.runtime[a]:
                raise SelectionError(
                    "a deployment-time selection cannot be completed",
                    [
                        f"{idx.names[v]} is a deployment-time feature under run-time feature "
                        f"{idx.names[a]}"
                    ],
                )
            val[a] = True
            a = idx.parent[a]
    for v in range(n):
        _decide_children(idx, val, v)
    problems = _violations(idx, val)
    if problems:
        chosen = ", ".join(idx.names[v] for v in given) or "nothing"
        raise SelectionError(
            f"the deployment-time selection ({chosen}) is inconsistent",
            [p.message for p in problems],
        )
    return frozenset(idx.names[v] for v in range(n) if val[v] and not idx.runtime[v])


def _decide_children(idx: _Index, val: list[Tri], v: int) -> None:
    """Fix the deployment-time children of `v` (visited in pre-order, so `v` is decided)."""
    if val[v] is not True or idx.runtime[v]:
        for c in idx.children[v]:
            if not idx.runtime[c]:
                val[c] = False
        return
    for gi in idx.child_groups[v]:
        g = idx.groups[gi]
        candidates = [c for c in g.children if not idx.runtime[c] and val[c] is not True]
        possible = sum(1 for c in g.children if idx.runtime[c] or val[c] is True)
        need = g.lo - possible
        if g.mandatory:
            picks = candidates
        elif need <= 0:
            picks = []
        else:
            fits = [c for c in candidates if _fits(idx, val, c)]
            picks = (fits + [c for c in candidates if c not in fits])[: max(need, 0)]
        for c in candidates:
            val[c] = c in picks


def _fits(idx: _Index, val: list[Tri], c: int) -> bool:
    val[c] = True
    ok = all(_kleene(idx.constraints[k].expr, val) is not False for k in idx.cons_of[c])
    val[c] = None
    return ok


def selectable_runtime(fm: FeatureModel, deployment: Collection[str]) -> frozenset[str]:
    """Run-time features selected in at least one valid full selection with `deployment`.

    `deployment` is a complete deployment-time selection (see `complete_deployment`); names may
    be aliases, run-time or unknown names raise `SelectionError`. Exact (a witness selection is
    found for every feature returned, and no feature is left out) unless a search exceeds
    `SEARCH_BUDGET` conflicts, when the feature is left out. Empty when the deployment selection
    admits no valid full selection. Cached per model and deployment selection.
    """
    ctx = _context(fm, deployment)
    return ctx.names(ctx.selectable)


def default_runtime_selection(fm: FeatureModel, deployment: Collection[str]) -> frozenset[str]:
    """A valid run-time selection to start from.

    Mandatory run-time features are selected; a group that needs children gets the ones with a
    ``default`` attribute first, then the first in model order; optional features stay off.
    Choices are made in model order and each must leave a valid completion (so "first" means
    first that can still lead to a valid selection). Raises `SelectionError` (with reasons)
    when no valid selection exists with this deployment selection.
    """
    ctx = _context(fm, deployment)
    return ctx.names(ctx.default)


# ---- run-time requests --------------------------------------------------------------------


def apply_requests(
    fm: FeatureModel,
    deployment: Collection[str],
    previous: Collection[str],
    requests: Sequence[Request],
    trace: list[tuple[int, list[str]]] | None = None,
) -> tuple[frozenset[str], list[tuple[int, str]]]:
    """Apply the Adaptation Engine's (de)activation requests, in order, to a run-time selection.

    `previous` is the current run-time selection (run-time features only; names may be
    aliases). Each request works on the result of the ones before it; one that cannot be
    honoured leaves the selection as it was and is reported as (its index, the reason).

    - ``activate F``: F must be a selectable run-time feature. F and its unselected ancestors
      are selected; their siblings in alternative groups (in ``[n..m]`` groups, the surplus
      from the last in model order) are deselected with their subtrees; the new features'
      mandatory children and groups that need children are completed as in
      `default_runtime_selection`. Activating a selected feature changes nothing.
    - ``deactivate F``: F and its subtree are deselected. If that leaves F's group below its
      lower bound, F's parent is deselected too when it is a run-time feature whose own group
      allows it (``deactivate Large; deactivate Small`` drops RackSize); otherwise the first
      other selectable sibling in model order that gives a valid selection is activated;
      otherwise the request is rejected. Deactivating an unselected feature changes nothing.

    After each request the full selection (deployment + run-time) must have no violation, or
    the request is rejected with the violations as its reason. Features no request touches
    keep their state. Returns the new run-time selection and the rejections. With ``trace``,
    each honoured request that changed the selection appends (its index, the run-time
    features it switched on or off): which request made each change.
    """
    ctx = _context(fm, deployment)
    idx = ctx.idx
    cur, valid = _starting_selection(ctx, previous)
    rejected: list[tuple[int, str]] = []
    for i, (action, name) in enumerate(requests):
        outcome = _request(ctx, cur, action, name)
        if isinstance(outcome, str):
            rejected.append((i, outcome))
            continue
        work, span, hint = outcome
        changed = [v for v in span if work[v] != cur[v]]
        if not changed:
            continue
        problems = _local_violations(idx, work, changed) if valid else _violations(idx, work)
        if problems:
            reasons = "; ".join(p.message for p in problems)
            rejected.append((i, f"cannot {action} {_canonical(idx, name)}: {reasons}{hint}"))
        else:
            cur, valid = work, True
            if trace is not None:
                trace.append((i, [idx.names[v] for v in changed if idx.runtime[v]]))
    result = frozenset(idx.names[v] for v in range(len(cur)) if cur[v] and idx.runtime[v])
    if valid:
        ctx.remember_valid(result)
    return result, rejected


def _starting_selection(ctx: _Context, previous: Collection[str]) -> tuple[list[Tri], bool]:
    """The full selection the requests start from (deployment + ``previous``), and whether it
    is valid. The engine passes back what the last call returned: a selection known to be
    valid needs no full re-check (which costs time linear in the model on every tick)."""
    idx = ctx.idx
    cur: list[Tri] = [x is True for x in ctx.base]
    for v in _resolve_all(
        idx, _names(previous, "a run-time selection"), "runtime", "a run-time selection"
    ):
        cur[v] = True
    return cur, ctx.known_valid(frozenset(previous)) or not _violations(idx, cur)


def _canonical(idx: _Index, name: str) -> str:
    i = idx.lookup(name)
    return name if i is None else idx.names[i]


def _request(
    ctx: _Context, cur: list[Tri], action: str, name: str
) -> str | tuple[list[Tri], range, str]:
    """The selection one request asks for, the index range it may change, and a hint for the
    reason should it be invalid; or the reason it is rejected outright."""
    idx = ctx.idx
    f = idx.lookup(name)
    if f is None:
        return f"unknown feature {name!r}"
    if not idx.runtime[f]:
        return f"{name} is a deployment-time feature; only run-time features change at run time"
    if action == "activate":
        if cur[f]:
            return cur, range(0), ""
        if f not in ctx.selectable:
            return f"cannot activate {idx.names[f]}: {_unselectable_reason(ctx, cur, f)}"
        work = list(cur)
        top = _activate_into(ctx, work, f)
        if isinstance(top, str):
            return f"cannot activate {idx.names[f]}: {top}"
        p = idx.parent[top]
        return work, idx.subtree(p if p >= 0 else top), ""
    if action == "deactivate":
        if not cur[f]:
            return cur, range(0), ""
        work = list(cur)
        span, hint = _deactivate_into(ctx, cur, work, f)
        return work, span, hint
    return f"unknown request {action!r} (expected 'activate' or 'deactivate')"


def _deselect(work: list[Tri], span: range) -> None:
    for v in span:
        work[v] = False


def _trim_group(idx: _Index, work: list[Tri], x: int) -> None:
    """Make room for `x` in its group: deselect run-time siblings, from the last."""
    if idx.group_of[x] < 0:
        return
    g = idx.groups[idx.group_of[x]]
    chosen = [c for c in g.children if work[c]]
    excess = len(chosen) - g.hi
    for c in reversed(chosen):
        if excess <= 0:
            break
        if c != x and idx.runtime[c]:
            _deselect(work, idx.subtree(c))
            excess -= 1


def _chain(idx: _Index, work: Sequence[Tri], f: int) -> list[int]:
    """`f` and its unselected ancestors, bottom-up."""
    chain = [f]
    a = idx.parent[f]
    while a >= 0 and not work[a]:
        chain.append(a)
        a = idx.parent[a]
    return chain


def _activate_into(ctx: _Context, work: list[Tri], f: int) -> int | str:
    """Select `f` in `work` (see `apply_requests`); the topmost newly selected feature, or
    the reason no completion of the new features' subtrees exists."""
    idx = ctx.idx
    chain = _chain(idx, work, f)
    for x in chain:
        work[x] = True
    for x in chain:
        _trim_group(idx, work, x)
    top = chain[-1]
    on_chain = set(chain)
    free = [v for v in idx.subtree(top) if v in ctx.free_set and v not in on_chain]
    if not free:
        return top
    trial = list(work)
    for v in free:
        trial[v] = None
    search = _Search(idx, trial, free)
    try:
        found = search.run(_prefer_default)
    except _BudgetExceeded:
        return f"no completion found within {SEARCH_BUDGET} search conflicts"
    if not found:
        for v in free:
            trial[v] = None
        return "; ".join(_explain(idx, trial, free)) or "no valid completion of its subtree"
    for v in free:
        work[v] = trial[v]
    return top


def _unselectable_reason(ctx: _Context, cur: Sequence[Tri], f: int) -> str:
    idx = ctx.idx
    if ctx.problems:
        return "the deployment-time selection is inconsistent: " + "; ".join(
            p.message for p in ctx.problems
        )
    if f not in ctx.free_set:
        a = idx.parent[f]
        while a >= 0 and (idx.runtime[a] or a in ctx.deployment):
            a = idx.parent[a]
        missing = idx.names[a] if a >= 0 else "?"
        return f"its deployment-time ancestor {missing} is not selected"
    attempt = list(cur)
    chain = _chain(idx, attempt, f)
    for x in chain:
        attempt[x] = True
    for x in chain:
        _trim_group(idx, attempt, x)
    free = [v for v in idx.subtree(chain[-1]) if v in ctx.free_set and v not in chain]
    for v in free:
        attempt[v] = None
    reasons = _explain(idx, attempt, free)
    detail = "; ".join(reasons) if reasons else "no valid selection contains it"
    return f"not selectable with this deployment-time selection: {detail}"


def _deactivate_into(
    ctx: _Context, cur: Sequence[Tri], work: list[Tri], f: int
) -> tuple[range, str]:
    """Deselect `f` in `work` (see `apply_requests`); the range it may change and a hint."""
    idx = ctx.idx
    _deselect(work, idx.subtree(f))
    p = idx.parent[f]
    if p < 0 or not work[p]:
        return idx.subtree(f), ""
    g = idx.groups[idx.group_of[f]]
    if sum(bool(work[c]) for c in g.children) >= g.lo:
        return idx.subtree(f), ""
    if _deselectable(idx, work, p):
        _deselect(work, idx.subtree(p))
        return idx.subtree(p), ""
    span = idx.subtree(p)
    for s in g.children:
        if s == f or work[s] or s not in ctx.selectable:
            continue
        trial = list(work)
        if isinstance(_activate_into(ctx, trial, s), str):
            continue
        if not _local_violations(idx, trial, [v for v in span if trial[v] != cur[v]]):
            work[:] = trial
            return span, ""
    return span, f" (and no other child of {idx.names[p]} can take its place)"


def _deselectable(idx: _Index, work: Sequence[Tri], p: int) -> bool:
    """A run-time feature whose own group still meets its lower bound without it."""
    if not idx.runtime[p] or idx.parent[p] < 0:
        return False
    g = idx.groups[idx.group_of[p]]
    return sum(bool(work[c]) for c in g.children) - 1 >= g.lo
