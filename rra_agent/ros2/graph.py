"""The live ROS 2 graph, from rmw_zenoh's liveliness tokens.

`Graph` is pure state: feed it token keys as they appear and disappear (`apply`) and ask
it for nodes, topics and services. A token that does not parse is refused and counted while
it is alive (`refused`, `last_refused`), never raised. `GraphWatcher` is the thin Zenoh shell: a
liveliness subscriber on ``@ros2_lv/<domain>/**`` with history, feeding a `Graph`;
`query_graph` asks once.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rra_agent.ros2.errors import BadToken
from rra_agent.ros2.names import check_domain
from rra_agent.ros2.tokens import ADMIN_SPACE, Kind, Token, parse_token


@dataclass(frozen=True, slots=True)
class Endpoint:
    kind: Kind
    name: str
    ros_type: str
    type_hash: str
    qos: str


@dataclass(slots=True)
class NodeInfo:
    """A ROS 2 node and its endpoints, as the graph knows them."""

    domain: int
    zid: str
    node_id: int
    name: str
    namespace: str
    enclave: str
    #: Whether its own (NN) token is there; endpoints can be seen before it.
    announced: bool = False
    endpoints: list[Endpoint] = field(default_factory=list)

    @property
    def fq_name(self) -> str:
        return f"{self.namespace.rstrip('/')}/{self.name}"

    def of(self, kind: Kind) -> list[Endpoint]:
        return sorted((e for e in self.endpoints if e.kind is kind), key=lambda e: e.name)

    def to_json(self) -> dict[str, Any]:
        def eps(kind: Kind) -> list[dict[str, str]]:
            return [{"name": e.name, "type": e.ros_type, "qos": e.qos} for e in self.of(kind)]

        return {
            "name": self.fq_name,
            "domain": self.domain,
            "zid": self.zid,
            "publishers": eps(Kind.PUBLISHER),
            "subscriptions": eps(Kind.SUBSCRIPTION),
            "services": eps(Kind.SERVICE),
            "clients": eps(Kind.CLIENT),
        }


class Graph:
    """The entities of the tokens seen alive; ``domain`` None accepts every domain."""

    def __init__(self, domain: int | None = 0) -> None:
        self.domain = None if domain is None else check_domain(domain)
        self._tokens: dict[str, Token] = {}
        #: Tokens alive now that were refused, and why.
        self._refused: dict[str, str] = {}
        self.last_refused: str | None = None

    @property
    def refused(self) -> int:
        """How many tokens alive now were refused (each counted once, however often seen)."""
        return len(self._refused)

    def apply(self, key: str, alive: bool) -> Token | None:
        """Take one token's appearance (``alive``) or disappearance; the token, or None
        when it was refused (counted) or changes nothing."""
        if not alive:
            self._refused.pop(key, None)
            return self._tokens.pop(key, None)
        try:
            token = parse_token(key)
        except BadToken as e:
            self._refused[key] = self.last_refused = str(e)
            return None
        if self.domain is not None and token.domain != self.domain:
            return None
        self._tokens[key] = token
        return token

    def __len__(self) -> int:
        return len(self._tokens)

    def tokens(self) -> list[Token]:
        return list(self._tokens.values())

    def nodes(self) -> list[NodeInfo]:
        """Every node, by fully qualified name (then Zenoh id)."""
        nodes: dict[tuple[int, str, int], NodeInfo] = {}
        for t in self._tokens.values():
            info = nodes.get(t.node_key)
            if info is None:
                info = nodes[t.node_key] = NodeInfo(
                    t.domain, t.zid, t.node_id, t.node, t.namespace, t.enclave
                )
            if t.kind is Kind.NODE:
                info.announced = True
            else:
                assert t.name and t.ros_type and t.type_hash and t.qos
                ep = Endpoint(t.kind, t.name, t.ros_type, t.type_hash, t.qos.describe())
                info.endpoints.append(ep)
        return sorted(nodes.values(), key=lambda n: (n.fq_name, n.zid, n.node_id))

    def find(self, fq_name: str) -> list[NodeInfo]:
        return [n for n in self.nodes() if n.fq_name == fq_name]

    def names(self, *kinds: Kind) -> dict[str, set[str]]:
        """Topic (or service) name -> its types, over the endpoints of ``kinds``."""
        out: dict[str, set[str]] = {}
        for t in self._tokens.values():
            if t.kind in kinds and t.name and t.ros_type:
                out.setdefault(t.name, set()).add(t.ros_type)
        return out

    def topics(self) -> dict[str, set[str]]:
        return self.names(Kind.PUBLISHER, Kind.SUBSCRIPTION)

    def services(self) -> dict[str, set[str]]:
        return self.names(Kind.SERVICE)

    def endpoints(self, kind: Kind, name: str) -> list[Token]:
        return [t for t in self._tokens.values() if t.kind is kind and t.name == name]

    def to_json(self) -> dict[str, Any]:
        return {
            "domain": self.domain,
            "nodes": [n.to_json() for n in self.nodes()],
            "refused_tokens": self.refused,
        }

    def lines(self, width: int = 100) -> list[str]:
        """A compact listing for ``rra status``: one line per node and per endpoint."""
        return graph_lines(self.to_json(), width)


def graph_lines(graph: dict[str, Any], width: int = 100) -> list[str]:
    """`Graph.lines` from `Graph.to_json` (what ``rra status --json`` carries)."""
    nodes = graph.get("nodes", [])
    refused = graph.get("refused_tokens", 0)
    out = [f"ROS 2 graph (domain {graph.get('domain')}): {len(nodes)} nodes"
           + (f", {refused} tokens refused" if refused else "")]
    tags = (("publishers", "pub"), ("subscriptions", "sub"), ("services", "srv"),
            ("clients", "cli"))
    # Nodes of one name are shown as one, with all their endpoints (some implementations,
    # zenoh-ros2-sdk's, declare a node per endpoint; --json lists them apart).
    by_name: dict[str, list[dict[str, Any]]] = {}
    for node in nodes:
        by_name.setdefault(node["name"], []).append(node)
    for name, same in by_name.items():
        many = f"  ({len(same)} nodes of this name)" if len(same) > 1 else ""
        out.append(_fit(f"  {name}{many}", width))
        for field_name, tag in tags:
            seen = sorted({(e["name"], e["type"]) for n in same for e in n.get(field_name, [])})
            out += [_fit(f"    {tag} {e} [{t}]", width) for e, t in seen]
    return out


def _fit(text: str, width: int) -> str:
    return text if len(text) <= width else text[: width - 1] + "…"


def query_graph(session: Any, domain: int = 0, timeout: float = 1.0) -> Graph:
    """The graph as the tokens alive now say (one liveliness query: for a one-shot tool
    such as ``rra status``; a process that follows the graph uses `GraphWatcher`, and reads
    its snapshot: a liveliness query from a session that has a liveliness subscriber on
    the same keys was seen to come back empty at once, now and then)."""
    graph = Graph(domain)
    for reply in session.liveliness().get(f"{ADMIN_SPACE}/{domain}/**", timeout=timeout):
        if reply.ok is not None:
            graph.apply(str(reply.ok.key_expr), True)
    return graph


class GraphWatcher:
    """A `Graph` kept up to date from a Zenoh session (close it, or close the session)."""

    def __init__(
        self,
        session: Any,  # zenoh.Session
        domain: int = 0,
        on_change: Callable[[Token, bool], None] | None = None,
    ) -> None:
        self.graph = Graph(domain)
        self._lock = threading.Lock()
        self._on_change = on_change
        self._sub = session.liveliness().declare_subscriber(
            f"{ADMIN_SPACE}/{domain}/**", self._on_sample, history=True
        )

    def _on_sample(self, sample: Any) -> None:
        import zenoh

        alive = sample.kind == zenoh.SampleKind.PUT
        with self._lock:
            token = self.graph.apply(str(sample.key_expr), alive)
        if token is not None and self._on_change is not None:
            with contextlib.suppress(Exception):  # a listener's bug must not stop the graph
                self._on_change(token, alive)

    def snapshot(self) -> Graph:
        """A copy of the graph as it is now (safe to read while tokens keep coming)."""
        with self._lock:
            copy = Graph(self.graph.domain)
            copy._tokens = dict(self.graph._tokens)
            copy._refused = dict(self.graph._refused)
            copy.last_refused = self.graph.last_refused
        return copy

    def close(self) -> None:
        self._sub.undeclare()
