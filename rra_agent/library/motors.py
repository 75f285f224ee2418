"""Functions on the ``MotorTelemetry`` data type (paper Sec. IV).

``MotorTelemetry`` is ``{desired_speed, measured_speed, current}``: one entry per motor, speeds
in rad/s, currents in A. The Context Monitor infers how many motors work "as expected" from
the discrepancy between expected and measured current. A rotor's load torque goes with the
square of its speed and a motor's current with its torque, so the current expected at a
desired speed ``w`` is ``k_i * w**2 + i_idle``. A motor that lost its propeller spins with no
load and draws about ``i_idle``; a dead one draws nothing; a jammed one draws far more.

The default constants describe the simulated 1 kg quadcopter's motors: about 3.9 A each at
the ~470 rad/s hover speed. The simulator should compute the current it publishes from these
same module constants, so the model and the monitor cannot drift apart.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

#: Current per squared speed, A / (rad/s)^2.
CURRENT_PER_SPEED_SQ = 1.6e-5
#: No-load current of a spinning motor, A.
IDLE_CURRENT = 0.4
#: A motor works when |measured - expected| <= max(ABS_TOLERANCE, REL_TOLERANCE * expected).
REL_TOLERANCE = 0.25
ABS_TOLERANCE = 0.5


def expected_current(
    desired_speed: float, *, k_i: float = CURRENT_PER_SPEED_SQ, i_idle: float = IDLE_CURRENT
) -> float:
    """The current (A) a healthy motor draws at ``desired_speed`` (rad/s)."""
    return k_i * desired_speed * desired_speed + i_idle


def working_motors(
    telemetry: Mapping,
    *,
    k_i: float = CURRENT_PER_SPEED_SQ,
    i_idle: float = IDLE_CURRENT,
    rel_tol: float = REL_TOLERANCE,
    abs_tol: float = ABS_TOLERANCE,
) -> int:
    """How many motors draw the current expected from their desired speed.

    A motor whose reading is not finite counts as not working. ``desired_speed`` and
    ``current`` must have one entry per motor (``ValueError`` otherwise); ``measured_speed``
    is not needed for the current check.
    """
    desired, current = telemetry["desired_speed"], telemetry["current"]
    if len(desired) != len(current):
        raise ValueError(
            f"{len(desired)} desired speeds but {len(current)} currents in MotorTelemetry"
        )
    return sum(
        _works(float(w), float(i), k_i=k_i, i_idle=i_idle, rel_tol=rel_tol, abs_tol=abs_tol)
        for w, i in zip(desired, current, strict=True)
    )


def _works(
    speed: float, current: float, *, k_i: float, i_idle: float, rel_tol: float, abs_tol: float
) -> bool:
    if not (math.isfinite(speed) and math.isfinite(current)):
        return False
    expected = expected_current(speed, k_i=k_i, i_idle=i_idle)
    return abs(current - expected) <= max(abs_tol, rel_tol * expected)
