"""Samples the Context Monitor can trust: decoded against their port's declared data type.

Each data type of ``measurements.yaml`` becomes, once, a msgspec ``TypedDict`` (its fields
required unless listed in ``optional``; ``list[T]`` and other data types nested) and one
reused msgpack decoder of it: checking a sample is decoding it. A missing field or a value of
the wrong type refuses the sample (msgspec accepts an integer for a ``float`` field, never a
boolean for a number, nor a float for an ``int``); fields the type does not declare are left
out of the decoded sample. A port whose type is not a declared data type (``rra validate``
warns about it) only needs its samples to be msgpack maps.

With ``finite=True`` (a node's inputs) the decoder itself refuses NaN and infinities in
every float, except within the fields a type lists in ``non_finite``: a float there is
``Annotated[float, Meta(ge=-MAX, le=MAX)]``, which NaN fails as the infinities do, checked in
msgspec's C code. The Context Monitor decodes with ``finite=False`` and applies each
measurement's own ``finite`` instead (`SampleType.nonfinite`).

A `Refusal` says which source, why (one of `REASONS`) and what was wrong; a `Tally` counts
them per source and reason. Pure: no I/O, no clock.
"""

from __future__ import annotations

import math
import re
import sys
import threading
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Annotated, Any, NotRequired, TypedDict

import msgspec

from rra_agent.models.measurements import DataType

#: Why a sample was refused: ``malformed`` (not msgpack, or truncated), ``not_a_map``,
#: ``missing_field``, ``wrong_type``, ``non_finite`` (NaN or an infinity a measurement does
#: not allow), ``implausible`` (outside the measurement's ``plausible`` bounds),
#: ``too_large`` (over the source's size limit).
REASONS = (
    "malformed",
    "not_a_map",
    "missing_field",
    "wrong_type",
    "non_finite",
    "implausible",
    "too_large",
)
#: Reasons of samples that are not even well-formed (counted as dropped, the rest rejected).
MALFORMED = frozenset({"malformed", "not_a_map", "too_large"})

_PRIMITIVES: dict[str, type] = {
    "float": float,
    "int": int,
    "bool": bool,
    "str": str,
    "bytes": bytes,
}
_LIST_RE = re.compile(r"^list\[(.+)\]$")
#: A float a finite reader accepts: NaN fails both bounds, an infinity one of them.
FiniteFloat = Annotated[float, msgspec.Meta(ge=-sys.float_info.max, le=sys.float_info.max)]
_BOUND_RE = re.compile(r"^Expected `float` [<>]= \S+ - at `(?P<at>[^`]*)`$")
#: Where in the sample a non-finite number is (``.ranges[3]``), or None.
FiniteCheck = Callable[[Any], str | None]


@dataclass(frozen=True)
class Refusal:
    """A sample of ``source`` (``component.port``) that was refused, and why."""

    source: str
    reason: str
    detail: str


class Tally:
    """Refusals counted per source and reason, with the newest detail of each. Safe to call
    from several threads (the bus's and the monitor's main loop)."""

    def __init__(self, observer: Callable[[Refusal], None] | None = None) -> None:
        #: Called with every refusal once counted (e.g. to log it).
        self.observer = observer
        self._lock = threading.Lock()
        self._counts: dict[tuple[str, str], int] = {}
        self._last: dict[tuple[str, str], str] = {}

    def add(self, refusal: Refusal) -> None:
        key = (refusal.source, refusal.reason)
        with self._lock:
            self._counts[key] = self._counts.get(key, 0) + 1
            self._last[key] = refusal.detail
        if self.observer is not None:
            self.observer(refusal)

    def count(self, source: str | None = None, reason: str | None = None) -> int:
        """How many refusals of ``source`` for ``reason`` (None: any)."""
        with self._lock:
            return sum(
                n
                for (s, r), n in self._counts.items()
                if (source is None or s == source) and (reason is None or r == reason)
            )

    def rows(self) -> list[tuple[str, str, int, str]]:
        """(source, reason, count, newest detail), sorted by source and reason."""
        with self._lock:
            return [(s, r, n, self._last[(s, r)]) for (s, r), n in sorted(self._counts.items())]


# ---- one decoder per data type ----------------------------------------------------------
@dataclass(frozen=True)
class SampleType:
    """How samples of one port type are decoded and where their non-finite numbers are."""

    name: str
    decoder: msgspec.msgpack.Decoder[Any]
    #: None when the type holds no float at all.
    nonfinite: FiniteCheck | None

    def decode(self, source: str, raw: bytes | memoryview) -> dict[str, Any] | Refusal:
        try:
            return self.decoder.decode(raw)  # type: ignore[no-any-return]
        except msgspec.DecodeError as e:
            return self.refused(source, e)

    def refused(self, source: str, e: msgspec.DecodeError) -> Refusal:
        """The refusal of a sample whose decoding raised ``e``."""
        if not isinstance(e, msgspec.ValidationError):
            return Refusal(source, "malformed", f"not msgpack: {e}")
        bound = _BOUND_RE.match(str(e))
        if bound:  # only a FiniteFloat has bounds
            return Refusal(source, "non_finite", f"{self.name}: {bound['at']} is not finite")
        return Refusal(source, _validation_reason(str(e)), f"{self.name}: {e}")


class _Untyped:
    """A port type that is not a declared data type: any msgpack map."""

    name = "map"

    def __init__(self) -> None:
        self.decoder: msgspec.msgpack.Decoder[Any] = msgspec.msgpack.Decoder()
        self.nonfinite: FiniteCheck | None = _any_nonfinite

    def decode(self, source: str, raw: bytes | memoryview) -> dict[str, Any] | Refusal:
        try:
            data = self.decoder.decode(raw)
        except msgspec.DecodeError as e:
            return self.refused(source, e)
        if not isinstance(data, dict):
            return not_a_map(source, data)
        return data

    def refused(self, source: str, e: msgspec.DecodeError) -> Refusal:
        """The refusal of a sample whose decoding raised ``e``."""
        return Refusal(source, "malformed", f"not msgpack: {e}")


def not_a_map(source: str, data: Any) -> Refusal:
    """The refusal of a sample that decoded to something other than a map."""
    return Refusal(source, "not_a_map", f"a sample must be a map, got {type(data).__name__}")


Decoder = SampleType | _Untyped


def _validation_reason(message: str) -> str:
    if message.startswith("Object missing required field"):
        return "missing_field"
    if message.startswith("Expected `object`"):
        return "not_a_map"
    return "wrong_type"


class SampleTypes:
    """The decoders of every data type of a model, built once (see the module doc);
    ``finite``: they refuse non-finite numbers outside the types' ``non_finite`` fields."""

    def __init__(self, data_types: Iterable[DataType], *, finite: bool = False) -> None:
        self.declared = {t.name: t for t in data_types}
        self._typed: dict[tuple[str, bool], Any] = {}
        self._building: set[tuple[str, bool]] = set()
        self._checks: dict[str, FiniteCheck | None] = {}
        self.types: dict[str, SampleType] = {}
        for name in self.declared:
            self.types[name] = SampleType(
                name,
                msgspec.msgpack.Decoder(self._typeddict(name, finite)),
                self._finite_check(name),
            )

    def for_port(self, type_name: str | None) -> Decoder:
        """The decoder of a port of type ``type_name`` (any map when it is not declared)."""
        return self.types.get(type_name or "", _UNTYPED)

    # ---- the TypedDicts ------------------------------------------------------------------
    def _typeddict(self, name: str, finite: bool) -> Any:
        key = (name, finite)
        if key in self._typed:
            return self._typed[key]
        if key in self._building:  # a recursive type: its inner occurrences are any map
            return dict[str, Any]
        self._building.add(key)
        dt = self.declared[name]
        fields: dict[str, Any] = {}
        for fname, expr in dt.fields.items():
            tp = self._python_type(expr, finite and fname not in dt.non_finite)
            fields[fname] = NotRequired[tp] if fname in dt.optional else tp
        self._building.discard(key)
        self._typed[key] = TypedDict(name, fields)  # type: ignore[operator]
        return self._typed[key]

    def _python_type(self, expr: str, finite: bool) -> Any:
        expr = expr.strip()
        match = _LIST_RE.match(expr)
        if match:
            return list[self._python_type(match[1], finite)]  # type: ignore[misc]
        if expr == "float" and finite:
            return FiniteFloat
        if expr in _PRIMITIVES:
            return _PRIMITIVES[expr]
        if expr in self.declared:
            return self._typeddict(expr, finite)
        return Any  # an unknown type name: `rra validate` reports it

    # ---- where the non-finite numbers are ------------------------------------------------
    def _finite_check(self, expr: str) -> FiniteCheck | None:
        expr = expr.strip()
        if expr in self._checks:
            return self._checks[expr]
        self._checks[expr] = _any_nonfinite  # while building: a recursive type is scanned
        check = self._build_check(expr)
        self._checks[expr] = check
        return check

    def _build_check(self, expr: str) -> FiniteCheck | None:
        match = _LIST_RE.match(expr)
        if match:
            inner = self._finite_check(match[1])
            if inner is None:
                return None
            return _float_list if inner is _float else _list_of(inner)
        if expr == "float":
            return _float
        if expr in _PRIMITIVES:
            return None
        if expr not in self.declared:
            return _any_nonfinite
        checks = {
            f: c for f, e in self.declared[expr].fields.items() if (c := self._finite_check(e))
        }
        return _fields_of(checks) if checks else None


def _float(value: Any) -> str | None:
    return None if math.isfinite(value) else ""


def _float_list(values: list[float]) -> str | None:
    if all(map(math.isfinite, values)):
        return None
    return next(f"[{i}]" for i, v in enumerate(values) if not math.isfinite(v))


def _list_of(inner: FiniteCheck) -> FiniteCheck:
    def check(values: list[Any]) -> str | None:
        for i, v in enumerate(values):
            where = inner(v)
            if where is not None:
                return f"[{i}]{where}"
        return None

    return check


def _fields_of(checks: Mapping[str, FiniteCheck]) -> FiniteCheck:
    def check(sample: Mapping[str, Any]) -> str | None:
        for name, inner in checks.items():
            if name in sample:
                where = inner(sample[name])
                if where is not None:
                    return f".{name}{where}"
        return None

    return check


def _any_nonfinite(value: Any) -> str | None:
    """Where a non-finite float is in any msgpack value (maps, arrays, scalars)."""
    if isinstance(value, float):
        return None if math.isfinite(value) else ""
    if isinstance(value, dict):
        for k, v in value.items():
            where = _any_nonfinite(v)
            if where is not None:
                return f".{k}{where}"
    elif isinstance(value, list):
        for i, v in enumerate(value):
            where = _any_nonfinite(v)
            if where is not None:
                return f"[{i}]{where}"
    return None


_UNTYPED = _Untyped()


def nested(data_types: Iterable[DataType], names: Iterable[str]) -> list[DataType]:
    """The data types named (those declared) and every declared type they nest, in their
    declaration order: what a reader of ports of types ``names`` needs to decode them."""
    declared = {t.name: t for t in data_types}
    seen: set[str] = set()
    todo = [n for n in names if n in declared]
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        seen.add(name)
        for expr in declared[name].fields.values():
            inner = expr.strip()
            while (match := _LIST_RE.match(inner)) is not None:
                inner = match[1].strip()
            if inner in declared:
                todo.append(inner)
    return [t for t in declared.values() if t.name in seen]
