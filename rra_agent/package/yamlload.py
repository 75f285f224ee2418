"""YAML model files -> msgspec Structs, with every error located as ``file:line:col``.

PyYAML composes the text into a node tree that keeps positions; plain Python values are built
from it (rejecting duplicate keys, which PyYAML accepts silently) and converted to the Struct
with `msgspec.convert`. A `msgspec.ValidationError` carries a JSON path (``$.components[0].
ports[1].type``); it is mapped back onto the node tree to find the position. Dict values
(``$.parameters[...]``, msgspec does not say which key) are found by converting each entry
of that mapping on its own.

`YamlDoc` keeps the node tree so later checks (cross-references) can locate what they report.
"""

from __future__ import annotations

import difflib
import re
import types
import typing
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import yaml
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode

from rra_agent.errors import ErrorGroup, Location, ModelError

T = TypeVar("T")
PathItem = str | int

_MAP_TAG = "tag:yaml.org,2002:map"
_SEQ_TAG = "tag:yaml.org,2002:seq"
_MERGE_TAG = "tag:yaml.org,2002:merge"
_AT_RE = re.compile(r"^(?P<msg>.*) - at `(?:(?P<key>key)` in `)?(?P<path>\$[^`]*)`$", re.DOTALL)
_TOKEN_RE = re.compile(r"\.(?P<field>[^.\[]+)|\[(?P<index>\d+)\]|\[(?P<dict>\.\.\.)\]")
_DUP_RE = re.compile(r"^duplicate [\w ]+ name\(s\) (?P<names>.+)$")


# ---- the document --------------------------------------------------------------------------
@dataclass(frozen=True)
class YamlDoc:
    """A composed YAML file: its name, text and node tree, to locate model elements."""

    file: str
    root: Node | None
    text: str = field(default="", repr=False)

    def node(self, *path: PathItem) -> Node | None:
        """The value node at ``path`` (mapping keys and sequence indices), or None."""
        return _walk(self.root, path)[1] if self.root is not None else None

    def loc(self, *path: PathItem) -> Location:
        """Where the value at ``path`` is, else its nearest existing ancestor."""
        if self.root is None:
            return Location(self.file, 1, 1)
        return self.node_loc(_walk(self.root, path)[0])

    def key_loc(self, *path: PathItem) -> Location:
        """Where the *key* of the last path item is (the value's place for an index)."""
        if self.root is not None and path:
            parent = self.node(*path[:-1])
            key = _key_node(parent, path[-1]) if parent is not None else None
            if key is not None:
                return self.node_loc(key)
        return self.loc(*path)

    def node_loc(self, node: Node) -> Location:
        mark = node.start_mark
        return Location(self.file, mark.line + 1, mark.column + 1)

    def source_line(self, line: int) -> str | None:
        lines = self.text.splitlines()
        return lines[line - 1] if 0 < line <= len(lines) else None

    def error(self, message: str, location: Location) -> ModelError:
        """A ModelError at ``location`` of this file, with its source line for the caret."""
        return ModelError(message, location, source_line=self.source_line(location.line))


def _walk(root: Node, path: tuple[PathItem, ...]) -> tuple[Node, Node | None]:
    """(deepest existing node along ``path``, the node at ``path`` or None)."""
    node = root
    for item in path:
        child = _child(node, item)
        if child is None:
            return node, None
        node = child
    return node, node


def _child(node: Node, item: PathItem) -> Node | None:
    if isinstance(node, MappingNode):
        for k, v in _entries(node):
            if isinstance(k, ScalarNode) and _scalar_matches(k, item):
                return v
        return None
    if isinstance(node, SequenceNode) and isinstance(item, int) and 0 <= item < len(node.value):
        return node.value[item]
    return None


def _key_node(node: Node, item: PathItem) -> Node | None:
    if isinstance(node, MappingNode):
        for k, _ in _entries(node):
            if isinstance(k, ScalarNode) and _scalar_matches(k, item):
                return k
    return None


def _scalar_matches(node: ScalarNode, item: PathItem) -> bool:
    if isinstance(item, str):
        return node.value == item
    return _construct_scalar(node) == item


def _entries(node: MappingNode, _seen: frozenset[int] = frozenset()) -> Iterator[tuple[Node, Node]]:
    """A mapping's entries, own keys first, then those merged in with ``<<``."""
    merged: list[tuple[Node, Node]] = []
    for k, v in node.value:
        if k.tag == _MERGE_TAG:
            sources = v.value if isinstance(v, SequenceNode) else [v]
            for src in sources:
                if isinstance(src, MappingNode) and id(src) not in _seen:
                    merged.extend(_entries(src, _seen | {id(node)}))
        else:
            yield k, v
    yield from merged


# ---- node tree -> plain values ----------------------------------------------------------------
_CONSTRUCTOR = yaml.constructor.SafeConstructor()


def _construct_scalar(node: ScalarNode) -> Any:
    return _CONSTRUCTOR.construct_object(node, deep=True)


class _Builder:
    """Plain Python values from a node tree; collects duplicate-key errors."""

    def __init__(self, doc: YamlDoc) -> None:
        self.doc = doc
        self.errors: list[ModelError] = []
        self._memo: dict[int, Any] = {}  # aliases share one value, as in PyYAML
        self._active: set[int] = set()

    def build(self, node: Node) -> Any:
        if isinstance(node, ScalarNode):
            return _construct_scalar(node)
        if id(node) in self._memo:
            return self._memo[id(node)]
        if id(node) in self._active:
            raise self.doc.error("a YAML alias refers to itself", self.doc.node_loc(node))
        self._active.add(id(node))
        try:
            if isinstance(node, SequenceNode):
                self._check_tag(node, _SEQ_TAG)
                value: Any = [self.build(n) for n in node.value]
            else:
                assert isinstance(node, MappingNode)
                self._check_tag(node, _MAP_TAG)
                value = self._mapping(node)
        finally:
            self._active.discard(id(node))
        self._memo[id(node)] = value
        return value

    def _mapping(self, node: MappingNode) -> dict[Any, Any]:
        out: dict[Any, Any] = {}
        merges: list[Node] = []
        for k, v in node.value:
            if k.tag == _MERGE_TAG:
                merges.extend(v.value if isinstance(v, SequenceNode) else [v])
                continue
            key = self._key(k)
            if key in out:
                self.errors.append(self.doc.error(_dup_message(node, k), self.doc.node_loc(k)))
            out[key] = self.build(v)
        for src in merges:  # ``<<: *base``: own keys win over merged ones
            merged = self.build(src)
            if not isinstance(merged, dict):
                raise self.doc.error("'<<' merges mappings only", self.doc.node_loc(src))
            for key, value in merged.items():
                out.setdefault(key, value)
        return out

    def _key(self, node: Node) -> Any:
        key = self.build(node) if isinstance(node, ScalarNode) else None
        if key is None or not isinstance(key, str | int | float | bool):
            raise self.doc.error("a mapping key must be a plain value", self.doc.node_loc(node))
        return key

    def _check_tag(self, node: Node, expected: str) -> None:
        if node.tag != expected:
            raise self.doc.error(f"unsupported YAML tag {node.tag!r}", self.doc.node_loc(node))


def _dup_message(node: MappingNode, key: Node) -> str:
    same = (k for k, _ in node.value if k.tag == key.tag and k.value == key.value and k is not key)
    first = next(same, None)
    where = f" (first at line {first.start_mark.line + 1})" if first is not None else ""
    return f"duplicate key '{key.value}'{where}"


# ---- loading ------------------------------------------------------------------------------------
#: The floats of YAML 1.2 (and JSON) that PyYAML, a YAML 1.1 reader, takes for strings: an
#: exponent without a decimal point (``1e-3``) or without a sign (``2.5e3``). A gain written
#: ``1e-3`` is the number it looks like, in the models as on the command line.
_FLOAT_12 = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")


def _yaml12_floats(base: type[yaml.SafeLoader]) -> type[yaml.SafeLoader]:
    """``base`` resolving `_FLOAT_12` as floats too (PyYAML's resolvers come first)."""
    loader: type[yaml.SafeLoader] = type(base.__name__, (base,), {})
    loader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT_12, list("-+0123456789."))
    return loader


#: The pure-Python loader, with YAML 1.2's floats.
SafeLoader = _yaml12_floats(yaml.SafeLoader)
#: libyaml's composer when PyYAML has it: nine times faster on the shipped packages (a replay
#: loads the run's models: tools/bench_replay.py), the same nodes, lines and columns.
_C: type[yaml.SafeLoader] | None = getattr(yaml, "CSafeLoader", None)
_FAST: type[yaml.SafeLoader] | None = _yaml12_floats(_C) if _C is not None else None


def scalar(text: str) -> Any:
    """The value of one YAML scalar as a command line gives it (``NAME=VALUE``): ``1e-3``
    a float as in the model files; raises `yaml.YAMLError` if it is not YAML."""
    return yaml.load(text, Loader=_FAST or SafeLoader)  # a safe loader's subclass


def _compose(text: str) -> yaml.Node | None:
    """The YAML node tree of ``text``; on a syntax error, the pure-Python composer's error
    (its messages are the ones documented and tested)."""
    if _FAST is not None:
        try:
            root = yaml.compose(text, Loader=_FAST)
        except yaml.YAMLError:
            pass
        else:
            _plain_style(root)
            return root
    return yaml.compose(text, Loader=SafeLoader)


def _plain_style(node: yaml.Node | None) -> None:
    """libyaml names a plain scalar's style ``""``, the pure-Python composer ``None``."""
    stack = [node] if node is not None else []
    seen: set[int] = set()  # an alias is the same node: walked once (recursive, or nested)
    while stack:
        n = stack.pop()
        if id(n) in seen:
            continue
        seen.add(id(n))
        if isinstance(n, ScalarNode):
            if n.style == "":
                n.style = None
        elif isinstance(n, MappingNode):
            for k, v in n.value:
                stack += (k, v)
        elif isinstance(n.value, list):
            stack += n.value


def compose_text(text: str, file: str) -> YamlDoc:
    """Compose YAML text into a `YamlDoc`; a syntax error becomes a located ModelError."""
    try:
        root = _compose(text)
    except yaml.MarkedYAMLError as e:
        raise _syntax_error(e, file, text) from None
    return YamlDoc(file, root, text)


def load_yaml_text(text: str, file: str, type_: type[T]) -> tuple[T, YamlDoc]:
    """Parse ``text`` (named ``file`` in errors) into ``type_``, located on error."""
    doc = compose_text(text, file)
    builder = _Builder(doc)
    try:
        value = builder.build(doc.root) if doc.root is not None else {}
    except yaml.MarkedYAMLError as e:
        raise _syntax_error(e, file, text) from None
    ErrorGroup.raise_if_any(builder.errors)
    try:
        return msgspec.convert(value, type_), doc
    except msgspec.ValidationError as e:
        raise locate_validation_error(str(e), doc, type_) from None


def load_yaml(path: str | Path, type_: type[T]) -> tuple[T, YamlDoc]:
    """Read the YAML file at ``path`` into ``type_``; every problem is a located ModelError."""
    file = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ModelError(f"{file}: no such file", None) from None
    except (OSError, UnicodeDecodeError) as e:
        raise ModelError(f"{file}: cannot read: {e}", None) from None
    return load_yaml_text(text, file, type_)


def _syntax_error(e: yaml.MarkedYAMLError, file: str, text: str) -> ModelError:
    mark = e.problem_mark or e.context_mark
    message = e.problem or e.context or "invalid YAML"
    if e.context and e.problem and e.context_mark is not None:
        at = f"{e.context_mark.line + 1}:{e.context_mark.column + 1}"
        message = f"{message} ({e.context} at {at})"
    loc = Location(file, mark.line + 1, mark.column + 1) if mark else Location(file, 1, 1)
    return YamlDoc(file, None, text).error(f"YAML syntax: {message}", loc)


# ---- msgspec error path -> node ------------------------------------------------------------
def locate_validation_error(text: str, doc: YamlDoc, type_: Any) -> ModelError:
    """Turn a msgspec.ValidationError message into a ModelError at the offending node."""
    m = _AT_RE.match(text)
    message, path, is_key = (m["msg"], m["path"], bool(m["key"])) if m else (text, "$", False)
    if doc.root is None:
        return doc.error(_explain(message, type_), doc.loc())
    node, tp = _find(doc.root, _tokens(path), type_, message, is_key)
    return doc.error(_explain(message, tp), doc.node_loc(node))


def _explain(message: str, tp: Any) -> str:
    """Say what was expected where msgspec only says what was found."""
    unknown = re.match(r"Object contains unknown field `(.+)`$", message)
    missing = re.match(r"Object missing required field `(.+)`$", message)
    fields = _struct_fields(tp)
    if unknown and fields:
        return unknown_name("field", unknown[1], fields)
    if missing:
        return f"missing required field '{missing[1]}'"
    return message


def unknown_name(kind: str, name: str, known: Iterable[str], where: str = "") -> str:
    """``unknown <kind> 'name'<where> (did you mean 'x'? known: a, b, c)``."""
    names = sorted(set(known))
    close = difflib.get_close_matches(name, names, n=1)
    hint = f"did you mean '{close[0]}'? " if close else ""
    shown = ", ".join(names[:15]) + (", ..." if len(names) > 15 else "")
    return f"unknown {kind} '{name}'{where} ({hint}known: {shown or 'none'})"


def _tokens(path: str) -> list[str | int | None]:
    """``$.a[0].b[...]`` -> ``['a', 0, 'b', None]`` (None: a dict value, key unknown)."""
    out: list[str | int | None] = []
    for t in _TOKEN_RE.finditer(path[1:]):
        out.append(t["field"] if t["field"] else int(t["index"]) if t["index"] else None)
    return out


def _find(
    node: Node, tokens: list[str | int | None], tp: Any, message: str, is_key: bool
) -> tuple[Node, Any]:
    """Follow the error path from ``node`` (of type ``tp``) to (offending node, its type)."""
    for tok in tokens:
        if tok is None:
            return _find_dict_entry(node, tp, message)
        child = _child(node, tok)
        if child is None:
            return node, tp
        node, tp = child, _subtype(tp, tok)
    if is_key:
        return _find_bad_key(node, tp), tp
    return _refine(node, message), tp


def _find_dict_entry(node: Node, tp: Any, message: str) -> tuple[Node, Any]:
    """Find the entry of a mapping whose key or value fails its type on its own."""
    key_tp, value_tp = _dict_types(tp)
    if not isinstance(node, MappingNode):
        return node, tp
    builder = _Builder(YamlDoc("", node))
    for k, v in _entries(node):
        try:
            msgspec.convert(builder.build(k), key_tp)
        except (msgspec.ValidationError, yaml.YAMLError):
            return k, key_tp
        try:
            msgspec.convert(builder.build(v), value_tp)
        except msgspec.ValidationError as e:
            sub = _AT_RE.match(str(e))
            sub_tokens = _tokens(sub["path"]) if sub else []
            return _find(v, sub_tokens, value_tp, message, bool(sub and sub["key"]))
        except yaml.YAMLError:
            return v, value_tp
    return node, tp


def _find_bad_key(node: Node, tp: Any) -> Node:
    key_tp, _ = _dict_types(tp)
    if isinstance(node, MappingNode):
        for k, _v in _entries(node):
            try:  # keys may be any node: a non-scalar one fails as the value it builds
                msgspec.convert(_CONSTRUCTOR.construct_object(k, deep=True), key_tp)
            except (msgspec.ValidationError, yaml.YAMLError, AttributeError):
                return k
    return node


def _refine(node: Node, message: str) -> Node:
    """Point inside a mapping when the message names a key or a value of it."""
    if not isinstance(node, MappingNode):
        return node
    field_m = re.match(r"Object contains unknown field `(.+)`$", message)
    if field_m:
        return _key_node(node, field_m[1]) or node
    if message.startswith("Object missing required field"):
        return node
    dup = _DUP_RE.match(message)
    if dup:
        return _find_duplicate_name(node, dup["names"].split(", ")[0]) or node
    named = re.match(r"'(\w+)' ", message)  # "'plausible' bounds need ...": at that key
    if named:
        return _key_node(node, named[1]) or node
    for _k, v in _entries(node):
        is_str = isinstance(v, ScalarNode) and v.tag == "tag:yaml.org,2002:str"
        if is_str and repr(v.value) in message:
            return v
    return node


def _find_duplicate_name(node: Node, name: str) -> Node | None:
    """The ``name:`` value of the second mapping named ``name`` in a sequence under ``node``."""
    seqs = [v for _, v in _entries(node)] if isinstance(node, MappingNode) else [node]
    for seq in seqs:
        if not isinstance(seq, SequenceNode):
            continue
        hits = [n for item in seq.value if (n := _child(item, "name")) is not None]
        hits = [n for n in hits if isinstance(n, ScalarNode) and n.value == name]
        if len(hits) > 1:
            return hits[1]
    return None


# ---- Python types along a path -------------------------------------------------------------
def _subtype(tp: Any, token: str | int | None) -> Any:
    """The type of the child ``token`` of a value of type ``tp`` (Any when unknown)."""
    for cand in _union_members(tp):
        origin = typing.get_origin(cand) or cand
        if isinstance(token, str) and isinstance(cand, type) and issubclass(cand, msgspec.Struct):
            return _struct_field_type(cand, token)
        if isinstance(token, int) and origin in (list, tuple, set, frozenset):
            args = typing.get_args(cand)
            return args[0] if args else Any
        if token is None and origin is dict:
            return _dict_types(cand)[1]
    return Any


def _union_members(tp: Any) -> list[Any]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return list(typing.get_args(tp))
    return [tp]


def _dict_types(tp: Any) -> tuple[Any, Any]:
    for cand in _union_members(tp):
        if typing.get_origin(cand) is dict:
            args = typing.get_args(cand)
            return (args[0], args[1]) if args else (Any, Any)
    return Any, Any


def _struct_fields(tp: Any) -> list[str]:
    """The encoded field names of the Struct in ``tp`` (first Struct of a union)."""
    for cand in _union_members(tp):
        if isinstance(cand, type) and issubclass(cand, msgspec.Struct):
            return list(cand.__struct_encode_fields__)
    return []


def _struct_field_type(cls: type[msgspec.Struct], encoded: str) -> Any:
    hints = typing.get_type_hints(cls)
    for name, enc in zip(cls.__struct_fields__, cls.__struct_encode_fields__, strict=True):
        if enc == encoded:
            return hints.get(name, Any)
    return Any
