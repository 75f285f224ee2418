"""A small synchronous client of an RRA system's control endpoints.

Used by the CLI (``rra status``), the resolution engine and the tests: send one control
request to a node, host agent or engine and get its `Reply`; wait for liveliness tokens.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.keys import Keys
from rra_agent.bus.runtime import open_session
from rra_agent.errors import RraError

_REPLY = m.Codec[m.Reply](m.Reply)
_ENC = m.Codec[Any](Any)


class NoReply(RraError):
    """Nobody answered a control request in time."""


class BusClient:
    def __init__(self, bus: BusConfig, system: str, session: zenoh.Session | None = None):
        self.keys = Keys(system)
        #: A client with a certificate (``--certs``) is an operator: the access control lets
        #: it call the engines, not host or node control, so it asks the engines instead.
        self.restricted = bus is not None and bus.tls is not None
        self._own = session is None
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
