"""Context Monitor logic: fields, functions, type coercion, multi-input synchronisation."""

from __future__ import annotations

import math

import msgspec
import pytest

from rra_agent.core.monitor import ContextMonitor, coerce, measurement_problem
from rra_agent.library.laser import closest_obstacle
from rra_agent.models.measurements import MeasurementsModel


def model(*measurements: dict) -> MeasurementsModel:
    return msgspec.convert({"measurements": list(measurements)}, MeasurementsModel)


def test_field_and_function_measurements():
    mon = ContextMonitor(
        model(
            {"name": "BattLev", "type": "float", "source": "robot.battery", "field": "level"},
            # inf in a scan is "no return", and the value is inf with nothing in sight.
            {"name": "ObstDist", "type": "float", "source": "laser.scan", "function": "f",
             "finite": False},
        ),
        {"ObstDist": closest_obstacle},
    )  # fmt: skip
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


# ---- data the monitor can trust ------------------------------------------------------------
def typed_monitor(*measurements: dict, functions: dict | None = None) -> ContextMonitor:
    """A monitor of robot.battery (BatteryState), laser.scan (LaserScan), nav.odom (Odometry:
    a nested Pose) and radio.rx (str: no declared type), as object_storing declares them."""
    m = msgspec.convert(
        {
            "data_types": [
                {"name": "BatteryState", "fields": {"level": "float", "voltage": "float",
                 "charging": "bool", "note": "str"}, "optional": ["note"]},
                {"name": "LaserScan", "fields": {"ranges": "list[float]", "range_min": "float",
                 "range_max": "float"}},
                {"name": "Pose", "fields": {"x": "float", "y": "float"}},
                {"name": "Odometry", "fields": {"poses": "list[Pose]", "v": "float"}},
                {"name": "Tree", "fields": {"value": "float", "children": "list[Tree]"}},
            ],
            "measurements": list(measurements),
        },
        MeasurementsModel,
    )  # fmt: skip
    types = {"robot.battery": "BatteryState", "laser.scan": "LaserScan", "nav.odom": "Odometry",
             "radio.rx": "str", "tree.out": "Tree"}  # fmt: skip
    return ContextMonitor(m, functions or {}, types)


BATT = {"name": "BattLev", "type": "float", "source": "robot.battery", "field": "level",
        "plausible": {"min": 0, "max": 100}}  # fmt: skip
GOOD = {"level": 42.0, "voltage": 24.1, "charging": False}


def raw(value) -> bytes:
    return msgspec.msgpack.encode(value)


@pytest.mark.parametrize(
    ("sample", "reason"),
    [
        ({"level": 9.0}, "missing_field"),  # a BatteryState with only `level`
        ({**GOOD, "level": "9"}, "wrong_type"),
        ({**GOOD, "level": True}, "wrong_type"),  # a bool is not a number
        ({**GOOD, "charging": 1}, "wrong_type"),  # nor a number a bool
        ({**GOOD, "note": 3}, "wrong_type"),  # an optional field still has its type
        ([9.0], "not_a_map"),
        ({**GOOD, "level": math.nan}, "non_finite"),
        ({**GOOD, "level": math.inf}, "non_finite"),
        ({**GOOD, "level": -math.inf}, "non_finite"),
        ({**GOOD, "level": -1e9}, "implausible"),
        ({**GOOD, "level": 1e9}, "implausible"),
    ],
)
def test_a_sample_that_is_not_its_declared_type_or_not_plausible_is_refused(sample, reason):
    mon = typed_monitor(BATT)
    assert mon.on_raw("robot.battery", raw(sample), 1.0) == []
    assert mon.refusals.rows() == [("robot.battery", reason, 1, mon.refusals.rows()[0][3])]
    assert mon.refusals.count("robot.battery", reason) == 1
    # A good one after it is used: nothing was left behind.
    [c] = mon.on_raw("robot.battery", raw({**GOOD, "note": "ok", "extra": [1]}), 2.0)
    assert (c.name, c.value) == ("BattLev", 42.0)


def test_truncated_msgpack_is_malformed_and_an_integer_is_a_float():
    mon = typed_monitor(BATT)
    assert mon.on_raw("robot.battery", raw(GOOD)[:-3], 1.0) == []
    [(source, reason, n, detail)] = mon.refusals.rows()
    assert (source, reason, n) == ("robot.battery", "malformed", 1) and "truncated" in detail
    [c] = mon.on_raw("robot.battery", raw({**GOOD, "level": 42}), 2.0)
    assert c.value == 42.0 and isinstance(c.value, float)


def test_decoded_samples_hold_only_the_declared_fields():
    mon = typed_monitor(BATT)
    assert mon.decode("robot.battery", raw({**GOOD, "x": 1})) == GOOD


def test_nested_and_recursive_types_are_checked_inside():
    odo = {"name": "V", "type": "float", "source": "nav.odom", "field": "v"}
    tree = {"name": "T", "type": "float", "source": "tree.out", "field": "value"}
    mon = typed_monitor(odo, tree)
    good = {"poses": [{"x": 1.0, "y": 2.0}], "v": 0.5}
    assert [c.value for c in mon.on_raw("nav.odom", raw(good), 0.0)] == [0.5]
    assert mon.on_raw("nav.odom", raw({"poses": [{"x": 1.0}], "v": 0.5}), 0.0) == []
    assert mon.refusals.count("nav.odom", "missing_field") == 1
    leaf = {"value": 1.0, "children": []}
    assert [c.value for c in mon.on_raw("tree.out", raw({**leaf, "children": [leaf]}), 0)] == [1]
    assert mon.on_raw("tree.out", raw({"value": 1.0, "children": [3]}), 0.0) == []
    assert mon.refusals.count("tree.out", "not_a_map") == 1  # an inner Tree is a map at least


def test_a_port_without_a_declared_type_needs_maps_and_finite_values():
    mon = typed_monitor({"name": "Rx", "type": "float", "source": "radio.rx"})
    assert [c.value for c in mon.on_raw("radio.rx", raw({"value": 3}), 0.0)] == [3.0]
    assert mon.on_raw("radio.rx", raw("junk"), 0.0) == []
    assert mon.on_raw("radio.rx", raw({"value": math.nan}), 0.0) == []
    assert [r[:3] for r in mon.refusals.rows()] == [
        ("radio.rx", "non_finite", 1),
        ("radio.rx", "not_a_map", 1),
    ]


def test_a_function_reads_only_finite_samples_unless_its_measurement_allows_them():
    strict = {"name": "Closest", "type": "float", "source": "laser.scan", "function": "f"}
    lenient = {**strict, "name": "Lenient", "finite": False, "plausible": {"min": 0}}
    mon = typed_monitor(strict, lenient, functions={"Closest": closest_obstacle,
                                                    "Lenient": closest_obstacle})  # fmt: skip
    scan = {"ranges": [3.0, math.inf, 0.7], "range_min": 0.05, "range_max": 10.0}
    # Closest refuses the scan (an inf range); Lenient takes it; one refusal per sample.
    [c] = mon.on_raw("laser.scan", raw(scan), 0.0)
    assert (c.name, c.value) == ("Lenient", pytest.approx(0.7))
    [(_, reason, n, detail)] = mon.refusals.rows()
    assert (reason, n) == ("non_finite", 1) and "laser.scan.ranges[1]" in detail
    # Nothing in sight: inf is Lenient's value; Closest's function never even ran.
    nothing = {"ranges": [20.0], "range_min": 0.05, "range_max": 10.0}
    [c] = mon.on_raw("laser.scan", raw(nothing), 1.0)
    assert (c.name, c.value) == ("Lenient", math.inf)
    [c] = mon.on_raw("laser.scan", raw({**nothing, "range_min": -1.0, "ranges": [-0.5]}), 2.0)
    assert c.name == "Closest" and c.value == -0.5  # Lenient's bounds refuse it
    assert mon.refusals.count("laser.scan", "implausible") == 1


def test_a_refused_input_never_replaces_the_latest_good_one_of_a_multi_input_measurement():
    mon = ContextMonitor(
        model({"name": "S", "type": "float", "sources": ["a.o", "b.o"], "function": "f"}),
        {"S": _sum},
    )
    mon.on_sample("a.o", {"v": 1.0}, 0.0)
    assert mon.on_sample("a.o", {"v": math.nan}, 1.0) == []
    [c] = mon.on_sample("b.o", {"v": 2.0}, 2.0)
    assert c.value == 3.0 and c.sources == {"a.o": 0.0, "b.o": 2.0}
    assert mon.refusals.count("a.o", "non_finite") == 1


def test_refusals_reach_the_observer_once_per_sample():
    seen = []
    mon = typed_monitor(BATT, {**BATT, "name": "Copy"})
    mon.refusals.observer = seen.append
    mon.on_raw("robot.battery", raw({**GOOD, "level": math.nan}), 0.0)
    assert [(r.source, r.reason) for r in seen] == [("robot.battery", "non_finite")]


@pytest.mark.parametrize(
    ("name", "value", "reason"),
    [
        ("BattLev", 42, None),  # an int is a fine float
        ("BattLev", math.nan, "non_finite"),
        ("BattLev", -math.inf, "non_finite"),
        ("BattLev", 100.5, "implausible"),
        ("BattLev", "42", "wrong_type"),
        ("BattLev", True, "wrong_type"),
        ("Nope", 1.0, "unknown"),
        ("Lenient", math.inf, None),
        ("Lenient", -1.0, "implausible"),
    ],
)
def test_a_measurement_from_the_bus_is_checked_against_its_declaration(name, value, reason):
    declared = {
        "BattLev": model(BATT).measurements[0],
        "Lenient": model({"name": "Lenient", "type": "float", "source": "l.s", "finite": False,
                          "plausible": {"min": 0}}).measurements[0],
    }  # fmt: skip
    problem = measurement_problem(declared.get(name), value)
    assert (problem[0] if problem else None) == reason, problem
