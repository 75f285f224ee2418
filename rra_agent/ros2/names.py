"""ROS 2 names, type names and the key expressions rmw_zenoh puts data on.

A topic or service ``/ns/name`` of type ``pkg/msg/Type`` in ROS domain ``D`` is the Zenoh
key ``D/ns/name/pkg::msg::dds_::Type_/<type hash>``: the fully qualified name without its
leading slash, the type's DDS name (what CDR type support calls it) and its RIHS01 type
hash (``TypeHashNotSupported`` from Humble, which has no type hashes). Pure functions; a
bad name is a `BadName`, a key that is not such a data key a `BadToken`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from rra_agent.ros2.errors import BadName, BadToken

#: What a Humble peer puts where the type hash goes.
NO_TYPE_HASH = "TypeHashNotSupported"
_TOKEN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_NODE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_PKG = re.compile(r"[a-z][a-z0-9_]*")
_TYPE_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
_HASH = re.compile(r"RIHS01_[0-9a-f]{64}")
_DDS = re.compile(r"([a-z][a-z0-9_]*)::(msg|srv|action)::dds_::([A-Za-z][A-Za-z0-9_]*)_")


def qualify(name: str, namespace: str = "/") -> str:
    """The fully qualified form of a topic or service name (a relative name goes under
    ``namespace``); `BadName` unless every token is ``[A-Za-z_][A-Za-z0-9_]*``."""
    if not isinstance(name, str) or not name:
        raise BadName("a ROS 2 name must be a non-empty string")
    if name.startswith("~") or "{" in name:
        raise BadName(f"ROS 2 name {name!r}: '~' and substitutions are not supported here")
    full = name if name.startswith("/") else f"{check_namespace(namespace).rstrip('/')}/{name}"
    tokens = full[1:].split("/")
    if name.endswith("/") or not all(_TOKEN.fullmatch(t) for t in tokens):
        raise BadName(
            f"ROS 2 name {name!r} is not valid: tokens of letters, digits and '_', not starting "
            "with a digit, separated by single '/'"
        )
    return full


def check_namespace(namespace: str) -> str:
    """``/`` or a fully qualified name; `BadName` otherwise."""
    if namespace == "/":
        return namespace
    if not isinstance(namespace, str) or not namespace.startswith("/"):
        raise BadName(f"ROS 2 namespace {namespace!r} must start with '/'")
    return qualify(namespace)


def check_node_name(name: str) -> str:
    """A node's base name: ``[A-Za-z_][A-Za-z0-9_]*``; `BadName` otherwise."""
    if not isinstance(name, str) or not _NODE.fullmatch(name):
        raise BadName(f"ROS 2 node name {name!r} is not valid: letters, digits and '_' only")
    return name


def check_type_name(ros_type: str, kind: str | None = None) -> tuple[str, str, str]:
    """``pkg/msg/Type`` -> (pkg, "msg", Type); ``kind`` ("msg" or "srv") when it must be one."""
    parts = ros_type.split("/") if isinstance(ros_type, str) else []
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if (
        len(parts) != 3
        or not _PKG.fullmatch(parts[0])
        or parts[1] not in ("msg", "srv", "action")
        or not _TYPE_NAME.fullmatch(parts[2])
    ):
        raise BadName(f"ROS 2 type {ros_type!r} is not of the form package/msg/Type")
    if kind is not None and parts[1] != kind:
        raise BadName(f"ROS 2 type {ros_type!r} is not a {kind} type (package/{kind}/Name)")
    return parts[0], parts[1], parts[2]


def dds_type(ros_type: str) -> str:
    """``std_msgs/msg/String`` -> ``std_msgs::msg::dds_::String_`` (the key's type chunk)."""
    pkg, kind, name = check_type_name(ros_type)
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str:
    """``std_msgs::msg::dds_::String_`` -> ``std_msgs/msg/String``; `BadToken` otherwise."""
    m = _DDS.fullmatch(dds)
    if m is None:
        raise BadToken(f"{dds!r} is not a DDS type name (package::msg::dds_::Type_)")
    return f"{m[1]}/{m[2]}/{m[3]}"


def check_type_hash(type_hash: str) -> str:
    if not (type_hash == NO_TYPE_HASH or _HASH.fullmatch(type_hash)):
        raise BadToken(f"{type_hash!r} is not a type hash (RIHS01_<64 hex> or {NO_TYPE_HASH})")
    return type_hash


def check_domain(domain: int) -> int:
    """A ROS domain id: an int from 0 to 232 (what ROS 2 accepts)."""
    if isinstance(domain, bool) or not isinstance(domain, int) or not 0 <= domain <= 232:
        raise BadName(f"ROS domain id {domain!r} must be an integer from 0 to 232")
    return domain


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` written ``%`` (``/`` alone is ``%``)."""
    return name.replace("/", "%")


def demangle(chunk: str) -> str:
    return chunk.replace("%", "/")


@dataclass(frozen=True, slots=True)
class DataKey:
    """Where a topic's samples (or a service's calls) travel."""

    domain: int
    name: str  #: fully qualified, e.g. ``/battery``
    ros_type: str  #: e.g. ``sensor_msgs/msg/BatteryState`` (``pkg/srv/Name`` for a service)
    type_hash: str

    @property
    def key(self) -> str:
        return f"{self.domain}/{self.name[1:]}/{dds_type(self.ros_type)}/{self.type_hash}"

    @property
    def any_type(self) -> str:
        """This name with any type and hash: to see samples of a wrong type too."""
        return f"{self.domain}/{self.name[1:]}/*/*"


def data_key(domain: int, name: str, ros_type_name: str, type_hash: str) -> DataKey:
    check_type_name(ros_type_name)
    return DataKey(check_domain(domain), qualify(name), ros_type_name, check_type_hash(type_hash))


def parse_data_key(key: str) -> DataKey:
    """``0/battery/sensor_msgs::msg::dds_::BatteryState_/RIHS01_...`` -> its `DataKey`."""
    parts = str(key).split("/")
    if len(parts) < 4 or not parts[0].isdigit():
        raise BadToken(f"{key!r} is not a ROS 2 data key (<domain>/<name>/<type>/<hash>)")
    try:
        return DataKey(
            check_domain(int(parts[0])),
            qualify("/" + "/".join(parts[1:-2])),
            ros_type(parts[-2]),
            check_type_hash(parts[-1]),
        )
    except BadName as e:
        raise BadToken(f"{key!r}: {e}") from None
