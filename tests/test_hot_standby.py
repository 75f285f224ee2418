"""Hot standby in the Node SDK: a consumer listens to a hot standby's key in advance, holds
its newest sample without delivering it, and delivers it the moment a rewire selects it."""

from __future__ import annotations

from typing import Any

from rra_agent.bus import messages as m
from rra_agent.node import REPLAY_MAX_AGE, Node, NodeCore, encode_data

ACTIVE, HOT = "rra/t/data/controller/out", "rra/t/data/proploss/out"


class Sink(Node):
    def __init__(self, ctx) -> None:
        super().__init__(ctx)
        self.got: list[dict[str, Any]] = []

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        self.got.append(data)


class Bindings:
    """A transport that records how each port is bound."""

    def __init__(self) -> None:
        self.bound: dict[str, tuple[list[str], list[str]]] = {}

    def publish(self, port: str, payload: bytes, stamp: float) -> None:
        pass

    def rebind(self, port: str, direction: str, keys: list[str], standby=None) -> None:
        self.bound[port] = (list(keys), list(standby or ()))

    def subscribe(self, key_expr: str, callback) -> None:
        pass


def sink(now: list[float]) -> tuple[NodeCore, Bindings]:
    spec = m.NodeSpec(
        system="t", name="sim", host="h", implementation=f"{__name__}.Sink",
        ports={"cmd": m.PortSpec(direction="subscribe", type="Cmd", keys=[ACTIVE],
                                 standby=[HOT])},
    )  # fmt: skip
    transport = Bindings()
    core = NodeCore(spec, Sink, transport, monotonic=lambda: now[0])
    core.start()
    return core, transport


def select(core: NodeCore, key: str) -> m.Reply:
    return core.handle(m.Rewire(port="cmd", keys=[key]))


def test_a_held_sample_is_delivered_when_its_key_is_selected_and_not_before():
    now = [10.0]
    core, transport = sink(now)
    core.hold("cmd", HOT, encode_data({"n": 1}), None)
    core.hold("cmd", HOT, encode_data({"n": 2}), None)  # the newest only is kept
    core.deliver("cmd", encode_data({"n": 0}), None)
    assert core.node.got == [{"n": 0}]
    now[0] += REPLAY_MAX_AGE / 2
    assert isinstance(select(core, HOT), m.Ok)
    assert core.node.got == [{"n": 0}, {"n": 2}]
    # the bindings keep listening to the hot key (a standby key), the old key is dropped
    assert transport.bound["cmd"] == ([HOT], [HOT])
    # once selected, a sample on the hot key is delivered as it comes
    core.hold("cmd", HOT, encode_data({"n": 3}), None)
    assert core.node.got[-1] == {"n": 3}
    assert core.describe().ports[0].standby == [HOT]


def test_a_stale_held_sample_is_not_delivered_at_the_switch():
    now = [10.0]
    core, _ = sink(now)
    core.hold("cmd", HOT, encode_data({"n": 1}), None)
    now[0] += REPLAY_MAX_AGE * 2
    assert isinstance(select(core, HOT), m.Ok)
    assert core.node.got == []


def test_a_held_sample_is_delivered_once_and_a_malformed_one_is_refused_and_counted():
    now = [10.0]
    core, _ = sink(now)
    core.hold("cmd", HOT, encode_data({"n": 0}), None)
    core.hold("cmd", HOT, b"\xc1", None)  # junk after it: refused, it does not displace it
    core.hold("cmd", HOT, encode_data([1]), None)
    assert core.dropped == 2
    select(core, HOT)
    assert core.node.got == [{"n": 0}]
    core.node.got.clear()
    core.hold("cmd", HOT, encode_data({"n": 1}), None)  # selected: delivered as it comes
    select(core, ACTIVE)
    select(core, HOT)  # so nothing was held to replay
    assert core.node.got == [{"n": 1}]
