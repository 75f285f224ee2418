"""The Feature Model (paper Sec. II, III-D): features, groups, constraints and RRA attributes.

The model is read from UVL (`rra_agent.dsl.uvl`). RRA's additions are plain UVL attributes,
so any UVL tool can open the file:

- binding time: ``binding 'runtime'`` (default ``'deployment'``; children inherit it);
- Context Independent Measurement: ``Latency {kind 'cim', value 'High', scale ['Low', 'High']}``
  (``scale`` orders string values from lowest to highest so MIN/MAX can compare them);
- Non-Functional Requirement: ``VelocityLimit {kind 'nfr', tag 'max', value 0.5, unit 'm/s',
  constrains 'MaxVel'}``;
- Continuous Variability: ``MaxVel {kind 'cv', lower 0.4, upper 0.8, unit 'm/s'}``;
- ``alias 'CommunicChannel'`` gives a multi-word feature a name usable unquoted in rules;
- ``default`` marks the variant selected at start-up (else the first selectable one).

Attribute values are kept exactly as written (``value``), so exporting back to UVL round-trips;
the RRA view (`kind`, `lower`, ...) is derived from them.

The rest of the UVL language is kept as written too, so a community model is read, checked
and exported back whole: typed features (`Feature.type`), feature cardinalities
(`Feature.cardinality`), constraint attributes (`Attribute.constraints`), ``include`` language
levels and ``imports`` (`FeatureModel.includes`, `FeatureModel.imports`), and constraints beyond
propositional logic: comparisons, arithmetic, numbers, strings and aggregate functions
(`Compare`, `Arith`, `Num`, `Text`, `Aggregate`). rra-agent's reasoning uses the propositional
constraints over the model's own features (`FeatureModel.boolean_constraints`); what it cannot
use is listed, located, by ``rra_agent.dsl.uvl.uvl_warnings``.
"""

from __future__ import annotations

from collections.abc import Iterator
from functools import cached_property
from typing import Literal

import msgspec

from rra_agent.errors import Location
from rra_agent.models.base import FrozenModel

Binding = Literal["deployment", "runtime"]
AttributeKind = Literal["plain", "cim", "nfr", "cv"]
GroupKind = Literal["mandatory", "optional", "alternative", "or", "cardinality"]
FeatureType = Literal["Boolean", "Integer", "Real", "String"]
CompareOp = Literal["==", "!=", "<", "<=", ">", ">="]
ArithOp = Literal["+", "-", "*", "/"]
AggregateFunction = Literal["sum", "avg", "len", "floor", "ceil"]
Scalar = str | int | float | bool

#: Attributes whose meaning RRA defines; anything else is carried along untouched.
RRA_FEATURE_KEYS = frozenset({"binding", "alias", "abstract", "default"})


class Span(msgspec.Struct, frozen=True):
    """Where a model element was written: file, 1-based line and column."""

    file: str
    line: int
    col: int

    def location(self) -> Location:
        return Location(self.file, self.line, self.col)


class Attribute(FrozenModel, frozen=True):
    """A UVL attribute. ``value`` is a scalar, a list, a nested mapping, or None (a flag).

    A constraint attribute (``constraint E`` / ``constraints [E, ...]``) is an Attribute named
    ``constraint`` / ``constraints`` whose `constraints` holds the expressions (``value`` is
    None); inside a nested mapping the `ConstraintList` is the value of that key.
    """

    name: str
    value: Scalar | list | dict | None = None
    span: Span | None = None
    constraints: ConstraintList | None = None

    def _get(self, key: str) -> object:
        return self.value.get(key) if isinstance(self.value, dict) else None

    @property
    def kind(self) -> AttributeKind:
        k = self._get("kind")
        return k if k in ("cim", "nfr", "cv") else "plain"  # type: ignore[return-value]

    @property
    def unit(self) -> str | None:
        u = self._get("unit")
        return u if isinstance(u, str) else None

    @property
    def tag(self) -> str | None:
        """NFR tag: ``min``, ``max``, ``avg`` or ``count``."""
        t = self._get("tag")
        return t if isinstance(t, str) else None

    @property
    def lower(self) -> float | None:
        v = self._get("lower")
        return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None

    @property
    def upper(self) -> float | None:
        v = self._get("upper")
        return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None

    @property
    def scale(self) -> tuple[str, ...] | None:
        """Ordinal scale (lowest first) for string-valued CIM attributes."""
        s = self._get("scale")
        return tuple(str(x) for x in s) if isinstance(s, list) else None

    @property
    def constrains(self) -> str | None:
        """For an NFR: the name of the CV attribute it bounds."""
        c = self._get("constrains")
        return c if isinstance(c, str) else None

    @property
    def rra_value(self) -> Scalar | None:
        """The attribute's value in RRA terms: ``value`` of a kinded attribute, else itself."""
        if self.kind == "plain":
            return self.value if isinstance(self.value, Scalar) else None
        v = self._get("value")
        return v if isinstance(v, Scalar) else None

    @property
    def rank(self) -> float | None:
        """A number to order CIM values by: numbers as they are, strings by their scale."""
        v = self.rra_value
        if isinstance(v, bool):
            return float(v)
        if isinstance(v, int | float):
            return float(v)
        if isinstance(v, str) and self.scale and v in self.scale:
            return float(self.scale.index(v))
        return None


class Cardinality(FrozenModel, frozen=True):
    """A feature cardinality ``cardinality [lower..upper]`` (``upper`` None means ``*``)."""

    lower: int
    upper: int | None = None


class Feature(FrozenModel, frozen=True):
    """A feature with its attributes and child groups.

    ``type`` is the UVL type written before the name (None: untyped, i.e. Boolean);
    ``cardinality`` a feature cardinality (clones), which rra-agent's reasoning treats as one
    instance of the feature.
    """

    name: str
    attributes: tuple[Attribute, ...] = ()
    groups: tuple[Group, ...] = ()
    span: Span | None = None
    type: FeatureType | None = None
    cardinality: Cardinality | None = None

    def attribute(self, name: str) -> Attribute | None:
        return next((a for a in self.attributes if a.name == name), None)

    @property
    def declared_binding(self) -> Binding | None:
        """The binding written on this feature, if any (see `FeatureModel.binding`)."""
        a = self.attribute("binding")
        return a.value if a is not None and a.value in ("deployment", "runtime") else None  # type: ignore[return-value]

    @property
    def alias(self) -> str | None:
        a = self.attribute("alias")
        return a.value if a is not None and isinstance(a.value, str) else None

    @property
    def abstract(self) -> bool:
        a = self.attribute("abstract")
        return a is not None and a.value in (None, True)

    @property
    def default(self) -> bool:
        """Preferred variant of its group at run time (``{default}`` or ``default true``)."""
        a = self.attribute("default")
        return a is not None and a.value in (None, True)

    @property
    def children(self) -> Iterator[Feature]:
        for g in self.groups:
            yield from g.children


class Group(FrozenModel, frozen=True):
    """A child group. ``cardinality`` uses ``lower``/``upper`` (``upper`` None means ``*``)."""

    kind: GroupKind
    children: tuple[Feature, ...] = ()
    lower: int | None = None
    upper: int | None = None
    span: Span | None = None

    @property
    def bounds(self) -> tuple[int, int | None]:
        """How many children may be selected when the parent is: (min, max or None)."""
        n = len(self.children)
        match self.kind:
            case "mandatory":
                return n, n
            case "optional":
                return 0, n
            case "alternative":
                return 1, 1
            case "or":
                return 1, n
            case _:
                return self.lower or 0, self.upper


# Constraint expressions: a tagged union, dispatched with `match`.
class Ref(FrozenModel, frozen=True, tag="ref"):
    """A reference: a feature (``A``), an attribute (``A.price``) or a name from an imported
    model (``sub.A``); dotted parts are joined with ``.``."""

    name: str
    span: Span | None = None


class Not(FrozenModel, frozen=True, tag="not"):
    operand: Expr


class And(FrozenModel, frozen=True, tag="and"):
    left: Expr
    right: Expr


class Or(FrozenModel, frozen=True, tag="or"):
    left: Expr
    right: Expr


class Implies(FrozenModel, frozen=True, tag="implies"):
    left: Expr
    right: Expr


class Equiv(FrozenModel, frozen=True, tag="equiv"):
    left: Expr
    right: Expr


class Compare(FrozenModel, frozen=True, tag="compare"):
    """An equation of UVL's arithmetic level: ``left op right`` over terms."""

    op: CompareOp
    left: Expr
    right: Expr


class Arith(FrozenModel, frozen=True, tag="arith"):
    """A binary arithmetic term ``left op right``."""

    op: ArithOp
    left: Expr
    right: Expr


class Num(FrozenModel, frozen=True, tag="num"):
    value: int | float


class Text(FrozenModel, frozen=True, tag="text"):
    """A string literal of a string constraint (``name == 'x'``)."""

    value: str


class Aggregate(FrozenModel, frozen=True, tag="aggregate"):
    """An aggregate function: ``sum``/``avg`` (attribute, or feature and attribute), ``len``,
    ``floor``, ``ceil`` (one reference)."""

    function: AggregateFunction
    args: tuple[Ref, ...]
    span: Span | None = None


Expr = Ref | Not | And | Or | Implies | Equiv | Compare | Arith | Num | Text | Aggregate
#: The propositional connectives: a constraint made of these and `Ref` is Boolean-level UVL.
BOOLEAN_NODES = (Ref, Not, And, Or, Implies, Equiv)


class ConstraintList(FrozenModel, frozen=True, tag="constraints"):
    """The value of a constraint attribute: ``constraint E`` (``single``) or
    ``constraints [E, ...]``."""

    exprs: tuple[Expr, ...] = ()
    single: bool = False


class Constraint(FrozenModel, frozen=True):
    expr: Expr
    span: Span | None = None


class Import(FrozenModel, frozen=True):
    """``imports`` line: another model's namespace, optionally ``as`` an alias."""

    namespace: str
    alias: str | None = None
    span: Span | None = None

    @property
    def prefix(self) -> str:
        """What references into the imported model start with (``prefix.Feature``)."""
        return self.alias if self.alias is not None else self.namespace


def subexpressions(expr: Expr) -> Iterator[Expr]:
    """``expr`` and every expression inside it, in pre-order (left to right), iteratively."""
    stack: list[Expr] = [expr]
    while stack:
        e = stack.pop()
        yield e
        match e:
            case Not(operand=o):
                stack.append(o)
            case Aggregate(args=args):
                stack.extend(reversed(args))
            case (
                And(left=a, right=b)
                | Or(left=a, right=b)
                | Implies(left=a, right=b)
                | Equiv(left=a, right=b)
                | Compare(left=a, right=b)
                | Arith(left=a, right=b)
            ):
                stack.extend((b, a))


def refs(expr: Expr) -> Iterator[Ref]:
    """Every reference in a constraint expression, left to right."""
    return (e for e in subexpressions(expr) if isinstance(e, Ref))


def is_boolean(expr: Expr) -> bool:
    """Whether ``expr`` is propositional: references joined by ``! & | => <=>`` only."""
    return all(isinstance(e, BOOLEAN_NODES) for e in subexpressions(expr))


class FeatureModel(FrozenModel, frozen=True, dict=True):
    """A whole feature model: root feature, cross-tree constraints, and derived indexes."""

    root: Feature
    constraints: tuple[Constraint, ...] = ()
    namespace: str | None = None
    source: str = "<features>"
    #: ``include`` language levels as written (``Arithmetic.aggregate-function``, ``Type.*``).
    includes: tuple[str, ...] = ()
    imports: tuple[Import, ...] = ()

    @cached_property
    def boolean_constraints(self) -> tuple[Constraint, ...]:
        """The constraints rra-agent reasons with: propositional ones that name no feature of
        an imported model. The others are kept (and exported) but do not restrict selections."""
        return tuple(
            c
            for c in self.constraints
            if is_boolean(c.expr) and not any(self.imported(r.name) for r in refs(c.expr))
        )

    def imported(self, name: str) -> bool:
        """Whether ``name`` refers into an imported model (``prefix.Feature``) to a feature
        this model's tree does not hold (an imported root placed in the tree is one of ours)."""
        return name not in self.features and any(
            name.startswith(i.prefix + ".") for i in self.imports
        )

    # ---- derived views (computed once) ---------------------------------------------------
    @cached_property
    def features(self) -> dict[str, Feature]:
        """Every feature by name, in depth-first pre-order (the model's canonical order)."""
        out: dict[str, Feature] = {}
        stack = [self.root]
        while stack:
            f = stack.pop()
            out[f.name] = f
            stack.extend(reversed(list(f.children)))
        return out

    @cached_property
    def parent(self) -> dict[str, str | None]:
        out: dict[str, str | None] = {self.root.name: None}
        for f in self.features.values():
            for c in f.children:
                out[c.name] = f.name
        return out

    @cached_property
    def group_of(self) -> dict[str, Group]:
        """The group each non-root feature belongs to."""
        return {c.name: g for f in self.features.values() for g in f.groups for c in g.children}

    @cached_property
    def binding(self) -> dict[str, Binding]:
        """Effective binding time: the declared one, else the parent's, else deployment."""
        out: dict[str, Binding] = {}
        for name, f in self.features.items():  # pre-order: parents first
            p = self.parent[name]
            out[name] = f.declared_binding or (out[p] if p is not None else "deployment")
        return out

    @cached_property
    def aliases(self) -> dict[str, str]:
        """alias -> feature name."""
        return {f.alias: n for n, f in self.features.items() if f.alias}

    def resolve_name(self, name: str) -> str | None:
        """A feature's name from its name or alias, or None if there is no such feature."""
        if name in self.features:
            return name
        return self.aliases.get(name)

    @cached_property
    def attributes(self) -> dict[str, tuple[str, Attribute]]:
        """Every kinded (cim/nfr/cv) attribute by name -> (owning feature, attribute).

        NFR and CV names are unique in a model; a CIM name may repeat on the variants of a
        variation point (``Latency`` on ChannelA and ChannelB, for ``MIN(Latency)``): here the
        last one wins, so look CIMs up with `cim_attributes` or on the feature itself.
        """
        return {
            a.name: (fname, a)
            for fname, f in self.features.items()
            for a in f.attributes
            if a.kind != "plain"
        }

    @cached_property
    def cim_attributes(self) -> dict[str, dict[str, Attribute]]:
        """CIM attribute name -> {feature name: attribute}: variants share CIM names."""
        out: dict[str, dict[str, Attribute]] = {}
        for fname, f in self.features.items():
            for a in f.attributes:
                if a.kind == "cim":
                    out.setdefault(a.name, {})[fname] = a
        return out

    def runtime_features(self) -> list[str]:
        return [n for n, b in self.binding.items() if b == "runtime"]

    def deployment_features(self) -> list[str]:
        return [n for n, b in self.binding.items() if b == "deployment"]
