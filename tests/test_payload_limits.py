"""Payload limits enforced by Zenoh in the host's router (rra_agent.bus.counters.router_limits):
the generated settings, and a real router with two client sessions showing that what is over
a limit is never delivered while what is under it is."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest
import zenoh

from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.bus.counters import MAX_MESSAGE_SIZE, MAX_PAYLOAD, KiB, MiB, router_limits
from rra_agent.bus.keys import Keys
from rra_agent.bus.session import open_session

K = Keys("lim")


def rules(settings: dict) -> dict[str, tuple[list[str], int, list[str]]]:
    return {r["id"]: (r["key_exprs"], r["size_limit"], r["messages"])
            for r in settings["low_pass_filter"]}  # fmt: skip


def test_every_key_family_has_a_rule_and_the_router_reassembles_nothing_larger():
    settings = router_limits("lim")
    got = rules(settings)
    assert got["rra-data"] == (["rra/*/data/**"], MiB + 64, ["put", "delete", "query", "reply"])
    assert got["rra-ctx"][:2] == (["rra/*/ctx/*"], 16 * KiB + 64)
    assert got["rra-engine_ctl"] == (["rra/*/engine/*/ctl"], 64 * KiB + 64,
                                     ["put", "delete", "query"])  # fmt: skip
    assert got["rra-engine_ctl-reply"][1] == MAX_PAYLOAD["state"] + 64  # a whole state
    families = {"data", "ctx", "selection", "events", "state", "inject", "node_ctl", "host_ctl"}
    assert {f"rra-{f}" for f in families} <= set(got)
    assert settings[MAX_MESSAGE_SIZE] == 4 * MiB + 64 * KiB


def test_a_port_allowing_more_raises_the_data_rule_and_keeps_the_others_to_theirs():
    settings = router_limits("lim", {"cam/image": 8 * MiB, "laser/scan": MiB})
    got = rules(settings)
    assert got["rra-data"][1] == 8 * MiB + 64
    assert got["rra-data-laser/scan"][:2] == (["rra/lim/data/laser/scan"], MiB + 64)
    assert "rra-data-cam/image" not in got
    assert settings[MAX_MESSAGE_SIZE] == 8 * MiB + 64 * KiB


def test_the_limits_are_the_routers_and_the_operator_may_override_them():
    bus = BusConfig(connect=["tcp/127.0.0.1:1"], zenoh={MAX_MESSAGE_SIZE: 123})
    router = bus.host_router(hub=True, system="lim", topics={"cam/image": 8 * MiB})
    assert router.zenoh[MAX_MESSAGE_SIZE] == 123  # the operator's --bus-config wins
    assert router.zenoh["low_pass_filter"] and router.max_data_bytes == 8 * MiB
    client = router.local_client()
    assert client.zenoh == {} and client.max_data_bytes == 8 * MiB


@pytest.fixture
def router() -> Iterator[BusConfig]:
    """A host router with the limits of system ``lim`` (``cam/image`` allows 2 MiB)."""
    port = free_port()
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{port}"], lease_ms=500)
    cfg = bus.host_router(hub=True, system="lim", topics={"cam/image": 2 * MiB, "a/b": MiB})
    session = zenoh.open(cfg.to_zenoh())
    try:
        yield cfg.local_client()
    finally:
        session.close()


class Seen:
    def __init__(self, session: zenoh.Session, key: str) -> None:
        self.sizes: list[int] = []
        self.lock = threading.Lock()
        self.sub = session.declare_subscriber(key, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.sizes.append(len(sample.payload))


@pytest.mark.parametrize(
    ("key", "size", "delivered"),
    [
        (K.data("a/b"), MiB, True),
        (K.data("a/b"), MiB + KiB, False),
        (K.data("cam/image"), 2 * MiB, True),  # its port allows 2 MiB
        (K.data("cam/image"), 2 * MiB + KiB, False),
        (K.ctx("Level"), 17 * KiB, False),
        (K.selection, 300 * KiB, False),
        ("not/rra/at/all", 10_000_000, False),  # over max_message_size: never reassembled
        ("not/rra/at/all", 3 * MiB, True),  # no family: only the size cap applies
    ],
    ids=["data-1MiB", "data-over", "port-2MiB", "port-over", "ctx", "selection", "cap", "free"],
)
@pytest.mark.system
def test_the_router_delivers_what_is_within_the_limit_and_nothing_over_it(
    router: BusConfig, key: str, size: int, delivered: bool
):
    sender, receiver = open_session(router), open_session(router)
    seen = Seen(receiver, key)
    try:
        # BLOCK: the sender never drops a big sample itself; only the router may.
        pub = sender.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK)
        wait_until(lambda: pub.matching_status.matching, 10, "the subscriber matched")
        pub.put(b"\x01" * size)
        pub.put(b"\x02")  # after it, on the same key: in order
        wait_until(lambda: 1 in seen.sizes, 20, "the small sample after it")
        assert (size in seen.sizes) == delivered, seen.sizes
        pub.undeclare()
    finally:
        seen.sub.undeclare()
        sender.close()
        receiver.close()
