"""What a process accepts from the bus, and how it counts and reports what it refuses.

Every process (node, engine, host agent) keeps `Counters`: samples and requests received,
*dropped* (malformed, larger than the limit of their key family, or coalesced away under
load) and *rejected* (well-formed but refused: out of bounds, unknown names, stale leader
fences). ``rra status`` shows them (`ProcessStats`). Refusals are logged through a
`RateLimitedLog`: the first of each kind at once, then at most one line per period with
the count since the last line, so a flood of junk costs a counter increment, not a log line.

Size limits are enforced by Zenoh itself, in every host's router, before a sample reaches
any process (`router_limits`): the router reassembles no message larger than the largest
limit (``transport/link/rx/max_message_size``: a bigger one is dropped fragment by fragment,
never held whole), and its ``low_pass_filter`` drops, per key family, what is over that
family's limit, on the way in and out. The processes check the same limits again
(`too_large`), in case a sample comes another way (e.g. a peer session that bypasses the
router).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, NamedTuple, TypeVar

import msgspec

from rra_agent.bus import messages as m
from rra_agent.models.system import SystemModel

T = TypeVar("T")

KiB = 1024
MiB = 1024 * KiB

#: The largest payload accepted per key family (bytes). Larger ones are dropped (by the
#: routers; a process that still sees one counts it). ``data`` is the default of a port; a
#: port declares more with ``max_bytes`` (system.yaml) when its samples are images or clouds.
MAX_PAYLOAD: dict[str, int] = {
    "data": 1 * MiB,  # the largest sample of the shipped systems is ~10 KiB
    "ctx": 16 * KiB,
    "selection": 256 * KiB,
    "events": 256 * KiB,
    "state": 4 * MiB,  # the Run-time Configured System Model: ~0.4 KiB per node
    "node_ctl": 4 * MiB,  # exported state of a node being replaced
    "host_ctl": 4 * MiB,  # node specs
    "engine_ctl": 64 * KiB,
    "inject": 64 * KiB,
    "reflex": 16 * KiB,
}
#: The keys of each family, below ``rra/<system>/`` (`rra_agent.bus.keys`).
FAMILY_KEYS: dict[str, str] = {
    "data": "data/**",
    "ctx": "ctx/*",
    "selection": "selection",
    "events": "events",
    "state": "state/*",
    "node_ctl": "node/*/ctl",
    "host_ctl": "host/*/ctl",
    "engine_ctl": "engine/*/ctl",
    "inject": "inject/**",
    "reflex": "reflex/*",
}
#: Control families: their requests are small, their replies may carry a system's state.
_CONTROL = ("node_ctl", "host_ctl", "engine_ctl")
#: Zenoh's setting for the largest message a router reassembles.
MAX_MESSAGE_SIZE = "transport/link/rx/max_message_size"
#: Zenoh's filter counts the attachment too (a sample's 8-byte send time): room for it.
ATTACHMENT = 64
#: Room for a message's key expression and headers in a reassembled message.
HEADERS = 64 * KiB


def too_large(family: str, size: int) -> bool:
    return size > MAX_PAYLOAD[family]


class Refused(NamedTuple):
    """A payload refused before it was decoded: ``too_large`` or ``malformed``, and why."""

    code: str
    detail: str

    def err(self, what: str = "request") -> m.Err:
        """The reply that tells the sender (a query's answer)."""
        text = f"{what} too large ({self.detail})" if self.code == "too_large" else (
            f"malformed {what}: {self.detail}"
        )  # fmt: skip
        return m.Err(message=text, code=self.code)


def receive(payload: Any, family: str, codec: m.Codec[T]) -> T | Refused:
    """The preamble of everything a process receives: the size limit of its key family
    (``MAX_PAYLOAD``), then the decode with the channel's one reused decoder. ``payload``:
    a Zenoh payload (or None: empty) or bytes. The caller counts a `Refused` and, for a
    query, answers it (`Refused.err`)."""
    raw = b"" if payload is None else payload if isinstance(payload, bytes) else payload.to_bytes()
    if too_large(family, len(raw)):
        limit = MAX_PAYLOAD[family]
        return Refused("too_large", f"{len(raw)} bytes, more than the {limit} of {family}")
    try:
        return codec.decode(raw)
    except (msgspec.DecodeError, msgspec.ValidationError) as e:
        return Refused("malformed", str(e))


def data_limit(max_bytes: int | None) -> int:
    """The largest sample a data port accepts: its own ``max_bytes``, else the default."""
    return MAX_PAYLOAD["data"] if max_bytes is None else max_bytes


def topic_limits(system: SystemModel) -> dict[str, int]:
    """Topic -> the largest sample on it, for every publishing port of ``system``."""
    return {
        port.topic or f"{comp.name}/{port.name}": data_limit(port.max_bytes)
        for comp in system.components
        for port in comp.ports
        if port.direction == "publish"
    }


def router_limits(system: str | None, topics: Mapping[str, int] | None = None) -> dict[str, Any]:
    """The Zenoh settings of a host's router that enforce the limits (see the module doc):
    ``low_pass_filter`` rules per key family of every system (``rra/*/...``), the data rule
    raised to the largest port limit of ``topics`` (the topics of ``system`` -> their limit)
    and each topic under it kept to its own, and ``max_message_size`` at the largest limit.
    """
    topics = dict(topics or {})
    data = max([MAX_PAYLOAD["data"], *topics.values()])
    limits = {**MAX_PAYLOAD, "data": data}
    largest = max(limits.values())
    messages = ["put", "delete", "query", "reply"]
    rules = [
        _rule(f"rra-{family}", f"rra/*/{FAMILY_KEYS[family]}", limit, messages)
        for family, limit in limits.items()
        if family not in _CONTROL
    ]
    reply = max(limits[f] for f in ("state", *_CONTROL))
    for family in _CONTROL:  # a request is small; a reply may be a whole state
        key = f"rra/*/{FAMILY_KEYS[family]}"
        rules.append(_rule(f"rra-{family}", key, limits[family], ["put", "delete", "query"]))
        rules.append(_rule(f"rra-{family}-reply", key, reply, ["reply"]))
    if system is not None:
        for topic, limit in sorted(topics.items()):
            if limit < data:
                rules.append(
                    _rule(f"rra-data-{topic}", f"rra/{system}/data/{topic}", limit, messages)
                )
    return {"low_pass_filter": rules, MAX_MESSAGE_SIZE: largest + HEADERS}


def _rule(rid: str, key: str, limit: int, messages: list[str]) -> dict[str, Any]:
    """A low-pass filter rule: ``messages`` on ``key`` larger than ``limit`` are dropped."""
    return {"id": rid, "key_exprs": [key], "messages": messages, "size_limit": limit + ATTACHMENT}


class RateLimitedLog:
    """Log the first refusal of each kind at once, then one line per ``period`` at most.
    A kind is ``kind``, or (``kind``, ``about``) when the caller says what it is about (a
    source): a flood of one source's junk then never hides another's first refusal."""

    def __init__(
        self,
        emit: Callable[[str], None],
        period: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.emit = emit
        self.period = period
        self.clock = clock
        self._lock = threading.Lock()
        self._last: dict[tuple[str, str], float] = {}
        self._pending: dict[tuple[str, str], int] = {}

    def __call__(self, kind: str, detail: str, about: str = "") -> None:
        now, key = self.clock(), (kind, about)
        with self._lock:
            last = self._last.get(key)
            self._pending[key] = self._pending.get(key, 0) + 1
            if last is not None and now - last < self.period:
                return
            count = self._pending.pop(key)
            self._last[key] = now
        more = f" ({count} since the last report)" if last is not None and count > 1 else ""
        self.emit(f"{kind}: {detail}{more}")


@dataclass
class Counters:
    """A process's counters; increments are atomic enough under the GIL for counting."""

    received: int = 0
    dropped: int = 0
    rejected: int = 0
    extra: dict[str, int] = field(default_factory=dict)

    def bump(self, name: str, n: int = 1) -> None:
        self.extra[name] = self.extra.get(name, 0) + n

    def stats(self, name: str, role: str, pid: int) -> m.ProcessStats:
        return m.ProcessStats(
            name=name,
            role=role,  # type: ignore[arg-type]
            pid=pid,
            received=self.received,
            dropped=self.dropped,
            rejected=self.rejected,
            counters=dict(self.extra),
        )
