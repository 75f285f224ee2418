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
- ``state/<role>``      `StateMessage`    = EngineState
- ``node/<n>/ctl``      `NodeRequest` -> `Reply`
- ``host/<h>/ctl``      `HostRequest` -> `Reply`
- ``engine/<e>/ctl``    `EngineRequest` -> `Reply` (``ForceFeatures``, ``Explain``: the
  Adaptation Engine's; ``Inject``, ``OverrideMeasurement``: the Context Monitor's)
- ``inject/**``         `Injection`
- ``reflex/<n>``        `ReflexMessage`   = ReflexFired

Requests that change the running system carry a `Fence`: the epoch and name of the engine
leader that sends them. A receiver refuses a request whose fence is older than the newest it
has accepted, so a leader that was frozen and resumes cannot act after its successor has.
"""

from __future__ import annotations

import struct
from typing import Annotated, Any, Generic, Literal, TypeVar

import msgspec

from rra_agent.models.measurements import DataType
from rra_agent.models.system import Implementation, ParamType, Scheduling, Supervision
from rra_agent.package.bundle import ModelBundle

T = TypeVar("T")

NodeStateName = Literal[
    "STOPPED", "STARTING", "RUNNING", "UNRESPONSIVE", "BACKOFF", "STOPPING", "EXITED", "FATAL"
]
Level = Literal["debug", "info", "warning", "error"]


class Msg(
    msgspec.Struct, tag_field="t", kw_only=True, omit_defaults=True, forbid_unknown_fields=True
):
    """Base of every wire message."""


class Fence(msgspec.Struct, kw_only=True, forbid_unknown_fields=True, frozen=True):
    """A leader's term: ``epoch`` grows with every change of leader; at equal epochs the
    smaller ``leader`` name wins, then the smaller ``instance``
    (`rra_agent.core.election.newer`)."""

    epoch: int
    leader: str
    #: The leading process: its Zenoh session id, new with every process. Two processes
    #: with one replica name (a second system on the bus, the sides of a partition) never
    #: have the same term.
    instance: str = ""

    @property
    def term(self) -> tuple[int, str, str]:
        return (self.epoch, self.leader, self.instance)

    @classmethod
    def of(cls, term: tuple[int, str, str]) -> Fence:
        return cls(epoch=term[0], leader=term[1], instance=term[2])


# ---- context dependent measurements -------------------------------------------------------
class Measurement(Msg, tag="measurement"):
    name: str
    value: float | int | bool | str
    #: When the monitor computed it (wall clock, seconds since the epoch).
    stamp: float
    #: Send times of the source samples it was computed from, by ``component.port``.
    sources: dict[str, float] = {}
    #: An operator's override (``rra inject measurement``): who set it ("": computed), until
    #: when (wall clock), and the fence of the monitor leader that published it (an override
    #: without its leader's fence is refused).
    override: str = ""
    until: float = 0.0
    fence: Fence | None = None


CtxMessage = Measurement


# ---- run-time selection -----------------------------------------------------------------
class FiredRule(Msg, tag="fired"):
    rule: str
    action: str
    #: ``file:line:col`` of the action in the adaptation model.
    where: str = ""
    #: Measurements the rule read, with the stamps of the values it saw.
    reads: dict[str, float] = {}
    #: ... and the values it saw.
    values: dict[str, float | int | bool | str] = {}
    #: Of those, the values an operator set (``rra inject measurement``): name -> who.
    overrides: dict[str, str] = {}


class Overruled(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """A rule that fired wanting something else for a target, and why it did not prevail."""

    rule: str
    action: str
    where: str = ""
    #: ``on``/``off``, an alternative, or the CV value it computed.
    wants: str = ""
    #: ``priority``, ``later_rule``, ``operator``, ``nfr``, ``bounds``, ``unavailable``,
    #: ``refused`` or ``waiting`` (`rra_agent.core.adaptation.Overruled`).
    why: str
    detail: str = ""


class Why(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """Why a run-time feature or a CV attribute has its value: what changed it last."""

    target: str
    kind: Literal["feature", "cv"]
    #: ``on``/``off``, or the CV value.
    value: str
    #: When that change was decided (nil: before the engine's first change of it).
    since: float | None = None
    #: ``rule``, ``nfr``, ``operator``, ``unavailable``, ``model``, ``default``, ``resumed``.
    reason: str
    #: The rules that made the change, with what they read.
    by: list[FiredRule] = []
    detail: str = ""
    overruled: list[Overruled] = []


class ConflictReport(Msg, tag="conflict"):
    """A run-time conflict: two rules (outside one rule set) whose latest wishes on one
    target differ. Published on ``selection`` once when it starts (``state: started``) and
    once when it ends (``ended``, with its ``duration``); the conflicts in force are also in
    every `Selection` (``conflicts``), so a late subscriber learns the current set."""

    stamp: float
    target: str
    #: The rule that applies (written later) first, then the one overruled.
    rules: list[str]
    resolution: str
    state: Literal["started", "ended"] = "started"
    #: ``kind:target:winner|loser``: the same conflict has the same id when it ends.
    id: str = ""
    kind: str = ""
    #: What each rule wants (``on``/``off``, an alternative, a CV value), by rule.
    wants: dict[str, str] = {}
    #: The actions as written, and where (``file:line:col``), by rule.
    actions: dict[str, str] = {}
    where: dict[str, str] = {}
    #: When it started, and the measurement values the two rules read then.
    since: float = 0.0
    context: dict[str, float | int | bool | str] = {}
    #: Seconds it lasted (``ended`` only).
    duration: float | None = None


class Selection(Msg, tag="selection"):
    seq: int
    stamp: float
    deployment: list[str]
    features: list[str]
    cv: dict[str, float] = {}
    #: True when the selection differs from the previous one (heartbeats repeat it unchanged).
    changed: bool = False
    #: The rules that changed it (not every rule that fired), with what they read.
    cause: list[FiredRule] = []
    rejected: list[str] = []
    #: The Adaptation Engine leader that decided it (a selection from an older leader, or
    #: from nobody, is refused by the Run-time Resolution Engine).
    fence: Fence | None = None
    #: Run-time features an operator forced on (true) or off (false) (``rra select``).
    forced: dict[str, bool] = {}
    #: The run-time conflicts in force (``state: started``).
    conflicts: list[ConflictReport] = []
    #: Each feature and CV value this selection changes, and why (empty on heartbeats).
    why: list[Why] = []
    #: The digest of the models it was decided under (`ModelBundle.digest`): the Run-time
    #: Resolution Engine refuses a selection made under other models than its own.
    models: str = ""


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
    outcome: Literal["ok", "partial", "failed", "rolled_back", ""] = ""
    #: Phase durations in seconds: detect, decide, plan, execute, total.
    durations: dict[str, float] = {}
    seq: int | None = None
    #: The engine leader that acted, and the ``seq`` of the selection it acted on.
    fence: Fence | None = None
    selection: int | None = None
    #: Conflicts: the measurement values that made it.
    context: dict[str, float | int | bool | str] = {}
    #: An adaptation: each feature and CV value it changed, and why (the selection's).
    why: list[Why] = []
    #: Who asked (``user@host``), for operators' requests (``injection``...).
    operator: str = ""
    #: ``injection``: what was injected.
    injection: Inject | None = None


class Failure(
    msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True, frozen=True
):
    """Why a node failed: the exception its code raised (`rra_agent.bus.failure.describe`), as
    the node reported it to its host agent, or, for an external command, which reports
    nothing, the end of its output (``type`` empty)."""

    #: The exception's class (``RuntimeError``; ``pkg.module.Class`` outside builtins).
    type: str = ""
    #: Its message (an external command: its last lines of output).
    message: str = ""
    #: ``file:line`` of the innermost frame of the node's own code (relative to the package).
    where: str = ""
    #: The function of that frame.
    function: str = ""
    #: What the runtime was running: ``import``, ``constructor``, ``on_start``, ``step``...
    during: str = ""
    #: When (wall clock).
    stamp: float = 0.0
    #: The log (on the node's host) that holds the whole traceback.
    log: str = ""


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
    #: `spec_digest` of the spec the host agent (re)starts the node with.
    digest: str = ""
    #: The exception (or external command's output) that caused this transition; in
    #: ``ListNodes``, the node's last failure (``reason``: that failure's reason).
    failure: Failure | None = None


EventMessage = AdaptationEvent | NodeState


# ---- node control -----------------------------------------------------------------------
class Describe(Msg, tag="describe"):
    pass


class Ping(Msg, tag="ping"):
    """A direct probe: the process answers if it is not frozen (any control endpoint)."""


class Stats(Msg, tag="stats"):
    """Ask any process for its `ProcessStats` (received, dropped, rejected counts)."""


class Claim(Msg, tag="claim"):
    """A new leader makes itself known: older fences are refused from now on."""

    fence: Fence


class SetParams(Msg, tag="set_params"):
    params: dict[str, Any]
    fence: Fence | None = None
    #: New declarations (type and bounds) of these parameters, taken before the values are
    #: checked: a reload changed their bounds (``rra reload``).
    decl: dict[str, ParamDecl] = {}


class Rewire(Msg, tag="rewire"):
    port: str
    keys: list[str]
    fence: Fence | None = None


class Activate(Msg, tag="activate"):
    """Start publishing. With ``state``: first take over this exported state (of the node
    being replaced), so a switch with state transfer is one request, not two."""

    state: Any = None
    fence: Fence | None = None


class Deactivate(Msg, tag="deactivate"):
    fence: Fence | None = None


class ExportState(Msg, tag="export_state"):
    pass


class ImportState(Msg, tag="import_state"):
    state: Any
    fence: Fence | None = None


class Shutdown(Msg, tag="shutdown"):
    fence: Fence | None = None


# ---- reflexes (the engines' decisions compiled into the node that switches) -----------------
class ReflexTest(msgspec.Struct, kw_only=True, forbid_unknown_fields=True, frozen=True):
    """One comparison of a reflex's condition: ``measurement op value``."""

    measurement: str
    op: Literal["==", "!=", "<", "<=", ">", ">="]
    value: bool | int | float | str


class ReflexAction(
    msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True, frozen=True
):
    """What the node does when its reflex fires: bind an input ``port`` to ``keys``
    (``rewire``), or start (``activate``) or stop (``deactivate``) publishing; each as the
    control request of the same name would."""

    kind: Literal["rewire", "activate", "deactivate"]
    port: str = ""
    keys: list[str] = []


class Reflex(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """A decision of the engines compiled ahead: when the measurements computed from a sample
    on ``key`` satisfy ``any_of``, the node does ``actions`` at once, then reports it
    (`ReflexFired`). Data only: the node computes each measurement with the function its own
    copy of the package names for it (``measurements.yaml``), never with code from the bus."""

    #: Names this compiled reflex (the same decision in the same configuration: the same id).
    id: str
    #: The rule (``RuleSet.rule`` inside a rule set) and the branch whose decision it is.
    rule: str
    branch: int = 0
    #: The measured interface, ``component.port``, and the data key its samples come on (an
    #: output of this node, or a key one of its inputs listens to).
    source: str
    key: str
    #: The measurements of the package computed from each sample (named, not shipped).
    measurements: list[str]
    #: The condition: it holds when every test of some inner list holds (a measurement that
    #: cannot be computed, or is NaN, makes it false).
    any_of: list[list[ReflexTest]]
    actions: list[ReflexAction]
    #: The run-time selection the engines will decide when it fires (for reports).
    features: list[str] = []


class InstallReflex(Msg, tag="install_reflex"):
    """Arm a reflex (replacing one with the same ``id``); refused (``Err``) when the node
    cannot compute its measurements or has no such port."""

    reflex: Reflex
    fence: Fence | None = None


class WithdrawReflex(Msg, tag="withdraw_reflex"):
    """Disarm the reflex ``id`` (empty: every reflex of the node)."""

    id: str = ""
    fence: Fence | None = None


NodeRequest = (
    Describe
    | SetParams
    | Rewire
    | Activate
    | Deactivate
    | ExportState
    | ImportState
    | Shutdown
    | Ping
    | Stats
    | Claim
    | InstallReflex
    | WithdrawReflex
)


class PortInfo(Msg, tag="port"):
    name: str
    direction: Literal["publish", "subscribe"]
    type: str
    keys: list[str]
    #: Keys listened to without delivering (hot standbys' outputs), see `PortSpec.standby`.
    standby: list[str] = []


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
    rejected: int = 0
    #: Installed reflexes by id: when each fired (wall clock), 0 while armed.
    reflexes: dict[str, float] = {}


class RefusedSamples(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """How many samples of one source the Context Monitor refused for one reason."""

    #: The source interface, ``component.port``.
    source: str
    #: ``malformed``, ``not_a_map``, ``missing_field``, ``wrong_type``, ``non_finite``,
    #: ``implausible`` or ``too_large`` (`rra_agent.core.samples.REASONS`).
    reason: str
    count: int
    #: What was wrong with the newest one.
    last: str = ""


class ProcessStats(Msg, tag="process_stats"):
    """Counters of one process, for ``rra status``: samples and requests received, dropped
    (malformed, too large, or coalesced away under load) and rejected (refused: out of
    bounds, unknown names, stale fences)."""

    name: str
    role: Literal["node", "host", "monitor", "adaptation", "resolution", "tool"]
    pid: int
    received: int = 0
    dropped: int = 0
    rejected: int = 0
    #: Further counters by name (e.g. ``coalesced``, ``published``, ``restarts``).
    counters: dict[str, int] = {}
    #: A node's newest exception in a callback it went on after (``counters["errors"]``).
    failure: Failure | None = None
    #: The Context Monitor: its refused samples, per source and reason.
    refused: list[RefusedSamples] = []


class Ok(Msg, tag="ok"):
    result: Any = None


class Err(Msg, tag="err"):
    message: str
    code: str = "error"
    #: The exception of node code behind it (a hook raised, a component did not load).
    failure: Failure | None = None


Reply = Ok | Err


# ---- node specification (how to start a node) ------------------------------------------
class ParamDecl(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """A parameter's declared type and bounds: every value set at run time is checked
    against them by the node itself (and coerced to the type: a float stays a float)."""

    type: ParamType
    min: float | None = None
    max: float | None = None


class PortSpec(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    direction: Literal["publish", "subscribe"]
    type: str
    #: Publisher: the one key it publishes on. Subscriber: the keys it listens on.
    keys: list[str] = []
    #: Subscriber: keys also listened to but not delivered until a `Rewire` selects them (the
    #: outputs of hot standbys); the newest sample of each is held and delivered at the switch
    #: if it is younger than `REPLAY_MAX_AGE`.
    standby: list[str] = []


def typed_ports(
    node: str, ports: dict[str, PortSpec], declared: dict[str, str]
) -> dict[str, PortSpec]:
    """``ports`` as the model declares them: each of the type ``declared`` says (port name ->
    type); ``ValueError`` for a port the model does not declare."""
    out: dict[str, PortSpec] = {}
    for name, port in ports.items():
        if name not in declared:
            raise ValueError(f"node {node}: port {name!r} is not one the model declares")
        out[name] = msgspec.structs.replace(port, type=declared[name])
    return out


class Ros2Spec(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """A node's ROS 2 side (docs/ros2.md), filled in by its host agent from its own copy of
    the model: the system's ROS domain and distribution, the package's interface files on
    this host, the node's ROS 2 name, and the ROS 2 type of each ROS 2 port.
    ``executable``: the implementation is a ROS 2 executable (started with ``--ros-args``
    and driven through its ROS 2 services), not a node of this protocol; ``lifecycle``,
    ``rewire``, ``timeout``: the component's ``ros2`` section."""

    domain: int = 0
    distro: str = "jazzy"
    interfaces: str | None = None
    #: The system package's folder on this host: where an executable's command runs (its
    #: ``cwd`` is relative to it).
    folder: str | None = None
    node: str
    namespace: str = "/"
    executable: bool = False
    lifecycle: bool = False
    rewire: Literal["relay", "restart"] = "relay"
    timeout: Annotated[float, msgspec.Meta(gt=0.0)] = 1.0
    #: Port -> its ROS 2 message type.
    ports: dict[str, str] = {}


#: The environment variable that hands a node process its `NodeSpec` (JSON) when it is not
#: forked (here, not in the node's modules: the host agent sets it without the Node SDK).
SPEC_ENV = "RRA_NODE_SPEC"


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
    #: Declared type and bounds of each parameter (set_params is checked against them).
    decl: dict[str, ParamDecl] = {}
    supervision: Supervision = Supervision()
    scheduling: Scheduling = Scheduling()
    #: Folders put first on the import path (the system package's, for its own node classes).
    path: list[str] = []
    #: The newest leader fence the host agent has accepted: the node refuses older ones.
    fence: Fence | None = None
    #: Its ROS 2 side, if it has one (set by the host agent).
    ros2: Ros2Spec | None = None
    #: The declared data types its subscriber ports carry, with the types they nest (set by
    #: the host agent from its own copy of the model): each input sample is decoded against
    #: its port's type and refused, counted, if it does not match or is not finite.
    types: list[DataType] = []


# ---- host agent control -----------------------------------------------------------------
class StartNode(Msg, tag="start_node"):
    """Supervise and start a node (replies once spawned; RUNNING follows as a NodeState).
    A node already running with the same spec is left as it is (the reply says so)."""

    spec: NodeSpec
    fence: Fence | None = None


class StopNode(Msg, tag="stop_node"):
    """Stop a node (SIGINT, then SIGTERM, then SIGKILL) and stop supervising it. With a
    ``deadline`` (seconds), the node is killed (SIGKILL) if it has not stopped by then; 0:
    killed at once, without its ``on_stop`` (the strategy's choice, runtime.yaml
    ``replacement: stop_deadline``)."""

    node: str
    fence: Fence | None = None
    deadline: Annotated[float, msgspec.Meta(ge=0.0)] | None = None


class ReplaceNode(Msg, tag="replace_node"):
    """A ``stop-then-start`` swap on one host in one request: stop ``node`` as `StopNode`
    does (with ``deadline``) and start ``spec`` as `StartNode` does, but only once ``node``
    is gone. Meanwhile the replacement's process is prepared (forked, its session opened,
    its data ports declared); none of its code runs before the old node has been reaped.
    With ``export``, the agent first asks ``node`` for its state (`ExportState`) and starts
    ``spec`` with it; a node that does not export it is left running (the reply is an
    `Err`, code ``export``)."""

    node: str
    spec: NodeSpec
    fence: Fence | None = None
    deadline: Annotated[float, msgspec.Meta(ge=0.0)] | None = None
    export: bool = False


class UpdateSpec(Msg, tag="update_spec"):
    """These nodes' params/ports/active flag changed at run time: restart them with these
    specs from now on (the running processes are left alone)."""

    specs: list[NodeSpec]
    fence: Fence | None = None


class SignalNode(Msg, tag="signal_node"):
    """Send a signal to a node process (fault injection: SIGKILL, SIGSTOP, SIGCONT)."""

    node: str
    signal: int


class ListNodes(Msg, tag="list_nodes"):
    pass


class PrepareModels(Msg, tag="prepare_models"):
    """From the Run-time Resolution Engine leader during a reload, to every engine replica
    and host agent: load and check these models and hold them ready (nothing changes yet).
    A host agent also admits what they add from now on (its catalog: both versions)."""

    bundle: ModelBundle
    fence: Fence | None = None


class CommitModels(Msg, tag="commit_models"):
    """From the Run-time Resolution Engine leader once it runs the models ``digest``: a
    host agent keeps only their catalog."""

    digest: str
    fence: Fence | None = None


HostRequest = (
    StartNode | StopNode | ReplaceNode | UpdateSpec | SignalNode | ListNodes | Ping | Stats | Claim
    | PrepareModels | CommitModels
)


# ---- component containers (host agent -> its containers) ----------------------------------
class LoadNode(Msg, tag="load_node"):
    """Load a component into this container and start it (replies once it is ready)."""

    spec: NodeSpec


class UnloadNode(Msg, tag="unload_node"):
    """Stop a component of this container and unload it."""

    node: str


class NodeCall(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    """One component's control request inside a `NodeBatch`."""

    node: str
    request: NodeRequest


class NodeBatch(Msg, tag="node_batch"):
    """Control requests to several components of this container in one query (a switch's
    batch): each is answered as the component's own control endpoint would answer it, and
    the reply is ``Ok`` with the list of those replies, in order."""

    calls: list[NodeCall]


ContainerRequest = LoadNode | UnloadNode | NodeBatch | Ping | Stats | Describe


# ---- scenario injections ----------------------------------------------------------------
class Inject(Msg, tag="inject"):
    """A fault or context change.

    Example: ``{"t": "inject", "kind": "break_motor", "args": {"k": 2}}``. Sent to the
    Context Monitor leader's control (``rra inject``), it is published on ``inject/<kind>``
    and recorded as an ``injection`` event naming ``operator``.
    """

    kind: str
    target: str = ""
    args: dict[str, Any] = {}
    stamp: float = 0.0
    operator: str = ""


Injection = Inject


# ---- engine control ---------------------------------------------------------------------
class Status(Msg, tag="status"):
    pass


class SetParam(Msg, tag="set_param"):
    """An operator sets parameters of a node (``rra param``): they become part of the
    Run-time Configured System Model, are checked against the declared bounds, applied to
    the running node and re-applied whenever it is (re)started. ``reset`` drops earlier
    operator values (back to the model's)."""

    node: str
    params: dict[str, Any] = {}
    reset: list[str] = []
    #: Who asks (``user@host``); with ``injection`` the event is an ``injection`` (``rra
    #: inject set_params``) rather than a ``param`` one.
    operator: str = ""
    injection: bool = False


class GetState(Msg, tag="get_state"):
    """The engine's current `EngineState` (a restarted engine resumes from it)."""


class GetParams(Msg, tag="get_params"):
    """A node's parameters as the Run-time Resolution Engine leader holds them (``rra param
    NODE``): ``Ok`` with ``{"node", "state", "params", "overrides"}``, ``state`` being
    ``running``, ``standby`` (started, inactive) or ``stopped``, and ``params`` the values it
    runs with, or, stopped, the values it will start with (the model's, the CV values', the
    operators'); ``Err`` ``unknown`` for a name that is no component of the system."""

    node: str


class ForceFeatures(Msg, tag="force_features"):
    """An operator forces run-time features of the Adaptation Engine (``rra select``):
    ``on`` or ``off`` until released with ``auto``. The rules cannot change a forced
    feature; the feature model still holds (a refused choice changes nothing). ``operator``
    names who asks (for the ``override`` event)."""

    features: dict[str, Literal["on", "off", "auto"]]
    operator: str = ""


class Retry(Msg, tag="retry"):
    """An operator re-admits unavailable implementations (``rra retry``): the Run-time
    Resolution Engine forgets that they failed, the Adaptation Engine may select the
    features needing them again, and the next plan tries them. ``components`` empty: all."""

    components: list[str] = []
    operator: str = ""


class Explain(Msg, tag="explain"):
    """Ask the Adaptation Engine leader why the run-time features and CV values are what
    they are (``rra why``): ``Ok`` with ``{"why": [Why...]}`` for ``targets`` (empty: all),
    and with ``reachable`` the run-time configurations its rules can reach from the current
    one (``{"reachable": {...}}``)."""

    targets: list[str] = []
    reachable: bool = False


class OverrideMeasurement(Msg, tag="override_measurement"):
    """An operator makes the Context Monitor leader publish ``value`` for measurement
    ``name`` instead of the computed one for ``duration`` seconds (``rra inject
    measurement``); 0 ends an override at once. Refused for an unknown measurement or a value
    its declaration does not admit."""

    name: str
    value: float | int | bool | str
    duration: Annotated[float, msgspec.Meta(ge=0.0, le=86400.0)]
    operator: str = ""


class Reload(Msg, tag="reload"):
    """An operator's edited models for the running system (``rra reload``), to the Run-time
    Resolution Engine leader: checked (what cannot change live is refused, nothing changed),
    prepared by every engine replica and host agent, then taken by all at once. ``base``: the
    digest of the models the operator's diff was made against (refused if they changed
    since). ``undo``: go back to the models before the last reload (no ``bundle``)."""

    bundle: ModelBundle | None = None
    base: str = ""
    undo: bool = False
    operator: str = ""


class GetModels(Msg, tag="get_models"):
    """The model files of one version (``digest``; empty: the current one), as a bundle."""

    digest: str = ""


EngineRequest = (
    Status
    | Describe
    | Ping
    | Stats
    | SetParam
    | GetState
    | GetParams
    | ForceFeatures
    | Retry
    | Explain
    | Inject
    | OverrideMeasurement
    | Reload
    | GetModels
    | PrepareModels
)


# ---- engine state -----------------------------------------------------------------------
class Unavailable(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """An implementation of a component that cannot start or keeps crashing: the engines
    decide without the features that need it until a probe (a start, then a stop) succeeds
    or an operator re-admits it (``rra retry``)."""

    component: str
    #: The key of the implementation in the component's ``implementations`` ("": its own).
    implementation: str = ""
    #: Why (the last failure: the node's exception, or what its host agent saw).
    reason: str
    #: Since when (wall clock), after how many failures, and when the next probe is due.
    since: float
    failures: int = 1
    probe_at: float = 0.0


class EngineState(Msg, tag="engine_state"):
    """The Run-time Configured System Model as the Run-time Resolution Engine leader holds
    it: published on ``state/resolution`` whenever it changes, so a standby engine mirrors
    it and takes over from it, and a restarted Adaptation Engine resumes from its selection.
    """

    fence: Fence
    #: Grows with every change published by this leader.
    version: int
    selection: list[str]
    cv: dict[str, float] = {}
    #: Parameters set by operators, by node.
    overrides: dict[str, dict[str, Any]] = {}
    #: ``seq`` of the last selection applied, and the Adaptation Engine leader that sent it
    #: (selections with older fences are refused).
    applied: int = 0
    selection_fence: Fence | None = None
    running: list[NodeSpec] = []
    standby: list[NodeSpec] = []
    #: Run-time features forced by operators and the conflicts in force, as the Adaptation
    #: Engine leader last published them (a restarted Adaptation Engine resumes from them).
    forced: dict[str, bool] = {}
    conflicts: list[ConflictReport] = []
    #: What is in effect: the run-time selection and CV values the running system shows
    #: (``selection`` and ``cv`` are what was decided; they differ while a plan is applied
    #: in part, e.g. a node that cannot start).
    effective: list[str] = []
    effective_cv: dict[str, float] = {}
    #: Implementations that are unavailable (failure as context).
    unavailable: list[Unavailable] = []
    #: Why the running system differs from the decision (the failed steps), if it does.
    degraded: list[str] = []
    #: When this state was made (wall clock).
    stamp: float = 0.0
    #: Reflexes installed in nodes (armed, or fired and not yet confirmed).
    reflexes: list[ReflexRecord] = []
    #: The digest of the models the engines run (`ModelBundle.digest`), and those before
    #: it, newest last (``rra reload --undo`` goes back to the last one).
    models: str = ""
    history: list[str] = []
    #: Whether the leader has deployed the system. A leader that has just claimed answers
    #: ``GetState`` before its first deployment: a replica that takes over from that state
    #: deploys the system itself rather than continuing from it.
    deployed: bool = True


StateMessage = EngineState


# ---- reflexes fired: ``reflex/<node>`` ----------------------------------------------------
class ReflexFired(Msg, tag="reflex_fired"):
    """A node's reflex fired: it did its actions (those that failed are in ``failed``); the
    Run-time Resolution Engine confirms it with the engines' own decision or rolls it back."""

    node: str
    id: str
    rule: str
    #: When it fired (the node's wall clock) and the send time of the sample it fired on.
    stamp: float
    sample: float | None = None
    #: The measurement values it fired on.
    values: dict[str, bool | int | float | str] = {}
    #: Actions that could not be done, and why (empty: all were done).
    failed: list[str] = []


ReflexMessage = ReflexFired


class ReflexRecord(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """A reflex the Run-time Resolution Engine leader installed, in its state (``rra status``;
    a standby that takes over goes on from it)."""

    id: str
    rule: str
    #: Where it is armed (every node with a part of the switch).
    nodes: list[str]
    #: The run-time selection the engines are expected to decide when it fires.
    features: list[str]
    #: What each node does when it fires (what a rollback undoes).
    actions: dict[str, list[ReflexAction]] = {}
    #: The run-time selection it was compiled in (its switch changes it to ``features``).
    before: list[str] = []
    #: When it fired (0: armed), and by which nodes.
    fired: float = 0.0
    fired_by: list[str] = []


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


def spec_digest(spec: NodeSpec) -> str:
    """What a node is configured to be (implementation, host, parameters, wiring, active),
    as a short hash: equal digests, equal configurations. The state to take over, the fence
    and the import path (each host derives it from its own copy of the package) are not
    part of it, nor its ROS 2 side and its data types (each host derives them from its
    model, like the path)."""
    fixed = msgspec.structs.replace(spec, state=None, fence=None, path=[], ros2=None, types=[])
    return _short_hash(fixed)


def implementation_id(impl: Implementation | NodeSpec) -> str:
    """How an implementation is shown on the bus: a Python class by its dotted path, an
    external command by a hash (its command line and environment are not disclosed)."""
    if isinstance(impl, NodeSpec):
        impl = impl.implementation
    return impl if isinstance(impl, str) else f"command:{_short_hash(impl)}"


def _short_hash(obj: Any) -> str:
    import hashlib

    return hashlib.blake2b(_DIGEST_ENC.encode(obj), digest_size=8).hexdigest()


_DIGEST_ENC = msgspec.msgpack.Encoder(order="sorted")


def pack_stamp(t: float) -> bytes:
    return _STAMP.pack(t)


def unpack_stamp(data: bytes | None) -> float | None:
    if data is None or len(data) != 8:
        return None
    return _STAMP.unpack(data)[0]
