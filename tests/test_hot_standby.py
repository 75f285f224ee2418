"""Hot standby in the Node SDK: a consumer listens to a hot standby's key in advance, holds
its newest sample without delivering it, and delivers it the moment a rewire selects it."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.bus.data import encode_data
from rra_agent.node import Node
from rra_agent.node.core import REPLAY_MAX_AGE, NodeCore

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


def sim_spec() -> m.NodeSpec:
    """A simulator's command input: the active controller's key, the hot standby's held."""
    return m.NodeSpec(
        system="t", name="sim", host="h", implementation=f"{__name__}.Sink",
        ports={"cmd": m.PortSpec(direction="subscribe", type="Cmd", keys=[ACTIVE],
                                 standby=[HOT])},
    )  # fmt: skip


def sink(now: list[float]) -> tuple[NodeCore, Bindings]:
    spec = sim_spec()
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


class FakeSession:
    """Enough of a Zenoh session for `ZenohTransport`: it keeps each subscription's callback."""

    def __init__(self) -> None:
        self.callbacks: dict[str, Any] = {}

    def declare_subscriber(self, key: str, callback):
        self.callbacks[key] = callback
        return SimpleNamespace(undeclare=lambda: None)

    def declare_publisher(self, key: str, **_: Any):
        return SimpleNamespace(undeclare=lambda: None, put=lambda *a, **k: None)


def sample(data: dict[str, Any]) -> SimpleNamespace:
    payload = encode_data(data)
    return SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: payload), attachment=None)


def test_a_sample_of_the_producer_swapped_out_is_not_delivered_after_the_switch():
    """A command of the old controller that was on its way when the rewire dropped it (in
    its subscription's queue, or waiting for the node's lock while the rewire ran) must not
    reach the node after the switch: it would drive one more step with the old command."""
    from rra_agent.node.runtime import ZenohTransport, bind_ports

    session = FakeSession()
    transport = ZenohTransport(session)  # type: ignore[arg-type]
    spec = sim_spec()
    core = NodeCore(spec, Sink, transport)
    bind_ports(transport, core.ports)  # as the node runtime binds them
    transport.core = core
    core.start()
    old = session.callbacks[ACTIVE]  # the old controller's subscription, as it was
    old(sample({"n": 1}))
    session.callbacks[HOT](sample({"n": 2}))  # held
    assert core.node.got == [{"n": 1}]
    assert isinstance(select(core, HOT), m.Ok)
    assert core.node.got == [{"n": 1}, {"n": 2}]  # the held one, at the switch
    old(sample({"n": 3}))  # late: the old controller's, after the switch
    assert core.node.got == [{"n": 1}, {"n": 2}]
    assert core.counters.extra["unselected"] == 1
    session.callbacks[HOT](sample({"n": 4}))
    assert core.node.got[-1] == {"n": 4}


def test_a_switch_to_the_hot_standby_and_back_declares_no_subscriber():
    """The switch runs under the node's lock (a reflex: on the node's own thread): it flips
    which key is held and declares nothing, so it never waits on Zenoh while Zenoh's threads
    wait on that lock (a reflex's switch once held the simulator for 160 ms that way)."""
    from rra_agent.node.runtime import ZenohTransport, bind_ports

    session = FakeSession()
    declared: list[str] = []
    declare = session.declare_subscriber
    session.declare_subscriber = lambda key, cb: (declared.append(key), declare(key, cb))[1]  # type: ignore[method-assign]
    transport = ZenohTransport(session)  # type: ignore[arg-type]
    spec = sim_spec()
    core = NodeCore(spec, Sink, transport)
    bind_ports(transport, core.ports)
    transport.core = core
    core.start()
    assert sorted(declared) == sorted([ACTIVE, HOT])
    transport.rebind("cmd", "subscribe", [HOT], [ACTIVE])  # the switch
    transport.rebind("cmd", "subscribe", [ACTIVE], [HOT])  # and back
    assert sorted(declared) == sorted([ACTIVE, HOT])  # nothing declared again
    session.callbacks[HOT](sample({"n": 1}))  # held again: not delivered
    session.callbacks[ACTIVE](sample({"n": 2}))
    assert core.node.got == [{"n": 2}]
