"""The Context Monitor's logic (paper Sec. III-C): source samples in, measurements out.

For each Context Dependent Measurement the model names its source interface(s) and how the
value is obtained:

- ``function``: a callable on the source sample (one argument per source for multi-input
  measurements); the shell resolves the model's name or dotted path to the callable;
- ``field``: that field of the sample;
- neither: the sample's only field, else its ``value`` field.

Samples are checked before they are used (`rra_agent.core.samples`): `decode` turns the raw
bytes of a source into a sample of its port's declared data type, or a `Refusal` (missing
field, wrong type, not msgpack, not a map). A measurement then refuses NaN and infinities in
what it reads (the field; for a function, every number of its source samples) and in its
value, unless it says ``finite: false``, and a value outside its ``plausible`` bounds. A
refused sample is counted per source and reason in ``refusals`` and never yields a
measurement (nor replaces a good sample a multi-input measurement keeps).

The value is coerced to the declared type (``float``, ``int``, ``bool``, ``str``). A sample
whose value cannot be obtained otherwise (function raised, a value that does not fit the
type) yields no measurement and is counted in ``failures`` with the reason; nothing here
raises on bad data.

Multi-input synchronisation (the paper's first future-work item):

- ``latest``: on every input, once each source has been seen, compute from the latest sample
  of each source;
- ``window``: compute only when the latest samples of all sources were sent within
  ``window_ms`` of each other (sender time stamps), so a measurement never mixes a fresh
  sample with a stale one.

Pure: no clock is read, no I/O; the shell passes samples with their stamps.
"""

from __future__ import annotations

import math
from collections import defaultdict
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from rra_agent.core.samples import Decoder, Refusal, SampleTypes, Tally
from rra_agent.models.measurements import Measurement, MeasurementsModel

Value = float | int | bool | str
Function = Callable[..., Any]


@dataclass(frozen=True)
class Computed:
    """One computed measurement and the send times of the samples it came from."""

    name: str
    value: Value
    sources: dict[str, float]


def coerce(value: Any, type_: str) -> Value:
    """The value as the measurement's declared type; ValueError when it does not fit."""
    if type_ == "str":
        if isinstance(value, str):
            return value
        raise ValueError(f"expected a string, got {value!r}")
    if type_ == "bool":
        if isinstance(value, bool):
            return value
        raise ValueError(f"expected a boolean, got {value!r}")
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"expected a number, got {value!r}")
    if type_ == "int":
        if isinstance(value, float) and not value.is_integer():
            raise ValueError(f"expected an integer, got {value!r}")
        return int(value)
    return float(value)


def _plain(sample: Mapping[str, Any], fieldname: str | None) -> Any:
    if fieldname is not None:
        return sample[fieldname]
    if len(sample) == 1:
        return next(iter(sample.values()))
    return sample["value"]


@dataclass
class _Spec:
    m: Measurement
    fn: Function | None
    latest: dict[str, tuple[Mapping[str, Any], float]] = field(default_factory=dict)


class ContextMonitor:
    """Feeds samples of ``component.port`` interfaces; returns the measurements they yield."""

    def __init__(
        self,
        model: MeasurementsModel,
        functions: Mapping[str, Function],
        port_types: Mapping[str, str] | None = None,
    ) -> None:
        """``functions``: measurement name -> callable, for measurements with a function.
        ``port_types``: ``component.port`` -> the type its port declares (a source whose
        type is not a data type of ``model``, or not given, only needs maps)."""
        self.specs = [_Spec(m, functions.get(m.name)) for m in model.measurements]
        missing = [s.m.name for s in self.specs if s.m.function and s.fn is None]
        if missing:
            raise ValueError(f"no callable given for measurement(s) {', '.join(missing)}")
        self.by_source: dict[str, list[_Spec]] = defaultdict(list)
        for s in self.specs:
            for src in s.m.inputs:
                self.by_source[src].append(s)
        types = SampleTypes(model.data_types)
        self.decoders: dict[str, Decoder] = {
            src: types.for_port((port_types or {}).get(src)) for src in self.by_source
        }
        self.failures: dict[str, int] = defaultdict(int)
        self.last_failure: dict[str, str] = {}
        #: Refused samples, per source and reason.
        self.refusals = Tally()

    @property
    def sources(self) -> list[str]:
        """Every ``component.port`` the monitor listens to."""
        return sorted(self.by_source)

    def decode(self, source: str, raw: bytes | memoryview) -> Mapping[str, Any] | None:
        """A raw sample of ``source`` as its declared data type; None when it is refused
        (counted in ``refusals``)."""
        decoder = self.decoders.get(source)
        if decoder is None:
            return None
        sample = decoder.decode(source, raw)
        if isinstance(sample, Refusal):
            self.refusals.add(sample)
            return None
        return sample

    def on_raw(self, source: str, raw: bytes | memoryview, stamp: float) -> list[Computed]:
        """`decode`, then `on_sample`."""
        sample = self.decode(source, raw)
        return [] if sample is None else self.on_sample(source, sample, stamp)

    def on_sample(self, source: str, sample: Mapping[str, Any], stamp: float) -> list[Computed]:
        """The measurements a decoded sample of ``source`` yields (a refusal is counted once
        per sample and reason, however many measurements refuse it)."""
        out = []
        refused: dict[str, str] = {}
        for spec in self.by_source.get(source, ()):
            why = self._unreadable(spec, source, sample)
            if why is not None:
                refused.setdefault("non_finite", why)
                continue
            spec.latest[source] = (sample, stamp)
            computed = self._compute(spec, refused)
            if computed is not None:
                out.append(computed)
        for reason, detail in refused.items():
            self.refusals.add(Refusal(source, reason, detail))
        return out

    def _unreadable(self, spec: _Spec, source: str, sample: Mapping[str, Any]) -> str | None:
        """Why a function measurement may not read ``sample`` (a non-finite number in it)."""
        if not spec.m.finite or spec.fn is None:
            return None  # a field measurement reads one value: its value is checked
        check = self.decoders[source].nonfinite
        where = check(sample) if check is not None else None
        if where is None:
            return None
        return f"{spec.m.name}: {source}{where or ''} is not finite"

    def _compute(self, spec: _Spec, refused: dict[str, str]) -> Computed | None:
        m = spec.m
        inputs = m.inputs
        if len(spec.latest) < len(inputs):
            return None
        stamps = {src: spec.latest[src][1] for src in inputs}
        spread_ms = (max(stamps.values()) - min(stamps.values())) * 1000.0
        if m.sync.policy == "window" and spread_ms > (m.sync.window_ms or 0.0):
            return None
        samples = [spec.latest[src][0] for src in inputs]
        try:
            raw = spec.fn(*samples) if spec.fn is not None else _plain(samples[0], m.field)
            value = coerce(raw, m.type)
        except Exception as e:  # user functions and bad samples must not stop the monitor
            self.failures[m.name] += 1
            self.last_failure[m.name] = f"{type(e).__name__}: {e}"
            return None
        problem = value_problem(m, value)
        if problem is not None:
            refused.setdefault(problem[0], f"{m.name} would be {problem[1]}")
            return None
        return Computed(m.name, value, stamps)


def value_problem(m: Measurement, value: Value) -> tuple[str, str] | None:
    """(reason, what) when ``value``, of ``m``'s type, may not be a value of ``m``: NaN or an
    infinity it does not allow, or outside its plausible bounds; None when it may."""
    if m.finite and isinstance(value, float) and not math.isfinite(value):
        return "non_finite", f"{value}"
    if m.plausible is not None and not m.plausible.admits(value):  # type: ignore[arg-type]
        return "implausible", f"{value}, {_bounds(m)}"
    return None


def measurement_problem(m: Measurement | None, value: Any) -> tuple[str, str] | None:
    """(reason, what) when a measurement received on the bus (``ctx/<name>``) may not reach
    the rules: a name the model does not declare (``unknown``), a value not of its declared
    type (``wrong_type``), or one `value_problem` refuses; None when it may."""
    if m is None:
        return "unknown", "not a measurement of the model"
    try:
        typed = coerce(value, m.type)
    except ValueError as e:
        return "wrong_type", str(e)
    problem = value_problem(m, typed)
    return None if problem is None else (problem[0], f"{m.name} = {problem[1]}")


def _bounds(m: Measurement) -> str:
    assert m.plausible is not None
    low, high = m.plausible.min, m.plausible.max
    if low is not None and high is not None:
        return f"outside [{low:g}, {high:g}]"
    return f"below {low:g}" if low is not None else f"above {high:g}"
