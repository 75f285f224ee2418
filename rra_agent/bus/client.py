"""A small synchronous client of an RRA system's control endpoints.

Used by the CLI (``rra status``), the resolution engine and the tests: send one control
request to a node, host agent or engine and get its `Reply`; wait for liveliness tokens.

`connect_system` is how a tool finds a system: it fails at once with one actionable line
when nothing listens at the hub endpoint (a refused TCP connection is a definite answer),
asks the hub which systems run there (their host agents' liveliness tokens), and picks the
one system (``--system`` is needed only when several run at the endpoint).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any, TypeVar

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus import probe
from rra_agent.bus.config import (
    START_HINT,
    BusConfig,
    accepts_tcp,
    explain_open_failure,
    no_system,
    split_endpoint,
)
from rra_agent.bus.keys import ROOT, Keys
from rra_agent.bus.session import NoPeer, open_session
from rra_agent.errors import RraError

_REPLY = m.Codec[m.Reply](m.Reply)
_ENC = m.Codec[Any](Any)
T = TypeVar("T")


def decoded(replies: Iterable[zenoh.Reply], codec: m.Codec[T]) -> Iterator[T]:
    """The answers of a get that decode with ``codec``, in order: error replies and answers
    that do not decode (a forged queryable's, a process of another version) are skipped."""
    for reply in replies:
        if reply.ok is None:
            continue
        try:
            answer = codec.decode(reply.ok.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            continue
        yield answer


def oks(replies: Iterable[zenoh.Reply]) -> Iterator[m.Ok]:
    """The `Ok` answers of a get (`Err`s, error replies and malformed answers skipped)."""
    return (a for a in decoded(replies, _REPLY) if isinstance(a, m.Ok))


#: How long a tool waits for the hub to answer which systems run there, once connected. The
#: hub answers from its own table at once (an empty answer too): this bounds only a hub that
#: does not answer at all, so it is not a race against anything periodic.
ANSWER_TIMEOUT = 3.0


class NoReply(RraError):
    """Nobody answered a control request in time."""


def open_tool_session(bus: BusConfig) -> zenoh.Session:
    """A tool's session with the hub, or an `RraError` in one line: at once when every
    connect endpoint refuses the connection (nothing listens there); when the hub cannot be
    this session's (`rra_agent.bus.probe.diagnose`: TLS on one side only, another system's
    CA...), once a first try of `probe.AFTER` has not linked; else after Zenoh's connect
    timeout, with what went wrong. A hub that is only slow is tried again for the rest of
    the connect timeout."""
    # A TCP connection closed unused costs a Zenoh TLS listener ~0.1 s before its next
    # accept (measured): a tls/ endpoint is looked at only once the first try failed.
    plain = all(split_endpoint(ep)[0] == "tcp" for ep in bus.connect)
    if bus.connect and plain and _nothing_listens(bus):
        raise no_system(bus)
    started = time.monotonic()
    first_ms = min(bus.connect_timeout_ms, int(probe.AFTER * 1000))
    try:
        return _open(msgspec.structs.replace(bus, connect_timeout_ms=first_ms), bus)
    except _NotLinked:
        pass
    why = probe.diagnose(bus)
    if why is not None:
        raise RraError(why)
    if not plain and _nothing_listens(bus):
        raise no_system(bus)
    left = bus.connect_timeout_ms - int((time.monotonic() - started) * 1000)
    try:
        return _open(msgspec.structs.replace(bus, connect_timeout_ms=max(left, 1)), bus)
    except _NotLinked:
        raise no_system(bus, reachable=any(accepts_tcp(ep) for ep in bus.connect)) from None


def _nothing_listens(bus: BusConfig) -> bool:
    """Every connect endpoint refuses a TCP connection: a definite answer, at once."""
    return all(accepts_tcp(ep) is False for ep in bus.connect)


class _NotLinked(Exception):
    """No router linked within the connect timeout of the try."""


def _open(attempt: BusConfig, bus: BusConfig) -> zenoh.Session:
    """A session linked to the hub (`_NotLinked` if none links within ``attempt``'s connect
    timeout; any other failure explained in one line)."""
    try:
        return open_session(attempt, wait_connected=True)
    except NoPeer:
        raise _NotLinked from None
    except zenoh.ZError as e:
        if "Unable to connect" in str(e):
            raise _NotLinked from None
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


# ---- a system's status, parameters and leaders, as the tools read them ----------
def _leader_token(client: BusClient, role: str) -> str:
    return f"{client.keys.lead(role)}/**"


def wait_for_leader(client: BusClient, timeout: float) -> None:
    """Until the Resolution Engine leader's token has reached this session (TimeoutError)."""
    wait_until(
        lambda: list(
            client.session.liveliness().get(_leader_token(client, "resolution"), timeout=0.5)
        ),
        timeout,
        "the resolution engine",
        interval=0.02,
    )


def engine_request(
    client: BusClient, role: str, request: m.EngineRequest, timeout: float = 5.0
) -> dict[str, Any]:
    """One request to the leader of an engine ``role`` (``monitor``, ``adaptation``,
    ``resolution``), once its token has reached this session; its ``Ok`` result. `RraError`
    in one line when no leader answers or it refuses (its reason)."""
    what = {"monitor": "Context Monitor", "adaptation": "Adaptation Engine"}.get(
        role, "Run-time Resolution Engine"
    )
    try:
        wait_until(
            lambda: list(
                client.session.liveliness().get(_leader_token(client, role), timeout=0.5)
            ),
            timeout,
            f"the {what}",
            interval=0.02,
        )
    except TimeoutError:
        raise RraError(
            f"no {what} leads system {client.keys.system!r} on this bus "
            "(right --system and --connect?)"
        ) from None
    try:
        reply = client.request(client.keys.engine_ctl(role), request, timeout)
    except NoReply:
        raise RraError(
            f"the {what} leader of system {client.keys.system!r} did not answer within "
            f"{timeout:g} s (a busy machine? try again)"
        ) from None
    if isinstance(reply, m.Err):
        raise RraError(reply.message)
    return reply.result if isinstance(reply.result, dict) else {}


def context(client: BusClient, timeout: float = 2.0) -> list[dict[str, Any]] | None:
    """Every measurement with its newest value, as the Context Monitor leader publishes it
    (``value``, ``stamp``, ``sources``, ``override``...; `rra_agent.engines.injection`), or
    None when no monitor answers."""
    try:
        reply = client.request(client.keys.engine_ctl("monitor"), m.Status(), timeout)
    except NoReply:
        return None
    if not isinstance(reply, m.Ok) or not isinstance(reply.result, dict):
        return None
    found = reply.result.get("context")
    return found if isinstance(found, list) else None


def gather(client: BusClient, timeout: float = 2.0) -> dict[str, Any]:
    """The engine's status, every host's nodes and every process's counters, and the
    Context Monitor's measurements. An operator with a certificate (``client.restricted``)
    may not call host or node control: its view is the engine's (what the host agents last
    reported to it) and the engines' counters."""
    engine = engine_status(client, timeout)
    eng = engine or {}
    present = {
        str(r.ok.key_expr).rsplit("/", 1)[-1]
        for r in client.session.liveliness().get(client.keys.host_alive_all, timeout=1)
        if r.ok is not None
    }
    nodes = [] if client.restricted else _listed_nodes(client, sorted(present), timeout)
    listed = {n["node"] for n in nodes}
    unreachable = set(eng.get("unreachable", []))
    for name, st in (eng.get("observed") or {}).items():
        if name in listed:
            continue
        # On a host the engine cannot reach now: as it last heard of it.
        state = f"{st['state']}?" if st.get("host") in unreachable else st["state"]
        nodes.append({"node": name, **st, "state": state})
    families = ("engine",) if client.restricted else ("node", "host")
    hosts = sorted({*eng.get("hosts", {}), *present})
    status = {
        "engine": engine,
        "nodes": nodes,
        # The model's hosts as the engine sees them (an unreachable one too), and any other.
        "hosts": hosts,
        "host_agents": _host_agents(client, hosts, present, unreachable, nodes, timeout),
        "stats": process_stats(client, timeout, families=families),
        "context": context(client, timeout) if engine is not None else None,
    }
    graph = ros2_graph(client, eng, timeout)
    if graph is not None:
        status["ros2"] = graph
    return status


def ros2_graph(client: BusClient, eng: dict[str, Any], timeout: float) -> dict[str, Any] | None:
    """The ROS 2 graph of the system's domain (a package with ``ros2:``, as the engine's
    status says), from the liveliness tokens alive now, asked from this tool's session:
    every ROS 2 node, rra-agent's and the robot's, with its endpoints
    (`rra_agent.ros2.graph.Graph.to_json`)."""
    ros = eng.get("ros2")
    if not isinstance(ros, dict) or not isinstance(ros.get("domain"), int):
        return None
    from rra_agent.ros2.graph import query_graph

    return query_graph(client.session, ros["domain"], timeout=min(timeout, 1.0)).to_json()


def _host_agents(
    client: BusClient,
    hosts: list[str],
    present: set[str],
    unreachable: set[str],
    nodes: list[dict[str, Any]],
    timeout: float,
) -> list[dict[str, Any]]:
    """Each host agent: whether it is up, its router's endpoints (its answer to a ``Ping``;
    an operator with a certificate may not ask) and how many nodes run on it."""
    out = []
    for host in hosts:
        info: dict[str, Any] = {}
        if host in present and not client.restricted:
            with contextlib.suppress(NoReply):
                reply = client.host(host, m.Ping(), timeout)
                if isinstance(reply, m.Ok) and isinstance(reply.result, dict):
                    info = reply.result
        live = [n for n in nodes if n.get("host") == host and n.get("state") in LIVE_STATES]
        state = "up" if host in present else "unreachable" if host in unreachable else "absent"
        out.append(
            {
                "host": host,
                "state": state,
                "pid": info.get("pid"),
                "listen": info.get("listen", []),
                "connect": info.get("connect", []),
                "cpu_latency_us": info.get("cpu_latency_us"),
                "nodes": len(live),
            }
        )
    return out


#: Node states in which a process exists (``rra status`` counts them per host).
LIVE_STATES = frozenset({"STARTING", "RUNNING", "UNRESPONSIVE", "STOPPING"})


def engine_status(client: BusClient, timeout: float) -> dict[str, Any] | None:
    # A client just connected has not been told about the engine yet: query it once the
    # leader's token has reached this session (its queryable was declared before it).
    with contextlib.suppress(TimeoutError):
        wait_for_leader(client, timeout)
    try:
        reply = client.request(client.keys.engine_ctl("resolution"), m.Status(), timeout)
    except NoReply:
        return None
    return reply.result if isinstance(reply, m.Ok) else None


def _listed_nodes(client: BusClient, hosts: list[str], timeout: float) -> list[dict[str, Any]]:
    """Every node the host agents of ``hosts`` supervise (``ListNodes``)."""
    out: list[dict[str, Any]] = []
    for host in hosts:
        try:
            reply = client.host(host, m.ListNodes(), timeout)
        except NoReply:
            continue
        if isinstance(reply, m.Ok):
            out.extend(reply.result)
    return out


def process_stats(
    client: BusClient, timeout: float = 1.0, families: tuple[str, ...] = ("node", "host")
) -> dict[str, dict[str, Any]]:
    """Every process's counters (`ProcessStats`) by name: one query to all at once."""
    out: dict[str, dict[str, Any]] = {}
    for key in (f"{client.keys.prefix}/{family}/*/ctl" for family in families):
        replies = client.session.get(
            key,
            payload=_ENC.encode(m.Stats()),
            timeout=timeout,
            consolidation=zenoh.ConsolidationMode.NONE,
        )
        for answer in oks(replies):
            if isinstance(answer.result, dict):
                stats = answer.result
                out[f"{stats.get('role')}:{stats.get('name')}"] = stats
    return out


def set_params(
    client: BusClient,
    node: str,
    values: dict[str, Any],
    reset: Sequence[str] = (),
    timeout: float = 5.0,
) -> dict[str, Any]:
    """Set a node's parameters as an operator: through the Run-time Resolution Engine, so
    they are checked, become part of the Run-time Configured System Model and survive
    restarts. Raises `RraError` with the engine's refusal."""
    try:
        wait_for_leader(client, timeout)
    except TimeoutError:
        raise RraError(
            f"no Run-time Resolution Engine leads system {client.keys.system!r}"
        ) from None
    request = m.SetParam(node=node, params=values, reset=list(reset))
    reply = client.request(client.keys.engine_ctl("resolution"), request, timeout)
    if isinstance(reply, m.Err):
        raise RraError(f"{node}: {reply.message}")
    return reply.result  # type: ignore[union-attr]


def engine_params(client: BusClient, node: str, timeout: float = 5.0) -> dict[str, Any]:
    """A node's parameters in the Run-time Configured System Model (the engine's state)."""
    return node_params(client, node, timeout)["params"]


def node_params(client: BusClient, node: str, timeout: float = 5.0) -> dict[str, Any]:
    """``GetParams`` of the Run-time Resolution Engine leader: ``{"node", "state", "params",
    "overrides"}`` (``state``: ``running``, ``standby`` or ``stopped``, then ``params`` are
    the values it will start with). `RraError` in one line for a name that is no node of the
    system (at once: the engine knows its model) or when no engine leads."""
    try:
        wait_for_leader(client, timeout)
        key = client.keys.engine_ctl("resolution")
        reply = client.request(key, m.GetParams(node=node), timeout)
    except (TimeoutError, NoReply):
        raise RraError(f"no Run-time Resolution Engine leads {client.keys.system!r}") from None
    if isinstance(reply, m.Err):
        raise RraError(reply.message if reply.code == "unknown" else f"{node}: {reply.message}")
    return reply.result  # type: ignore[no-any-return]
