"""Measurement functions of the reflex test package."""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from typing import Any


def level(sample: Mapping[str, Any]) -> float:
    """The plant's level."""
    return float(sample["value"])


def level_but_not_in_the_plant(sample: Mapping[str, Any]) -> float:
    """The level, except in the plant's own process, where it raises (a node that cannot
    evaluate its reflex: the Context Monitor computes it, the plant does not)."""
    spec = json.loads(os.environ.get("RRA_NODE_SPEC") or "{}")
    if spec.get("name") == "plant":
        raise RuntimeError("this function does not run in the plant")
    return float(sample["value"])
