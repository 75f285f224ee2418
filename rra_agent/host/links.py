"""Whether a host agent's router is linked to the routers it connects to, said when it is.

A router's ``--connect`` endpoint is a wish: Zenoh keeps dialling it (every second at most,
`rra_agent.bus.config.RETRY`) whether or not anything listens there. So the banners of
``rra up`` and ``rra agent`` say "links to X (not yet)" until a link to X exists, and
`LinkWatch` follows the router's links (``session.info.links()``: a link this router dialled
has the endpoint as its far end) and prints one line when each endpoint is linked, one
warning when one is not linked `DEADLINE` seconds after the start (with what a TCP connection
to it says: nothing listens, no answer, or something that does not open a Zenoh link), and
one line when a link is lost (Zenoh dials again).
"""

from __future__ import annotations

import contextlib
import socket
import threading
import time
from collections.abc import Callable, Iterable

import zenoh

from rra_agent import text
from rra_agent.bus.config import BusConfig, accepts_tcp, split_endpoint

#: How long after its start a router may take to link to an endpoint before it is warned
#: about (Zenoh dials within 0.25 s, then every second; a TLS link on a slow network takes
#: a few round trips).
DEADLINE = 5.0
#: How often the links are looked at.
PERIOD = 0.1


def _addresses(host: str) -> set[str]:
    """``host`` and the addresses it resolves to (an endpoint may name a host)."""
    out = {host}
    with contextlib.suppress(OSError):
        out |= {str(info[4][0]) for info in socket.getaddrinfo(host, None)}
    return out


class Endpoints:
    """The connect endpoints of a router, matched against the far ends of its links."""

    def __init__(self, endpoints: Iterable[str]) -> None:
        self.endpoints = list(endpoints)
        self._parts = {ep: split_endpoint(ep) for ep in self.endpoints}
        self._addresses = {ep: _addresses(parts[1]) for ep, parts in self._parts.items()}

    def linked(self, session: zenoh.Session) -> set[str]:
        """The endpoints this router has a link to now (a link's far end is the endpoint)."""
        ends = {split_endpoint(str(link.dst)) for link in session.info.links()}
        return {
            ep
            for ep, (proto, _, port) in self._parts.items()
            if any(p == proto and pt == port and h in self._addresses[ep] for p, h, pt in ends)
        }


def why_not_linked(endpoint: str) -> str:
    """What a TCP connection to ``endpoint`` says about a missing link, in a few words."""
    match accepts_tcp(endpoint, timeout=0.5):
        case False:
            return "nothing listens there (is its `rra up` or `rra agent` running there?)"
        case None:
            return "no answer (a firewall, or a machine that is down?)"
    return (
        "it accepts connections but no Zenoh link opens (not an rra router, or TLS "
        "certificates of another system?)"
    )


class LinkWatch:
    """A daemon thread saying (with ``say``) when each connect endpoint of ``session``'s
    router is linked, warning once about each one not linked after ``deadline`` s, and saying
    when a link is lost. It ends with the session."""

    def __init__(
        self,
        session: zenoh.Session,
        endpoints: Iterable[str],
        say: Callable[[str], None],
        *,
        deadline: float = DEADLINE,
        linked: Iterable[str] = (),
    ) -> None:
        self.session = session
        self.endpoints = Endpoints(endpoints)
        self.say = say
        self.deadline = deadline
        #: Endpoints already said to be linked (the banner's).
        self.linked: set[str] = set(linked)
        self.warned: set[str] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="link-watch", daemon=True)

    def start(self) -> LinkWatch:
        if self.endpoints.endpoints:
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()

    def _run(self) -> None:
        started = time.monotonic()
        while not self._stop.wait(PERIOD):
            try:
                now_linked = self.endpoints.linked(self.session)
            except Exception:  # the session closed: the agent is stopping
                return
            self.check(now_linked, time.monotonic() - started)

    def check(self, now_linked: set[str], elapsed: float) -> None:
        """Say what changed since the last look (``elapsed`` s after the start)."""
        for ep in self.endpoints.endpoints:
            if ep in now_linked and ep not in self.linked:
                self.linked.add(ep)
                self.say(f"linked to {ep}")
            elif ep not in now_linked and ep in self.linked:
                self.linked.discard(ep)
                self.say(f"link to {ep} lost; dialling it again every second")
            elif ep not in now_linked and ep not in self.warned and elapsed >= self.deadline:
                self.warned.add(ep)
                self.say(
                    f"WARNING: not linked to {ep} after {self.deadline:g} s: "
                    f"{why_not_linked(ep)}; dialling it again every second"
                )


def printer(prefix: str, *, wide: bool = False) -> Callable[[str], None]:
    """A `LinkWatch` ``say``: ``prefix`` and the line, wrapped at `rra_agent.text.WIDTH`."""

    def say(line: str) -> None:
        print("\n".join(text.wrap(f"{prefix}{line}", indent="    ", wide=wide)), flush=True)

    return say


def banner(
    head: str,
    router: BusConfig,
    session: zenoh.Session | None,
    fields: Iterable[tuple[str, str]],
    *,
    wide: bool = False,
) -> tuple[str, set[str]]:
    """A host agent's banner: ``head`` (ending in "Ctrl-C to stop"), then its router's
    endpoints (``listens on``; ``links to`` each connect endpoint, linked or not yet), then
    ``fields``, each wrapped at `rra_agent.text.WIDTH` unless ``wide``; and the endpoints
    linked already (said so here, so `LinkWatch` does not say it again)."""
    linked = Endpoints(router.connect).linked(session) if session is not None else set()
    rows = [("router", f"listens on {', '.join(router.listen)}")]
    rows += [
        ("links", f"to {ep}" + (" (linked)" if ep in linked else ": not linked yet"))
        for ep in router.connect
    ]
    lines = text.wrap(head, indent="    ", wide=wide)
    for label, value in (*rows, *fields):
        lines += text.wrap(f"  {label:<7} {value}", indent=" " * 10, wide=wide)
    return "\n".join(lines), linked
