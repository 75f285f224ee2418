"""Wire messages: tagged msgspec Structs, one union per channel, msgpack-encoded.

Each Struct is a msgpack map with a ``"t"`` tag field naming its type (e.g.
``{"t": "rewire", "port": "in", "keys": [...]}``), so a node in another language decodes
them with any msgpack library (see docs/protocol.md). Component *data* samples are not
wrapped: they are plain msgpack maps of the data type's fields, with the sender's wall-clock
time as an 8-byte little-endian float64 attachment.

Channels and their unions:

- ``ctx/<m>``           `CtxMessage`      = Measurement
- ``selection``         `SelectionMessage` = Selection | ConflictReport
- ``events``            `EventMessage`    = AdaptationEvent | NodeState
- ``node/<n>/ctl``      `NodeRequest` -> `Reply`
- ``host/<h>/ctl``      `HostRequest` -> `Reply`
- ``engine/<e>/ctl``    `EngineRequest` -> `Reply`
- ``inject/**``         `Injection`
"""

from __future__ import annotations

import struct
from typing import Any, Generic, Literal, TypeVar

import msgspec

from rra_agent.models.system import Implementation

T = TypeVar("T")

NodeStateName = Literal["STOPPED", "STARTING", "RUNNING", "BACKOFF", "STOPPING", "EXITED", "FATAL"]
Level = Literal["debug", "info", "warning", "error"]


class Msg(
    msgspec.Struct, tag_field="t", kw_only=True, omit_defaults=True, forbid_unknown_fields=True
):
    """Base of every wire message."""


# ---- context dependent measurements -------------------------------------------------------
class Measurement(Msg, tag="measurement"):
    name: str
    value: float | int | bool | str
    #: When the monitor computed it (wall clock, seconds since the epoch).
    stamp: float
    #: Send times of the source samples it was computed from, by ``component.port``.
    sources: dict[str, float] = {}


CtxMessage = Measurement


# ---- run-time selection -----------------------------------------------------------------
class FiredRule(Msg, tag="fired"):
    rule: str
    action: str
    #: ``file:line:col`` of the action in the adaptation model.
    where: str = ""
    #: Measurements the rule read, with the stamps of the values it saw.
    reads: dict[str, float] = {}


class Selection(Msg, tag="selection"):
    seq: int
    stamp: float
    deployment: list[str]
    features: list[str]
    cv: dict[str, float] = {}
    #: True when the selection differs from the previous one (heartbeats repeat it unchanged).
    changed: bool = False
    cause: list[FiredRule] = []
    rejected: list[str] = []


class ConflictReport(Msg, tag="conflict"):
    stamp: float
    target: str
    rules: list[str]
    resolution: str


SelectionMessage = Selection | ConflictReport


# ---- adaptation events ------------------------------------------------------------------
class AdaptationEvent(Msg, tag="event"):
    stamp: float
    kind: str
    message: str
    level: Level = "info"
    source: str = ""
    node: str | None = None
    cause: list[FiredRule] = []
    plan: list[str] = []
    outcome: Literal["ok", "failed", "rolled_back", ""] = ""
    #: Phase durations in seconds: detect, decide, plan, execute, total.
    durations: dict[str, float] = {}
    seq: int | None = None


class NodeState(Msg, tag="node_state"):
    stamp: float
    node: str
    host: str
    state: NodeStateName
    previous: NodeStateName | None = None
    pid: int | None = None
    implementation: str = ""
    active: bool = True
    restarts: int = 0
    reason: str = ""


EventMessage = AdaptationEvent | NodeState


# ---- node control -----------------------------------------------------------------------
class Describe(Msg, tag="describe"):
    pass


class SetParams(Msg, tag="set_params"):
    params: dict[str, Any]


class Rewire(Msg, tag="rewire"):
    port: str
    keys: list[str]


class Activate(Msg, tag="activate"):
    """Start publishing. With ``state``: first take over this exported state (of the node
    being replaced), so a switch with state transfer is one request, not two."""

    state: Any = None


class Deactivate(Msg, tag="deactivate"):
    pass


class ExportState(Msg, tag="export_state"):
    pass


class ImportState(Msg, tag="import_state"):
    state: Any


class Shutdown(Msg, tag="shutdown"):
    pass


NodeRequest = (
    Describe | SetParams | Rewire | Activate | Deactivate | ExportState | ImportState | Shutdown
)


class PortInfo(Msg, tag="port"):
    name: str
    direction: Literal["publish", "subscribe"]
    type: str
    keys: list[str]


class NodeInfo(Msg, tag="node_info"):
    name: str
    implementation: str
    pid: int
    host: str
    active: bool
    params: dict[str, Any]
    ports: list[PortInfo]
    received: int = 0
    published: int = 0
    dropped: int = 0


class Ok(Msg, tag="ok"):
    result: Any = None


class Err(Msg, tag="err"):
    message: str
    code: str = "error"


Reply = Ok | Err


# ---- node specification (how to start a node) ------------------------------------------
class PortSpec(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    direction: Literal["publish", "subscribe"]
    type: str
    #: Publisher: the one key it publishes on. Subscriber: the keys it listens on.
    keys: list[str] = []


class NodeSpec(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """Everything a node process needs; passed as JSON in ``RRA_NODE_SPEC``."""

    system: str
    name: str
    host: str
    implementation: Implementation
    params: dict[str, Any] = {}
    ports: dict[str, PortSpec] = {}
    active: bool = True
    #: Exported state of a node this one replaces.
    state: Any = None


# ---- host agent control -----------------------------------------------------------------
class StartNode(Msg, tag="start_node"):
    """Supervise and start a node (replies once spawned; RUNNING follows as a NodeState)."""

    spec: NodeSpec


class StopNode(Msg, tag="stop_node"):
    """Stop a node (SIGINT, then SIGTERM, then SIGKILL) and stop supervising it."""

    node: str


class UpdateSpec(Msg, tag="update_spec"):
    """These nodes' params/ports/active flag changed at run time: restart them with these
    specs from now on (the running processes are left alone)."""

    specs: list[NodeSpec]


class SignalNode(Msg, tag="signal_node"):
    """Send a signal to a node process (fault injection: SIGKILL, SIGSTOP, SIGCONT)."""

    node: str
    signal: int


class ListNodes(Msg, tag="list_nodes"):
    pass


HostRequest = StartNode | StopNode | UpdateSpec | SignalNode | ListNodes


# ---- engine control ---------------------------------------------------------------------
class Status(Msg, tag="status"):
    pass


EngineRequest = Status | Describe


# ---- scenario injections ----------------------------------------------------------------
class Inject(Msg, tag="inject"):
    """A fault or context change.

    Example: ``{"t": "inject", "kind": "break_motor", "args": {"k": 2}}``.
    """

    kind: str
    target: str = ""
    args: dict[str, Any] = {}
    stamp: float = 0.0


Injection = Inject


# ---- codecs -----------------------------------------------------------------------------
class Codec(Generic[T]):
    """One reused encoder/decoder pair for one message union."""

    __slots__ = ("_dec", "_enc")

    def __init__(self, type_: Any) -> None:
        self._enc = msgspec.msgpack.Encoder()
        self._dec = msgspec.msgpack.Decoder(type_)

    def encode(self, msg: Any) -> bytes:
        return self._enc.encode(msg)

    def decode(self, data: bytes | bytearray | memoryview) -> T:
        """Decode or raise `msgspec.DecodeError`/`ValidationError` (callers count and drop)."""
        return self._dec.decode(data)


_STAMP = struct.Struct("<d")


def pack_stamp(t: float) -> bytes:
    return _STAMP.pack(t)


def unpack_stamp(data: bytes | None) -> float | None:
    if data is None or len(data) != 8:
        return None
    return _STAMP.unpack(data)[0]
