"""Shared helpers of the object-storing nodes: tolerant sample parsing, parameters, timers.

Every node of the case study derives from `SafeNode`. Input samples arrive as msgpack maps
that may miss fields or carry the wrong types; the parsers here return None for anything
unusable so a node ignores the sample (and logs it, throttled) instead of raising.
"""

from __future__ import annotations

import math
from typing import Any, ClassVar, NamedTuple

from rra_agent.node.api import Node, NodeContext, NodeError

#: Log the first bad sample of a port, then one in this many.
LOG_EVERY = 100


class Pose(NamedTuple):
    """A planar pose: x, y in m, theta in rad."""

    x: float
    y: float
    theta: float = 0.0

    def to_msg(self) -> dict[str, float]:
        return {"x": self.x, "y": self.y, "theta": self.theta}

    def distance(self, other: Pose) -> float:
        return math.hypot(other.x - self.x, other.y - self.y)


# ---- parsing ----------------------------------------------------------------------------
def num(value: Any) -> float | None:
    """A finite real number (bools are not numbers), else None."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    f = float(value)
    return f if math.isfinite(f) else None


def real(value: Any) -> float | None:
    """A real number, infinities included (NaN and non-numbers are None)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    f = float(value)
    return None if math.isnan(f) else f


def text(value: Any) -> str | None:
    return value if isinstance(value, str) else None


def numbers(value: Any, length: int | None = None) -> list[float] | None:
    """A list of finite numbers (of ``length`` items if given), else None."""
    if not isinstance(value, list | tuple):
        return None
    out = [num(v) for v in value]
    if any(v is None for v in out) or (length is not None and len(out) != length):
        return None
    return out  # type: ignore[return-value]


def pose(value: Any) -> Pose | None:
    """A ``Pose2D`` map ({x, y, theta}; theta defaults to 0), else None."""
    if not isinstance(value, dict):
        return None
    x, y = num(value.get("x")), num(value.get("y"))
    theta = num(value.get("theta", 0.0))
    if x is None or y is None or theta is None:
        return None
    return Pose(x, y, theta)


def clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


def wrap_angle(a: float) -> float:
    """``a`` in (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


# ---- timing -----------------------------------------------------------------------------
class Every:
    """A periodic trigger driven by the caller's clock (robust to clock jumps backwards)."""

    def __init__(self) -> None:
        self.last: float | None = None

    def due(self, now: float, period: float) -> bool:
        if self.last is None or now - self.last >= period or now < self.last:
            self.last = now
            return True
        return False


class StepClock:
    """Time elapsed between two steps, clamped to ``[0, max_dt]`` (a stall is not a jump)."""

    def __init__(self, max_dt: float = 0.5) -> None:
        self.max_dt = max_dt
        self.last: float | None = None

    def dt(self, now: float) -> float:
        last, self.last = self.last, now
        return 0.0 if last is None else clamp(now - last, 0.0, self.max_dt)


# ---- the base node ----------------------------------------------------------------------
class SafeNode(Node):
    """A node that never raises on bad input and only publishes on declared ports.

    ``inputs`` maps each subscribed port to the name of its handler, which receives the
    sample map and returns False to reject it; ``outputs`` lists the published ports. Both
    use exactly the port names of the component in ``scenarios/object_storing/system.yaml``.
    """

    inputs: ClassVar[dict[str, str]] = {}
    outputs: ClassVar[tuple[str, ...]] = ()

    def __init__(self, ctx: NodeContext) -> None:
        super().__init__(ctx)
        self._bad: dict[str, int] = {}

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        handler = self.inputs.get(port)
        if handler is None:
            self.warn(port, f"sample on unexpected port {port!r} ignored")
        elif not isinstance(data, dict) or not getattr(self, handler)(data):
            self.warn(port, f"malformed {port} sample ignored")

    # -- output ---------------------------------------------------------------------------
    def emit(self, port: str, data: dict[str, Any]) -> bool:
        """Publish on ``port``; False while inactive or if the port is not wired (logged)."""
        try:
            return self.ctx.publish(port, data)
        except NodeError as e:
            self.warn(f"out:{port}", str(e))
            return False

    def warn(self, key: str, message: str) -> None:
        """``ctx.log`` the first ``key`` problem, then one in `LOG_EVERY`."""
        n = self._bad.get(key, 0)
        self._bad[key] = n + 1
        if n % LOG_EVERY == 0:
            suffix = f" ({n + 1} so far)" if n else ""
            self.ctx.log(message + suffix)

    # -- parameters -----------------------------------------------------------------------
    def fparam(
        self, name: str, default: float, low: float = -math.inf, high: float = math.inf
    ) -> float:
        """A float parameter clamped to ``[low, high]``; ``default`` when unset or not a number."""
        value = num(self.ctx.param(name))
        return default if value is None else clamp(value, low, high)

    def iparam(self, name: str, default: int, low: int, high: int) -> int:
        value = self.ctx.param(name)
        if isinstance(value, bool) or not isinstance(value, int):
            return default
        return int(clamp(value, low, high))

    def sparam(self, name: str, default: str) -> str:
        value = self.ctx.param(name)
        return value if isinstance(value, str) else default
