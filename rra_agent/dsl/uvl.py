"""UVL feature models: `parse_uvl` / `load_uvl` read them, `to_uvl` writes them back.

The grammar (``uvl.lark`` beside this module) covers the Boolean level of UVL plus group
cardinalities and attributes, which is all the RRA Feature Model needs. UVL constructs beyond
that are parsed and rejected with a located `SemanticError`, never dropped. Every problem with
the text is an `RraError`: `DslSyntaxError` (with the expected tokens) or `SemanticError`s,
collected and raised through `ErrorGroup.raise_if_any`.
"""

from __future__ import annotations

import math
import re
import threading
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from functools import cache
from pathlib import Path
from typing import Any

import msgspec
from lark import Lark, Token, Tree, v_args
from lark.exceptions import (
    LarkError,
    UnexpectedCharacters,
    UnexpectedEOF,
    UnexpectedInput,
    UnexpectedToken,
    VisitError,
)
from lark.indenter import DedentError, Indenter
from lark.lexer import PatternStr
from lark.tree import Meta
from lark.visitors import Transformer_NonRecursive

from rra_agent.dsl.parser_cache import cached_lark
from rra_agent.errors import DslSyntaxError, ErrorGroup, Location, RraError, SemanticError
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
    Span,
    refs,
)

__all__ = [
    "build_parser",
    "check_feature_model",
    "load_uvl",
    "parse_uvl",
    "same_model",
    "strip_spans",
    "to_uvl",
]

_GRAMMAR = Path(__file__).with_name("uvl.lark")
#: Parse trees deeper than this are rejected: later passes recurse over features and
#: expressions, and this keeps them far from Python's recursion limit.
MAX_DEPTH = 400

# ---- the parser ---------------------------------------------------------------------------------


class _IndentError(LarkError):
    """An inconsistent dedent, with the newline token that caused it."""

    def __init__(self, token: Token, message: str) -> None:
        super().__init__(message)
        self.token = token


class _UvlIndenter(Indenter):
    """lark's Indenter for UVL; _INDENT/_DEDENT are placed where the next line's text starts."""

    NL_type = "_NL"
    OPEN_PAREN_types = ["LBRACE", "LSQB", "LPAR"]
    CLOSE_PAREN_types = ["RBRACE", "RSQB", "RPAR"]
    INDENT_type = "_INDENT"
    DEDENT_type = "_DEDENT"
    tab_len = 4

    def __init__(self) -> None:
        super().__init__()
        self.last_token: Token | None = None  # the last token that is not layout

    def handle_NL(self, token: Token) -> Iterator[Token]:
        try:
            yield from super().handle_NL(token)
        except DedentError as e:
            raise _IndentError(token, str(e)) from e

    def process(self, stream: Iterator[Token]) -> Iterator[Token]:
        self.last_token = None
        for tok in super().process(stream):
            if tok.type in (self.INDENT_type, self.DEDENT_type):
                tok = _token_at_end(tok)
            elif tok.type != self.NL_type:
                self.last_token = tok
            yield tok


def _token_at_end(tok: Token) -> Token:
    """The token moved to where its (borrowed) position ends: the next line's first column."""
    end_line, end_col, end_pos = tok.end_line, tok.end_column, tok.end_pos
    return Token(tok.type, tok.value, end_pos, end_line, end_col, end_line, end_col, end_pos)


def _have_interegular() -> bool:
    try:
        import interegular  # noqa: F401
    except ImportError:
        return False
    return True


_OPTIONS: dict[str, Any] = {
    "parser": "lalr",
    "lexer": "contextual",
    "propagate_positions": True,
    "maybe_placeholders": True,
}


def build_parser(*, strict: bool | None = None) -> Lark:
    """A new UVL parser, built from the grammar (`parse_uvl` uses a cached one).

    ``strict`` (lark rejects shift/reduce conflicts and terminal collisions) works together with
    the Indenter postlexer, but lark needs the optional ``interegular`` package for it; by
    default it is on exactly when that package is installed. Strictness only checks the grammar
    when it is built: the parser is the same either way (the tests build it strictly).
    """
    return Lark(
        _GRAMMAR.read_text(encoding="utf-8"),
        postlex=_UvlIndenter(),
        strict=_have_interegular() if strict is None else strict,
        **_OPTIONS,
    )


@cache
def _parser() -> Lark:
    """The parser `parse_uvl` uses: built (strictly, when possible) once per grammar version
    and then loaded from the on-disk cache (`rra_agent.dsl.parser_cache`)."""
    return cached_lark(
        "uvl",
        _GRAMMAR.read_text(encoding="utf-8"),
        postlex=_UvlIndenter(),
        strict=_have_interegular(),
        **_OPTIONS,
    )


# lark's postlexer keeps its state on the one cached instance: one parse at a time.
_PARSE_LOCK = threading.Lock()


# ---- syntax errors ------------------------------------------------------------------------------

_TERMINAL_NAMES = {
    "ID": "name",
    "QUOTED_ID": "quoted name",
    "STRING": "string",
    "INT": "integer",
    "FLOAT": "number",
    "_NL": "end of line",
    "_INDENT": "indent",
    "_DEDENT": "dedent",
    "$END": "end of input",
}


def _human(terminal: str) -> str:
    """A readable name for a lark terminal: ``'{'`` for literals, words for the others."""
    if terminal in _TERMINAL_NAMES:
        return _TERMINAL_NAMES[terminal]
    try:
        pattern = _parser().get_terminal(terminal).pattern
    except KeyError:
        return terminal.lower()
    return f"'{pattern.value}'" if isinstance(pattern, PatternStr) else terminal.lower()


def _line_of(text: str, line: int) -> str | None:
    lines = text.split("\n")  # lark counts lines by "\n" only
    return lines[line - 1].rstrip("\r") if 1 <= line <= len(lines) else None


@dataclass(frozen=True, slots=True)
class _Source:
    """The text being parsed and where its last real token ends (for end-of-input errors)."""

    text: str
    file: str
    eof: tuple[int, int]

    def syntax_error(self, what: str, line: int, col: int, expected: set[str]) -> DslSyntaxError:
        names = sorted({_human(t) for t in expected})
        message = f"unexpected {what}"
        if len(names) == 1:
            message += f", expected {names[0]}"
        elif names:
            message += f", expected one of {', '.join(names)}"
        return DslSyntaxError(
            message,
            Location(self.file, line, col),
            expected=names,
            source_line=_line_of(self.text, line),
        )


def _expected(e: UnexpectedInput) -> set[str]:
    parser = getattr(e, "interactive_parser", None)
    if parser is not None:
        accepts = parser.accepts()
        if accepts:
            return set(accepts)
    return set(getattr(e, "expected", None) or getattr(e, "allowed", None) or ())


def _syntax_error(e: UnexpectedInput, src: _Source) -> DslSyntaxError:
    expected = _expected(e)
    if isinstance(e, UnexpectedCharacters):
        return src.syntax_error(f"character {e.char!r}", e.line, e.column, expected)
    if isinstance(e, UnexpectedToken):
        tok = e.token
        if tok.type == "$END" or (tok.type == "_DEDENT" and tok.end_pos >= len(src.text)):
            return src.syntax_error("end of input", *src.eof, expected)
        what = _human(tok.type)
        if tok.type in ("ID", "QUOTED_ID", "STRING", "INT", "FLOAT"):
            what = (
                f"{what} {tok.value}" if tok.type in ("QUOTED_ID", "STRING") else f"{what} '{tok}'"
            )
        return src.syntax_error(what, tok.line, tok.column, expected)
    if isinstance(e, UnexpectedEOF):
        return src.syntax_error("end of input", *src.eof, expected)
    return src.syntax_error("input", e.line, e.column, expected)  # pragma: no cover


def _indent_error(e: _IndentError, src: _Source) -> DslSyntaxError:
    tok = e.token
    # The Indenter has popped the blocks this line closes; the rest are the dedent targets.
    columns = [f"{n + 1}" for n in _parser().options.postlex.indent_level]
    return DslSyntaxError(
        f"inconsistent dedent to column {tok.end_column}, which matches no enclosing block "
        f"(expected column {' or '.join(columns)})",
        Location(src.file, tok.end_line, tok.end_column),
        expected=[f"indentation to column {c}" for c in columns],
        source_line=_line_of(src.text, tok.end_line),
    )


def _parse_tree(text: str, file: str) -> Tree:
    """lark's parse tree of ``text``; every failure becomes a located `DslSyntaxError`."""
    padded = text if text.endswith("\n") else text + "\n"
    parser = _parser()
    indenter: _UvlIndenter = parser.options.postlex
    with _PARSE_LOCK:
        try:
            return parser.parse(padded)
        except (UnexpectedInput, _IndentError) as e:
            last = indenter.last_token
            eof = (last.end_line, last.end_column) if last is not None else (1, 1)
            src = _Source(padded, file, eof)
            if isinstance(e, _IndentError):
                raise _indent_error(e, src) from None
            raise _syntax_error(e, src) from None
        except LarkError as e:  # pragma: no cover - lark's other errors are grammar errors
            raise DslSyntaxError(f"cannot parse: {e}", Location(file, 1, 1)) from None


def _check_depth(tree: Tree, file: str) -> None:
    stack: list[tuple[Tree, int]] = [(tree, 1)]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_DEPTH:
            where = Location(file, node.meta.line, node.meta.column)
            raise DslSyntaxError(f"nested more than {MAX_DEPTH} levels deep", where)
        stack.extend((c, depth + 1) for c in node.children if isinstance(c, Tree))


# ---- the transformer ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Name:
    text: str
    span: Span


@dataclass(frozen=True, slots=True)
class _Entry:
    """One ``key value`` of an attribute list, before it becomes an Attribute or a dict item."""

    name: _Name
    value: Any
    key_spans: dict[str, Span] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class _AttrList:
    entries: list[_Entry]


@dataclass(frozen=True, slots=True)
class _Unsupported:
    """A constraint sub-expression outside Boolean UVL; the lowest rank is reported."""

    construct: str
    span: Span
    rank: int
    has_string: bool = False

    def merge(self, other: object) -> _Unsupported:
        if not isinstance(other, _Unsupported):
            return self
        mine = (self.rank, self.span.line, self.span.col)
        theirs = (other.rank, other.span.line, other.span.col)
        best = self if mine <= theirs else other
        return replace(best, has_string=self.has_string or other.has_string)


@dataclass(frozen=True, slots=True)
class _Parsed:
    namespace: str | None
    root: Feature
    constraints: tuple[Constraint, ...]


def _unsupported(construct: str, span: Span) -> SemanticError:
    return SemanticError(
        f"UVL construct {construct} is not supported by rra-agent", span.location()
    )


@v_args(meta=True)
class _ToModel(Transformer_NonRecursive):
    """Parse tree -> model objects. Problems are collected in `errors`, never raised."""

    def __init__(self, file: str) -> None:
        super().__init__()
        self.file = file
        self.errors: list[SemanticError] = []
        self.unsupported = False
        #: attribute span -> spans of the keys of its map value (for precise error locations)
        self.key_spans: dict[Span, dict[str, Span]] = {}

    # -- helpers --
    def _span(self, line: int, col: int) -> Span:
        return Span(self.file, line, col)

    def _tok_span(self, tok: Token) -> Span:
        return self._span(tok.line, tok.column)

    def _reject(self, construct: str, span: Span) -> None:
        self.unsupported = True
        self.errors.append(_unsupported(construct, span))

    def _int(self, tok: Token) -> int:
        try:
            return int(tok)
        except ValueError:  # more digits than Python converts
            self.errors.append(SemanticError("number too long", self._tok_span(tok).location()))
            return 0

    def _plain(self, value: Any) -> Any:
        """A parsed value as the model holds it: attribute lists become dicts."""
        if not isinstance(value, _AttrList):
            return value
        out: dict[str, Any] = {}
        seen: dict[str, Span] = {}
        for entry in value.entries:
            key = entry.name.text
            if key in seen:
                first = seen[key]
                self.errors.append(
                    SemanticError(
                        f"duplicate key '{key}' (first given at {first.line}:{first.col})",
                        entry.name.span.location(),
                    )
                )
                continue
            seen[key] = entry.name.span
            out[key] = entry.value
        return out

    # -- sections --
    def start(self, meta: Meta, children: list[Any]) -> _Parsed:
        namespace = next((c for c in children if isinstance(c, str)), None)
        root = next(c for c in children if isinstance(c, Feature))
        constraints = next((c for c in children if isinstance(c, tuple)), ())
        return _Parsed(namespace, root, constraints)

    def namespace(self, meta: Meta, children: list[Any]) -> str:
        return children[0].text

    def include(self, meta: Meta, children: list[Any]) -> None:
        self._reject("'include'", self._tok_span(children[0]))

    def include_line(self, meta: Meta, children: list[Any]) -> None:
        return None

    def imports(self, meta: Meta, children: list[Any]) -> None:
        self._reject("'imports'", self._tok_span(children[0]))

    def import_line(self, meta: Meta, children: list[Any]) -> None:
        return None

    def features(self, meta: Meta, children: list[Any]) -> Feature:
        return children[0]

    # -- the feature tree --
    def feature(self, meta: Meta, children: list[Any]) -> Feature:
        _type, name, _card, attributes, groups = children
        attrs = []
        for entry in attributes.entries if attributes is not None else ():
            attr = Attribute(name=entry.name.text, value=entry.value, span=entry.name.span)
            if entry.key_spans:
                self.key_spans[entry.name.span] = entry.key_spans
            attrs.append(attr)
        return Feature(name=name.text, attributes=tuple(attrs), groups=groups or (), span=name.span)

    def feature_type(self, meta: Meta, children: list[Any]) -> None:
        self._reject(f"'typed feature ({children[0]})'", self._span(meta.line, meta.column))

    def feature_cardinality(self, meta: Meta, children: list[Any]) -> None:
        self._reject("'feature cardinality'", self._span(meta.line, meta.column))

    def children(self, meta: Meta, children: list[Group]) -> tuple[Group, ...]:
        return tuple(children)

    def group(self, meta: Meta, children: list[Any]) -> Group:
        keyword, members = children
        span = self._tok_span(keyword)
        return Group(kind=str(keyword), children=members or (), span=span)

    def cardinality_group(self, meta: Meta, children: list[Any]) -> Group:
        (lower, upper), members = children
        span = self._span(meta.line, meta.column)
        return Group(
            kind="cardinality", children=members or (), lower=lower, upper=upper, span=span
        )

    def group_cardinality(self, meta: Meta, children: list[Any]) -> tuple[int, int | None]:
        low_tok, high_tok = children
        lower = self._int(low_tok)
        if high_tok is None:
            return lower, lower
        return lower, None if high_tok.type == "STAR" else self._int(high_tok)

    def members(self, meta: Meta, children: list[Feature]) -> tuple[Feature, ...]:
        return tuple(children)

    # -- attributes --
    def attributes(self, meta: Meta, children: list[Any]) -> _AttrList:
        return _AttrList([c for c in children if isinstance(c, _Entry)])

    def value_attribute(self, meta: Meta, children: list[Any]) -> _Entry:
        name, value = children
        spans = (
            {e.name.text: e.name.span for e in value.entries}
            if isinstance(value, _AttrList)
            else {}
        )
        return _Entry(name, self._plain(value), spans)

    def constraint_attribute(self, meta: Meta, children: list[Any]) -> None:
        self._reject("'constraint attribute'", self._tok_span(children[0]))

    def string(self, meta: Meta, children: list[Token]) -> str:
        return str(children[0])[1:-1]

    def number(self, meta: Meta, children: list[Any]) -> int | float:
        minus, tok = children
        value: int | float = self._int(tok) if tok.type == "INT" else float(tok)
        if not math.isfinite(value):
            self.errors.append(SemanticError("number out of range", self._tok_span(tok).location()))
            value = 0.0
        return -value if minus is not None else value

    def true(self, meta: Meta, children: list[Any]) -> bool:
        return True

    def false(self, meta: Meta, children: list[Any]) -> bool:
        return False

    def vector(self, meta: Meta, children: list[Any]) -> list[Any]:
        return [self._plain(c) for c in children]

    # -- constraints --
    def constraints(self, meta: Meta, children: list[Any]) -> tuple[Constraint, ...]:
        return tuple(c for c in children if isinstance(c, Constraint))

    def constraint_line(self, meta: Meta, children: list[Any]) -> Constraint | None:
        (expr,) = children
        if isinstance(expr, _Unsupported):
            self._reject(expr.construct, expr.span)
            return None
        return Constraint(expr=expr, span=self._span(meta.line, meta.column))

    def _binary(self, cls: type, children: list[Any]) -> Expr | _Unsupported:
        left, right = children
        if isinstance(left, _Unsupported):
            return left.merge(right)
        if isinstance(right, _Unsupported):
            return right
        return cls(left=left, right=right)

    def equiv(self, meta: Meta, children: list[Any]) -> Expr | _Unsupported:
        return self._binary(Equiv, children)

    def implies(self, meta: Meta, children: list[Any]) -> Expr | _Unsupported:
        return self._binary(Implies, children)

    def disjunction(self, meta: Meta, children: list[Any]) -> Expr | _Unsupported:
        return self._binary(Or, children)

    def conjunction(self, meta: Meta, children: list[Any]) -> Expr | _Unsupported:
        return self._binary(And, children)

    def negation(self, meta: Meta, children: list[Any]) -> Expr | _Unsupported:
        (operand,) = children
        return operand if isinstance(operand, _Unsupported) else Not(operand=operand)

    def _outside(self, meta: Meta, children: list[Any], construct: str, rank: int) -> _Unsupported:
        here = _Unsupported(construct, self._span(meta.line, meta.column), rank)
        for child in children:
            here = here.merge(child)
        return here

    def comparison(self, meta: Meta, children: list[Any]) -> _Unsupported:
        strings = any(isinstance(c, _Unsupported) and c.has_string for c in children)
        if strings:
            return self._outside(meta, children, "'string constraint'", 1)
        return self._outside(meta, children, "'arithmetic/attribute constraint'", 2)

    def arithmetic(self, meta: Meta, children: list[Any]) -> _Unsupported:
        return self._outside(meta, children, "'arithmetic expression'", 3)

    def literal(self, meta: Meta, children: list[Token]) -> _Unsupported:
        span = self._span(meta.line, meta.column)
        is_string = children[0].type == "STRING"
        construct = "'string constraint'" if is_string else "'arithmetic expression'"
        return _Unsupported(construct, span, 3, has_string=is_string)

    def call(self, meta: Meta, children: list[Any]) -> _Unsupported:
        name = children[0]
        here = _Unsupported(f"'function {name.text}()'", name.span, 0)
        for child in children[1:]:
            here = here.merge(child)
        return here

    def ref(self, meta: Meta, children: list[_Name]) -> Ref:
        (name,) = children
        return Ref(name=name.text, span=name.span)

    def name(self, meta: Meta, children: list[Token]) -> _Name:
        (tok,) = children
        text = str(tok)[1:-1] if tok.type == "QUOTED_ID" else str(tok)
        return _Name(text, self._tok_span(tok))


# ---- semantic checks ----------------------------------------------------------------------------

BINDINGS = ("deployment", "runtime")
KINDS = ("cim", "nfr", "cv")
NFR_TAGS = ("min", "max", "avg", "count")
KINDED_KEYS = frozenset(
    {"kind", "value", "unit", "tag", "lower", "upper", "scale", "constrains", "description"}
)
_IDENTIFIER = re.compile(r"[^\W\d]\w*")


def _loc(span: Span | None) -> Location | None:
    return span.location() if span is not None else None


def _at(span: Span | None, words: str = "first at") -> str:
    """`` (first at line:col)`` to point at an earlier occurrence, if it has a place."""
    return f" ({words} {span.line}:{span.col})" if span is not None else ""


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _walk(root: Feature) -> Iterator[tuple[Feature, Feature | None]]:
    """(feature, parent) in depth-first pre-order, without recursion."""
    stack: list[tuple[Feature, Feature | None]] = [(root, None)]
    while stack:
        f, parent = stack.pop()
        yield f, parent
        stack.extend((c, f) for c in reversed(list(f.children)))


class _Checker:
    """The semantic checks of a feature model; `run` returns every problem found."""

    def __init__(self, fm: FeatureModel, key_spans: Mapping[Span, Mapping[str, Span]]) -> None:
        self.fm = fm
        self.key_spans = key_spans
        self.tree = list(_walk(fm.root))
        self.errors: list[SemanticError] = []

    def error(self, message: str, span: Span | None) -> None:
        self.errors.append(SemanticError(message, _loc(span)))

    def run(self) -> list[SemanticError]:
        unique = self.check_names()
        for f, _parent in self.tree:
            self.check_feature_attributes(f)
            self.check_groups(f)
        if unique:
            self.check_binding_inheritance()
        self.check_aliases()
        self.check_kinded()
        self.check_constraints()
        return sorted(self.errors, key=_error_order)

    # -- features and groups --
    def check_names(self) -> bool:
        first: dict[str, Feature] = {}
        for f, _parent in self.tree:
            if f.name in first:
                where = _at(first[f.name].span, "first declared at")
                self.error(f"duplicate feature name '{f.name}'{where}", f.span)
            else:
                first[f.name] = f
        return len(first) == len(self.tree)

    def check_groups(self, f: Feature) -> None:
        for g in f.groups:
            if g.kind == "cardinality" and g.upper is not None and (g.lower or 0) > g.upper:
                self.error(
                    f"group cardinality lower bound {g.lower} exceeds upper bound {g.upper}",
                    g.span,
                )

    def check_feature_attributes(self, f: Feature) -> None:
        seen: dict[str, Attribute] = {}
        for a in f.attributes:
            if a.name in seen:
                self.error(
                    f"feature '{f.name}' has attribute '{a.name}' twice{_at(seen[a.name].span)}",
                    a.span,
                )
                continue
            seen[a.name] = a
            if a.name == "binding" and a.value not in BINDINGS:
                self.error(
                    f"binding must be 'deployment' or 'runtime', not {_show(a.value)}", a.span
                )
            elif a.name == "alias" and not (
                isinstance(a.value, str) and _IDENTIFIER.fullmatch(a.value)
            ):
                self.error(
                    f"alias must be a string holding a plain identifier, not {_show(a.value)}",
                    a.span,
                )
            elif a.name == "abstract" and a.value not in (None, True, False):
                self.error(f"abstract must be a flag or true/false, not {_show(a.value)}", a.span)

    def check_binding_inheritance(self) -> None:
        binding = self.fm.binding
        for f, parent in self.tree:
            if (
                parent is not None
                and f.declared_binding == "deployment"
                and binding[parent.name] == "runtime"
            ):
                self.error(
                    f"feature '{f.name}' is bound at deployment time but its parent "
                    f"'{parent.name}' is bound at run time",
                    _attr_span(f, "binding"),
                )

    def check_aliases(self) -> None:
        names = {f.name for f, _ in self.tree}
        owner: dict[str, Feature] = {}
        for f, _parent in self.tree:
            alias = f.alias
            if alias is None or not _IDENTIFIER.fullmatch(alias):
                continue
            span = _attr_span(f, "alias")
            if alias in owner:
                self.error(f"alias '{alias}' is already used by '{owner[alias].name}'", span)
            elif alias in names and alias != f.name:
                self.error(f"alias '{alias}' of '{f.name}' is the name of another feature", span)
            owner.setdefault(alias, f)

    # -- cim / nfr / cv attributes --
    def check_kinded(self) -> None:
        kinded = [
            a
            for f, _ in self.tree
            for a in f.attributes
            if isinstance(a.value, dict) and "kind" in a.value
        ]
        cvs = {a.name for a in kinded if a.kind == "cv"}
        first: dict[str, Attribute] = {}
        for a in kinded:
            self.check_attribute_shape(a, cvs)
            if a.name in first:
                self.check_reuse(first[a.name], a)
            first.setdefault(a.name, a)

    def check_reuse(self, first: Attribute, a: Attribute) -> None:
        """Rules name attributes bare: only CIM attributes (one per variant) may share a name."""
        if a.kind != "cim" or first.kind != "cim":
            self.error(
                f"attribute name '{a.name}' is used twice{_at(first.span)}; rules refer to "
                "attributes by name, so only cim attributes of different features may share one",
                a.span,
            )
            return
        for key in ("scale", "unit"):
            if a.value.get(key) != first.value.get(key):  # type: ignore[union-attr]
                self.error(
                    f"cim attribute '{a.name}' has a different {key} than its first use"
                    f"{_at(first.span, 'at')}; "
                    "variants are compared by it, so it must be the same",
                    self.key_span(a, key),
                )

    def key_span(self, a: Attribute, key: str) -> Span | None:
        spans = self.key_spans.get(a.span) if a.span is not None else None
        return (spans or {}).get(key, a.span)

    def check_attribute_shape(self, a: Attribute, cvs: set[str]) -> None:
        assert isinstance(a.value, dict)
        v = a.value
        if v["kind"] not in KINDS:
            self.error(
                f"attribute '{a.name}': kind must be 'cim', 'nfr' or 'cv', not {_show(v['kind'])}",
                self.key_span(a, "kind"),
            )
            return
        for key in v:
            if key not in KINDED_KEYS:
                allowed = ", ".join(sorted(KINDED_KEYS))
                self.error(
                    f"attribute '{a.name}': unknown key '{key}' (allowed: {allowed})",
                    self.key_span(a, key),
                )
        for key in ("unit", "description"):
            if key in v and not isinstance(v[key], str):
                self.error(f"attribute '{a.name}': {key} must be a string", self.key_span(a, key))
        {"cim": self.check_cim, "nfr": self.check_nfr, "cv": self.check_cv}[v["kind"]](a, cvs)

    def require(self, a: Attribute, key: str, what: str, ok: bool) -> bool:
        """Report ``key`` of ``a`` unless ``ok``; says whether it was fine."""
        assert isinstance(a.value, dict)
        if ok:
            return True
        if key not in a.value:
            self.error(f"{a.kind} attribute '{a.name}' needs {key} ({what})", a.span)
        else:
            shown = _show(a.value[key])
            self.error(
                f"{a.kind} attribute '{a.name}': {key} must be {what}, not {shown}",
                self.key_span(a, key),
            )
        return False

    def check_cim(self, a: Attribute, cvs: set[str]) -> None:
        assert isinstance(a.value, dict)
        value, scale = a.value.get("value"), a.value.get("scale")
        ok = self.require(
            a, "value", "a number or a string", _is_number(value) or isinstance(value, str)
        )
        if "scale" in a.value or isinstance(value, str):
            good_scale = (
                isinstance(scale, list)
                and bool(scale)
                and all(isinstance(s, str) for s in scale)
                and len(set(scale)) == len(scale)
            )
            what = "a list of distinct strings, lowest first"
            if self.require(a, "scale", what, good_scale) and ok and isinstance(value, str):
                self.require(a, "value", f"one of the scale {scale}", value in scale)

    def check_nfr(self, a: Attribute, cvs: set[str]) -> None:
        assert isinstance(a.value, dict)
        v = a.value
        self.require(a, "tag", "'min', 'max', 'avg' or 'count'", v.get("tag") in NFR_TAGS)
        self.require(a, "value", "a number", _is_number(v.get("value")))
        if "constrains" in v:
            known = ", ".join(sorted(cvs)) or "none"
            what = f"the name of a cv attribute (known: {known})"
            target = v["constrains"]
            self.require(a, "constrains", what, isinstance(target, str) and target in cvs)

    def check_cv(self, a: Attribute, cvs: set[str]) -> None:
        assert isinstance(a.value, dict)
        v = a.value
        low = self.require(a, "lower", "a number", _is_number(v.get("lower")))
        high = self.require(a, "upper", "a number", _is_number(v.get("upper")))
        if low and high and v["lower"] > v["upper"]:
            self.error(
                f"cv attribute '{a.name}': lower {v['lower']} exceeds upper {v['upper']}",
                self.key_span(a, "lower"),
            )

    # -- constraints --
    def check_constraints(self) -> None:
        names = {f.name for f, _ in self.tree}
        for c in self.fm.constraints:
            for r in refs(c.expr):
                if r.name in names:
                    continue
                hint = ""
                if r.name in self.fm.aliases:
                    hint = f" ('{r.name}' is the alias of '{self.fm.aliases[r.name]}'; "
                    hint += "UVL constraints use feature names)"
                self.error(f"constraint refers to unknown feature '{r.name}'{hint}", r.span)


def _attr_span(f: Feature, name: str) -> Span | None:
    a = f.attribute(name)
    return a.span if a is not None and a.span is not None else f.span


def _show(value: object) -> str:
    return "nothing" if value is None else _format_value(value, strict=False)


def _error_order(e: SemanticError) -> tuple[str, int, int]:
    loc = e.location
    return (loc.file, loc.line, loc.col) if loc is not None else ("", 0, 0)


def check_feature_model(
    fm: FeatureModel, key_spans: Mapping[Span, Mapping[str, Span]] | None = None
) -> list[SemanticError]:
    """Every semantic problem of ``fm``, in source order.

    Checked: unique feature names; constraints name existing features; ``binding`` is
    'deployment' or 'runtime', and no deployment-bound feature sits under a runtime-bound one;
    aliases are identifiers, unique, and not another feature's name; ``abstract`` is a flag;
    group cardinalities have lower <= upper; ``{kind ...}`` attributes have the shape their
    kind needs (cim: value, and a scale holding a string value; nfr: tag and numeric value,
    ``constrains`` naming a cv attribute; cv: numeric lower <= upper), only known keys, and
    names unique across the model except cim attributes repeated on several variants with the
    same scale and unit.

    ``key_spans`` (attribute span -> spans of its map's keys) sharpens error locations inside
    ``{kind ..., ...}`` maps; `parse_uvl` passes it, models built in code need not.
    """
    return _Checker(fm, key_spans or {}).run()


# ---- public entry points ------------------------------------------------------------------------


def parse_uvl(text: str, file: str = "<uvl>") -> FeatureModel:
    """Parse UVL text into a `FeatureModel` (``file`` names the text in errors and spans)."""
    tree = _parse_tree(text, file)
    _check_depth(tree, file)
    to_model = _ToModel(file)
    try:
        parsed: _Parsed = to_model.transform(tree)
    except VisitError as e:  # pragma: no cover - a bug in a transformer method
        raise e.orig_exc from None
    errors: list[SemanticError] = sorted(to_model.errors, key=_error_order)
    if to_model.unsupported:  # parts were left out: checking the rest would mislead
        ErrorGroup.raise_if_any(errors)
    fm = FeatureModel(
        root=parsed.root,
        constraints=parsed.constraints,
        namespace=parsed.namespace,
        source=file,
    )
    errors += check_feature_model(fm, to_model.key_spans)
    ErrorGroup.raise_if_any(sorted(errors, key=_error_order))
    return fm


def load_uvl(path: str | Path) -> FeatureModel:
    """Read and parse a UVL file; errors name the file as ``path`` was given."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise RraError(f"{path}: cannot read UVL file: {e}") from None
    return parse_uvl(text, file=str(path))


# ---- export -------------------------------------------------------------------------------------

_INDENT = "    "
#: Words the grammar treats as keywords somewhere: such names are always written quoted.
KEYWORDS = frozenset(
    {
        "namespace", "include", "imports", "as", "features", "constraints", "constraint",
        "cardinality", "mandatory", "optional", "alternative", "or", "true", "false",
        "Integer", "String", "Real", "Boolean",
    }
)  # fmt: skip
_PLAIN_NAME = re.compile(r"[^\W\d]\w*(\.[^\W\d]\w*)*")
_QUOTABLE = re.compile(r'[^"\r\n]+')
_STRING_OK = re.compile(r"[^'\r\n]*")


def _format_name(name: object) -> str:
    if not isinstance(name, str):
        raise RraError(f"UVL names are strings, not {name!r}")
    if _PLAIN_NAME.fullmatch(name) and name not in KEYWORDS:
        return name
    if _QUOTABLE.fullmatch(name):
        return f'"{name}"'
    raise RraError(f"name {name!r} cannot be written in UVL (empty, or holds '\"' or a newline)")


def _format_value(value: object, *, strict: bool = True) -> str:
    """A value in UVL syntax; with ``strict`` (export) an unwritable value is an error."""
    match value:
        case bool():
            return "true" if value else "false"
        case int():
            return _format_int(value, strict=strict)
        case float() if math.isfinite(value) or not strict:
            return repr(value)
        case str() if _STRING_OK.fullmatch(value) or not strict:
            return f"'{value}'"
        case list() | tuple():
            return "[" + ", ".join(_format_value(v, strict=strict) for v in value) + "]"
        case dict():
            return _format_map(value, strict=strict)
    if strict:
        raise RraError(f"value {value!r} cannot be written in UVL")
    return repr(value)


def _format_int(value: int, *, strict: bool) -> str:
    try:
        return str(value)
    except ValueError:  # beyond Python's int -> str digit limit
        if strict:
            raise RraError("integer too large to be written in UVL") from None
        return "<huge integer>"


def _format_map(items: Mapping[Any, Any], *, strict: bool = True) -> str:
    return _format_pairs(items.items(), strict=strict)


def _format_pairs(items: Iterable[tuple[Any, Any]], *, strict: bool = True) -> str:
    """``{key value, flag, ...}``; a None value is written as a bare key (a flag)."""
    parts = []
    for key, v in items:
        k = _format_name(key) if strict else str(key)
        parts.append(k if v is None else f"{k} {_format_value(v, strict=strict)}")
    return "{" + ", ".join(parts) + "}"


def _feature_lines(f: Feature, depth: int, out: list[str]) -> None:
    line = _INDENT * depth + _format_name(f.name)
    if f.attributes:
        line += " " + _format_pairs((a.name, a.value) for a in f.attributes)
    out.append(line)
    for g in f.groups:
        out.append(_INDENT * (depth + 1) + _group_keyword(g))
        for child in g.children:
            _feature_lines(child, depth + 2, out)


def _group_keyword(g: Group) -> str:
    if g.kind in ("mandatory", "optional", "alternative", "or"):
        return g.kind
    if g.kind != "cardinality":
        raise RraError(f"group kind {g.kind!r} cannot be written in UVL")
    lower = g.lower or 0
    if g.upper is None:
        return f"[{lower}..*]"
    return f"[{lower}]" if lower == g.upper else f"[{lower}..{g.upper}]"


#: Binding strength of each operator (higher binds tighter), as in the grammar.
_PRECEDENCE: dict[type, int] = {Equiv: 1, Implies: 2, Or: 3, And: 4, Not: 5, Ref: 6}
_OPERATOR: dict[type, str] = {Equiv: "<=>", Implies: "=>", Or: "|", And: "&"}


def _format_expr(e: Expr, context: int = 0) -> str:
    """``e`` in UVL syntax, parenthesised if it binds looser than ``context`` needs."""
    match e:
        case Ref(name=name):
            text = _format_name(name)
        case Not(operand=o):
            text = "!" + _format_expr(o, _PRECEDENCE[Not])
        case (
            And(left=a, right=b)
            | Or(left=a, right=b)
            | Implies(left=a, right=b)
            | Equiv(left=a, right=b)
        ):
            p = _PRECEDENCE[type(e)]  # left-associative: the right operand must bind tighter
            text = f"{_format_expr(a, p)} {_OPERATOR[type(e)]} {_format_expr(b, p + 1)}"
        case _:
            raise RraError(f"not a constraint expression: {e!r}")
    return f"({text})" if _PRECEDENCE[type(e)] < context else text


def to_uvl(fm: FeatureModel) -> str:
    """``fm`` as UVL text (4-space indentation); `parse_uvl` reads it back to an equal model."""
    out: list[str] = []
    if fm.namespace is not None:
        out += [f"namespace {_format_name(fm.namespace)}", ""]
    out.append("features")
    _feature_lines(fm.root, 1, out)
    if fm.constraints:
        out += ["", "constraints"]
        out += [_INDENT + _format_expr(c.expr) for c in fm.constraints]
    return "\n".join(out) + "\n"


# ---- comparing models ---------------------------------------------------------------------------


def _strip_expr(e: Expr) -> Expr:
    match e:
        case Ref():
            return msgspec.structs.replace(e, span=None)
        case Not(operand=o):
            return Not(operand=_strip_expr(o))
        case And() | Or() | Implies() | Equiv():
            return type(e)(left=_strip_expr(e.left), right=_strip_expr(e.right))
    raise RraError(f"not a constraint expression: {e!r}")


def _strip_feature(f: Feature) -> Feature:
    return Feature(
        name=f.name,
        attributes=tuple(msgspec.structs.replace(a, span=None) for a in f.attributes),
        groups=tuple(
            msgspec.structs.replace(g, span=None, children=tuple(map(_strip_feature, g.children)))
            for g in f.groups
        ),
    )


def strip_spans(fm: FeatureModel) -> FeatureModel:
    """``fm`` without source positions, to compare models regardless of where they were read."""
    return msgspec.structs.replace(
        fm,
        root=_strip_feature(fm.root),
        constraints=tuple(Constraint(expr=_strip_expr(c.expr)) for c in fm.constraints),
    )


def same_model(a: FeatureModel, b: FeatureModel) -> bool:
    """Whether two models are equal up to spans, value types included (``1`` is not ``true``)."""
    enc = msgspec.json.encode
    return enc(strip_spans(a)) == enc(strip_spans(b))
