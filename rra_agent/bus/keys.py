"""The key-expression layout of an RRA system: the one place that defines it.

::

    rra/<system>/data/<topic>              component data
    rra/<system>/ctx/<measurement>         context dependent measurements
    rra/<system>/selection                 run-time feature selection + CV values
    rra/<system>/events                    adaptation events
    rra/<system>/node/<node>/ctl           node control (queryable)
    rra/<system>/alive/<host>/<node>       liveliness tokens
    rra/<system>/host/<host>/ctl           host agent control (queryable)
    rra/<system>/hostagent/<host>          host agent liveliness token
    rra/<system>/engine/<name>/ctl         engine control/status (queryable): <name> is a
                                           role (its leader answers) or a replica
    rra/<system>/state/<role>              an engine leader's published state
    rra/<system>/member/<role>/<replica>   liveliness token of each engine replica
    rra/<system>/lead/<role>/<epoch>/<replica>/<instance>
                                           liveliness token of the role's leader
                                           (<instance>: its session's Zenoh id)
    rra/<system>/inject/**                 scenario injections (faults, context changes)
    rra/<system>/reflex/<node>             a node's reflex fired
"""

from __future__ import annotations

import re
from dataclasses import dataclass

ROOT = "rra"
_CHUNK = re.compile(r"^[A-Za-z0-9_.\-]+$")


def check_chunk(text: str, what: str = "name") -> str:
    """A name used as one key-expression chunk: no '/', '*', '$', '?', '#' or spaces."""
    if not _CHUNK.match(text):
        raise ValueError(f"{what} {text!r} cannot be used in a key expression")
    return text


def check_topic(topic: str) -> str:
    """A topic may have several chunks (``robot_driver/battery``), each a valid chunk."""
    for part in topic.split("/"):
        check_chunk(part, "topic chunk")
    return topic


@dataclass(frozen=True, slots=True)
class Keys:
    """Key expressions of one system, e.g. ``Keys("object_storing").data("laser/scan")``."""

    system: str

    def __post_init__(self) -> None:
        check_chunk(self.system, "system name")

    @property
    def prefix(self) -> str:
        return f"{ROOT}/{self.system}"

    def data(self, topic: str) -> str:
        return f"{self.prefix}/data/{check_topic(topic)}"

    def ctx(self, measurement: str) -> str:
        return f"{self.prefix}/ctx/{check_chunk(measurement, 'measurement')}"

    @property
    def ctx_all(self) -> str:
        return f"{self.prefix}/ctx/*"

    @property
    def selection(self) -> str:
        return f"{self.prefix}/selection"

    @property
    def events(self) -> str:
        return f"{self.prefix}/events"

    def node_ctl(self, node: str) -> str:
        return f"{self.prefix}/node/{check_chunk(node, 'node name')}/ctl"

    def alive(self, host: str, node: str) -> str:
        return f"{self.prefix}/alive/{check_chunk(host, 'host')}/{check_chunk(node, 'node name')}"

    @property
    def alive_all(self) -> str:
        return f"{self.prefix}/alive/**"

    def host_alive(self, host: str) -> str:
        """The host agent's own liveliness token."""
        return f"{self.prefix}/hostagent/{check_chunk(host, 'host')}"

    @property
    def host_alive_all(self) -> str:
        return f"{self.prefix}/hostagent/*"

    def host_ctl(self, host: str) -> str:
        return f"{self.prefix}/host/{check_chunk(host, 'host')}/ctl"

    def engine_ctl(self, engine: str) -> str:
        return f"{self.prefix}/engine/{check_chunk(engine, 'engine')}/ctl"

    def state(self, role: str) -> str:
        return f"{self.prefix}/state/{check_chunk(role, 'engine role')}"

    def member(self, role: str, replica: str) -> str:
        """An engine replica's liveliness token (``replica`` may be ``*``)."""
        replica = replica if replica == "*" else check_chunk(replica, "replica")
        return f"{self.prefix}/member/{check_chunk(role, 'engine role')}/{replica}"

    def lead(self, role: str) -> str:
        """Prefix of the leader tokens of a role:
        ``.../lead/<role>/<epoch>/<replica>/<instance>``."""
        return f"{self.prefix}/lead/{check_chunk(role, 'engine role')}"

    def inject(self, what: str) -> str:
        return f"{self.prefix}/inject/{check_topic(what)}"

    @property
    def inject_all(self) -> str:
        return f"{self.prefix}/inject/**"

    def reflex(self, node: str) -> str:
        """Where ``node`` reports that a reflex of it fired."""
        return f"{self.prefix}/reflex/{check_chunk(node, 'node name')}"

    @property
    def reflex_all(self) -> str:
        return f"{self.prefix}/reflex/*"

    @property
    def everything(self) -> str:
        return f"{self.prefix}/**"

    def parse_alive(self, key: str) -> tuple[str, str] | None:
        """(host, node) of a liveliness key of this system, else None."""
        head = f"{self.prefix}/alive/"
        if not key.startswith(head):
            return None
        parts = key[len(head) :].split("/")
        return (parts[0], parts[1]) if len(parts) == 2 else None

    def parse_ctx(self, key: str) -> str | None:
        head = f"{self.prefix}/ctx/"
        return key[len(head) :] if key.startswith(head) else None
