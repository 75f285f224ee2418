"""rmw_zenoh's graph: liveliness tokens of nodes, publishers, subscriptions, services, clients.

Every ROS 2 entity declares one liveliness token while it exists::

    @ros2_lv/<domain>/<zid>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node>
        [/<name>/<DDS type>/<type hash>/<qos>]        (all but nodes)

``kind`` is NN (node), MP (publisher), MS (subscription), SS (service server) or SC
(service client); enclave, namespace and name are written with ``/`` as ``%``; a node's own
token has its node id twice. ``qos`` is rmw_zenoh's compact QoS (`Qos`). `parse_token`
refuses anything else with a `BadToken` (it never raises anything else), so a peer with odd
tokens is counted, not a crash.
"""

from __future__ import annotations

import enum
import re
from dataclasses import dataclass, field

from rra_agent.ros2.errors import BadName, BadToken
from rra_agent.ros2.names import (
    check_domain,
    check_namespace,
    check_node_name,
    check_type_hash,
    dds_type,
    demangle,
    mangle,
    qualify,
    ros_type,
)

ADMIN_SPACE = "@ros2_lv"
_ZID = re.compile(r"[0-9a-f]{1,32}")
_UINT = re.compile(r"[0-9]{1,19}")


class Kind(enum.StrEnum):
    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


#: rmw's infinite duration (seconds, nanoseconds): RMW_DURATION_INFINITE.
INFINITE = (9223372036, 854775807)
# rmw/types.h enum values that a token may carry.
RELIABILITY = {"system_default": 0, "reliable": 1, "best_effort": 2, "best_available": 4}
DURABILITY = {"system_default": 0, "transient_local": 1, "volatile": 2, "best_available": 4}
HISTORY = {"system_default": 0, "keep_last": 1, "keep_all": 2}
LIVELINESS = {"system_default": 0, "automatic": 1, "manual_by_topic": 3, "best_available": 5}


@dataclass(frozen=True, slots=True)
class Qos:
    """A QoS profile as rmw_zenoh encodes it; the defaults are rmw_zenoh's (reliable,
    volatile, keep last 42, no deadline, no lifespan, automatic liveliness)."""

    reliability: int = 1
    durability: int = 2
    history: int = 1
    depth: int = 42
    deadline: tuple[int, int] = INFINITE
    lifespan: tuple[int, int] = INFINITE
    liveliness: int = 1
    lease: tuple[int, int] = INFINITE

    def encode(self) -> str:
        """``<rel>:<dur>:<hist>,<depth>:<s>,<ns>:<s>,<ns>:<liv>,<s>,<ns>``, defaults left empty."""
        d = Qos()

        def f(value: object, default: object) -> str:
            return "" if value == default else str(value)

        def dur(value: tuple[int, int], default: tuple[int, int]) -> str:
            return f"{f(value[0], default[0])},{f(value[1], default[1])}"

        return ":".join(
            [
                f(self.reliability, d.reliability),
                f(self.durability, d.durability),
                f"{f(self.history, d.history)},{f(self.depth, d.depth)}",
                dur(self.deadline, d.deadline),
                dur(self.lifespan, d.lifespan),
                f"{f(self.liveliness, d.liveliness)},{dur(self.lease, d.lease)}",
            ]
        )

    @classmethod
    def decode(cls, text: str) -> Qos:
        """The inverse of `encode`; `BadToken` for anything else."""
        parts = text.split(":")
        if len(parts) != 6:
            raise BadToken(f"QoS {text!r} does not have 6 ':'-separated fields")
        hist, dl, ls, liv = (p.split(",") for p in parts[2:])
        if len(hist) != 2 or len(dl) != 2 or len(ls) != 2 or len(liv) != 3:
            raise BadToken(f"QoS {text!r} has a field with the wrong number of ',' parts")
        d = cls()
        return cls(
            reliability=_enum(parts[0], d.reliability, RELIABILITY, text),
            durability=_enum(parts[1], d.durability, DURABILITY, text),
            history=_enum(hist[0], d.history, HISTORY, text),
            depth=_uint(hist[1], d.depth, text),
            deadline=(_uint(dl[0], d.deadline[0], text), _uint(dl[1], d.deadline[1], text)),
            lifespan=(_uint(ls[0], d.lifespan[0], text), _uint(ls[1], d.lifespan[1], text)),
            liveliness=_enum(liv[0], d.liveliness, LIVELINESS, text),
            lease=(_uint(liv[1], d.lease[0], text), _uint(liv[2], d.lease[1], text)),
        )

    def describe(self) -> str:
        """e.g. ``reliable volatile keep_last(42)``."""
        name = {v: k for k, v in RELIABILITY.items()}.get(self.reliability, "?")
        dur = {v: k for k, v in DURABILITY.items()}.get(self.durability, "?")
        hist = "keep_all" if self.history == 2 else f"keep_last({self.depth})"
        return f"{name} {dur} {hist}"


def _uint(chunk: str, default: int, text: str) -> int:
    if chunk == "":
        return default
    if not _UINT.fullmatch(chunk):
        raise BadToken(f"QoS {text!r}: {chunk!r} is not a number")
    return int(chunk)


def _enum(chunk: str, default: int, allowed: dict[str, int], text: str) -> int:
    value = _uint(chunk, default, text)
    if value not in allowed.values():
        raise BadToken(f"QoS {text!r}: {value} is not one of {sorted(allowed.values())}")
    return value


@dataclass(frozen=True, slots=True)
class Token:
    """One graph entity, as its liveliness token says."""

    domain: int
    zid: str
    node_id: int
    entity_id: int
    kind: Kind
    node: str
    namespace: str = "/"
    enclave: str = "/"
    #: Topic or service (fully qualified), its ROS type (``pkg/srv/Name`` for services),
    #: type hash and QoS: None for a node's own token.
    name: str | None = None
    ros_type: str | None = None
    type_hash: str | None = None
    qos: Qos | None = field(default=None)

    @property
    def key(self) -> str:
        """The liveliness key expression of this entity."""
        head = [
            ADMIN_SPACE,
            str(self.domain),
            self.zid,
            str(self.node_id),
            str(self.entity_id),
            self.kind.value,
            mangle(self.enclave),
            mangle(self.namespace),
            self.node,
        ]
        if self.kind is Kind.NODE:
            return "/".join(head)
        assert self.name and self.ros_type and self.type_hash and self.qos
        tail = [mangle(self.name), dds_type(self.ros_type), self.type_hash, self.qos.encode()]
        return "/".join(head + tail)

    @property
    def node_key(self) -> tuple[int, str, int]:
        """What identifies this entity's node: (domain, zid, node id)."""
        return (self.domain, self.zid, self.node_id)

    @property
    def fq_node(self) -> str:
        """The node's fully qualified name, e.g. ``/robot1/battery_node``."""
        return f"{self.namespace.rstrip('/')}/{self.node}"


def node_token(domain: int, zid: str, node_id: int, node: str, namespace: str = "/") -> Token:
    return Token(check_domain(domain), zid, node_id, node_id, Kind.NODE,
                 check_node_name(node), check_namespace(namespace))


def parse_token(key: str) -> Token:
    """The `Token` of a liveliness key expression; `BadToken` if it is not one."""
    parts = str(key).split("/")
    if len(parts) not in (9, 13) or parts[0] != ADMIN_SPACE:
        raise BadToken(f"{key!r} is not an rmw_zenoh liveliness token (9 or 13 chunks)")
    try:
        kind = Kind(parts[5])
    except ValueError:
        raise BadToken(f"{key!r}: unknown entity kind {parts[5]!r}") from None
    if (kind is Kind.NODE) != (len(parts) == 9):
        raise BadToken(f"{key!r}: a {kind.value} token has the wrong number of chunks")
    if not (parts[1].isdigit() and _ZID.fullmatch(parts[2])):
        raise BadToken(f"{key!r}: bad domain id or Zenoh id")
    if not (_UINT.fullmatch(parts[3]) and _UINT.fullmatch(parts[4])):
        raise BadToken(f"{key!r}: bad node or entity id")
    enclave = demangle(parts[6])
    if not enclave.startswith("/"):
        raise BadToken(f"{key!r}: bad enclave {parts[6]!r}")
    try:
        head = dict(
            domain=check_domain(int(parts[1])),
            zid=parts[2],
            node_id=int(parts[3]),
            entity_id=int(parts[4]),
            kind=kind,
            node=check_node_name(parts[8]),
            namespace=check_namespace(demangle(parts[7])),
            enclave=enclave,
        )
        if kind is Kind.NODE:
            return Token(**head)  # type: ignore[arg-type]
        return Token(
            **head,  # type: ignore[arg-type]
            name=qualify(demangle(parts[9])),
            ros_type=ros_type(parts[10]),
            type_hash=check_type_hash(parts[11]),
            qos=Qos.decode(parts[12]),
        )
    except (BadName, BadToken) as e:
        raise BadToken(f"{key!r}: {e}") from None
