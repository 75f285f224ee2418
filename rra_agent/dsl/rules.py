"""The adaptation-rule DSL (``adaptation.rra``, paper Fig. 5): parser, transformer, resolver.

``rules.lark`` is parsed LALR(1) with ``strict=True``; `_Builder` turns the parse tree into
the `rra_agent.models.adaptation` AST (one method per grammar rule, positions from lark's
``meta``), and `_Resolver` binds every name to the feature model and the measurements model
and checks types. Syntax errors raise `DslSyntaxError`; all semantic problems of a file are
reported together (`SemanticError`, or an `ErrorGroup` of them). The language is documented
in ``docs/rules.md``.
"""

from __future__ import annotations

import difflib
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Literal

from lark import Lark, Token, Tree, UnexpectedCharacters, UnexpectedInput, UnexpectedToken
from lark.lexer import PatternStr
from lark.visitors import Transformer_NonRecursive, v_args

from rra_agent.dsl.parser_cache import cached_lark
from rra_agent.errors import DslSyntaxError, ErrorGroup, Location, RraError, SemanticError
from rra_agent.models.adaptation import (
    FUNCTIONS,
    Action,
    Activate,
    AdaptationModel,
    Arith,
    AttrRef,
    AttrValue,
    Bool,
    Bound,
    Branch,
    Call,
    Compare,
    Const,
    Deactivate,
    Expr,
    FeatureRef,
    Import,
    Logic,
    Measure,
    Name,
    Neg,
    Not,
    Num,
    Rule,
    RuleSet,
    SelectVariant,
    SetAttribute,
    Str,
    depth,
)
from rra_agent.models.features import Attribute, FeatureModel, Span
from rra_agent.models.measurements import Measurement, MeasurementsModel

#: Expressions nested deeper than this are rejected (the compiled code must stay small).
MAX_DEPTH = 40

_GRAMMAR = Path(__file__).with_name("rules.lark")
_NUMERIC = re.compile(r"\s*[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?\s*")
_IN_FEATURE_LIST = re.compile(
    r"\b(activate_feature|deactivate_feature|select_feature_from_variants_of)\s*\([^()]*$"
)
_FRIENDLY = {
    "NAME": "name",
    "NUMBER": "number",
    "STRING": "string",
    "COMP_OP": "comparison operator",
    "ADD_OP": "'+' or '-'",
    "MUL_OP": "'*' or '/'",
    "POW": "'^'",
    "$END": "end of input",
}
_ESCAPES = {"n": "\n", "t": "\t", "\\": "\\", '"': '"', "'": "'"}

Ty = Literal["num", "str", "bool", "any"]


@cache
def _parser() -> Lark:
    # Built once per grammar version, then loaded from the on-disk parser cache.
    return cached_lark(
        "rules",
        _GRAMMAR.read_text(encoding="utf-8"),
        parser="lalr",
        strict=True,  # no shift/reduce conflicts, no colliding terminals (needs interegular)
        propagate_positions=True,
        maybe_placeholders=True,
    )


def parse_rules(
    text: str, file: str, fm: FeatureModel, measurements: MeasurementsModel | None
) -> AdaptationModel:
    """Parse and resolve an Adaptation Model; raise a located `RraError` on any problem.

    ``measurements`` None skips the checks of measurement names and types (any ``cdm.X`` and
    any bare name that is no attribute is then taken as a measurement of unknown type).
    """
    lines = text.split("\n")
    tree = _parse_tree(text, file, lines)
    builder = _Builder(file, lines)
    try:
        raw = builder.transform(tree)
        resolver = _Resolver(file, lines, fm, measurements)
        model = resolver.model(raw)
    except RecursionError:  # pragma: no cover - depth is bounded before anything recurses
        raise DslSyntaxError("rules nested too deeply", Location(file, 1, 1)) from None
    errors = sorted(builder.errors + resolver.errors, key=_source_order)
    ErrorGroup.raise_if_any(errors)
    return model


def load_rules(
    path: str | Path, fm: FeatureModel, measurements: MeasurementsModel | None
) -> AdaptationModel:
    """Read and parse an ``adaptation.rra`` file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise RraError(f"{p}: cannot read rules: {e}") from None
    return parse_rules(text, str(p), fm, measurements)


# ---- syntax --------------------------------------------------------------------------------
def _parse_tree(text: str, file: str, lines: list[str]) -> Tree:
    try:
        return _parser().parse(text)
    except UnexpectedInput as e:
        raise _syntax_error(e, text, file, lines) from None


def _syntax_error(e: UnexpectedInput, text: str, file: str, lines: list[str]) -> DslSyntaxError:
    if isinstance(e, UnexpectedToken) and e.token.type == "$END":
        line, col = len(lines), len(lines[-1]) + 1
        what = "end of input"
    elif isinstance(e, UnexpectedToken):
        line, col = e.token.line or 1, e.token.column or 1
        what = repr(str(e.token))
    elif isinstance(e, UnexpectedCharacters):
        line, col = e.line, e.column
        what = f"character {e.char!r}"  # text[e.pos_in_stream], which lark types as None
    else:  # pragma: no cover - the LALR front end raises only the two above
        line, col, what = e.line or 1, e.column or 1, "input"
    expected = sorted({_terminal_text(t) for t in _expected(e)})
    message = f"unexpected {what}"
    if expected:
        message += f", expected {'one of ' if len(expected) > 1 else ''}{', '.join(expected)}"
    if _IN_FEATURE_LIST.search(lines[line - 1][: col - 1] if 0 < line <= len(lines) else ""):
        message += " (multi-word feature names are written quoted or by their alias)"
    source = lines[line - 1] if 0 < line <= len(lines) else None
    return DslSyntaxError(message, Location(file, line, col), expected=expected, source_line=source)


def _expected(e: UnexpectedInput) -> Iterable[str]:
    if isinstance(e, UnexpectedToken):
        return e.accepts or e.expected
    if isinstance(e, UnexpectedCharacters):
        return e.allowed or ()
    return ()  # pragma: no cover


def _terminal_text(name: str) -> str:
    if name in _FRIENDLY:
        return _FRIENDLY[name]
    try:
        pattern = _parser().get_terminal(name).pattern
    except KeyError:  # pragma: no cover
        return name.lower()
    return repr(pattern.value) if isinstance(pattern, PatternStr) else name.lower()


# ---- parse tree -> AST ---------------------------------------------------------------------
@dataclass(frozen=True)
class _Header:
    """``ruleSet Name:`` before the rules that follow it are gathered."""

    name: str
    span: Span


_LITERALS = (Num, Str)  # `true`/`false` are conditions themselves


@v_args(meta=True)
class _Builder(Transformer_NonRecursive):
    """Parse tree -> AST, one method per grammar rule; syntax-level checks go to `errors`."""

    def __init__(self, file: str, lines: list[str]) -> None:
        super().__init__()
        self.file = file
        self.lines = lines
        self.errors: list[SemanticError] = []

    # helpers
    def _span(self, meta_or_token: object) -> Span:
        line = getattr(meta_or_token, "line", 1) or 1
        col = getattr(meta_or_token, "column", 1) or 1
        return Span(self.file, line, col)

    def _error(self, message: str, span: Span | None) -> None:
        self.errors.append(_located(message, span, self.file, self.lines))

    # file structure
    def start(self, meta, children) -> AdaptationModel:
        imports = tuple(c for c in children if isinstance(c, Import))
        items = self._group([c for c in children if not isinstance(c, Import)])
        return AdaptationModel(imports=imports, items=tuple(items), source=self.file)

    def _group(self, flat: Sequence[_Header | Rule]) -> list[Rule | RuleSet]:
        """Gather each ``ruleSet`` header with the prioritised rules that follow it."""
        out: list[Rule | RuleSet] = []
        header: _Header | None = None
        members: list[Rule] = []
        for item in [*flat, None]:
            if header is not None and not (isinstance(item, Rule) and item.priority is not None):
                if not members:
                    self._error(
                        f"rule set {header.name} has no rules (its rules are written "
                        f"'rule NAME priority N: ...' right after it)",
                        header.span,
                    )
                out.append(RuleSet(name=header.name, rules=tuple(members), span=header.span))
                header, members = None, []
            if isinstance(item, _Header):
                header = item
            elif isinstance(item, Rule) and header is not None:
                members.append(item)
            elif isinstance(item, Rule):
                if item.priority is not None:
                    self._error(
                        f"rule {item.name} has a priority but belongs to no rule set", item.span
                    )
                out.append(item)
        return out

    def import_decl(self, meta, children) -> Import:
        module, alias = children
        return Import(module=module, alias=str(alias), span=self._span(meta))

    def module(self, meta, children) -> str:
        return ".".join(str(c) for c in children)

    def ruleset_header(self, meta, children) -> _Header:
        return _Header(str(children[0]), self._span(meta))

    def rule(self, meta, children) -> Rule:
        name, priority, period, reflex, body = children
        branches = body if isinstance(body, tuple) and isinstance(body[0], Branch) else None
        if branches is None:
            branches = (Branch(condition=None, actions=body, span=self._span(meta)),)
        return Rule(
            name=str(name),
            branches=branches,
            priority=priority,
            period_ms=period,
            reflex=reflex is not False,
            span=self._span(meta),
        )

    def reflex(self, meta, children) -> bool:
        """``reflex on`` / ``reflex off``: whether the rule's decision may be delegated."""
        tok = children[0]
        if str(tok) not in ("on", "off"):
            self._error(f"reflex takes on or off, got {tok}", self._span(tok))
        return str(tok) != "off"

    def priority(self, meta, children) -> int:
        tok = children[0]
        value = float(tok)
        if not value.is_integer() or value > 1e9:
            self._error(f"priority must be a whole number, got {tok}", self._span(tok))
            return 0
        return int(value)

    def period(self, meta, children) -> float:
        number, unit = children
        scale = {"ms": 1.0, "s": 1000.0}.get(str(unit))
        if scale is None:
            self._error(f"unknown period unit {unit!s} (use ms or s)", self._span(unit))
            scale = 1.0
        value = float(number) * scale
        if not math.isfinite(value):
            self._error(f"period {number} is out of range", self._span(number))
            value = 0.0
        return value

    # rule bodies
    def if_chain(self, meta, children) -> tuple[Branch, ...]:
        condition, actions, *rest = children
        first = Branch(condition=condition, actions=actions, span=self._span(meta))
        return (first, *(b for b in rest if b is not None))

    def else_if(self, meta, children) -> Branch:
        condition, actions = children
        return Branch(condition=condition, actions=actions, span=self._span(meta))

    def else_branch(self, meta, children) -> Branch:
        return Branch(condition=None, actions=children[0], span=self._span(meta))

    def condition(self, meta, children) -> Expr:
        return children[0]

    def actions(self, meta, children) -> tuple[Action, ...]:
        return tuple(children)

    def activate(self, meta, children) -> Activate:
        return Activate(features=children[0], span=self._span(meta))

    def deactivate(self, meta, children) -> Deactivate:
        return Deactivate(features=children[0], span=self._span(meta))

    def feature_list(self, meta, children) -> tuple[FeatureRef, ...]:
        return tuple(c for c in children if isinstance(c, FeatureRef))

    def feature_ref(self, meta, children) -> FeatureRef:
        tok = children[0]
        name = _unquote(tok) if tok.type == "STRING" else str(tok)
        return FeatureRef(name=name, span=self._span(tok))

    def select_variant(self, meta, children) -> SelectVariant:
        point, extremum, attribute = children
        return SelectVariant(
            point=point, attribute=str(attribute), extremum=extremum, span=self._span(meta)
        )

    def extremum(self, meta, children) -> str:
        return str(children[0]).lower()

    def set_attribute(self, meta, children) -> SetAttribute:
        target, value = children
        return SetAttribute(target=target, value=value, span=self._span(meta))

    def attribute_ref(self, meta, children) -> AttrRef:
        head, member = children
        first = _unquote(head) if head.type == "STRING" else str(head)
        if member is None:
            return AttrRef(name=first, span=self._span(meta))
        return AttrRef(name=str(member), feature=first, span=self._span(meta))

    # expressions
    def or_expr(self, meta, children) -> Expr:
        result = children[0]
        for op, operand in zip(children[1::2], children[2::2], strict=True):
            operand = self._shorthand(result, operand)
            result = Logic(op="or", left=result, right=operand, span=self._span(op))
        return result

    def _shorthand(self, left: Expr, operand: Expr) -> Expr:
        """``x == "A" OR "B"`` (Fig. 5): a bare literal after OR repeats the last ``x ==``."""
        if not isinstance(operand, _LITERALS):
            return operand
        target = left
        while isinstance(target, Logic) and target.op == "or":
            target = target.right
        if isinstance(target, Compare) and target.op == "==":
            return Compare(op="==", left=target.left, right=operand, span=operand.span)
        if isinstance(target, Compare) and target.op == "!=":
            self._error('the shorthand only extends ==; write x != "A" AND x != "B"', operand.span)
        else:
            self._error(
                "a bare value after OR needs a comparison `x == value` before it", operand.span
            )
        return Bool(value=False, span=operand.span)  # reported; keeps later checks quiet

    def and_expr(self, meta, children) -> Expr:
        result = children[0]
        for op, operand in zip(children[1::2], children[2::2], strict=True):
            result = Logic(op="and", left=result, right=operand, span=self._span(op))
        return result

    def negation(self, meta, children) -> Expr:
        return Not(operand=children[1], span=self._span(children[0]))

    def comparison(self, meta, children) -> Expr:
        left, op, right = children
        return Compare(op=str(op), left=left, right=right, span=self._span(op))  # type: ignore[arg-type]

    def sum(self, meta, children) -> Expr:
        return self._fold(children)

    def product(self, meta, children) -> Expr:
        return self._fold(children)

    def _fold(self, children: list) -> Expr:
        result = children[0]
        for op, operand in zip(children[1::2], children[2::2], strict=True):
            result = Arith(op=str(op), left=result, right=operand, span=self._span(op))  # type: ignore[arg-type]
        return result

    def sign(self, meta, children) -> Expr:
        op, operand = children
        return Neg(operand=operand, span=self._span(op)) if str(op) == "-" else operand

    def power(self, meta, children) -> Expr:
        base, op, exponent = children
        return Arith(op="^", left=base, right=exponent, span=self._span(op))

    def number(self, meta, children) -> Expr:
        value = float(children[0])
        if not math.isfinite(value):
            self._error(f"number {children[0]} is out of range", self._span(meta))
            value = 0.0
        return Num(value=value, span=self._span(meta))

    def string(self, meta, children) -> Expr:
        return Str(value=_unquote(children[0]), span=self._span(meta))

    def true(self, meta, children) -> Expr:
        return Bool(value=True, span=self._span(meta))

    def false(self, meta, children) -> Expr:
        return Bool(value=False, span=self._span(meta))

    def reference(self, meta, children) -> Expr:
        return Name(parts=tuple(str(c) for c in children), span=self._span(meta))

    def call(self, meta, children) -> Expr:
        func, *args = children
        return Call(func=str(func), args=tuple(args), span=self._span(meta))  # type: ignore[arg-type]


def _unquote(token: Token) -> str:
    body = str(token)[1:-1]
    return re.sub(r"\\(.)", lambda m: _ESCAPES.get(m.group(1), m.group(0)), body)


def _source_order(e: SemanticError) -> tuple[int, int]:
    """Where ``e`` is in the file; `_located` places every error, so none sorts first."""
    loc = e.location
    return (loc.line, loc.col) if loc is not None else (0, 0)


def _located(message: str, span: Span | None, file: str, lines: list[str]) -> SemanticError:
    if span is None:  # pragma: no cover - the parser sets every span
        return SemanticError(message, Location(file, 1, 1))
    source = lines[span.line - 1] if 0 < span.line <= len(lines) else None
    return SemanticError(message, span.location(), source_line=source)


def _number(text: str) -> float | None:
    """A string literal that spells a number means that number ("50" is 50)."""
    if not _NUMERIC.fullmatch(text):
        return None
    value = float(text)
    return value if math.isfinite(value) else None


def _suggest(name: str, candidates: Iterable[str]) -> str:
    close = difflib.get_close_matches(name, list(candidates), n=3, cutoff=0.6)
    if not close:
        lowered = {c.lower(): c for c in candidates}
        close = [lowered[c] for c in difflib.get_close_matches(name.lower(), list(lowered), n=3)]
    return f" (did you mean {' or '.join(close)}?)" if close else ""


# ---- name resolution and types ------------------------------------------------------------
class _Resolver:
    """Binds names to the feature and measurements models, checks types, collects errors."""

    def __init__(
        self, file: str, lines: list[str], fm: FeatureModel, meas: MeasurementsModel | None
    ) -> None:
        self.file, self.lines, self.fm, self.meas = file, lines, fm, meas
        self.errors: list[SemanticError] = []
        self.aliases: set[str] = set()
        self.attrs: dict[str, list[tuple[str, Attribute]]] = {}
        for fname, feature in fm.features.items():
            for a in feature.attributes:
                if a.kind != "plain":
                    self.attrs.setdefault(a.name, []).append((fname, a))
        self.by_name: dict[str, Measurement] = {}
        self.by_lower: dict[str, list[Measurement]] = {}
        for m in meas.measurements if meas else ():
            self.by_name[m.name] = m
            self.by_lower.setdefault(m.name.lower(), []).append(m)

    def error(self, message: str, span: Span | None) -> None:
        self.errors.append(_located(message, span, self.file, self.lines))

    # model structure
    def model(self, raw: AdaptationModel) -> AdaptationModel:
        for imp in raw.imports:
            if imp.alias in self.aliases:
                self.error(f"import alias {imp.alias} is declared twice", imp.span)
            self.aliases.add(imp.alias)
        seen: dict[str, Span | None] = {}
        items: list[Rule | RuleSet] = []
        for item in raw.items:
            self._unique(item.name, item.span, seen)
            if isinstance(item, RuleSet):
                rules = tuple(self._rule(r, seen) for r in item.rules)
                self._priorities(item)
                items.append(RuleSet(name=item.name, rules=rules, span=item.span))
            else:
                items.append(self._rule(item, None))
        return AdaptationModel(imports=raw.imports, items=tuple(items), source=raw.source)

    def _unique(self, name: str, span: Span | None, seen: dict[str, Span | None]) -> None:
        if name in seen:
            first = seen[name]
            where = f" (first at {first.location()})" if first else ""
            self.error(f"name {name} is already used{where}", span)
        else:
            seen[name] = span

    def _priorities(self, rs: RuleSet) -> None:
        first: dict[int, Rule] = {}
        for r in rs.rules:
            assert r.priority is not None
            if r.priority in first:
                other = first[r.priority]
                where = other.span.location() if other.span else "?"
                self.error(
                    f"rules {other.name} ({where}) and {r.name} of rule set {rs.name} have the "
                    f"same priority {r.priority}: priorities inside a rule set must differ",
                    r.span,
                )
            else:
                first[r.priority] = r

    def _rule(self, rule: Rule, seen: dict[str, Span | None] | None) -> Rule:
        if seen is not None:
            self._unique(rule.name, rule.span, seen)
        branches = tuple(self._branch(b) for b in rule.branches)
        return Rule(
            name=rule.name,
            branches=branches,
            priority=rule.priority,
            period_ms=rule.period_ms,
            reflex=rule.reflex,
            span=rule.span,
        )

    def _branch(self, branch: Branch) -> Branch:
        condition = None
        if branch.condition is not None:
            condition = self.condition(branch.condition)
        actions = tuple(self._action(a) for a in branch.actions)
        return Branch(condition=condition, actions=actions, span=branch.span)

    def condition(self, expr: Expr) -> Expr:
        resolved, ty = self.expr(expr)
        if ty not in ("bool", "any"):
            self.error(f"a condition must be true or false, not a {_TY_TEXT[ty]}", expr.span)
        return resolved

    # actions
    def _action(self, action: Action) -> Action:
        match action:
            case Activate(features=fs, span=span):
                return Activate(features=tuple(self._feature(f) for f in fs), span=span)
            case Deactivate(features=fs, span=span):
                return Deactivate(features=tuple(self._feature(f) for f in fs), span=span)
            case SelectVariant():
                return self._select(action)
            case SetAttribute(target=target, value=value, span=span):
                value, ty = self.expr(value)
                value = _numeric(value) if ty == "str" else value
                if ty not in ("num", "any") and not isinstance(value, Num):
                    self.error(f"set_attribute needs a number, not a {_TY_TEXT[ty]}", span)
                return SetAttribute(target=self._cv(target), value=value, span=span)
        raise TypeError(action)  # pragma: no cover

    def _feature(self, ref: FeatureRef, *, runtime: bool = True) -> FeatureRef:
        name = self.fm.resolve_name(ref.name)
        if name is None:
            names = [*self.fm.features, *self.fm.aliases]
            self.error(f"unknown feature {ref.name!r}{_suggest(ref.name, names)}", ref.span)
            return ref
        if runtime and self.fm.binding[name] != "runtime":
            self.error(
                f"feature {name} is bound at deployment time; rules act only on run-time features",
                ref.span,
            )
        return FeatureRef(name=name, span=ref.span)

    def _select(self, action: SelectVariant) -> SelectVariant:
        point = self._feature(action.point, runtime=False)
        feature = self.fm.features.get(point.name)
        if feature is not None:
            variants = list(feature.children)
            if not variants:
                self.error(f"feature {point.name} has no variants to select from", point.span)
            for v in variants:
                self._variant(v.name, action)
        return SelectVariant(
            point=point, attribute=action.attribute, extremum=action.extremum, span=action.span
        )

    def _variant(self, name: str, action: SelectVariant) -> None:
        attr = self.fm.features[name].attribute(action.attribute)
        if self.fm.binding[name] != "runtime":
            self.error(f"variant {name} is bound at deployment time", action.point.span)
        elif attr is None or attr.kind != "cim":
            hint = "" if action.attribute in self.attrs else _suggest(action.attribute, self.attrs)
            self.error(f"variant {name} has no CIM attribute {action.attribute}{hint}", action.span)
        elif attr.rank is None:
            self.error(
                f"{name}.{action.attribute} = {attr.rra_value!r} cannot be ordered: give the "
                f"attribute a number or a scale listing its values",
                action.span,
            )

    def _cv(self, ref: AttrRef) -> AttrRef:
        found = self._attribute(ref.feature, ref.name, ref.span, settable=True)
        if found is None:
            return ref
        fname, attr = found
        if attr.kind != "cv":
            self.error(
                f"{ref.name} is a {attr.kind.upper()} attribute; only Continuous Variability "
                f"(cv) attributes can be set",
                ref.span,
            )
        elif self.fm.binding[fname] != "runtime":
            self.error(f"{ref.name} belongs to deployment-time feature {fname}", ref.span)
        return AttrRef(name=attr.name, feature=fname, span=ref.span)

    def _attribute(
        self, feature: str | None, name: str, span: Span | None, *, settable: bool = False
    ) -> tuple[str, Attribute] | None:
        """A kinded attribute by (optional owner, name), with a located error if none/many.
        ``settable`` (``set_attribute``): an ambiguous name is said not to be settable."""
        if feature is not None:
            fname = self.fm.resolve_name(feature)
            if fname is None:
                self.error(
                    f"unknown feature {feature!r}{_suggest(feature, self.fm.features)}", span
                )
                return None
            attr = self.fm.features[fname].attribute(name)
            if attr is None or attr.kind == "plain":
                self.error(f"feature {fname} has no attribute {name}", span)
                return None
            return fname, attr
        owners = self.attrs.get(name, [])
        if len(owners) == 1:
            return owners[0]
        if owners and settable:
            self._ambiguous_setting(name, owners, span)
        elif owners:
            which = ", ".join(f"{f}.{name}" for f, _ in owners)
            self.error(f"attribute {name} is ambiguous: write one of {which}", span)
        else:
            self.error(f"unknown attribute {name}{_suggest(name, self.attrs)}", span)
        return None

    def _ambiguous_setting(
        self, name: str, owners: list[tuple[str, Attribute]], span: Span | None
    ) -> None:
        """The error of ``set_attribute`` naming an attribute several features have. Only CIM
        attributes of different features may share a name (`rra_agent.dsl.uvl`), and none
        can be set: say so, rather than suggest writing one of them (a second error)."""
        which = ", ".join(f"{f}.{name} ({a.kind.upper()})" for f, a in owners)
        self.error(
            f"attribute {name} cannot be set: {which} (only run-time Continuous Variability "
            "(cv) attributes can be set)",
            span,
        )

    # expressions
    def expr(self, expr: Expr) -> tuple[Expr, Ty]:
        """Resolve names and infer the type of an expression (after a depth check)."""
        if depth(expr) > MAX_DEPTH:
            self.error(f"expression nested too deeply (more than {MAX_DEPTH} levels)", expr.span)
            return expr, "any"
        return self._expr(expr)

    def _expr(self, expr: Expr) -> tuple[Expr, Ty]:
        match expr:
            case Num() | Const():
                return expr, "num"
            case Str():
                return expr, "str"
            case Bool():
                return expr, "bool"
            case Name():
                return self._name(expr)
            case Neg(operand=o, span=span):
                return Neg(operand=self._numeric(o, "-"), span=span), "num"
            case Arith(op=op, left=a, right=b, span=span):
                left, right = self._numeric(a, op), self._numeric(b, op)
                return Arith(op=op, left=left, right=right, span=span), "num"
            case Call():
                return self._call(expr)
            case Compare():
                return self._compare(expr)
            case Logic(op=op, left=a, right=b, span=span):
                left, right = self._boolean(a, op.upper()), self._boolean(b, op.upper())
                return Logic(op=op, left=left, right=right, span=span), "bool"
            case Not(operand=o, span=span):
                return Not(operand=self._boolean(o, "NOT"), span=span), "bool"
        return expr, "any"  # already resolved nodes (Measure, AttrValue, Bound)

    def _numeric(self, expr: Expr, op: str) -> Expr:
        resolved, ty = self._expr(expr)
        if ty == "str":
            number = _numeric(resolved)
            if isinstance(number, Num):
                return number
        if ty not in ("num", "any"):
            self.error(f"{op} needs numbers, not a {_TY_TEXT[ty]}", expr.span)
        return resolved

    def _boolean(self, expr: Expr, op: str) -> Expr:
        resolved, ty = self._expr(expr)
        if ty not in ("bool", "any"):
            self.error(f"{op} needs conditions, not a {_TY_TEXT[ty]}", expr.span)
        return resolved

    def _call(self, call: Call) -> tuple[Expr, Ty]:
        arity = FUNCTIONS.get(call.func.lower())
        args = tuple(self._numeric(a, call.func) for a in call.args)
        if arity is None:
            self.error(
                f"unknown function {call.func} (functions: {', '.join(FUNCTIONS)})", call.span
            )
        elif len(args) < arity[0] or (arity[1] is not None and len(args) > arity[1]):
            self.error(f"{call.func} takes {arity[0]} argument(s), got {len(args)}", call.span)
        func = call.func.lower()
        return Call(func=func, args=args, span=call.span), "num"  # type: ignore[arg-type]

    def _compare(self, cmp: Compare) -> tuple[Expr, Ty]:
        left, lt = self._expr(cmp.left)
        right, rt = self._expr(cmp.right)
        # Quoted numbers compare as numbers ("50" is 50) unless the other side is a string.
        both = lt == rt == "str" and _both_numeric(left, right)
        if both or (lt == "str" and rt in ("num", "any")):
            left, lt = _as_num(left, lt)
        if rt == "str" and lt in ("num", "any"):
            right, rt = _as_num(right, rt)
        # Quoted booleans compare as booleans with a bool ("false" is false).
        if (lt, rt) == ("str", "bool"):
            left, lt = self._as_bool(left, right)
        elif (lt, rt) == ("bool", "str"):
            right, rt = self._as_bool(right, left)
        if "any" not in (lt, rt) and lt != rt:
            self.error(f"cannot compare a {_TY_TEXT[lt]} to a {_TY_TEXT[rt]}", cmp.span)
        elif cmp.op not in ("==", "!=") and "num" not in (lt, rt) and (lt, rt) != ("any", "any"):
            kind = _TY_TEXT[lt if lt != "any" else rt]
            self.error(f"{cmp.op} orders numbers; a {kind} compares only with == and !=", cmp.span)
        return Compare(op=cmp.op, left=left, right=right, span=cmp.span), "bool"

    def _as_bool(self, expr: Expr, other: Expr) -> tuple[Expr, Ty]:
        """A string literal ``"true"``/``"false"`` (any case) compared with a bool: that
        bool; another string is a located error."""
        if isinstance(expr, Str):
            value = _BOOLS.get(expr.value.strip().lower())
            if value is not None:
                return Bool(value=value, span=expr.span, quoted=True), "bool"
            what = _bool_subject(other)
            self.error(
                f'"{expr.value}" is not a boolean: {what} is true or false (write true, false,'
                ' "true" or "false")',
                expr.span,
            )
            return expr, "bool"
        return expr, "str"

    # names
    def _name(self, name: Name) -> tuple[Expr, Ty]:
        parts, span = name.parts, name.span
        if parts[0] in self.aliases and len(parts) == 2:
            return self._measure(parts[1], span, prefixed=True)
        if len(parts) == 1:
            return self._bare(parts[0], span)
        if len(parts) == 2 and parts[1].lower() in ("min", "max") and parts[0] in self.attrs:
            return self._bound(None, parts[0], parts[1].lower(), span)
        if len(parts) == 3 and parts[2].lower() in ("min", "max"):
            return self._bound(parts[0], parts[1], parts[2].lower(), span)
        if len(parts) == 2 and self.fm.resolve_name(parts[0]) is not None:
            found = self._attribute(parts[0], parts[1], span)
            return self._attr_value(found, span) if found else (name, "any")
        written = ".".join(parts)
        if len(parts) == 2 and not self.aliases:
            hint = f" (no import declares {parts[0]}: write `import ... as {parts[0]}` first)"
        else:
            hint = f" (imports: {', '.join(sorted(self.aliases))})" if self.aliases else ""
        self.error(f"unknown name {written}{hint}", span)
        return name, "any"

    def _bare(self, text: str, span: Span | None) -> tuple[Expr, Ty]:
        measurement = self._find_measurement(text, span, quiet=True)
        owners = self.attrs.get(text, [])
        if measurement is not None and owners:
            self.error(
                f"{text} is both a measurement and an attribute: write cdm.{text} (with the "
                f"import alias) or Feature.{text}",
                span,
            )
            return Name(parts=(text,), span=span), "any"
        if owners:
            found = self._attribute(None, text, span)
            return self._attr_value(found, span) if found else (Name(parts=(text,)), "any")
        if measurement is not None or (self.meas is None and text not in ("e", "pi")):
            return self._measure(text, span, prefixed=False)
        if text in ("e", "pi"):
            return Const(name=text, span=span), "num"  # type: ignore[arg-type]
        if len(self.by_lower.get(text.lower(), [])) > 1:
            return Name(parts=(text,), span=span), "any"  # ambiguous: reported above
        names = [*self.by_name, *self.attrs]
        self.error(f"unknown name {text}{_suggest(text, names)}", span)
        return Name(parts=(text,), span=span), "any"

    def _find_measurement(self, text: str, span: Span | None, *, quiet: bool) -> Measurement | None:
        """Exact name first, then a unique case-insensitive match (cdm.material -> Material)."""
        if text in self.by_name:
            return self.by_name[text]
        matches = self.by_lower.get(text.lower(), [])
        if len(matches) == 1:
            return matches[0]
        if len(matches) > 1:
            names = ", ".join(m.name for m in matches)
            self.error(f"measurement {text} is ambiguous: it matches {names} ignoring case", span)
        elif not quiet:
            self.error(f"unknown measurement {text}{_suggest(text, self.by_name)}", span)
        return None

    def _measure(self, text: str, span: Span | None, *, prefixed: bool) -> tuple[Expr, Ty]:
        if self.meas is None:
            return Measure(name=text, type=None, span=span), "any"
        m = self._find_measurement(text, span, quiet=not prefixed)
        if m is None:
            return Name(parts=(text,), span=span), "any"
        node = Measure(name=m.name, type=m.type, max_age_ms=m.max_age_ms, span=span)
        return node, _MEAS_TY[m.type]

    def _attr_value(self, found: tuple[str, Attribute], span: Span | None) -> tuple[Expr, Ty]:
        fname, attr = found
        node = AttrValue(feature=fname, attribute=attr.name, kind=attr.kind, span=span)  # type: ignore[arg-type]
        if attr.kind == "cv":
            return node, "num"
        value = attr.rra_value
        if value is None:
            self.error(f"attribute {fname}.{attr.name} has no value", span)
            return node, "any"
        return node, _value_ty(value)

    def _bound(
        self, feature: str | None, name: str, bound: str, span: Span | None
    ) -> tuple[Expr, Ty]:
        found = self._attribute(feature, name, span)
        if found is None:
            return Name(parts=(name, bound), span=span), "num"
        fname, attr = found
        if attr.kind != "cv":
            self.error(f"{name} is not a Continuous Variability attribute: it has no {bound}", span)
        elif (attr.lower if bound == "min" else attr.upper) is None:
            self.error(
                f"{fname}.{name} declares no {'lower' if bound == 'min' else 'upper'} bound", span
            )
        return Bound(feature=fname, attribute=name, bound=bound, span=span), "num"  # type: ignore[arg-type]


_TY_TEXT: dict[str, str] = {"num": "number", "str": "string", "bool": "condition", "any": "value"}
_MEAS_TY: dict[str, Ty] = {"float": "num", "int": "num", "str": "str", "bool": "bool"}


def _value_ty(value: object) -> Ty:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int | float):
        return "num"
    return "str"


_BOOLS = {"true": True, "false": False}


def _bool_subject(expr: Expr) -> str:
    if isinstance(expr, Measure):
        return f"measurement {expr.name} (bool)"
    return "the other side"


def _numeric(expr: Expr) -> Expr:
    """A string literal spelling a number as that number; anything else unchanged."""
    if isinstance(expr, Str):
        value = _number(expr.value)
        if value is not None:
            return Num(value=value, span=expr.span, quoted=True)
    return expr


def _as_num(expr: Expr, ty: Ty) -> tuple[Expr, Ty]:
    number = _numeric(expr)
    return (number, "num") if isinstance(number, Num) else (expr, ty)


def _both_numeric(a: Expr, b: Expr) -> bool:
    return isinstance(_numeric(a), Num) and isinstance(_numeric(b), Num)
