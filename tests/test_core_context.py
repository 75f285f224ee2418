"""Context Monitor logic: fields, functions, type coercion, multi-input synchronisation."""

from __future__ import annotations

import math

import msgspec
import pytest

from rra_agent.core.context import ContextMonitor, coerce
from rra_agent.library.laser import closest_obstacle
from rra_agent.models.measurements import MeasurementsModel


def model(*measurements: dict) -> MeasurementsModel:
    return msgspec.convert({"measurements": list(measurements)}, MeasurementsModel)


def test_field_and_function_measurements():
    mon = ContextMonitor(
        model(
            {"name": "BattLev", "type": "float", "source": "robot.battery", "field": "level"},
            {"name": "ObstDist", "type": "float", "source": "laser.scan", "function": "f"},
        ),
        {"ObstDist": closest_obstacle},
    )
    assert mon.sources == ["laser.scan", "robot.battery"]
    [c] = mon.on_sample("robot.battery", {"level": 42, "voltage": 24.1}, 1.0)
    assert (c.name, c.value, c.sources) == ("BattLev", 42.0, {"robot.battery": 1.0})
    assert isinstance(c.value, float)
    scan = {"ranges": [3.0, 0.7, math.inf, 0.01], "range_min": 0.05, "range_max": 10.0}
    [d] = mon.on_sample("laser.scan", scan, 2.0)
    assert d.value == pytest.approx(0.7)
    assert mon.on_sample("unknown.port", {"x": 1}, 3.0) == []


def test_single_field_sample_needs_no_field_name():
    mon = ContextMonitor(model({"name": "SemLoc", "type": "str", "source": "nav.loc"}), {})
    [c] = mon.on_sample("nav.loc", {"label": "Corridor"}, 0.0)
    assert c.value == "Corridor"


def test_bad_samples_are_counted_not_raised():
    def boom(sample):
        raise ZeroDivisionError("x")

    mon = ContextMonitor(
        model(
            {"name": "A", "type": "int", "source": "c.p", "field": "n"},
            {"name": "B", "type": "float", "source": "c.q", "function": "g"},
        ),
        {"B": boom},
    )
    assert mon.on_sample("c.p", {"other": 1}, 0.0) == []  # missing field
    assert mon.on_sample("c.p", {"n": 2.5}, 0.0) == []  # not an integer
    assert mon.on_sample("c.p", {"n": "3"}, 0.0) == []  # a string is not a number
    assert mon.on_sample("c.q", {"x": 1}, 0.0) == []
    assert mon.failures == {"A": 3, "B": 1}
    assert "ZeroDivisionError" in mon.last_failure["B"]
    [c] = mon.on_sample("c.p", {"n": 3.0}, 0.0)
    assert c.value == 3 and isinstance(c.value, int)


def _sum(a, b):
    return a["v"] + b["v"]


def test_multi_input_latest_policy():
    mon = ContextMonitor(
        model({"name": "S", "type": "float", "sources": ["a.o", "b.o"], "function": "f"}),
        {"S": _sum},
    )
    assert mon.on_sample("a.o", {"v": 1.0}, 0.0) == []  # b not seen yet
    [c] = mon.on_sample("b.o", {"v": 2.0}, 10.0)
    assert c.value == 3.0 and c.sources == {"a.o": 0.0, "b.o": 10.0}
    [c] = mon.on_sample("a.o", {"v": 5.0}, 11.0)
    assert c.value == 7.0


def test_multi_input_window_policy_never_mixes_stale_samples():
    mon = ContextMonitor(
        model(
            {
                "name": "S",
                "type": "float",
                "sources": ["a.o", "b.o"],
                "function": "f",
                "sync": {"policy": "window", "window_ms": 50},
            }
        ),
        {"S": _sum},
    )
    mon.on_sample("a.o", {"v": 1.0}, 0.000)
    assert mon.on_sample("b.o", {"v": 2.0}, 0.200) == []  # 200 ms apart: out of window
    [c] = mon.on_sample("a.o", {"v": 4.0}, 0.230)  # 30 ms apart: in window
    assert c.value == 6.0


def test_missing_function_is_an_error():
    with pytest.raises(ValueError, match="S"):
        ContextMonitor(model({"name": "S", "type": "float", "source": "a.o", "function": "f"}), {})


@pytest.mark.parametrize(
    ("value", "type_", "expected"),
    [(1, "float", 1.0), (2.0, "int", 2), (True, "bool", True), ("x", "str", "x")],
)
def test_coerce(value, type_, expected):
    out = coerce(value, type_)
    assert out == expected and type(out) is type(expected)


@pytest.mark.parametrize(
    ("value", "type_"), [(True, "float"), ("1", "int"), (1, "bool"), (1, "str")]
)
def test_coerce_rejects(value, type_):
    with pytest.raises(ValueError):
        coerce(value, type_)
