"""Measurement functions of rra_agent.library, and their use by the packages' measurement models."""

from __future__ import annotations

import importlib
import math
from pathlib import Path

import msgspec
import pytest
import yaml
from hypothesis import given
from hypothesis import strategies as st

from rra_agent.library import laser, motors
from rra_agent.library.laser import closest_obstacle
from rra_agent.library.motors import expected_current, working_motors
from rra_agent.models.measurements import MeasurementsModel

SCENARIOS = Path(__file__).resolve().parents[1] / "scenarios"
INF, NAN = math.inf, math.nan


# ---- laser.closest_obstacle --------------------------------------------------------------------
def scan(ranges: list[float], low: float = 0.1, high: float = 10.0) -> dict:
    return {"ranges": ranges, "range_min": low, "range_max": high, "angle_min": -1.57}


def test_closest_obstacle_is_the_smallest_valid_range() -> None:
    assert closest_obstacle(scan([3.0, 1.25, 7.5])) == 1.25


@pytest.mark.parametrize("bad", [INF, -INF, NAN, 0.05, 12.0, -1.0])
def test_invalid_ranges_are_ignored(bad: float) -> None:
    assert closest_obstacle(scan([2.0, bad, 4.0])) == 2.0


def test_bounds_are_inclusive() -> None:
    assert closest_obstacle(scan([0.1, 5.0])) == 0.1
    assert closest_obstacle(scan([10.0])) == 10.0


def test_nothing_in_sight_is_infinitely_far() -> None:
    assert closest_obstacle(scan([])) == INF
    assert closest_obstacle(scan([INF, NAN, 0.0, 11.0])) == INF


def test_missing_bounds_accept_any_finite_non_negative_range() -> None:
    assert closest_obstacle({"ranges": [0.0, 30.0, INF]}) == 0.0


def test_closest_obstacle_returns_a_float() -> None:
    d = closest_obstacle(scan([2, 3]))
    assert d == 2.0 and isinstance(d, float)


@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=50))
def test_closest_obstacle_is_a_valid_range_or_inf(ranges: list[float]) -> None:
    d = closest_obstacle(scan(ranges))
    valid = [r for r in ranges if 0.1 <= r <= 10.0]
    assert d == (min(valid) if valid else INF)


# ---- motors.working_motors ---------------------------------------------------------------------
HOVER = 470.0  # rad/s: each motor lifts a quarter of 1 kg


def telemetry(speeds: list[float], currents: list[float]) -> dict:
    return {"desired_speed": speeds, "measured_speed": speeds, "current": currents}


def healthy(speeds: list[float]) -> list[float]:
    return [expected_current(w) for w in speeds]


def test_expected_current_grows_with_speed_squared() -> None:
    assert expected_current(0.0) == motors.IDLE_CURRENT
    assert expected_current(HOVER) == pytest.approx(1.6e-5 * HOVER**2 + 0.4)
    assert 3.5 < expected_current(HOVER) < 4.5  # a ~1 kg quad's motor at hover
    assert expected_current(2.0, k_i=1.0, i_idle=0.0) == 4.0


def test_four_healthy_motors_work() -> None:
    speeds = [HOVER, HOVER * 1.1, HOVER * 0.9, HOVER]
    assert working_motors(telemetry(speeds, healthy(speeds))) == 4
    noisy = [i * f for i, f in zip(healthy(speeds), (1.1, 0.9, 1.2, 0.8), strict=True)]
    assert working_motors(telemetry(speeds, noisy)) == 4


def test_a_lost_propeller_draws_only_the_idle_current() -> None:
    speeds = [HOVER] * 4
    currents = healthy(speeds)
    currents[2] = motors.IDLE_CURRENT + 0.1  # spinning free
    assert working_motors(telemetry(speeds, currents)) == 3


def test_dead_and_jammed_motors_do_not_work() -> None:
    speeds = [HOVER] * 4
    currents = healthy(speeds)
    currents[0] = 0.0  # dead
    currents[3] = 3 * currents[3]  # jammed
    assert working_motors(telemetry(speeds, currents)) == 2


def test_an_idle_motor_drawing_nothing_counts_as_working() -> None:
    # Within the absolute tolerance of i_idle: a disarmed vehicle is not a failed one.
    assert working_motors(telemetry([0.0] * 4, [0.0] * 4)) == 4


def test_non_finite_readings_do_not_work() -> None:
    speeds = [HOVER] * 4
    currents = healthy(speeds)
    currents[1] = NAN
    assert working_motors(telemetry(speeds, currents)) == 3


def test_constants_are_keyword_arguments() -> None:
    t = telemetry([200.0, 200.0], [4.0, 4.0])  # the defaults expect 1.04 A here
    assert working_motors(t) == 0
    assert working_motors(t, k_i=1e-4, i_idle=0.0) == 2  # 4 A expected
    off = telemetry([200.0], [4.9])
    assert working_motors(off, k_i=1e-4, i_idle=0.0, abs_tol=0.1, rel_tol=0.2) == 0
    assert working_motors(off, k_i=1e-4, i_idle=0.0, abs_tol=0.1, rel_tol=0.25) == 1
    assert working_motors(off, k_i=1e-4, i_idle=0.0, abs_tol=1.0, rel_tol=0.0) == 1


def test_mismatched_lengths_are_an_error() -> None:
    with pytest.raises(ValueError, match="4 desired speeds but 3 currents"):
        working_motors(telemetry([HOVER] * 4, [1.0] * 3))


@given(
    st.lists(st.floats(0.0, 1000.0), min_size=1, max_size=8),
    st.lists(st.floats(0.0, 30.0), min_size=8, max_size=8),
)
def test_working_motors_counts_motors_within_tolerance(
    speeds: list[float], currents: list[float]
) -> None:
    currents = currents[: len(speeds)]
    n = working_motors(telemetry(speeds, currents))
    expected = sum(
        abs(i - expected_current(w)) <= max(0.5, 0.25 * expected_current(w))
        for w, i in zip(speeds, currents, strict=True)
    )
    assert n == expected
    assert working_motors(telemetry(speeds, healthy(speeds))) == len(speeds)


# ---- the measurement models name these functions -----------------------------------------------
def resolve(dotted: str) -> object:
    module, _, name = dotted.rpartition(".")
    return getattr(importlib.import_module(module), name)


def test_measurement_models_name_the_library_functions() -> None:
    functions = {}
    for package in ("object_storing", "quadcopter"):
        text = (SCENARIOS / package / "measurements.yaml").read_text()
        model = msgspec.convert(yaml.safe_load(text), MeasurementsModel)
        for dt in model.data_types:
            functions.update({name: resolve(path) for name, path in dt.functions.items()})
    assert functions == {
        "getClosestObst": laser.closest_obstacle,
        "workingMotors": motors.working_motors,
    }
    assert functions["getClosestObst"](scan([4.0, 0.5])) == 0.5
    speeds = [HOVER] * 4
    assert functions["workingMotors"](telemetry(speeds, healthy(speeds))) == 4
