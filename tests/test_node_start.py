"""Samples that come while a node starts: its ports are declared before its code runs (a
replacement's even before the node it replaces is gone), and the newest sample of each key
that came meanwhile is delivered once ``on_start`` has returned, as a subscription queue of
depth one would (`ZenohTransport.start_delivery`)."""

from __future__ import annotations

from test_hot_standby import ACTIVE, HOT, FakeSession, Sink, sample

from rra_agent.bus import messages as m
from rra_agent.node.core import REPLAY_MAX_AGE, NodeCore
from rra_agent.node.runtime import ZenohTransport


def starting(now: list[float]) -> tuple[ZenohTransport, FakeSession, NodeCore]:
    """A node bound as the runtime binds it (ports first), its code not started yet."""
    session = FakeSession()
    transport = ZenohTransport(session, monotonic=lambda: now[0])  # type: ignore[arg-type]
    spec = m.NodeSpec(
        system="t", name="sim", host="h", implementation="test_hot_standby.Sink",
        ports={"cmd": m.PortSpec(direction="subscribe", type="Cmd", keys=[ACTIVE],
                                 standby=[HOT])},
    )  # fmt: skip
    for name, port in spec.ports.items():
        transport.rebind(name, port.direction, list(port.keys), list(port.standby))
    core = NodeCore(spec, Sink, transport, monotonic=lambda: now[0])
    return transport, session, core


def test_the_newest_sample_that_came_while_the_node_started_is_delivered_after_on_start():
    now = [10.0]
    transport, session, core = starting(now)
    session.callbacks[ACTIVE](sample({"n": 1}))
    session.callbacks[ACTIVE](sample({"n": 2}))
    core.start()
    assert core.node.got == []  # nothing reaches the node before on_start has returned
    now[0] += REPLAY_MAX_AGE / 2
    transport.start_delivery(core)
    assert core.node.got == [{"n": 2}]  # the newest only, once
    session.callbacks[ACTIVE](sample({"n": 3}))
    assert core.node.got == [{"n": 2}, {"n": 3}]


def test_a_sample_too_old_when_the_node_starts_is_not_delivered():
    now = [10.0]
    transport, session, core = starting(now)
    session.callbacks[ACTIVE](sample({"n": 1}))
    core.start()
    now[0] += REPLAY_MAX_AGE * 2
    transport.start_delivery(core)
    assert core.node.got == []


def test_a_standby_key_sample_that_came_while_starting_is_held_not_delivered():
    now = [10.0]
    transport, session, core = starting(now)
    session.callbacks[HOT](sample({"n": 7}))
    core.start()
    transport.start_delivery(core)
    assert core.node.got == []
    assert isinstance(core.handle(m.Rewire(port="cmd", keys=[HOT])), m.Ok)
    assert core.node.got == [{"n": 7}]  # held, and delivered at the switch to its key
