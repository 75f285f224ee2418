"""The expectation language of scenarios: parse the short textual forms, evaluate them purely.

An expectation is one line of text in a scenario's ``expect`` list, e.g.::

    feature ChannelA selected within 1 s after low_battery
    node radio_driver_b STOPPED from low_battery + 2
    measurement BattLev < 50 during [4, 10]
    cv MaxVel == 0.5 +- 0.001 from corridor + 1
    swap(radio_driver_b -> radio_driver_a) before low_battery + 2
    node controller not restarted
    no node FATAL

`parse` turns the text into an `Expectation` (keeping the offset of every name it refers
to, so the scenario loader reports a dangling name at its file:line:col); `evaluate` decides
it against a `Recording` of a run (what the runner saw on the bus), with no I/O: every
expectation is a pure function of the recorded data. The grammar is in docs/scenarios.md.

Times are seconds since the deployment (the resolution engine's ``deploy`` event). Recorded
values are step functions of time: a measurement, CV value, parameter, feature selection or
node state holds from the sample that set it until the next one.

Effect, not intent: ``feature F selected`` and ``cv X ...`` check what is *in effect* (the
run-time selection and CV values the running system shows, as the Run-time Resolution Engine
publishes them in its state); ``decided feature F selected`` and ``decided cv X ...`` check
what the Adaptation Engine decided. They differ while a plan is applied in part (a node that
cannot start).
"""

from __future__ import annotations

import bisect
import dataclasses
import math
import re
import typing
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import msgspec

from rra_agent.bus import messages as m
from rra_agent.core.conflicts import target_name
from rra_agent.errors import Location

STATES: tuple[str, ...] = typing.get_args(m.NodeStateName)
#: Event kinds and how many arguments each takes (None: an optional single argument).
EVENT_KINDS: dict[str, int | None] = {
    "swap": 2,
    "start": 1,
    "stop": 1,
    "restart": 1,
    "crash": 1,
    "set_params": 1,
    "activate": 1,
    "deactivate": 1,
    "rewire": 1,
    "select": 1,
    "deselect": 1,
    "injection": 1,
    "sample": 1,
    "conflict": None,
    "adaptation": 0,
    "rollback": 0,
    "deploy": 0,
}
_NODE_EVENTS = ("start", "stop", "restart", "crash", "set_params", "activate", "deactivate")
OPS = ("==", "!=", "<", "<=", ">", ">=", "in")
_UNITS = {"s": 1.0, "ms": 1e-3}
Mode = Literal["eventually", "always", "at", "end"]


class ExpectationError(ValueError):
    """An expectation that does not parse; ``offset`` is where in its text."""

    def __init__(self, message: str, offset: int) -> None:
        super().__init__(message)
        self.message = message
        self.offset = offset


# ---- the parsed forms ----------------------------------------------------------------------
@dataclass(frozen=True)
class EventPattern:
    """``kind(args)``; an argument ``*`` matches anything."""

    kind: str
    args: tuple[str, ...] = ()

    def matches(self, kind: str, args: tuple[str, ...]) -> bool:
        if kind != self.kind:
            return False
        if not self.args:
            return True
        if len(args) != len(self.args):
            return False
        return all(p in ("*", a) for p, a in zip(self.args, args, strict=True))

    def __str__(self) -> str:
        if self.kind == "swap":
            return f"swap({self.args[0]} -> {self.args[1]})"
        if self.kind == "rewire":
            return f"rewire({self.args[0]}.{self.args[1]})"
        return f"{self.kind}({', '.join(self.args)})" if self.args else self.kind


@dataclass(frozen=True)
class TimeRef:
    """A time: ``offset`` seconds after an anchor (the deployment, an injection, the first
    occurrence of an event, or the end of the run)."""

    offset: float = 0.0
    injection: str | None = None
    event: EventPattern | None = None
    end: bool = False

    def __str__(self) -> str:
        anchor = (
            "end"
            if self.end
            else self.injection
            if self.injection
            else str(self.event)
            if self.event
            else ""
        )
        if not anchor:
            return f"{self.offset:g}"
        if self.offset:
            return f"{anchor} {'+' if self.offset > 0 else '-'} {abs(self.offset):g}"
        return anchor


@dataclass(frozen=True)
class When:
    """When a condition must hold: at some instant of [start, stop] (``eventually``), at every
    instant of it (``always``), at the instant ``start`` (``at``) or at the end (``end``)."""

    mode: Mode
    start: TimeRef = TimeRef()
    stop: TimeRef | None = None  # None: the end of the run

    def describe(self) -> str:
        stop = "end" if self.stop is None else str(self.stop)
        if self.mode == "end":
            return "at the end"
        if self.mode == "at":
            return f"at {self.start}"
        word = "at some time" if self.mode == "eventually" else "throughout"
        return f"{word} in [{self.start}, {stop}]"


EVENTUALLY = When("eventually")
ALWAYS = When("always")


@dataclass(frozen=True)
class Quantity:
    """A recorded quantity: a measurement, a CV value, a node parameter, a field of a data
    topic, the implementation a node runs, or a bare ``name`` (a scenario alias, a
    measurement or a CV attribute: the loader binds it)."""

    kind: Literal["measurement", "cv", "param", "data", "implementation", "name"]
    #: The measurement or CV name, ``node.param``, ``component.port``, the node whose
    #: implementation it is, or the bare name.
    name: str
    #: For ``data`` and ``param``: the path inside the value (keys and list indices).
    path: tuple[str | int, ...] = ()
    #: For ``data``: the port's topic (bound by the loader; ``component/port`` by default).
    topic: str = ""
    #: For ``cv``: what was decided, not what is in effect (``decided cv X``).
    decided: bool = False

    def __str__(self) -> str:
        first = "decided " if self.decided else ""
        if self.kind == "name":
            return first + self.name
        tail = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in self.path)
        return f"{first}{self.kind} {self.name}{tail}"


@dataclass(frozen=True)
class Ref:
    """A name an expectation refers to, and its offset in the text (for located errors)."""

    kind: Literal[
        "feature",
        "node",
        "injection",
        "measurement",
        "cv",
        "param",
        "port",
        "name",
        "conflict",
        "rewire",
    ]
    name: str
    offset: int


@dataclass(frozen=True)
class Expectation:
    text: str
    location: Location | None
    when: When
    refs: tuple[Ref, ...] = field(default=(), compare=False)

    def where(self) -> str:
        return f"{self.location.file}:{self.location.line}" if self.location else "?"


@dataclass(frozen=True)
class FeatureExpectation(Expectation):
    feature: str = ""
    selected: bool = True
    #: What the Adaptation Engine decided, not what is in effect.
    decided: bool = False


@dataclass(frozen=True)
class StateExpectation(Expectation):
    node: str = ""
    state: str = "RUNNING"


@dataclass(frozen=True)
class NotRestartedExpectation(Expectation):
    """``node N not restarted``: one process (one pid) for the node throughout the window."""

    node: str = ""


@dataclass(frozen=True)
class ValueExpectation(Expectation):
    quantity: Quantity = Quantity("name", "")
    op: str = "=="
    value: Any = None
    tolerance: float = 0.0
    #: For ``in [low, high]``.
    high: float | None = None


@dataclass(frozen=True)
class EventExpectation(Expectation):
    event: EventPattern = EventPattern("adaptation")
    #: ``no EVENT``: it must not happen in the window.
    negated: bool = False


@dataclass(frozen=True)
class NoStateExpectation(Expectation):
    """``no node FATAL``: no node is ever in that state in the window."""

    state: str = "FATAL"


@dataclass(frozen=True)
class AbsentNodeExpectation(Expectation):
    """``no node arm_controller``: the node never existed in this run."""

    node: str = ""


@dataclass(frozen=True)
class NoOrphanExpectation(Expectation):
    """``no orphan process``: every process of the run is gone once it is stopped."""


# ---- tokens ---------------------------------------------------------------------------------
_TOKEN = re.compile(
    r"""
    (?P<ws>\s+)
   |(?P<number>(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)
   |(?P<string>"[^"]*"|'[^']*')
   |(?P<op>==|!=|<=|>=|->|\+/-|\+-|±|[<>=()\[\],.+*-])
   |(?P<name>[A-Za-z_][A-Za-z0-9_]*)
    """,
    re.VERBOSE,
)


@dataclass(frozen=True)
class _Tok:
    kind: str  # number, string, op, name, eof
    text: str
    offset: int

    @property
    def value(self) -> str:
        return self.text[1:-1] if self.kind == "string" else self.text


def _tokens(text: str) -> list[_Tok]:
    out, pos = [], 0
    while pos < len(text):
        mt = _TOKEN.match(text, pos)
        if mt is None:
            raise ExpectationError(f"unexpected character {text[pos]!r}", pos)
        kind = mt.lastgroup or ""
        if kind != "ws":
            out.append(_Tok(kind, mt.group(), pos))
        pos = mt.end()
    out.append(_Tok("eof", "", len(text)))
    return out


# ---- the parser -----------------------------------------------------------------------------
_WHEN_WORDS = ("within", "at", "from", "during", "before", "by", "after", "always", "eventually")


class _Parser:
    def __init__(self, text: str) -> None:
        self.text = text
        self.toks = _tokens(text)
        self.i = 0
        self.refs: list[Ref] = []

    # -- token helpers
    def peek(self, ahead: int = 0) -> _Tok:
        return self.toks[min(self.i + ahead, len(self.toks) - 1)]

    def next(self) -> _Tok:
        tok = self.peek()
        self.i = min(self.i + 1, len(self.toks) - 1)
        return tok

    def at(self, *texts: str, ahead: int = 0) -> bool:
        tok = self.peek(ahead)
        return tok.kind in ("op", "name") and tok.text in texts

    def accept(self, *texts: str) -> _Tok | None:
        return self.next() if self.at(*texts) else None

    def expect(self, *texts: str) -> _Tok:
        if self.at(*texts):
            return self.next()
        raise self.error(f"expected {' or '.join(repr(t) for t in texts)}")

    def error(self, message: str, tok: _Tok | None = None) -> ExpectationError:
        tok = tok or self.peek()
        found = "the end" if tok.kind == "eof" else repr(tok.text)
        return ExpectationError(f"{message}, found {found}", tok.offset)

    def name(self, what: str, ref: str | None = None, *, star: bool = False) -> str:
        tok = self.peek()
        if tok.kind in ("name", "string") or (star and tok.text == "*"):
            self.next()
            if ref is not None and tok.text != "*":
                self.refs.append(Ref(ref, tok.value, tok.offset))  # type: ignore[arg-type]
            return tok.value
        raise self.error(f"expected {what}")

    def number(self, what: str = "a number") -> float:
        sign = -1.0 if self.accept("-") else 1.0
        tok = self.peek()
        if tok.kind == "number":
            self.next()
            return sign * float(tok.text)
        if tok.kind == "name" and tok.text == "inf":
            self.next()
            return sign * math.inf
        raise self.error(f"expected {what}")

    def seconds(self) -> float:
        value = self.number("a time in seconds")
        unit = self.accept(*_UNITS)
        return value * _UNITS[unit.text] if unit else value

    # -- the forms
    def parse(self, location: Location | None) -> Expectation:
        first = self.peek()
        if first.kind == "eof":
            raise self.error("empty expectation")
        decided = first.kind == "name" and first.text == "decided"
        if decided:
            self.next()
            first = self.peek()
        if first.kind == "name" and first.text == "feature":
            exp = self.feature(location)
        elif first.kind == "name" and first.text == "node":
            exp = self.node(location)
        elif first.kind == "name" and first.text == "no":
            exp = self.no(location)
        elif self.is_event():
            ev = self.event()
            when = self.when(EVENTUALLY, events=True)
            exp = EventExpectation(self.text, location, when, event=ev)
        else:
            exp = self.value(location)
        if self.peek().kind != "eof":
            raise self.error("unexpected text after the expectation")
        if decided:
            exp = self._decided(exp)
        return dataclasses.replace(exp, refs=tuple(self.refs))

    def _decided(self, exp: Expectation) -> Expectation:
        """``decided ...``: a feature or a CV value as decided."""
        match exp:
            case FeatureExpectation():
                return dataclasses.replace(exp, decided=True)
            case ValueExpectation(quantity=q) if q.kind in ("cv", "name"):
                return dataclasses.replace(exp, quantity=dataclasses.replace(q, decided=True))
        raise ExpectationError("'decided' applies to a feature or a CV value", 0)

    def feature(self, location: Location | None) -> Expectation:
        self.expect("feature")
        name = self.name("a feature name", "feature")
        if self.accept("not"):
            self.expect("selected")
            selected = False
        else:
            selected = self.expect("selected", "deselected").text == "selected"
        when = self.when(EVENTUALLY)
        return FeatureExpectation(self.text, location, when, feature=name, selected=selected)

    def node(self, location: Location | None) -> Expectation:
        self.expect("node")
        name = self.name("a node name", "node")
        if self.accept("not"):
            self.expect("restarted")
            return NotRestartedExpectation(self.text, location, self.window(), node=name)
        tok = self.peek()
        if tok.text not in STATES:
            raise self.error(f"expected a node state ({', '.join(STATES)})")
        self.next()
        when = self.when(EVENTUALLY)
        return StateExpectation(self.text, location, when, node=name, state=tok.text)

    def no(self, location: Location | None) -> Expectation:
        self.expect("no")
        if self.accept("orphan"):
            self.expect("process", "processes")
            return NoOrphanExpectation(self.text, location, ALWAYS)
        if self.at("node") and not self.at("(", ahead=1):
            self.next()
            tok = self.peek()
            if tok.text in STATES:
                self.next()
                return NoStateExpectation(self.text, location, self.window(), state=tok.text)
            node = self.name("a node name or a node state", "node")
            return AbsentNodeExpectation(self.text, location, ALWAYS, node=node)
        if self.accept("failed"):
            self.expect("adaptation", "adaptations")
            ev = EventPattern("rollback")
        elif self.is_event():
            ev = self.event()
        else:
            raise self.error(
                "expected 'orphan process', 'node ...', 'failed adaptation' or an event"
            )
        return EventExpectation(self.text, location, self.window(), event=ev, negated=True)

    def window(self) -> When:
        """The window of a ``no ...`` expectation: the whole run unless given."""
        when = self.when(When("always"), events=True)
        return When("always", when.start, when.stop)

    def value(self, location: Location | None) -> Expectation:
        quantity = self.quantity()
        op_tok = self.peek()
        if op_tok.text not in OPS:
            raise self.error(f"expected a comparison ({' '.join(OPS)})")
        self.next()
        op, tolerance, high = op_tok.text, 0.0, None
        if op == "in":
            self.expect("[")
            value: Any = self.number()
            self.expect(",")
            high = self.number()
            self.expect("]")
        else:
            value = self.literal()
            if self.accept("+-", "+/-", "±"):
                if not isinstance(value, float):
                    raise self.error("a tolerance needs a number before it")
                tolerance = abs(self.number("a tolerance"))
        when = self.when(EVENTUALLY)
        return ValueExpectation(
            self.text,
            location,
            when,
            quantity=quantity,
            op=op,
            value=value,
            tolerance=tolerance,
            high=high,
        )

    def literal(self) -> Any:
        tok = self.peek()
        if tok.kind == "string":
            self.next()
            return tok.value
        if tok.kind == "number" or tok.text in ("-", "inf"):
            return self.number()
        if tok.kind == "name":
            self.next()
            return {"true": True, "false": False}.get(tok.text, tok.text)
        raise self.error("expected a value (number, string or name)")

    def quantity(self) -> Quantity:
        tok = self.peek()
        if tok.kind != "name" and tok.kind != "string":
            raise self.error("expected an expectation")
        kind = tok.text if tok.kind == "name" else ""
        if kind in ("measurement", "cv"):
            self.next()
            return Quantity(kind, self.name(f"a {kind} name", kind))  # type: ignore[arg-type]
        if kind == "param":
            self.next()
            at = self.peek().offset
            node = self.name("a node name")
            self.expect(".")
            param = self.name("a parameter name")
            self.refs.append(Ref("param", f"{node}.{param}", at))
            return Quantity("param", f"{node}.{param}", self.path())
        if kind == "implementation":
            self.next()
            return Quantity("implementation", self.name("a node name", "node"))
        if kind == "data":
            self.next()
            return self.data_path(required=True)
        return self.data_path(required=False)

    def data_path(self, *, required: bool) -> Quantity:
        at = self.peek().offset
        first = self.name("a quantity (component.port.field, measurement, cv, param)")
        if not self.at(".", "["):
            if required:
                raise self.error("expected '.port' after the component name")
            self.refs.append(Ref("name", first, at))
            return Quantity("name", first)
        self.expect(".")
        port = self.name("a port name")
        self.refs.append(Ref("port", f"{first}.{port}", at))
        return Quantity("data", f"{first}.{port}", self.path())

    def path(self) -> tuple[str | int, ...]:
        """``.field`` and ``[index]`` steps into a value."""
        path: list[str | int] = []
        while self.at(".", "["):
            if self.next().text == ".":
                path.append(self.name("a field name"))
            else:
                idx = self.number("an index")
                if idx != int(idx):
                    raise self.error("an index must be an integer")
                path.append(int(idx))
                self.expect("]")
        return tuple(path)

    # -- events
    def is_event(self) -> bool:
        tok = self.peek()
        if tok.kind != "name" or tok.text not in EVENT_KINDS:
            return False
        nxt = self.peek(1)
        return nxt.text == "(" or nxt.kind == "eof" or nxt.text in _WHEN_WORDS

    def event(self) -> EventPattern:
        kind_tok = self.next()
        kind, arity = kind_tok.text, EVENT_KINDS[kind_tok.text]
        if not self.accept("("):
            if arity:
                raise self.error(f"expected '(' after {kind}")
            return EventPattern(kind)
        args: list[str] = []
        if kind == "swap":
            args.append(self.name("the node swapped out", "node", star=True))
            self.expect("->")
            args.append(self.name("the node swapped in", "node", star=True))
        elif kind == "rewire":
            at = self.peek().offset
            node = self.name("a node name", star=True)
            if node != "*":
                self.refs.append(Ref("node", node, at))
            port = "*"
            if self.accept("."):
                port_at = self.peek().offset
                port = self.name("a port name", star=True)
                if node != "*" and port != "*":
                    self.refs.append(Ref("rewire", f"{node}.{port}", port_at))
            args += [node, port]
        elif arity == 0:
            pass
        elif not self.at(")"):
            ref = {
                "select": "feature",
                "deselect": "feature",
                "injection": "injection",
                "sample": "measurement",
                "conflict": "conflict",
            }.get(kind, "node" if kind in _NODE_EVENTS else None)
            args.append(self.name("an argument", ref, star=True))
        elif arity:
            raise self.error(f"{kind}(...) needs an argument")
        self.expect(")")
        return EventPattern(kind, tuple(args))

    # -- timing
    def when(self, default: When, *, events: bool = False) -> When:
        tok = self.peek()
        if tok.kind == "eof":
            return default
        word = tok.text
        if word == "within":
            self.next()
            span = self.seconds()
            if self.accept("after"):
                start = self.timeref()
                return When("eventually", start, _shift(start, span))
            return When("eventually", TimeRef(), TimeRef(span))
        if word == "at":
            self.next()
            if self.accept("end"):
                self._no_instant(events, tok)
                return When("end")
            if self.accept("or"):
                self.expect("after")
                return self._always_from(self.timeref(), events, tok)
            self._no_instant(events, tok)
            return When("at", self.timeref())
        if word == "from":
            self.next()
            return self._always_from(self.timeref(), events, tok)
        if word == "during":
            self.next()
            self.expect("[")
            start = self.timeref()
            self.expect(",")
            stop = self.timeref()
            self.expect("]")
            return When("always" if not events else "eventually", start, stop)
        if word in ("before", "by"):
            self.next()
            return When("eventually", TimeRef(), self.timeref())
        if word == "after":
            self.next()
            return When("eventually", self.timeref(), None)
        if word == "always":
            self.next()
            self._no_instant(events, tok)
            return When("always")
        if word == "eventually":
            self.next()
            return When("eventually")
        raise self.error(
            "expected a time clause (within, at, at end, from, during, before, after, always)"
        )

    def _always_from(self, start: TimeRef, events: bool, tok: _Tok) -> When:
        self._no_instant(events, tok)
        return When("always", start, None)

    def _no_instant(self, events: bool, tok: _Tok) -> None:
        if events:
            raise ExpectationError(
                "an event happens at an instant: use within, before, after or during",
                tok.offset,
            )

    def timeref(self) -> TimeRef:
        self.accept("injection")
        tok = self.peek()
        if tok.kind == "number" or tok.text == "-":
            return TimeRef(self.seconds())
        if self.accept("end"):
            ref = TimeRef(end=True)
        elif self.is_event() and self.at("(", ahead=1):
            ref = TimeRef(event=self.event())
        elif tok.kind in ("name", "string"):
            ref = TimeRef(injection=self.name("an injection name", "injection"))
        else:
            raise self.error("expected a time (seconds, an injection name, an event or end)")
        sign = self.accept("+", "-")
        if sign is None:
            return ref
        offset = self.seconds()
        return _shift(ref, offset if sign.text == "+" else -offset)


def _shift(ref: TimeRef, by: float) -> TimeRef:
    return TimeRef(ref.offset + by, ref.injection, ref.event, ref.end)


def parse(text: str, location: Location | None = None) -> Expectation:
    """Parse one expectation; `ExpectationError` (with the offset) if it does not parse."""
    return _Parser(text).parse(location)


# ---- what a run recorded ----------------------------------------------------------------------
class DataSample(msgspec.Struct, array_like=True):
    stamp: float
    topic: str
    value: Any


class Effect(msgspec.Struct, array_like=True):
    """What was in effect from ``stamp`` on (the Run-time Resolution Engine's state)."""

    stamp: float
    features: list[str]
    cv: dict[str, float]


class ParamSample(msgspec.Struct, array_like=True):
    stamp: float
    node: str
    params: dict[str, Any]


class Applied(msgspec.Struct, kw_only=True):
    """One timeline step as the runner applied it."""

    name: str
    at: float
    stamp: float
    ok: bool = True
    detail: str = ""


class Recording(msgspec.Struct, kw_only=True):
    """Everything a scenario run saw on the bus, with wall-clock stamps (``t0``: deployment)."""

    system: str
    t0: float
    #: Seconds after ``t0`` at which recording stopped.
    end: float
    deployment: list[str] = []
    #: The run-time selection and CV values the system was deployed with.
    initial_features: list[str] = []
    initial_cv: dict[str, float] = {}
    #: Pairs of components that can replace each other (same peers): the swaps to look for.
    swap_pairs: list[tuple[str, str]] = []
    events: list[m.EventMessage] = []
    selections: list[m.SelectionMessage] = []
    #: What was in effect, each time it changed (empty: taken as what was decided).
    effects: list[Effect] = []
    measurements: list[m.Measurement] = []
    data: list[DataSample] = []
    params: list[ParamSample] = []
    injections: list[Applied] = []
    #: Processes of the run still alive once it was stopped (None: not checked).
    orphans: list[int] | None = None
    #: Every node as its host agent listed it at the end of the run (``ListNodes``): what a
    #: host did while it was cut off from the recorder shows here (a new pid).
    nodes: list[m.NodeState] = []


def _steps(
    rec: Recording, changes: list[tuple[float, list[str], dict[str, float]]], dep: frozenset[str]
) -> tuple[Signal, dict[str, Signal]]:
    """The feature selection and each CV value as step signals, from the initial ones."""
    features: Signal = [(-math.inf, frozenset(rec.initial_features) | dep)]
    cv: dict[str, Signal] = {k: [(-math.inf, v)] for k, v in rec.initial_cv.items()}
    for stamp, names, values in changes:
        t = stamp - rec.t0
        feats = frozenset(names) | dep
        if feats != features[-1][1]:
            features.append((t, feats))
        for k, v in values.items():
            sig = cv.setdefault(k, [])
            if not sig or sig[-1][1] != v:
                sig.append((t, v))
    return features, cv


def save_recording(rec: Recording) -> bytes:
    return msgspec.msgpack.encode(rec)


def load_recording(data: bytes) -> Recording:
    return msgspec.msgpack.decode(data, type=Recording)


# ---- the recording as signals and events ------------------------------------------------------
Signal = list[tuple[float, Any]]
_PLAN_LINE = re.compile(r"^(?P<what>.+?) +\((?P<ms>[-\d.]+) ms\) (?P<status>.*)$")
_REWIRE = re.compile(r"^rewire (?P<port>\S+) of (?P<node>\S+)$")


@dataclass(frozen=True)
class Occurrence:
    t: float
    kind: str
    args: tuple[str, ...]


class Index:
    """A `Recording` as step signals and a list of events, times relative to deployment."""

    def __init__(self, rec: Recording) -> None:
        self.rec = rec
        self.end = rec.end
        t0 = rec.t0
        dep = frozenset(rec.deployment)
        selections = sorted(
            (s for s in rec.selections if isinstance(s, m.Selection)), key=lambda s: s.stamp
        )
        #: What was decided (the Adaptation Engine's selections) ...
        self.decided_features, self.decided_cv = _steps(
            rec, [(s.stamp, s.features, s.cv) for s in selections], dep
        )
        #: ... and what was in effect (the Run-time Resolution Engine's state).
        effects = sorted(rec.effects, key=lambda e: e.stamp)
        if effects:
            self.features, self.cv = _steps(
                rec, [(e.stamp, e.features, e.cv) for e in effects], dep
            )
        else:  # a recording without states: what was decided stands for it
            self.features, self.cv = self.decided_features, self.decided_cv
        self.measurements: dict[str, Signal] = {}
        self.occurrences: list[Occurrence] = []
        for ms in sorted(rec.measurements, key=lambda x: x.stamp):
            self.measurements.setdefault(ms.name, []).append((ms.stamp - t0, ms.value))
            self.occurrences.append(Occurrence(ms.stamp - t0, "sample", (ms.name,)))
        self.data: dict[str, Signal] = {}
        for d in sorted(rec.data, key=lambda x: x.stamp):
            self.data.setdefault(d.topic, []).append((d.stamp - t0, d.value))
        self.params: dict[str, Signal] = {}
        for p in sorted(rec.params, key=lambda x: x.stamp):
            for k, v in p.params.items():
                self.params.setdefault(f"{p.node}.{k}", []).append((p.stamp - t0, v))
        self.injections = {a.name: a for a in rec.injections}
        self.states: dict[str, Signal] = {}
        self.implementations: dict[str, Signal] = {}
        #: Node -> its process ids (from every NodeState carrying one).
        self.pids: dict[str, Signal] = {}
        #: Node -> (host, pid) its host agent listed at the end of the run.
        self.final_pids = {s.node: (s.host, s.pid) for s in rec.nodes if s.pid is not None}
        self.known_nodes: set[str] = set()
        self._index_events(t0)
        for (_, prev), (t, feats) in zip(self.features, self.features[1:], strict=False):
            self.occurrences += [Occurrence(t, "select", (f,)) for f in sorted(feats - prev)]
            self.occurrences += [Occurrence(t, "deselect", (f,)) for f in sorted(prev - feats)]
        for a in rec.injections:
            if a.ok:
                self.occurrences.append(Occurrence(a.stamp - t0, "injection", (a.name,)))
        for c in rec.selections:
            if isinstance(c, m.ConflictReport) and c.state == "started":
                # By the name a scenario gives it: conflict(Localization) is a conflict
                # over Localization or over the choice among its alternatives.
                target = target_name(c.target)
                self.occurrences.append(Occurrence(c.stamp - t0, "conflict", (target,)))
        self.occurrences.sort(key=lambda o: o.t)

    def _index_events(self, t0: float) -> None:
        pairs = {tuple(p) for p in self.rec.swap_pairs}
        ran: set[str] = set()
        for ev in sorted(self.rec.events, key=lambda e: e.stamp):
            t = ev.stamp - t0
            if isinstance(ev, m.NodeState):
                self.known_nodes.add(ev.node)
                sig = self.states.setdefault(ev.node, [(-math.inf, "STOPPED")])
                if sig[-1][1] != ev.state:
                    sig.append((t, ev.state))
                pids = self.pids.setdefault(ev.node, [])
                if ev.pid is not None and (not pids or pids[-1][1] != ev.pid):
                    pids.append((t, ev.pid))
                if ev.state in ("STARTING", "RUNNING") and ev.implementation:
                    impl = self.implementations.setdefault(ev.node, [])
                    if not impl or impl[-1][1] != ev.implementation:
                        impl.append((t, ev.implementation))
                if ev.state == "RUNNING":
                    self.occurrences.append(Occurrence(t, "start", (ev.node,)))
                    if ev.node in ran:
                        self.occurrences.append(Occurrence(t, "restart", (ev.node,)))
                    ran.add(ev.node)
                elif ev.state == "STOPPED" and ev.previous is not None:
                    self.occurrences.append(Occurrence(t, "stop", (ev.node,)))
                elif ev.state in ("BACKOFF", "EXITED", "FATAL"):
                    self.occurrences.append(Occurrence(t, "crash", (ev.node,)))
                continue
            if ev.kind == "deploy" and ev.outcome == "ok":
                self.occurrences.append(Occurrence(t, "deploy", ()))
            if ev.outcome in ("rolled_back", "failed"):
                self.occurrences.append(Occurrence(t, "rollback", ()))
            if ev.outcome != "ok":
                continue
            if ev.kind == "adaptation" and ev.plan:
                self.occurrences.append(Occurrence(t, "adaptation", ()))
            self.occurrences += _plan_occurrences(t, ev.plan, pairs)
            for step in ev.plan:
                self.known_nodes.update(_plan_step(step)[1])

    # -- signals
    @staticmethod
    def value_at(sig: Signal, t: float) -> tuple[float, Any] | None:
        """The sample in force at ``t`` (the last one at or before it), or None."""
        i = bisect.bisect_right(sig, t, key=lambda s: s[0])
        return sig[i - 1] if i else None

    @classmethod
    def pieces(
        cls, sig: Signal, a: float, b: float, *, open_end: bool = False
    ) -> list[tuple[float, Any]]:
        """The values in force over [a, b] (or [a, b) with ``open_end``: a value that starts
        at ``b`` is not in force before it): (a, value at a) if any, then each later sample."""
        out = []
        first = cls.value_at(sig, a)
        if first is not None:
            out.append((a, first[1]))
        i = bisect.bisect_right(sig, a, key=lambda s: s[0])
        while i < len(sig) and (sig[i][0] < b if open_end else sig[i][0] <= b):
            out.append(sig[i])
            i += 1
        return out

    # -- times
    def resolve(self, ref: TimeRef) -> tuple[float | None, str]:
        """The time of ``ref`` (None and why, if its anchor never happened)."""
        if ref.end:
            return self.end + ref.offset, ""
        if ref.injection is not None:
            a = self.injections.get(ref.injection)
            if a is None:
                return None, f"injection {ref.injection} was never applied"
            if not a.ok:
                return None, f"injection {ref.injection} failed: {a.detail}"
            return a.stamp - self.rec.t0 + ref.offset, ""
        if ref.event is not None:
            first = next((o for o in self.occurrences if ref.event.matches(o.kind, o.args)), None)
            if first is None:
                return None, f"{ref.event} never happened"
            return first.t + ref.offset, ""
        return ref.offset, ""


def _plan_step(line: str) -> tuple[str, list[str], str]:
    """(action, nodes, port) of an ok plan line, or ("", [], "") if it failed or is unknown."""
    mt = _PLAN_LINE.match(line)
    if mt is None or mt["status"] != "ok":
        return "", [], ""
    what = mt["what"].strip()
    rw = _REWIRE.match(what)
    if rw:
        return "rewire", [rw["node"]], rw["port"]
    action, _, nodes = what.partition(" ")
    return action, [n for n in nodes.split(",") if n], ""


def _plan_occurrences(
    t: float, plan: Sequence[str], pairs: set[tuple[str, ...]]
) -> list[Occurrence]:
    out: list[Occurrence] = []
    gone: set[str] = set()
    came: set[str] = set()
    for line in plan:
        action, nodes, port = _plan_step(line)
        if action == "rewire":
            out.append(Occurrence(t, "rewire", (nodes[0], port)))
        elif action in ("set_params", "activate", "deactivate"):
            out += [Occurrence(t, action, (n,)) for n in nodes]
        if action in ("stop", "deactivate"):
            gone.update(nodes)
        elif action in ("start", "activate", "select"):  # select: a hot standby's switch
            came.update(nodes)
    for a in sorted(gone - came):
        for b in sorted(came - gone):
            if not pairs or (a, b) in pairs:
                out.append(Occurrence(t, "swap", (a, b)))
    return out


# ---- evaluation -------------------------------------------------------------------------------
@dataclass(frozen=True)
class Outcome:
    passed: bool
    #: What was observed, for humans: the value and time that decided the outcome.
    observed: str
    #: The time (s after deployment) the outcome refers to, if any.
    t: float | None = None


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, frozenset | set):
        return "{" + ", ".join(sorted(v)) + "}"
    if isinstance(v, str):
        return repr(v)
    return str(v)


def _window(idx: Index, when: When) -> tuple[float, float, str] | str:
    """(a, b, note) of the window of ``when``, or why it cannot be placed."""
    if when.mode == "end":
        return idx.end, idx.end, ""
    a, why = idx.resolve(when.start)
    if a is None:
        return why
    if a > idx.end:
        return f"{when.start} = {a:.2f} s is after the end of the run ({idx.end:.2f} s)"
    if when.mode == "at":
        return a, a, ""
    b, why = (idx.end, "") if when.stop is None else idx.resolve(when.stop)
    if b is None:
        return why
    note = ""
    if b > idx.end:
        note = f" (window cut by the end of the run at {idx.end:.2f} s)"
        b = idx.end
    return a, b, note


def _rel(t: float, when: When, idx: Index) -> str:
    """`` (0.31 s after low_battery)`` when the window starts at an injection or event."""
    if when.start.injection is None and when.start.event is None:
        return ""
    anchor = when.start.injection or when.start.event
    base, _ = idx.resolve(TimeRef(0.0, when.start.injection, when.start.event))
    return "" if base is None else f" ({t - base:.2f} s after {anchor})"


def check_signal(
    idx: Index,
    sig: Signal,
    when: When,
    pred: Callable[[Any], bool],
    show: Callable[[Any], str] = _fmt,
) -> Outcome:
    """Decide ``pred`` over a step signal within the window of ``when``."""
    win = _window(idx, when)
    if isinstance(win, str):
        return Outcome(False, win)
    a, b, note = win
    if b < a:
        return Outcome(False, f"empty window [{a:.2f}, {b:.2f}] s{note}")
    pieces = Index.pieces(sig, a, b, open_end=when.mode == "always" and b > a)
    if when.mode in ("at", "end", "always") and Index.value_at(sig, a) is None:
        return Outcome(False, f"no value yet at {a:.2f} s", a)
    if when.mode in ("at", "end"):
        v = pieces[0][1]
        return Outcome(pred(v), f"{show(v)} at {a:.2f} s", a)
    if when.mode == "always":
        for t, v in pieces:
            if not pred(v):
                return Outcome(False, f"{show(v)} at {t:.2f} s{_rel(t, when, idx)}{note}", t)
        return Outcome(True, _summary(pieces, show) + f" over [{a:.2f}, {b:.2f}] s", a)
    for t, v in pieces:
        if pred(v):
            already = _already(sig, pieces, a, b, show) if t == a else ""
            return Outcome(True, already or f"{show(v)} at {t:.2f} s{_rel(t, when, idx)}", t)
    if not pieces:
        return Outcome(False, f"no value in [{a:.2f}, {b:.2f}] s{note}")
    return Outcome(
        False, f"never in [{a:.2f}, {b:.2f}] s: {_summary(pieces, show)}{note}", pieces[-1][0]
    )


def _already(
    sig: Signal, pieces: list[tuple[float, Any]], a: float, b: float, show: Callable[[Any], str]
) -> str:
    """What an ``eventually`` that held at the window's start observed, when the value was
    already in force before it (``""`` otherwise): since when, and whether it ever changed in
    the window (a state that never changed after a kill: the kill did not show)."""
    held = Index.value_at(sig, a)
    if held is None or held[0] >= a:
        return ""  # the value came at the window's start itself: it did change there
    since = "the start" if held[0] == -math.inf else f"{held[0]:.2f} s"
    text = f"{show(pieces[0][1])} already, since {since}"
    if all(v == pieces[0][1] for _, v in pieces):
        return f"{text}; never changed in [{a:.2f}, {b:.2f}] s"
    changed = next(t for t, v in pieces if v != pieces[0][1])
    return f"{text}; first changed at {changed:.2f} s"


def _summary(pieces: list[tuple[float, Any]], show: Callable[[Any], str]) -> str:
    values = [v for _, v in pieces]
    nums = [v for v in values if isinstance(v, int | float) and not isinstance(v, bool)]
    if len(nums) == len(values) and len(set(values)) > 1:
        return f"{_fmt(min(nums))} .. {_fmt(max(nums))} (last {_fmt(values[-1])})"
    shown: list[str] = []
    for v in values:
        text = show(v)
        if not shown or shown[-1] != text:
            shown.append(text)
    return ("... -> " if len(shown) > 4 else "") + " -> ".join(shown[-4:])


def compare(observed: Any, op: str, value: Any, tolerance: float = 0.0, high: Any = None) -> bool:
    """``observed op value``: numbers as numbers (with ``tolerance`` for == and !=), anything
    else by equality only."""
    num = isinstance(observed, int | float) and not isinstance(observed, bool)
    if op == "in":
        return num and value <= observed <= high
    if isinstance(value, float) and num:
        # Within the tolerance, or equal but for float rounding (0.55 - 0.5 > 0.05).
        near = abs(observed - value) <= tolerance or math.isclose(
            abs(observed - value), tolerance, rel_tol=1e-9, abs_tol=1e-12
        )
        if op == "==":
            return near
        if op == "!=":
            return not near
        return {
            "<": observed < value,
            "<=": observed <= value,
            ">": observed > value,
            ">=": observed >= value,
        }[op]
    if op == "==":
        return observed == value
    if op == "!=":
        return observed != value
    return False


def field_of(sample: Any, path: Iterable[str | int]) -> Any:
    """The field at ``path`` inside a data sample (None where it is missing)."""
    value = sample
    for p in path:
        if isinstance(p, int) and isinstance(value, list) and -len(value) <= p < len(value):
            value = value[p]
        elif isinstance(p, str) and isinstance(value, dict):
            value = value.get(p)
        else:
            return None
    return value


def quantity_signal(idx: Index, q: Quantity) -> Signal:
    match q.kind:
        case "measurement":
            return idx.measurements.get(q.name, [])
        case "cv":
            return (idx.decided_cv if q.decided else idx.cv).get(q.name, [])
        case "param":
            return [(t, field_of(v, q.path)) for t, v in idx.params.get(q.name, [])]
        case "implementation":
            return idx.implementations.get(q.name, [])
        case "data":
            topic = q.topic or q.name.replace(".", "/", 1)
            return [(t, field_of(s, q.path)) for t, s in idx.data.get(topic, [])]
    raise ValueError(f"unbound quantity {q}")


def evaluate(exp: Expectation, idx: Index) -> Outcome:
    """Decide one expectation against a recording (pure)."""
    match exp:
        case FeatureExpectation(feature=f, selected=sel, decided=decided):
            signal = idx.decided_features if decided else idx.features
            return check_signal(
                idx, signal, exp.when, lambda s: (f in s) == sel, _feature_show(f, decided)
            )
        case StateExpectation(node=n, state=st):
            sig = idx.states.get(n, [(-math.inf, "STOPPED")])
            return check_signal(idx, sig, exp.when, lambda s: s == st, str)
        case ValueExpectation():
            sig = quantity_signal(idx, exp.quantity)
            return check_signal(
                idx,
                sig,
                exp.when,
                lambda v: compare(v, exp.op, exp.value, exp.tolerance, exp.high),
            )
        case EventExpectation():
            return _check_event(idx, exp)
        case NoStateExpectation(state=st):
            return _check_no_state(idx, exp, st)
        case AbsentNodeExpectation(node=n):
            seen = n in idx.known_nodes or any(k.startswith(f"{n}.") for k in idx.params)
            if not seen:
                return Outcome(True, "never seen")
            first = idx.states.get(n, [])
            t = first[1][0] if len(first) > 1 else None
            shown = f" ({first[1][1]} at {t:.2f} s)" if t is not None else ""
            return Outcome(False, f"node {n} was part of the run{shown}", t)
        case NotRestartedExpectation(node=n):
            return _check_not_restarted(idx, exp, n)
        case NoOrphanExpectation():
            if idx.rec.orphans is None:
                return Outcome(False, "not checked (the run did not stop normally)")
            if idx.rec.orphans:
                return Outcome(False, f"still alive after the stop: pids {idx.rec.orphans}")
            return Outcome(True, "none")
    raise TypeError(f"unknown expectation {exp!r}")


def _feature_show(f: str, decided: bool = False) -> Callable[[Any], str]:
    what = ("decided", "not decided") if decided else ("selected", "not selected")
    return lambda s: what[0] if f in s else what[1]


def _check_event(idx: Index, exp: EventExpectation) -> Outcome:
    win = _window(idx, exp.when)
    if isinstance(win, str):
        return Outcome(False, win)
    a, b, note = win
    hits = [o for o in idx.occurrences if exp.event.matches(o.kind, o.args)]
    inside = [o for o in hits if a <= o.t <= b]
    if exp.negated:
        if inside:
            o = inside[0]
            return Outcome(False, f"{_occ(o)} at {o.t:.2f} s", o.t)
        return Outcome(True, f"none in [{a:.2f}, {b:.2f}] s")
    if inside:
        o = inside[0]
        what = f"{_occ(o)} " if "*" in exp.event.args or not exp.event.args else ""
        return Outcome(True, f"{what}at {o.t:.2f} s{_rel(o.t, exp.when, idx)}", o.t)
    if not hits:
        return Outcome(False, f"never happened{note}")
    times = ", ".join(f"{o.t:.2f} s" for o in hits[:5]) + (" ..." if len(hits) > 5 else "")
    return Outcome(False, f"not in [{a:.2f}, {b:.2f}] s{note}; happened at {times}", hits[0].t)


def _occ(o: Occurrence) -> str:
    return str(EventPattern(o.kind, o.args))


def _check_not_restarted(idx: Index, exp: NotRestartedExpectation, node: str) -> Outcome:
    """One pid in the window: the one in force at its start, every later one, and the one
    the node's host agent listed at the end (when the window reaches it)."""
    win = _window(idx, exp.when)
    if isinstance(win, str):
        return Outcome(False, win)
    a, b, _ = win
    pids = Index.pieces(idx.pids.get(node, []), a, b)
    final = idx.final_pids.get(node)
    if final is not None and b >= idx.end:
        pids.append((idx.end, final[1]))
    if not pids:
        return Outcome(False, f"no process of node {node} recorded in [{a:.2f}, {b:.2f}] s")
    first = pids[0][1]
    for t, pid in pids:
        if pid != first:
            return Outcome(False, f"pid {first} -> {pid} at {t:.2f} s{_rel(t, exp.when, idx)}", t)
    seen = f", listed by host {final[0]} at the end" if final is not None and b >= idx.end else ""
    return Outcome(True, f"pid {first} throughout [{a:.2f}, {b:.2f}] s{seen}")


def _check_no_state(idx: Index, exp: NoStateExpectation, state: str) -> Outcome:
    win = _window(idx, exp.when)
    if isinstance(win, str):
        return Outcome(False, win)
    a, b, _ = win
    for node, sig in sorted(idx.states.items()):
        for t, v in Index.pieces(sig, a, b):
            if v == state:
                return Outcome(False, f"node {node} {state} at {t:.2f} s", t)
    return Outcome(True, f"no node {state} in [{a:.2f}, {b:.2f}] s")
