"""Opening a process's Zenoh session, and the QoS every process uses on the bus."""

from __future__ import annotations

import contextlib
import time
from typing import Any

import zenoh

from rra_agent.bus.config import BusConfig
from rra_agent.errors import RraError

#: A session a spare node process opened before it knew its node (`preopen`), with the
#: configuration it was opened with: `open_session` takes it for that configuration.
_preopened: tuple[BusConfig, zenoh.Session] | None = None


def preopen(bus: BusConfig) -> zenoh.Session | None:
    """Open the session of the node this process will become, before it is known (a spare
    of the fork server, when every node of its host has one bus configuration: no
    per-node identity). Takes zenoh's runtime start-up, the link to the router and its
    handshake (3 ms idle, 10-15 ms on a busy machine) off the start of the node; a failure
    leaves the node to open its own. The session, or None."""
    global _preopened
    with contextlib.suppress(Exception):
        _preopened = (bus, zenoh.open(bus.to_zenoh()))
    return _preopened[1] if _preopened is not None else None


def discard_preopened() -> None:
    """Close a pre-opened session this process will not use (a node of another bus
    configuration, a command ``exec``ed in its place)."""
    global _preopened
    if _preopened is not None:
        _, session = _preopened
        _preopened = None
        with contextlib.suppress(Exception):
            session.close()


def open_session(bus: BusConfig, *, wait_connected: bool = False) -> zenoh.Session:
    """Open a Zenoh session (or take the one pre-opened for this very configuration).
    With ``wait_connected``, return only once the hub is linked (``scouting/delay=0`` makes
    open return before the connect endpoints are reached, so a query sent at once would
    find nobody); raise `NoPeer` after ``connect_timeout_ms``."""
    global _preopened
    if _preopened is not None and _preopened[0] == bus:
        session, _preopened = _preopened[1], None
    else:
        discard_preopened()
        session = zenoh.open(bus.to_zenoh())
    if wait_connected and bus.connect:
        deadline = time.monotonic() + bus.connect_timeout_ms / 1000.0
        while not (session.info.routers_zid() or session.info.peers_zid()):
            if time.monotonic() >= deadline:
                session.close()
                raise NoPeer(f"nothing reachable at {', '.join(bus.connect)}")
            time.sleep(0.002)
    return session


class NoPeer(RraError):
    """Nothing answered at the bus endpoints (is the system running? right --connect?)."""


def beat_period(heartbeat_timeout: float) -> float:
    """How often a process beats: four times per deadline, between 50 ms and 1 s."""
    return min(1.0, max(0.05, heartbeat_timeout / 4)) if heartbeat_timeout > 0 else 1.0


#: Control requests and their replies (the Run-time Resolution Engine's rewires,
#: activations, state transfers) go ahead of data: a reconfiguration must not queue behind
#: the 500 Hz samples sharing the router's links, nor wait to be batched.
CONTROL_QOS: dict[str, Any] = {"priority": zenoh.Priority.INTERACTIVE_HIGH, "express": True}


def data_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """Reliable, blocking (never silently dropping), express (unbatched) publisher."""
    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        express=True,
    )
