"""Samples that come while a node starts: its ports are declared before its code runs (a
replacement's even before the node it replaces is gone), and the newest sample of each key
that came meanwhile is delivered once ``on_start`` has returned, as a subscription queue of
depth one would (`ZenohTransport.start_delivery`)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import zenoh
from test_hot_standby import ACTIVE, HOT, FakeSession, Sink, sample, sim_spec

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.node.core import REPLAY_MAX_AGE, NodeCore
from rra_agent.node.runtime import ZenohTransport, bind_ports, rehearse


def starting(now: list[float]) -> tuple[ZenohTransport, FakeSession, NodeCore]:
    """A node bound as the runtime binds it (ports first), its code not started yet."""
    session = FakeSession()
    transport = ZenohTransport(session, monotonic=lambda: now[0])  # type: ignore[arg-type]
    spec = sim_spec()
    bind_ports(transport, spec.ports)
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


class Ledger:
    """A stand-in Zenoh session that counts what is declared and not undeclared yet."""

    def __init__(self) -> None:
        self.live: list[str] = []
        self.seen: list[str] = []

    def _declare(self, what: str):
        self.live.append(what)
        self.seen.append(what)
        return SimpleNamespace(undeclare=lambda: self.live.remove(what), put=lambda *a, **k: None)

    def declare_subscriber(self, key: str, callback):
        return self._declare(f"subscriber {key}")

    def declare_publisher(self, key: str, **_):
        return self._declare(f"publisher {key}")

    def declare_queryable(self, key: str, callback):
        return self._declare(f"queryable {key}")

    def liveliness(self):
        return SimpleNamespace(declare_token=lambda key: self._declare(f"token {key}"))


def test_a_spare_rehearses_a_start_and_leaves_nothing_declared():
    """`rehearse` (a spare, while it waits) declares what a starting node declares, on keys of
    its own, and undeclares all of it."""
    session = Ledger()
    rehearse(session, "4242", BusConfig())  # type: ignore[arg-type]
    kinds = sorted(x.split()[0] for x in session.seen)
    assert kinds == ["publisher", "queryable", "subscriber", "token"]
    assert all(" rra/_spare/4242/" in x for x in session.seen)
    assert session.live == []


@pytest.mark.system
def test_a_sample_delivered_while_the_session_closes_is_no_fault_of_the_node():
    """At a node's stop its session closes while a bus callback may still be in the node's
    code: what it publishes then has nowhere to go (the full suite once logged that as a
    traceback of ``on_message``: ``zenoh.ZError: session closed``). A publish on a port it
    does not have still raises."""

    session = zenoh.open(BusConfig(mode="peer", connect=[], multicast=False).to_zenoh())
    transport = ZenohTransport(session)
    transport.rebind("out", "publish", ["rra/t/data/n/out"])
    transport.publish("out", b"\x80", 1.0)  # open: sent
    session.close()
    transport.publish("out", b"\x80", 2.0)  # closed under it: dropped, not raised
    with pytest.raises(KeyError):
        transport.publish("nope", b"\x80", 3.0)
