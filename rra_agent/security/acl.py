"""The Zenoh access-control configuration of a host's router, generated from the system model.

Trust model (federated): every host runs one Zenoh router inside its host agent, and every
other process of the host (nodes, engines, tools) is a client of that router over loopback
TLS. Each router therefore enforces the rules for *its own* clients; the links between
routers (authenticated by their ``agent.<host>`` certificates) are trusted for everything,
as each side has already filtered what its clients may send. The host agent's own session is
the router's, and Zenoh applies access control only to remote transports: the host agent is
not filtered (measured, zenoh 1.10: its queryable, queries and liveliness subscriber work
under ``default_permission: deny``).

Subjects (Zenoh ``access_control/subjects``; certificate common names need TLS links):

- ``agent.<h>`` for every host h of the system: everything (``**``);
- ``engine.<host>`` (the engines this host runs): everything under ``rra/<system>/**``;
- ``operator`` (``rra status``/``param``/``events``, ``rra up``'s control, scenario
  injections): queries to engine control (``engine/**``), puts and queries on ``inject/**``,
  and read-only access (subscribe, liveliness subscribe and query, query) to ``events``,
  ``selection``, ``state``, ``ctx``, ``alive``, ``member``, ``lead``, ``hostagent`` and
  ``data``. Never host or node control: those only the engines may call;
- one subject per node this host may run, matching the certificate ``node.<host>`` AND the
  node's fixed Zenoh id (`rra_agent.bus.config.node_zid`): Zenoh combines the fields of one
  subject with AND (a ``node.<host>`` certificate with another id, or another certificate
  with this id, is not this node; verified in tests/test_security.py).

A node may (keys of `rra_agent.bus.keys`, every run-time variant of the Deployment-time
Configured System Model included: every component, optional run-time ones too, and every
connection, optional run-time ones too; transformations neither add ports nor move
components between hosts):

- put on the keys of its own publisher ports (``data/<topic>``), and be told of the
  subscribers declared on ``data/**`` (a declared Zenoh publisher sends nothing until it
  knows of a matching subscriber; measured: without this, nothing a node published arrived);
- declare subscribers on the keys its subscriber ports can ever be wired to, and on
  ``inject/**`` (`rra_agent.node.NodeContext.subscribe`'s documented use, fault injection),
  and receive puts and deletes there;
- declare its control queryable ``node/<name>/ctl``, receive queries there and reply;
- declare its liveliness token ``alive/<host>/<name>``;
- put on ``reflex/<name>``: a reflex the engines installed in it fired.

A system with a ROS 2 side (``ros2:`` in ``rra.yaml``; docs/ros2.md) also allows, in its
ROS domain D, everything on ``D/**`` (topics and services) and ``@ros2_lv/D/**`` (the graph's
liveliness tokens) to the engines and to each node whose component speaks ROS 2 (a ROS 2
executable's node, which calls its services and relays its inputs; a node with ROS 2
ports), and reading them to the operator (``rra status`` lists the graph). The session of
each ROS 2 executable a node of this host starts (``ros2: PACKAGE EXECUTABLE``, or a
command with a ``ros2:`` section) is a subject of its own: the certificate ``node.<host>``
AND the executable's fixed Zenoh id (`rra_agent.bus.config.ros2_zid`, written into the
session configuration its host agent generates, ``ZENOH_SESSION_CONFIG_URI``), allowed
exactly ``D/**`` and ``@ros2_lv/D/**``, nothing of rra's own keys. Other ROS 2 processes
(not components) join only with a certificate of the system and their own Zenoh
configuration, and are then the subject of that certificate and id.

A component without a ``host`` runs where the Run-time Resolution Engine's leader runs,
which may be any host, so every host's router admits it. Everything else is denied
(``default_permission: deny``).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from rra_agent.bus.config import node_zid, ros2_zid
from rra_agent.bus.keys import Keys
from rra_agent.core.plan import topic_of
from rra_agent.deployment import Deployment
from rra_agent.models.system import (
    Component,
    SystemModel,
    is_ros2_implementation,
    parse_endpoint,
)
from rra_agent.security.certs import OPERATOR, common_name

#: Every message type Zenoh's access control filters (zenoh 1.10 rejects anything else).
ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "declare_queryable",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)
#: What a reader asks for (ingress) and what it is then sent (egress).
_READ_IN = ("declare_subscriber", "declare_liveliness_subscriber", "liveliness_query", "query")
_READ_OUT = ("put", "delete", "reply", "liveliness_token")
#: Keys the operator may read: everything but control.
_OPERATOR_READS = (
    "events",
    "selection",
    "state/**",
    "ctx/**",
    "alive/**",
    "member/**",
    "lead/**",
    "hostagent/**",
    "data/**",
    "reflex/*",
)
#: A host with no name in the model.
DEFAULT_HOST = "local"


def system_hosts(dep: Deployment) -> list[str]:
    """Every host a system may run on: the hosts the template and configured models declare
    and the ``host`` of every component; ``[DEFAULT_HOST]`` for a model that names none."""
    names: set[str] = set()
    for model in (dep.package.system, dep.configured):
        names.update(h.name for h in model.hosts)
        names.update(c.host for c in model.components if c.host)
    return sorted(names) or [DEFAULT_HOST]


@dataclass(frozen=True)
class NodeKeys:
    """The keys one node may ever use, over every run-time variant."""

    name: str
    host: str
    publish: tuple[str, ...]
    subscribe: tuple[str, ...]
    ctl: str
    alive: str
    #: Where it reports a reflex that fired.
    reflex: str = ""


def node_keys(model: SystemModel, component: Component, host: str) -> NodeKeys:
    """What component ``component`` of ``model``, run on ``host``, may publish and subscribe
    to: its publisher ports' topics, and the topics of every connection (optional ones too)
    that can feed one of its subscriber ports."""
    keys = Keys(model.system)
    publish = [
        keys.data(topic_of(model, component.name, p.name))
        for p in component.ports
        if p.direction == "publish"
    ]
    subscribe: list[str] = []
    for conn in model.connections:
        dst = parse_endpoint(conn.target)
        if dst.component == component.name:
            src = parse_endpoint(conn.source)
            key = keys.data(topic_of(model, src.component, src.port))
            if key not in subscribe:
                subscribe.append(key)
    return NodeKeys(
        name=component.name,
        host=host,
        publish=tuple(dict.fromkeys(publish)),
        subscribe=tuple(subscribe),
        ctl=keys.node_ctl(component.name),
        alive=keys.alive(host, component.name),
        reflex=keys.reflex(component.name),
    )


def _rule(
    rule_id: str, messages: Iterable[str], flow: str | Iterable[str], key_exprs: Iterable[str]
) -> dict[str, Any]:
    return {
        "id": rule_id,
        "messages": list(messages),
        "flows": [flow] if isinstance(flow, str) else list(flow),
        "permission": "allow",
        "key_exprs": list(key_exprs),
    }


class _Acl:
    """Collects rules, subjects and policies, one policy per subject."""

    def __init__(self) -> None:
        self.rules: list[dict[str, Any]] = []
        self.subjects: list[dict[str, Any]] = []
        self.policies: list[dict[str, Any]] = []

    def grant(self, subject: dict[str, Any], rules: list[dict[str, Any]]) -> None:
        rules = [r for r in rules if r["key_exprs"]]
        if not rules:
            return
        self.subjects.append(subject)
        self.rules += rules
        self.policies.append(
            {
                "id": subject["id"],
                "rules": [r["id"] for r in rules],
                "subjects": [subject["id"]],
            }
        )

    def config(self) -> dict[str, Any]:
        return {
            "enabled": True,
            "default_permission": "deny",
            "rules": self.rules,
            "subjects": self.subjects,
            "policies": self.policies,
        }


def _node_rules(n: NodeKeys, keys: Keys) -> list[dict[str, Any]]:
    reads = [*n.subscribe, keys.inject_all]
    # a declared publisher sends only where it knows of a subscriber: a node with outputs
    # is told of the subscribers on data keys (wildcard readers such as an operator's too)
    matching = [f"{keys.prefix}/data/**"] if n.publish else []
    matching += [n.reflex] if n.reflex else []
    p = f"node:{n.name}/"
    return [
        _rule(p + "publish", ["put"], "ingress", [*n.publish, *([n.reflex] if n.reflex else [])]),
        _rule(p + "publish-matching", ["declare_subscriber"], "egress", matching),
        _rule(p + "subscribe", ["declare_subscriber"], "ingress", reads),
        _rule(p + "receive", ["put", "delete"], "egress", reads),
        _rule(p + "control", ["declare_queryable", "reply"], "ingress", [n.ctl]),
        _rule(p + "control-queries", ["query"], "egress", [n.ctl]),
        _rule(p + "alive", ["liveliness_token"], "ingress", [n.alive]),
    ]


def ros2_keys(dep: Deployment) -> list[str]:
    """The keys of the system's ROS domain (none without ``ros2:``): its topics and services,
    and the liveliness tokens of its graph."""
    settings = dep.package.manifest.ros2
    if settings is None:
        return []
    return [f"{settings.domain}/**", f"@ros2_lv/{settings.domain}/**"]


def _ros2_rules(rule_id: str, ros2: list[str]) -> list[dict[str, Any]]:
    return [_rule(rule_id, ALL_MESSAGES, ["ingress", "egress"], ros2)]


def _operator_rules(keys: Keys, ros2: Sequence[str] = ()) -> list[dict[str, Any]]:
    control = [f"{keys.prefix}/engine/**", keys.inject_all]
    reads = [f"{keys.prefix}/{k}" for k in _OPERATOR_READS] + list(ros2)
    return [
        _rule("operator/control", ["query"], "ingress", control),
        _rule("operator/control-replies", ["reply"], "egress", control),
        _rule("operator/inject", ["put"], "ingress", [keys.inject_all]),
        _rule("operator/read", _READ_IN, "ingress", reads),
        _rule("operator/read-replies", _READ_OUT, "egress", reads),
    ]


def access_control(dep: Deployment, host: str) -> dict[str, Any]:
    """The Zenoh ``access_control`` object of host ``host``'s router (see the module doc)."""
    model = dep.configured
    keys = Keys(model.system)
    acl = _Acl()
    hosts = sorted({*system_hosts(dep), host})
    acl.grant(
        {"id": "routers", "cert_common_names": [common_name("agent", h) for h in hosts]},
        [_rule("routers/all", ALL_MESSAGES, ["ingress", "egress"], ["**"])],
    )
    ros2 = ros2_keys(dep)
    acl.grant(
        {"id": "engines", "cert_common_names": [common_name("engine", host)]},
        [_rule("engines/all", ALL_MESSAGES, ["ingress", "egress"], [keys.everything, *ros2])],
    )
    acl.grant(
        {"id": "operator", "cert_common_names": [OPERATOR]},
        _operator_rules(keys, ros2),
    )
    for c in model.components:
        if c.host not in (None, host):
            continue
        n = node_keys(model, c, host)
        acl.grant(
            {
                "id": f"node:{c.name}",
                "cert_common_names": [common_name("node", host)],
                "zids": [node_zid(model.system, c.name)],
            },
            _node_rules(n, keys) + (_ros2_rules(f"node:{c.name}/ros2", ros2)
                                    if c.speaks_ros2() else []),
        )
        if runs_ros2_executable(c):
            acl.grant(
                {
                    "id": f"ros2:{c.name}",
                    "cert_common_names": [common_name("node", host)],
                    "zids": [ros2_zid(model.system, c.name)],
                },
                _ros2_rules(f"ros2:{c.name}/domain", ros2),
            )
    return acl.config()


def runs_ros2_executable(component: Component) -> bool:
    """Whether a component's node may start a ROS 2 executable (any of its implementations
    is one): its session is then a subject of its own."""
    return any(is_ros2_implementation(i, component) for i in component.implementations_all)
