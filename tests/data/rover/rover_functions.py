"""Measurement functions of the rover package (named by dotted path in measurements.yaml)."""

from __future__ import annotations

from typing import Any


def speed(fix: dict[str, Any]) -> float:
    return abs(float(fix["speed"]))
