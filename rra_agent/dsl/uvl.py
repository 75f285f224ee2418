"""UVL feature models: `parse_uvl` / `load_uvl` read them, `to_uvl` writes them back.

The grammar (``uvl.lark`` beside this module) covers the whole UVL language of the reference
parser (``uvlparser``): namespace, include levels, imports, typed features, feature and group
cardinalities, attributes and constraint attributes, and constraints with comparisons,
arithmetic and aggregate functions. Everything is kept in the `FeatureModel` and exported back;
what rra-agent's propositional reasoning cannot use is listed by `uvl_warnings`, located. Every
problem with the text is an `RraError`: `DslSyntaxError` (with the expected tokens) or
`SemanticError`s, collected and raised through `ErrorGroup.raise_if_any`. The built parser is
loaded from the on-disk cache of `rra_agent.dsl.parser_cache`.
"""

from __future__ import annotations

import gc
import math
import re
import threading
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any, TypeVar, get_args

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
    Aggregate,
    And,
    Arith,
    ArithOp,
    Attribute,
    Cardinality,
    Compare,
    CompareOp,
    Constraint,
    ConstraintList,
    Equiv,
    Expr,
    Feature,
    FeatureModel,
    Group,
    GroupKind,
    Implies,
    Import,
    Not,
    Num,
    Or,
    Ref,
    Span,
    Text,
    refs,
    subexpressions,
)

__all__ = [
    "UvlWarning",
    "build_parser",
    "check_feature_model",
    "load_uvl",
    "parse_uvl",
    "same_model",
    "strip_spans",
    "to_uvl",
    "uvl_warnings",
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


def _position(line: int | None, col: int | None) -> tuple[int, int]:
    """A position lark left Optional; its lexer sets it on every token it makes."""
    if line is None or col is None:  # pragma: no cover - only hand-made tokens lack one
        raise ValueError("a UVL token without a position in the text")
    return line, col


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


def _indenter(parser: Lark) -> _UvlIndenter:
    """The postlexer `_parser` builds ``parser`` with."""
    postlex = parser.options.postlex
    if not isinstance(postlex, _UvlIndenter):  # pragma: no cover - _parser always sets it
        raise TypeError(f"the UVL parser's postlexer is {postlex!r}, not a _UvlIndenter")
    return postlex


def _indent_error(e: _IndentError, src: _Source) -> DslSyntaxError:
    line, col = _position(e.token.end_line, e.token.end_column)
    # The Indenter has popped the blocks this line closes; the rest are the dedent targets.
    columns = [f"{n + 1}" for n in _indenter(_parser()).indent_level]
    return DslSyntaxError(
        f"inconsistent dedent to column {col}, which matches no enclosing block "
        f"(expected column {' or '.join(columns)})",
        Location(src.file, line, col),
        expected=[f"indentation to column {c}" for c in columns],
        source_line=_line_of(src.text, line),
    )


def _parse_tree(text: str, file: str) -> Tree:
    """lark's parse tree of ``text``; every failure becomes a located `DslSyntaxError`."""
    padded = text if text.endswith("\n") else text + "\n"
    parser = _parser()
    indenter = _indenter(parser)
    with _PARSE_LOCK:
        try:
            return parser.parse(padded)
        except (UnexpectedInput, _IndentError) as e:
            last = indenter.last_token
            eof = _position(last.end_line, last.end_column) if last is not None else (1, 1)
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
class _Includes:
    levels: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class _Imports:
    imports: tuple[Import, ...]


@dataclass(frozen=True, slots=True)
class _Parsed:
    namespace: str | None
    includes: tuple[str, ...]
    imports: tuple[Import, ...]
    root: Feature
    constraints: tuple[Constraint, ...]


#: Expressions that are conditions (true or false) and those that are terms (values).
_CONDITIONS = (Ref, Not, And, Or, Implies, Equiv, Compare)
_TERMS = (Ref, Num, Text, Arith, Aggregate)
#: Aggregate functions and how many references each takes.
_FUNCTIONS: dict[str, tuple[int, int]] = {
    "sum": (1, 2),
    "avg": (1, 2),
    "len": (1, 1),
    "floor": (1, 1),
    "ceil": (1, 1),
}


def _describe(e: Expr) -> str:
    match e:
        case Num():
            return "a number"
        case Text():
            return "a string"
        case Arith():
            return "an arithmetic term"
        case Aggregate(function=f):
            return f"the function {f}()"
        case Compare():
            return "a comparison"
    return "a condition"


#: The grammar's group keywords and operators: the model's Literal values (a cardinality
#: group has no keyword).
_GROUP_KEYWORDS: tuple[GroupKind, ...] = tuple(k for k in get_args(GroupKind) if k != "cardinality")
_COMPARE_OPS: tuple[CompareOp, ...] = get_args(CompareOp)
_ARITH_OPS: tuple[ArithOp, ...] = get_args(ArithOp)

_Word = TypeVar("_Word", bound=str)


def _one_of(tok: Token, allowed: tuple[_Word, ...]) -> _Word:
    """``tok``'s text as the one of the ``allowed`` values it is (the grammar admits no other)."""
    for value in allowed:
        if tok == value:
            return value
    raise ValueError(f"{tok!r} is none of {allowed}")  # pragma: no cover - grammar guarantees


@v_args(meta=True)
class _ToModel(Transformer_NonRecursive):
    """Parse tree -> model objects. Problems are collected in `errors`, never raised."""

    def __init__(self, file: str) -> None:
        super().__init__()
        self.file = file
        self.errors: list[SemanticError] = []
        #: a constraint was malformed (a term where a condition belongs, ...): the model is
        #: incomplete, so the semantic checks would mislead
        self.broken = False
        #: attribute span -> spans of the keys of its map value (for precise error locations)
        self.key_spans: dict[Span, dict[str, Span]] = {}
        #: where each expression object was written (by id; they live until the transform ends)
        self.where: dict[int, Span] = {}

    # -- helpers --
    def _span(self, line: int, col: int) -> Span:
        return Span(self.file, line, col)

    def _tok_span(self, tok: Token) -> Span:
        return self._span(*_position(tok.line, tok.column))

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

    def _located(self, expr: Expr, meta: Meta) -> Expr:
        self.where[id(expr)] = self._span(meta.line, meta.column)
        return expr

    def _expect(self, e: Expr, kinds: tuple[type, ...], what: str) -> None:
        """Report ``e`` unless it is one of ``kinds`` (a condition, or a term)."""
        if isinstance(e, kinds):
            return
        self.broken = True
        span = self.where.get(id(e), Span(self.file, 1, 1))
        self.errors.append(SemanticError(f"expected {what}, not {_describe(e)}", span.location()))

    def _condition(self, e: Expr) -> Expr:
        self._expect(e, _CONDITIONS, "a condition (a feature, a comparison, or ! & | => <=>)")
        return e

    def _term(self, e: Expr) -> Expr:
        self._expect(e, _TERMS, "a value (a number, a string, a reference or a function)")
        return e

    # -- sections --
    def start(self, meta: Meta, children: list[Any]) -> _Parsed:
        namespace = next((c for c in children if isinstance(c, str)), None)
        includes = tuple(x for c in children if isinstance(c, _Includes) for x in c.levels)
        imports = tuple(x for c in children if isinstance(c, _Imports) for x in c.imports)
        root = next(c for c in children if isinstance(c, Feature))
        constraints = next((c for c in children if isinstance(c, tuple)), ())
        return _Parsed(namespace, includes, imports, root, constraints)

    def namespace(self, meta: Meta, children: list[Any]) -> str:
        return children[0].text

    def include(self, meta: Meta, children: list[Any]) -> _Includes:
        return _Includes(tuple(c for c in children[1:] if isinstance(c, str)))

    def include_line(self, meta: Meta, children: list[Any]) -> str:
        return "".join(str(c) for c in children if c is not None and c.type != "_NL")

    def imports(self, meta: Meta, children: list[Any]) -> _Imports:
        return _Imports(tuple(c for c in children if isinstance(c, Import)))

    def import_line(self, meta: Meta, children: list[Any]) -> Import:
        namespace, alias = children
        alias_text = alias.text if alias is not None else None
        return Import(namespace=namespace.text, alias=alias_text, span=namespace.span)

    def features(self, meta: Meta, children: list[Any]) -> Feature:
        return children[0]

    # -- the feature tree --
    def feature(self, meta: Meta, children: list[Any]) -> Feature:
        type_, name, cardinality, attributes, groups = children
        attrs = []
        for entry in attributes.entries if attributes is not None else ():
            if isinstance(entry.value, ConstraintList):
                attr = Attribute(
                    name=entry.name.text, constraints=entry.value, span=entry.name.span
                )
            else:
                attr = Attribute(name=entry.name.text, value=entry.value, span=entry.name.span)
            if entry.key_spans:
                self.key_spans[entry.name.span] = entry.key_spans
            attrs.append(attr)
        return Feature(
            name=name.text,
            attributes=tuple(attrs),
            groups=groups or (),
            span=name.span,
            type=type_,
            cardinality=cardinality,
        )

    def feature_type(self, meta: Meta, children: list[Any]) -> str:
        return str(children[0])

    def feature_cardinality(self, meta: Meta, children: list[Any]) -> Cardinality:
        _keyword, low_tok, high_tok = children
        lower = self._int(low_tok)
        if high_tok is None:
            return Cardinality(lower=lower, upper=lower)
        upper = None if high_tok.type == "STAR" else self._int(high_tok)
        if upper is not None and lower > upper:
            self.errors.append(
                SemanticError(
                    f"feature cardinality lower bound {lower} exceeds upper bound {upper}",
                    self._tok_span(low_tok).location(),
                )
            )
        return Cardinality(lower=lower, upper=upper)

    def children(self, meta: Meta, children: list[Group]) -> tuple[Group, ...]:
        return tuple(children)

    def group(self, meta: Meta, children: list[Any]) -> Group:
        keyword, members = children
        span = self._tok_span(keyword)
        return Group(kind=_one_of(keyword, _GROUP_KEYWORDS), children=members or (), span=span)

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

    def single_constraint_attribute(self, meta: Meta, children: list[Any]) -> _Entry:
        keyword, expr = children
        name = _Name(str(keyword), self._tok_span(keyword))
        return _Entry(name, ConstraintList(exprs=(self._condition(expr),), single=True))

    def list_constraint_attribute(self, meta: Meta, children: list[Any]) -> _Entry:
        keyword, *exprs = children
        name = _Name(str(keyword), self._tok_span(keyword))
        exprs = [self._condition(e) for e in exprs if e is not None]
        return _Entry(name, ConstraintList(exprs=tuple(exprs)))

    def string(self, meta: Meta, children: list[Token]) -> str:
        return str(children[0])[1:-1]

    def number(self, meta: Meta, children: list[Any]) -> int | float:
        minus, tok = children
        value = self._number(tok)
        return -value if minus is not None else value

    def _number(self, tok: Token) -> int | float:
        value: int | float = self._int(tok) if tok.type == "INT" else float(tok)
        if not math.isfinite(value):
            self.errors.append(SemanticError("number out of range", self._tok_span(tok).location()))
            value = 0.0
        return value

    def true(self, meta: Meta, children: list[Any]) -> bool:
        return True

    def false(self, meta: Meta, children: list[Any]) -> bool:
        return False

    def vector(self, meta: Meta, children: list[Any]) -> list[Any]:
        return [self._plain(c) for c in children]

    # -- constraints --
    def constraints(self, meta: Meta, children: list[Any]) -> tuple[Constraint, ...]:
        return tuple(c for c in children if isinstance(c, Constraint))

    def constraint_line(self, meta: Meta, children: list[Any]) -> Constraint:
        (expr,) = children
        return Constraint(expr=self._condition(expr), span=self._span(meta.line, meta.column))

    def _logic(self, cls: type, meta: Meta, children: list[Any]) -> Expr:
        left, right = children
        return self._located(cls(left=self._condition(left), right=self._condition(right)), meta)

    def equiv(self, meta: Meta, children: list[Any]) -> Expr:
        return self._logic(Equiv, meta, children)

    def implies(self, meta: Meta, children: list[Any]) -> Expr:
        return self._logic(Implies, meta, children)

    def disjunction(self, meta: Meta, children: list[Any]) -> Expr:
        return self._logic(Or, meta, children)

    def conjunction(self, meta: Meta, children: list[Any]) -> Expr:
        return self._logic(And, meta, children)

    def negation(self, meta: Meta, children: list[Any]) -> Expr:
        (operand,) = children
        return self._located(Not(operand=self._condition(operand)), meta)

    def comparison(self, meta: Meta, children: list[Any]) -> Expr:
        left, op, right = children
        compare = Compare(
            op=_one_of(op, _COMPARE_OPS), left=self._term(left), right=self._term(right)
        )
        return self._located(compare, meta)

    def arithmetic(self, meta: Meta, children: list[Any]) -> Expr:
        left, op, right = children
        arith = Arith(op=_one_of(op, _ARITH_OPS), left=self._term(left), right=self._term(right))
        return self._located(arith, meta)

    def negative(self, meta: Meta, children: list[Any]) -> Expr:
        _minus, operand = children
        if isinstance(operand, Num):  # UVL writes negative numbers as literals: -3, -0.5
            return self._located(Num(value=-operand.value), meta)
        self.broken = True
        self.errors.append(
            SemanticError(
                f"a minus sign applies to numbers only, not to {_describe(operand)} (write 0 - x)",
                self._span(meta.line, meta.column).location(),
            )
        )
        return operand

    def literal(self, meta: Meta, children: list[Token]) -> Expr:
        (tok,) = children
        if tok.type == "STRING":
            return self._located(Text(value=str(tok)[1:-1]), meta)
        return self._located(Num(value=self._number(tok)), meta)

    def call(self, meta: Meta, children: list[Any]) -> Expr:
        name, *args = children
        args = [a for a in args if a is not None]
        arity = _FUNCTIONS.get(name.text)
        error = None
        if arity is None:
            known = ", ".join(f"{f}()" for f in _FUNCTIONS)
            error = f"unknown function {name.text}() (UVL has {known})"
        elif not arity[0] <= len(args) <= arity[1]:
            counts = " or ".join(str(n) for n in sorted(set(arity)))
            error = f"{name.text}() takes {counts} reference(s), not {len(args)}"
        elif not all(isinstance(a, Ref) for a in args):
            bad = next(a for a in args if not isinstance(a, Ref))
            error = f"{name.text}() takes feature or attribute references, not {_describe(bad)}"
        if error is not None:
            self.broken = True
            self.errors.append(SemanticError(error, name.span.location()))
            return self._located(Aggregate(function="sum", args=(), span=name.span), meta)
        fn = Aggregate(function=name.text, args=tuple(args), span=name.span)
        return self._located(fn, meta)

    def ref(self, meta: Meta, children: list[_Name]) -> Ref:
        (name,) = children
        return self._located(Ref(name=name.text, span=name.span), meta)  # type: ignore[return-value]

    def name(self, meta: Meta, children: list[Token]) -> _Name:
        text = ".".join(str(t)[1:-1] if t.type == "QUOTED_ID" else str(t) for t in children)
        return _Name(text, self._tok_span(children[0]))


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
            if a.constraints is not None:  # a feature may carry several
                continue
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
            if (
                self.require(a, "scale", what, good_scale)
                and ok
                and isinstance(value, str)
                and isinstance(scale, list)  # good_scale says so; for the type checker
            ):
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
        """A reference used as a condition names a feature of this model (or of an imported
        one, ``prefix.Feature``). References inside comparisons, arithmetic and functions may
        also name attributes (``Feature.attribute``); rra-agent does not evaluate those."""
        names = {f.name for f, _ in self.tree}
        exprs = [c.expr for c in self.fm.constraints]
        exprs += [e for _f, _a, v in _constraint_attributes(self.fm.root) for e in v.exprs]
        for expr in exprs:
            for r in _condition_refs(expr):
                if r.name in names or self.fm.imported(r.name):
                    continue
                hint = ""
                if r.name in self.fm.aliases:
                    hint = f" ('{r.name}' is the alias of '{self.fm.aliases[r.name]}'; "
                    hint += "UVL constraints use feature names)"
                self.error(f"constraint refers to unknown feature '{r.name}'{hint}", r.span)


def _condition_refs(expr: Expr) -> Iterator[Ref]:
    """The references of ``expr`` that stand as conditions (not inside a comparison)."""
    stack = [expr]
    while stack:
        e = stack.pop()
        match e:
            case Ref():
                yield e
            case Not(operand=o):
                stack.append(o)
            case And(left=a, right=b) | Or(left=a, right=b) | Implies(left=a, right=b):
                stack.extend((b, a))
            case Equiv(left=a, right=b):
                stack.extend((b, a))


def _constraint_attributes(
    root: Feature,
) -> Iterator[tuple[Feature, Attribute, ConstraintList]]:
    """Every constraint attribute (also inside nested attribute maps) with its feature and the
    feature's attribute that holds it."""
    for f, _parent in _walk(root):
        for a in f.attributes:
            stack: list[Any] = [a.constraints or a.value]
            while stack:
                v = stack.pop()
                if isinstance(v, ConstraintList):
                    yield f, a, v
                elif isinstance(v, dict):
                    stack.extend(reversed(v.values()))
                elif isinstance(v, list):
                    stack.extend(reversed(v))


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


# ---- warnings -----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class UvlWarning:
    """Something a model says that rra-agent keeps (and exports) but does not reason with."""

    message: str
    location: Location | None

    def __str__(self) -> str:
        where = f"{self.location}: " if self.location is not None else ""
        return f"{where}warning: {self.message}"


def _uses(expr: Expr) -> str:
    kinds = {type(e) for e in subexpressions(expr)}
    if Aggregate in kinds:
        fns = sorted({e.function for e in subexpressions(expr) if isinstance(e, Aggregate)})
        return "the aggregate function" + ("s " if len(fns) > 1 else " ") + ", ".join(fns)
    if Text in kinds:
        return "a string comparison"
    if Arith in kinds:
        return "arithmetic"
    return "a comparison"


def uvl_warnings(fm: FeatureModel) -> list[UvlWarning]:
    """What rra-agent's feature reasoning ignores in ``fm``, located, in source order.

    Its reasoning (valid selections, run-time variants, rule conflicts) is propositional:
    constraints with comparisons, arithmetic, strings or aggregate functions, constraint
    attributes, and constraints naming features of imported models do not restrict a
    selection; a feature cardinality counts as one instance; imported models are not loaded.
    Typed features are fine: their selection is reasoned about, their value is not used.
    """
    out: list[UvlWarning] = []
    for i in fm.imports:
        out.append(
            UvlWarning(
                f"imported model '{i.namespace}' is not loaded: rra-agent's feature reasoning "
                f"does not know its features",
                _loc(i.span),
            )
        )
    for f, _parent in _walk(fm.root):
        if f.cardinality is not None:
            card = _format_cardinality(f.cardinality.lower, f.cardinality.upper)
            out.append(
                UvlWarning(
                    f"feature '{f.name}' has cardinality {card}: rra-agent's feature reasoning "
                    "treats it as a single instance",
                    _loc(f.span),
                )
            )
    for f, a, v in _constraint_attributes(fm.root):
        if v.exprs:
            out.append(
                UvlWarning(
                    f"constraint attribute of feature '{f.name}' is kept but rra-agent's "
                    "feature reasoning ignores it (write it under 'constraints' to enforce it)",
                    _loc(a.span),
                )
            )
    boolean = {id(c) for c in fm.boolean_constraints}
    for c in fm.constraints:
        if id(c) in boolean:
            continue
        imported = next((r.name for r in refs(c.expr) if fm.imported(r.name)), None)
        why = (
            f"names '{imported}' of an imported model"
            if imported is not None
            else f"uses {_uses(c.expr)}"
        )
        out.append(
            UvlWarning(f"constraint {why}: rra-agent's feature reasoning ignores it", _loc(c.span))
        )
    return sorted(out, key=lambda w: _loc_order(w.location))


def _loc_order(loc: Location | None) -> tuple[str, int, int]:
    return (loc.file, loc.line, loc.col) if loc is not None else ("", 0, 0)


# ---- public entry points ------------------------------------------------------------------------


@contextmanager
def _collector_paused() -> Iterator[None]:
    """Python's cyclic garbage collector off for a while (if it was on).

    Parsing allocates millions of short-lived objects that reference counting frees; each full
    collection meanwhile walks every live object, which made parse time grow faster than the
    model (267 instead of 174 us per feature at 20 000 features)."""
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_enabled:
            gc.enable()


def parse_uvl(text: str, file: str = "<uvl>") -> FeatureModel:
    """Parse UVL text into a `FeatureModel` (``file`` names the text in errors and spans)."""
    with _collector_paused():
        return _parse_uvl(text, file)


def _parse_uvl(text: str, file: str) -> FeatureModel:
    tree = _parse_tree(text, file)
    _check_depth(tree, file)
    to_model = _ToModel(file)
    try:
        parsed: _Parsed = to_model.transform(tree)
    except VisitError as e:  # pragma: no cover - a bug in a transformer method
        raise e.orig_exc from None
    errors: list[SemanticError] = sorted(to_model.errors, key=_error_order)
    if to_model.broken:  # a malformed constraint: checking the rest would mislead
        ErrorGroup.raise_if_any(errors)
    fm = FeatureModel(
        root=parsed.root,
        constraints=parsed.constraints,
        namespace=parsed.namespace,
        source=file,
        includes=parsed.includes,
        imports=parsed.imports,
    )
    errors += check_feature_model(fm, to_model.key_spans)
    errors.sort(key=_error_order)
    ErrorGroup.raise_if_any(errors)
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
#: Words the grammar (or the reference grammar) treats as keywords somewhere: such name parts
#: are always written quoted.
KEYWORDS = frozenset(
    {
        "namespace", "include", "imports", "as", "features", "constraints", "constraint",
        "cardinality", "mandatory", "optional", "alternative", "or", "true", "false",
        "Integer", "String", "Real", "Boolean", "Type", "Arithmetic",
        "sum", "avg", "len", "floor", "ceil",
    }
)  # fmt: skip
#: A name part written unquoted: what both grammars read as a plain name (the reference's
#: ID_STRICT); any other part is quoted.
_PLAIN_PART = re.compile(r"[a-zA-Z][a-zA-Z0-9_#§%?\\'äüöß;]*")
_QUOTABLE = re.compile(r'[^"\r\n]+')
_STRING_OK = re.compile(r"[^'\r\n]*")


def _format_part(part: str) -> str:
    return part if _PLAIN_PART.fullmatch(part) and part not in KEYWORDS else f'"{part}"'


def _format_name(name: object) -> str:
    """A name (dotted parts joined by ``.``) as UVL writes it: each part plain or quoted."""
    if not isinstance(name, str):
        raise RraError(f"UVL names are strings, not {name!r}")
    parts = name.split(".")
    if all(p and _QUOTABLE.fullmatch(p) for p in parts):
        return ".".join(map(_format_part, parts))
    if _QUOTABLE.fullmatch(name):  # an empty part: one quoted name holding the dots
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
        case ConstraintList(exprs=exprs):
            return "[" + ", ".join(_format_expr(e) for e in exprs) + "]"
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
    """``{key value, flag, ...}``; a None value is written as a bare key (a flag), a
    `ConstraintList` as ``constraint E`` or ``constraints [E, ...]``."""
    parts = []
    for key, v in items:
        if isinstance(v, ConstraintList):
            parts.append(_format_constraint_attribute(v))
            continue
        k = _format_name(key) if strict else str(key)
        parts.append(k if v is None else f"{k} {_format_value(v, strict=strict)}")
    return "{" + ", ".join(parts) + "}"


def _format_constraint_attribute(v: ConstraintList) -> str:
    if v.single and len(v.exprs) == 1:
        return f"constraint {_format_expr(v.exprs[0])}"
    return f"constraints {_format_value(v)}"


def _format_cardinality(lower: int, upper: int | None) -> str:
    if upper is None:
        return f"[{lower}..*]"
    return f"[{lower}]" if lower == upper else f"[{lower}..{upper}]"


def _feature_lines(f: Feature, depth: int, out: list[str]) -> None:
    line = _INDENT * depth
    if f.type is not None:
        line += f.type + " "
    line += _format_name(f.name)
    if f.cardinality is not None:
        line += " cardinality " + _format_cardinality(f.cardinality.lower, f.cardinality.upper)
    if f.attributes:
        line += " " + _format_pairs((a.name, a.constraints or a.value) for a in f.attributes)
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
    return _format_cardinality(g.lower or 0, g.upper)


#: Binding strength of each operator (higher binds tighter), as in the grammar.
_PRECEDENCE: dict[type, int] = {
    Equiv: 1, Implies: 2, Or: 3, And: 4, Not: 5, Compare: 6,
    Ref: 9, Num: 9, Text: 9, Aggregate: 9,
}  # fmt: skip
_OPERATOR: dict[type, str] = {Equiv: "<=>", Implies: "=>", Or: "|", And: "&"}


def _precedence(e: Expr) -> int:
    if isinstance(e, Arith):
        return 7 if e.op in ("+", "-") else 8
    return _PRECEDENCE[type(e)]


def _format_number(value: int | float) -> str:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise RraError(f"not a number: {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise RraError(f"number {value!r} cannot be written in UVL")
    return _format_int(value, strict=True) if isinstance(value, int) else repr(value)


def _format_expr(e: Expr, context: int = 0) -> str:
    """``e`` in UVL syntax, parenthesised if it binds looser than ``context`` needs."""
    match e:
        case Ref(name=name):
            text = _format_name(name)
        case Num(value=value):
            text = _format_number(value)
        case Text(value=value):
            if not isinstance(value, str) or not _STRING_OK.fullmatch(value):
                raise RraError(f"string {value!r} cannot be written in UVL")
            text = f"'{value}'"
        case Aggregate(function=fn, args=args):
            text = f"{fn}({', '.join(_format_expr(a) for a in args)})"
        case Not(operand=o):
            text = "!" + _format_expr(o, _PRECEDENCE[Not])
        case Compare(op=op, left=a, right=b):  # not associative: both operands bind tighter
            text = f"{_format_expr(a, 7)} {op} {_format_expr(b, 7)}"
        case (
            And(left=a, right=b)
            | Or(left=a, right=b)
            | Implies(left=a, right=b)
            | Equiv(left=a, right=b)
            | Arith(left=a, right=b)
        ):
            p = _precedence(e)  # left-associative: the right operand must bind tighter
            sym = e.op if isinstance(e, Arith) else _OPERATOR[type(e)]
            text = f"{_format_expr(a, p)} {sym} {_format_expr(b, p + 1)}"
        case _:
            raise RraError(f"not a constraint expression: {e!r}")
    return f"({text})" if _precedence(e) < context else text


_LEVEL = re.compile(
    r"(Boolean|Arithmetic|Type)"
    r"(\.(group-cardinality|feature-cardinality|aggregate-function|string-constraints|\*))?"
)


def _format_level(level: object) -> str:
    if not isinstance(level, str) or not _LEVEL.fullmatch(level):
        raise RraError(f"{level!r} is not a UVL language level (e.g. 'Arithmetic.*')")
    return level


def to_uvl(fm: FeatureModel) -> str:
    """``fm`` as UVL text (4-space indentation); `parse_uvl` reads it back to an equal model."""
    out: list[str] = []
    if fm.namespace is not None:
        out += [f"namespace {_format_name(fm.namespace)}", ""]
    if fm.includes:
        out += ["include", *(_INDENT + _format_level(level) for level in fm.includes), ""]
    if fm.imports:
        out.append("imports")
        for i in fm.imports:
            alias = f" as {_format_name(i.alias)}" if i.alias is not None else ""
            out.append(f"{_INDENT}{_format_name(i.namespace)}{alias}")
        out.append("")
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
        case Aggregate(function=fn, args=args):
            bare = tuple(msgspec.structs.replace(a, span=None) for a in args)
            return Aggregate(function=fn, args=bare)
        case Num() | Text():
            return e
        case Not(operand=o):
            return Not(operand=_strip_expr(o))
        case And() | Or() | Implies() | Equiv():
            return type(e)(left=_strip_expr(e.left), right=_strip_expr(e.right))
        case Compare():
            return Compare(op=e.op, left=_strip_expr(e.left), right=_strip_expr(e.right))
        case Arith():
            return Arith(op=e.op, left=_strip_expr(e.left), right=_strip_expr(e.right))
    raise RraError(f"not a constraint expression: {e!r}")


def _strip_value(v: Any) -> Any:
    """An attribute value without the spans of the constraints it may hold."""
    if isinstance(v, ConstraintList):
        return msgspec.structs.replace(v, exprs=tuple(map(_strip_expr, v.exprs)))
    if isinstance(v, dict):
        return {k: _strip_value(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_strip_value(x) for x in v]
    return v


def _strip_feature(f: Feature) -> Feature:
    return msgspec.structs.replace(
        f,
        span=None,
        attributes=tuple(
            msgspec.structs.replace(
                a,
                span=None,
                value=_strip_value(a.value),
                constraints=_strip_value(a.constraints),
            )
            for a in f.attributes
        ),
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
        imports=tuple(msgspec.structs.replace(i, span=None) for i in fm.imports),
    )


def same_model(a: FeatureModel, b: FeatureModel) -> bool:
    """Whether two models are equal up to spans, value types included (``1`` is not ``true``)."""
    enc = msgspec.json.encode
    return enc(strip_spans(a)) == enc(strip_spans(b))
