"""Functions on the ``LaserScan`` data type ({ranges, range_min, range_max, ...}, metres)."""

from __future__ import annotations

import math
from collections.abc import Mapping


def closest_obstacle(scan: Mapping) -> float:
    """Distance to the closest obstacle: the smallest valid range (the paper's getClosestObst).

    A range is valid when finite and within ``[range_min, range_max]`` (a reading outside
    them is "no return" or a sensor artefact; missing bounds mean 0 and +inf). Returns
    ``math.inf`` when no range is valid: nothing in sight.
    """
    low = float(scan.get("range_min", 0.0))
    high = float(scan.get("range_max", math.inf))
    valid = (
        float(r) for r in scan.get("ranges", ()) if math.isfinite(r) and low <= float(r) <= high
    )
    return min(valid, default=math.inf)
