"""Operators' injections at the Context Monitor, and the live context it shows.

``rra inject`` asks the Context Monitor leader for two things (`rra_agent.bus.messages`):

- `Inject`: a fault or context change for the nodes that take injections (the quadcopter's
  ``break_motor``...): published on ``inject/<kind>`` as a scenario's ``inject:`` step is,
  and refused when no process of the system listens for injections there;
- `OverrideMeasurement`: the leader publishes the operator's value of a measurement instead
  of the computed one until the duration ends (0: ends it now), marked as an override with
  its fence (`Measurement.override`, ``until``, ``fence``) and re-sent as often as an
  unchanged value is, so the rules never find it stale. The value is checked against the
  measurement's declaration (its type, finite, plausible) as computed values are; an unknown
  measurement or an ill-typed value is refused with the reason. When it ends, the newest
  computed value is published again.

Both are recorded as ``injection`` events naming the operator. An override is the leader's:
a replica that stops leading drops its overrides, and its successor publishes computed
values (what ``rra status`` then shows).
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.core.monitor import coerce, value_problem
from rra_agent.models.measurements import Measurement

_TRUE, _FALSE = ("true", "on", "yes", "1"), ("false", "off", "no", "0")


class InjectionError(ValueError):
    """A request the monitor refuses; ``code`` is the `Err` code."""

    def __init__(self, message: str, code: str = "refused") -> None:
        super().__init__(message)
        self.code = code


def typed_value(meas: Measurement, value: float | int | bool | str) -> float | int | bool | str:
    """``value`` (text from a command line, or a typed value) as a value of ``meas``; an
    `InjectionError` saying why it is not one."""
    raw: Any = value
    if isinstance(value, str) and meas.type != "str":
        raw = _parse(meas, value.strip())
    try:
        typed = coerce(raw, meas.type)
    except ValueError as e:
        raise InjectionError(f"{meas.name} is a {meas.type} measurement: {e}") from None
    problem = value_problem(meas, typed)
    if problem is not None:
        raise InjectionError(f"{meas.name} may not be {problem[1]} ({problem[0]})")
    return typed


def _parse(meas: Measurement, text: str) -> Any:
    if meas.type == "bool":
        if text.lower() in _TRUE:
            return True
        if text.lower() in _FALSE:
            return False
        raise InjectionError(f"{meas.name} is a bool measurement: {text!r} is not true or false")
    try:
        return int(text) if meas.type == "int" else float(text)
    except ValueError:
        kind = "an integer" if meas.type == "int" else "a number"
        raise InjectionError(
            f"{meas.name} is a {meas.type} measurement: {text!r} is not {kind}"
        ) from None


def find(declared: Mapping[str, Measurement], name: str, system: str) -> Measurement:
    """The declared measurement ``name``; an `InjectionError` (``unknown``) otherwise."""
    meas = declared.get(name)
    if meas is not None:
        return meas
    close = difflib.get_close_matches(name, list(declared), n=1)
    hint = f" (did you mean {close[0]}?)" if close else f" (it has: {', '.join(declared)})"
    raise InjectionError(f"system {system} has no measurement {name!r}{hint}", code="unknown")


@dataclass
class Override:
    """An operator's value of a measurement, until ``until`` (wall clock)."""

    value: float | int | bool | str
    operator: str
    until: float
    #: The same deadline on the monitor's main-loop clock, and the next re-send.
    deadline: float
    next_send: float


class Overrides:
    """The measurements overridden now, and when each must be re-sent or ends."""

    def __init__(self, refresh: Mapping[str, float]) -> None:
        self.refresh = refresh
        self.active: dict[str, Override] = {}

    def set(self, name: str, value: Any, operator: str, wall: float, mono: float,
            duration: float) -> Override:  # fmt: skip
        o = Override(value, operator, wall + duration, mono + duration, mono)
        self.active[name] = o
        return o

    def due(self, mono: float) -> tuple[list[str], list[str]]:
        """(names to re-send now, names whose override ends now)."""
        send = [n for n, o in self.active.items() if o.deadline > mono >= o.next_send]
        ended = [n for n, o in self.active.items() if o.deadline <= mono]
        for n in send:
            self.active[n].next_send = mono + self.refresh.get(n, 1.0)
        return send, ended

    def next_at(self) -> float | None:
        """When `due` has something to do next (main-loop clock), if ever."""
        times = [min(o.next_send, o.deadline) for o in self.active.values()]
        return min(times, default=None)

    def message(self, name: str, stamp: float, fence: m.Fence | None) -> m.Measurement:
        o = self.active[name]
        return m.Measurement(
            name=name, value=o.value, stamp=stamp, override=o.operator, until=o.until, fence=fence
        )


def derivation(meas: Measurement) -> str:
    """Where a measurement's value comes from, for people: its source interfaces, or what a
    derived one follows (``reachable: host``, ``available: component``)."""
    if meas.reachable is not None:
        return f"reachable: {meas.reachable}"
    if meas.available is not None:
        return f"available: {meas.available}"
    return ", ".join([meas.source] if meas.source else meas.sources)


def context_view(
    declared: Iterable[Measurement], latest: Mapping[str, m.Measurement]
) -> list[dict[str, Any]]:
    """Every measurement of the model with its newest value (as published: an override
    shows as such), for ``rra status``: name, type, unit, where it comes from, value, when
    it was computed and its sources' send times; ``value`` absent when none yet."""
    out = []
    for meas in declared:
        entry: dict[str, Any] = {
            "name": meas.name,
            "type": meas.type,
            "from": derivation(meas),
            "derived": meas.reachable is not None or meas.available is not None,
        }
        if meas.unit:
            entry["unit"] = meas.unit
        msg = latest.get(meas.name)
        if msg is not None:
            entry.update(value=msg.value, stamp=msg.stamp, sources=dict(msg.sources))
            if msg.override:
                entry.update(override=msg.override, until=msg.until)
        out.append(entry)
    return out


def inject_text(req: m.Inject) -> str:
    """``break_motor target=vehicle_simulator motor=2``: what an injection does."""
    parts = [req.kind] + ([f"target={req.target}"] if req.target else [])
    return " ".join(parts + [f"{k}={v}" for k, v in sorted(req.args.items())])
