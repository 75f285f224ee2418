"""A small synchronous client of an RRA system's control endpoints.

Used by the CLI (``rra status``), the resolution engine and the tests: send one control
request to a node, host agent or engine and get its `Reply`; wait for liveliness tokens.

`connect_system` is how a tool finds a system: it fails at once with one actionable line
when nothing listens at the hub endpoint (a refused TCP connection is a definite answer),
asks the hub which systems run there (their host agents' liveliness tokens), and picks the
one system (``--system`` is needed only when several run at the endpoint).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.config import (
    START_HINT,
    BusConfig,
    accepts_tcp,
    explain_open_failure,
    no_system,
)
from rra_agent.bus.keys import ROOT, Keys
from rra_agent.bus.runtime import NoPeer, open_session
from rra_agent.errors import RraError

_REPLY = m.Codec[m.Reply](m.Reply)
_ENC = m.Codec[Any](Any)


#: How long a tool waits for the hub to answer which systems run there, once connected. The
#: hub answers from its own table at once (an empty answer too): this bounds only a hub that
#: does not answer at all, so it is not a race against anything periodic.
ANSWER_TIMEOUT = 3.0


class NoReply(RraError):
    """Nobody answered a control request in time."""


def open_tool_session(bus: BusConfig) -> zenoh.Session:
    """A tool's session with the hub, or an `RraError` in one line: at once when every
    connect endpoint refuses the connection (nothing listens there), else after Zenoh's
    connect timeout with what went wrong (TLS identity, not a Zenoh router...)."""
    if bus.connect and all(accepts_tcp(ep) is False for ep in bus.connect):
        raise no_system(bus)
    try:
        return open_session(bus, wait_connected=True)
    except NoPeer:
        raise no_system(bus, reachable=any(accepts_tcp(ep) for ep in bus.connect)) from None
    except zenoh.ZError as e:
        raise explain_open_failure(e, bus) from None


def running_systems(
    session: zenoh.Session, system: str = "*", timeout: float = ANSWER_TIMEOUT
) -> dict[str, list[str]]:
    """The systems whose host agents are on the bus now (``system``: only that one), with
    their hosts: ``{"object_storing": ["local"]}``."""
    out: dict[str, set[str]] = {}
    for reply in session.liveliness().get(f"{ROOT}/{system}/hostagent/*", timeout=timeout):
        if reply.ok is None:
            continue
        parts = str(reply.ok.key_expr).split("/")
        if len(parts) == 4:
            out.setdefault(parts[1], set()).add(parts[3])
    return {name: sorted(hosts) for name, hosts in sorted(out.items())}


def pick_system(systems: dict[str, list[str]], wanted: str | None, bus: BusConfig) -> str:
    """The system a tool looks at: ``wanted`` if it runs, else the only one that runs."""
    where = ", ".join(bus.connect)
    if wanted is not None and wanted in systems:
        return wanted
    if not systems:
        if wanted is not None:
            raise RraError(f"no rra system {wanted!r} answers at {where}; {START_HINT}")
        if bus.tls is not None:  # the access control hides every system not named
            raise RraError(
                f"no rra system answers at {where} to an operator that names none (with "
                "--certs, the hub tells only about the system you name): give --system NAME"
            )
        raise no_system(bus)
    names = ", ".join(systems)
    if wanted is not None:
        raise RraError(f"no system {wanted!r} at {where}; running there: {names}")
    if len(systems) > 1:
        raise RraError(
            f"{len(systems)} systems run at {where} ({names}): choose one with --system NAME"
        )
    return next(iter(systems))


def connect_system(
    bus: BusConfig, system: str | None = None, timeout: float = ANSWER_TIMEOUT
) -> BusClient:
    """A `BusClient` of the system running at ``bus``'s hub (``system``, or the only one);
    an `RraError` in one actionable line when there is none or several."""
    session = open_tool_session(bus)
    try:
        # A named system is asked for by name: an operator's access control (--certs) allows
        # queries of its own system's keys only.
        found = running_systems(session, system or "*", timeout)
        name = pick_system(found, system, bus)
        return BusClient(bus, name, session=session, own=True)
    except BaseException:
        session.close()
        raise


class BusClient:
    def __init__(
        self,
        bus: BusConfig,
        system: str,
        session: zenoh.Session | None = None,
        *,
        own: bool | None = None,
    ):
        self.keys = Keys(system)
        #: A client with a certificate (``--certs``) is an operator: the access control lets
        #: it call the engines, not host or node control, so it asks the engines instead.
        self.restricted = bus is not None and bus.tls is not None
        #: Whether `close` closes the session (default: only one it opened itself).
        self._own = session is None if own is None else own
        self.session = session if session is not None else open_session(bus, wait_connected=True)

    def close(self) -> None:
        if self._own:
            self.session.close()

    def __enter__(self) -> BusClient:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def request(self, key: str, msg: m.Msg, timeout: float = 2.0) -> m.Reply:
        """One query, first reply decoded; `NoReply` if none arrives within ``timeout``."""
        replies = self.session.get(key, payload=_ENC.encode(msg), timeout=timeout)
        for reply in replies:
            ok = reply.ok
            if ok is not None:
                return _REPLY.decode(ok.payload.to_bytes())
            err = reply.err
            if err is not None:
                return m.Err(message=err.payload.to_string(), code="zenoh")
        raise NoReply(f"no reply from {key} within {timeout:g} s")

    def node(self, name: str, msg: m.NodeRequest, timeout: float = 2.0) -> m.Reply:
        return self.request(self.keys.node_ctl(name), msg, timeout)

    def host(self, name: str, msg: m.HostRequest, timeout: float = 2.0) -> m.Reply:
        return self.request(self.keys.host_ctl(name), msg, timeout)

    def alive(self, timeout: float = 1.0) -> set[tuple[str, str]]:
        """(host, node) of every liveliness token of this system right now."""
        out = set()
        for reply in self.session.liveliness().get(self.keys.alive_all, timeout=timeout):
            if reply.ok is not None:
                parsed = self.keys.parse_alive(str(reply.ok.key_expr))
                if parsed:
                    out.add(parsed)
        return out


def wait_until(
    predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.005
) -> Any:
    """Poll ``predicate`` until it returns a truthy value; raise TimeoutError naming ``what``."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() >= deadline:
            raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)
