"""One system, one set of engines: what a starting host agent checks before it serves.

A second ``rra up`` of a system that already runs on the bus, linked to its routers, would
run a second set of engines with the same replica names beside the first (they fight over
the leadership and over the nodes), and a second agent of a host would answer the host's
control requests beside the first (components of one host started by another). So a host
agent, once its router has linked to the routers it connects to and *before* it declares
anything, asks the bus:

- is there a host agent of this system for this host already (``hostagent/<host>``)?
- for ``rra up`` (it starts the engines): is any engine replica of this system up
  (``member/<role>/<replica>``)?

Either is refused with one line naming where the other runs (its host, its agent's pid and
router endpoints, from a ``Ping``); nothing has been started yet. A linked router's tokens
reach this one only after Zenoh has computed its routing trees (100 ms after a link
changes; 0.10-0.16 s measured, with both cores busy), so the answer "nobody" is trusted only
`CONFIRM` after the first host agent token of any system has arrived from behind the links
(every rra router has one), or at `SETTLE` after the links are up if none comes (a plain
router, or an agent still starting); a token seen earlier refuses at once. An agent whose
links hold its connection without answering (a router not listening yet behind a relay)
waits for them up to `LINK_WAIT`. What this cannot see: a
system on the other side of a partition, or routers that link to this one only later (a
``--listen`` endpoint another router dials). Those are kept apart by the leaders' terms,
which name the process (`rra_agent.core.election`): two leaders of one replica name are
two terms, and every receiver accepts only the newer one.
"""

from __future__ import annotations

import time
from typing import Any

import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.client import oks
from rra_agent.bus.config import BusConfig, accepts_tcp
from rra_agent.bus.keys import ROOT, Keys

#: How long a starting agent waits for its router's links to the routers it connects to.
LINK_WAIT = 3.0
#: How long after its links are up a starting agent keeps looking for the tokens of
#: another system behind them (Zenoh's routing trees: 100 ms after a link changes)...
SETTLE = 0.5
#: ... or after the first host agent token from behind them: one more look, in case the
#: linked router's tokens came in more than one batch.
CONFIRM = 0.1
#: How long a liveliness query may take to be answered.
ANSWER = 1.0
#: How long a starting agent that sees another system's engine replicas keeps looking for the
#: host that runs them (for the refusal's text): their member tokens and the liveliness
#: tokens that name their host can reach this router in different batches.
LOCATE = 1.0
#: How long the running agent's answer to a Ping (for the refusal's text) is waited for: it
#: answers at once unless its machine is busy (1 s was too short once, on two loaded cores).
PING = 2.0
_ANY = m.Codec[Any](Any)


def wait_linked(session: zenoh.Session, bus: BusConfig, timeout: float = LINK_WAIT) -> int:
    """Until this router has a link to each connect endpoint that accepts connections now,
    or ``timeout`` (an endpoint that refuses them has no system behind it yet); the number
    of routers it is linked to."""
    expected = sum(1 for ep in bus.connect if accepts_tcp(ep, timeout=0.5) is not False)
    deadline = time.monotonic() + timeout
    while len(session.info.routers_zid()) < expected and time.monotonic() < deadline:
        time.sleep(0.01)
    return len(session.info.routers_zid())


def refusal(
    session: zenoh.Session,
    bus: BusConfig,
    keys: Keys,
    host: str,
    *,
    engines: bool,
    who: str,
    settle: float = SETTLE,
) -> str | None:
    """Why this agent must not serve (one line), or None: asked again until the linked
    routers' tokens are in (`CONFIRM` after the first host agent token, at most ``settle``
    after this router's links are up; at once when it has none)."""
    linked = wait_linked(session, bus)
    deadline = time.monotonic() + (settle if linked else 0.0)
    while True:
        why = already_running(session, keys, host, engines=engines, who=who)
        now = time.monotonic()
        if why is not None or now >= deadline:
            return why
        if tokens(session, f"{ROOT}/*/hostagent/*"):  # the linked routers' tokens are in
            deadline = min(deadline, now + CONFIRM)
        time.sleep(0.02)


def tokens(session: zenoh.Session, key: str) -> list[str]:
    """The keys of the liveliness tokens matching ``key`` on the bus now."""
    return [
        str(reply.ok.key_expr)
        for reply in session.liveliness().get(key, timeout=ANSWER)
        if reply.ok is not None
    ]


def agent_identity(session: zenoh.Session, keys: Keys, host: str) -> dict[str, Any]:
    """A host agent's answer to a Ping (pid, host, router endpoints); {} if none within
    `PING`. Asked again while nobody answers at all: a router that has just linked may know
    the agent's tokens before its queryable (the routes follow the tokens)."""
    deadline = time.monotonic() + PING
    ping = _ANY.encode(m.Ping())
    while (left := deadline - time.monotonic()) > 0:
        for answer in oks(session.get(keys.host_ctl(host), payload=ping, timeout=left)):
            if isinstance(answer.result, dict):
                return answer.result
        time.sleep(0.02)
    return {}


def where(session: zenoh.Session, keys: Keys, host: str) -> str:
    """``host H (agent pid P, router E)``: where a host agent runs."""
    ident = agent_identity(session, keys, host)
    pid = f"agent pid {ident['pid']}" if ident.get("pid") else "its agent does not answer"
    listen = ident.get("listen") or []
    router = f", router {', '.join(map(str, listen))}" if listen else ""
    return f"host {host} ({pid}{router})"


def engines_host(
    session: zenoh.Session, keys: Keys, patience: float = 0.0, *, expected: bool = False
) -> str | None:
    """The host whose agent runs engine replicas of the system, or None if none is up; "?"
    if the host of none of them is known within ``patience`` seconds. ``expected``: a system
    is known to be there (its agent's token), so its replicas' tokens, which may come in a
    later batch, are waited for as long too (None only if none came)."""
    deadline = time.monotonic() + patience
    while True:
        members = tokens(session, f"{keys.prefix}/member/**")
        replicas = {key.rsplit("/", 1)[-1] for key in members}
        for key in tokens(session, f"{keys.prefix}/alive/**") if members else []:
            parsed = keys.parse_alive(key)
            if parsed is not None and parsed[1] in replicas:
                return parsed[0]
        if time.monotonic() >= deadline or not (members or expected):
            return "?" if members else None
        time.sleep(0.02)


def already_running(
    session: zenoh.Session, keys: Keys, host: str, *, engines: bool, who: str
) -> str | None:
    """Why this agent must not serve (one line), or None when the bus has room for it."""
    system = keys.system
    other = engines_host(session, keys, LOCATE) if engines else None
    agent_there = other is None and bool(tokens(session, keys.host_alive(host)))
    if engines and agent_there:  # a system is there: its engines may be in the next batch
        other = engines_host(session, keys, LOCATE, expected=True)
    if other is not None:
        at = where(session, keys, other) if other != "?" else "a host that does not answer"
        return (
            f"system {system!r} already runs on this bus, its engines on {at}; {who} "
            "refused (one system, one set of engines): stop it first, or run this one on "
            "another bus (another --connect)"
        )
    if agent_there:
        return (
            f"host {host} of system {system!r} already has its agent on this bus, "
            f"{where(session, keys, host)}; {who} refused: stop that agent first, or start "
            "this one as another host (--host) or on another bus (another --connect)"
        )
    return None
