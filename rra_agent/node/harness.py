"""Drive a `Node` without a bus, in a unit test (as dora's MockNode does)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.bus.data import decode_data, encode_data
from rra_agent.models.measurements import DataType
from rra_agent.node.api import Node, RawCallback
from rra_agent.node.core import NodeCore
from rra_agent.package.functions import load_measurements


class _CaptureTransport:
    """The harness' transport: records what the node publishes and how ports are bound."""

    def __init__(self) -> None:
        self.published: list[tuple[str, bytes, float]] = []
        self.bindings: dict[str, list[str]] = {}
        self.raw: dict[str, list[RawCallback]] = {}

    def publish(self, port: str, payload: bytes, stamp: float) -> None:
        self.published.append((port, payload, stamp))

    def rebind(
        self, port: str, direction: str, keys: list[str], standby: list[str] | None = None
    ) -> None:
        self.bindings[port] = keys

    def subscribe(self, key_expr: str, callback: RawCallback) -> None:
        self.raw.setdefault(key_expr, []).append(callback)


class NodeHarness:
    """Drive a `Node` without a bus: send inputs, step time, make control requests.

    >>> h = NodeHarness(MyNode, params={"gain": 2.0}, ports={"out": ("publish", "Cmd")})
    >>> h.send("in", {"x": 1.0}); h.step(0.01)
    >>> h.outputs("out")

    ``types``: the data types of ``measurements.yaml``, as `DataType`s or as the folder of
    the package that declares them: an input port of a declared type refuses what its type
    does not allow (counted: ``h.core.counters``), as on the bus; an input of an undeclared
    type takes any map.
    """

    def __init__(
        self,
        node_cls: type[Node],
        *,
        name: str = "node",
        params: dict[str, Any] | None = None,
        ports: dict[str, tuple[str, str]] | None = None,
        active: bool = True,
        state: Any = None,
        now: float = 0.0,
        path: list[str] | None = None,
        types: Iterable[DataType] | str | Path = (),
    ) -> None:
        if isinstance(types, str | Path):
            types = load_measurements(types).data_types
        self.time = now
        self.transport = _CaptureTransport()
        spec = m.NodeSpec(
            system="test",
            name=name,
            host="local",
            implementation=f"{node_cls.__module__}.{node_cls.__qualname__}",
            params=dict(params or {}),
            ports={
                p: m.PortSpec(direction=d, type=t, keys=[f"rra/test/data/{name}/{p}"])  # type: ignore[arg-type]
                for p, (d, t) in (ports or {}).items()
            },
            active=active,
            state=state,
            path=list(path or []),
            types=list(types),
        )
        self.logs: list[str] = []
        #: The reflexes that fired (`ReflexFired`), as the node reported them.
        self.fired: list[m.ReflexFired] = []
        self.core = NodeCore(
            spec,
            node_cls,
            self.transport,
            clock=lambda: self.time,
            logger=self.logs.append,
            monotonic=lambda: self.time,
        )
        self.core.on_reflex = self.fired.append
        self.core.start()

    @property
    def node(self) -> Node:
        return self.core.node

    def send(self, port: str, data: Any, stamp: float | None = None) -> None:
        """Deliver ``data`` on input ``port`` as if it came on the port's first key."""
        spec = self.core.ports.get(port)
        key = spec.keys[0] if spec is not None and spec.keys else None
        self.core.deliver(port, encode_data(data), stamp, key)

    def send_raw(self, port: str, payload: bytes) -> None:
        self.core.deliver(port, payload, None)

    def deliver_raw(self, key_expr: str, payload: bytes, stamp: float | None = None) -> int:
        """Hand ``payload`` to the node's raw subscriptions on exactly ``key_expr`` (as the
        node subscribed it, e.g. ``rra/test/inject/**``); returns how many got it."""
        callbacks = self.transport.raw.get(key_expr, [])
        for cb in callbacks:
            cb(key_expr, payload, stamp)
        return len(callbacks)

    def step(self, now: float | None = None) -> None:
        if now is not None:
            self.time = now
        self.core.step(self.time)

    def request(self, request: m.NodeRequest) -> m.Reply:
        # Round-trip through the wire codec so the harness checks what the bus would carry.
        codec: m.Codec[m.NodeRequest] = m.Codec(m.NodeRequest)
        return self.core.handle(codec.decode(codec.encode(request)))

    def outputs(self, port: str | None = None) -> list[dict[str, Any]]:
        return [decode_data(p) for (q, p, _) in self.transport.published if port in (None, q)]

    def iter_published(self) -> Iterator[tuple[str, dict[str, Any]]]:
        for port, payload, _ in self.transport.published:
            yield port, decode_data(payload)
