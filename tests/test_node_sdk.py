"""The Node SDK's data path (`NodeCore.deliver` / `publish`) keeps its guarantees: what is
malformed or too large is refused and counted, a node callback that raises is counted and the
node goes on, callbacks hold the node's lock (and leave it free), an inactive node publishes
nothing. No bus: `NodeHarness` drives the same `NodeCore` the node process runs."""

from __future__ import annotations

import threading
from typing import Any

import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.counters import MAX_PAYLOAD
from rra_agent.bus.data import encode_data
from rra_agent.node import Node, NodeError, NodeHarness

PORTS = {"in": ("subscribe", "T"), "out": ("publish", "T")}


def lock_free_elsewhere(lock: Any) -> bool:
    """Whether another thread can take ``lock`` at once (an RLock is re-entrant in its owner)."""
    got: list[bool] = []

    def try_it() -> None:
        ok = lock.acquire(blocking=False)
        got.append(ok)
        if ok:
            lock.release()

    t = threading.Thread(target=try_it)
    t.start()
    t.join(10)
    assert got, "the probing thread did not finish"
    return got[0]


class Recorder(Node):
    """Publishes what it gets; raises on ``{"fail": true}``; notes whether its lock was held."""

    def on_start(self) -> None:
        self.got: list[dict[str, Any]] = []
        self.lock_held: list[bool] = []

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        self.lock_held.append(not lock_free_elsewhere(self.ctx._core.lock))
        if data.get("fail"):
            raise ValueError("asked to fail")
        self.got.append(data)
        self.published = self.ctx.publish("out", data)


def harness(**kw: Any) -> NodeHarness:
    return NodeHarness(Recorder, ports=PORTS, **kw)


def test_malformed_non_map_and_oversized_samples_are_dropped_counted_and_logged_once():
    h = harness()
    h.send_raw("in", b"\xc1")  # never valid msgpack
    h.send_raw("in", encode_data([1, 2]))  # valid, but not a map
    h.send_raw("in", b"\x80" + b"\x00" * MAX_PAYLOAD["data"])  # a map padded beyond the limit
    h.send("in", {"x": 1})
    node: Any = h.node
    assert node.got == [{"x": 1}]
    assert (h.core.dropped, h.core.received, h.core.errors) == (3, 1, 0)
    assert sum("dropped sample on in" in line for line in h.logs) == 1  # rate-limited
    assert h.outputs("out") == [{"x": 1}]


def test_a_raising_callback_is_counted_and_logged_and_the_node_goes_on():
    h = harness()
    h.send("in", {"fail": True})
    h.send("in", {"x": 2})
    node: Any = h.node
    assert h.core.errors == 1 and h.core.received == 2
    assert any("on_message raised ValueError: asked to fail" in line for line in h.logs)
    assert node.got == [{"x": 2}] and h.outputs("out") == [{"x": 2}]
    # Every callback ran holding the node's lock, and no failure left it held.
    assert node.lock_held == [True, True]
    assert lock_free_elsewhere(h.core.lock)


def test_an_inactive_node_publishes_nothing_until_activated():
    h = harness(active=False)
    h.send("in", {"x": 3})
    node: Any = h.node
    assert node.got == [{"x": 3}] and node.published is False
    assert h.outputs() == [] and h.core.published == 0
    assert isinstance(h.request(m.Activate()), m.Ok)
    h.send("in", {"x": 4})
    assert node.published is True and h.outputs("out") == [{"x": 4}]
    assert h.core.published == 1


def test_publishing_on_an_input_or_unknown_port_is_refused():
    h = harness()
    for port in ("in", "nope"):
        with pytest.raises(NodeError, match="no output port"):
            h.node.ctx.publish(port, {"x": 5})
    assert h.outputs() == []
