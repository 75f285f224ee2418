"""A node's typed inputs: a subscriber port whose type is a declared data type hands the node
only samples of that type, with finite numbers outside the type's ``non_finite`` fields.
What else comes is refused and counted per reason, and never displaces a hot standby's held
sample. The host agent takes the ports' types and the data types from its own model, never
from the request. No bus: `NodeHarness` and `NodeCore` as the node process runs them."""

from __future__ import annotations

import math
from typing import Any

import msgspec
import pytest
from conftest import ROOT

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import RateLimitedLog
from rra_agent.bus.data import encode_data
from rra_agent.core.samples import Refusal, SampleTypes, nested
from rra_agent.deployment import deploy
from rra_agent.host.catalog import Catalog, Refused
from rra_agent.models.measurements import DataType
from rra_agent.node import Node, NodeError, NodeHarness
from rra_agent.node.container import ContainerRuntime
from rra_agent.node.core import NodeCore

TYPES = [
    DataType(name="Pose", fields={"x": "float", "y": "float"}),
    DataType(
        name="Cmd",
        fields={"seq": "int", "speeds": "list[float]", "pose": "Pose", "note": "str"},
        optional=["note"],
    ),
    DataType(
        name="Scan", fields={"angle": "float", "ranges": "list[float]"}, non_finite=["ranges"]
    ),
    DataType(name="Unused", fields={"a": "int"}),
]
GOOD = {"seq": 1, "speeds": [1.0, 2], "pose": {"x": 0.0, "y": 1.0}}
#: Reason -> samples of Cmd a typed input refuses.
BAD: dict[str, list[Any]] = {
    "missing_field": [{"seq": 1, "speeds": [1.0]}],
    "wrong_type": [
        {**GOOD, "seq": "1"},
        {**GOOD, "seq": True},
        {**GOOD, "speeds": [True]},
        {**GOOD, "seq": 1.5},
    ],
    "non_finite": [
        {**GOOD, "speeds": [1.0, math.nan]},
        {**GOOD, "pose": {"x": -math.inf, "y": 0}},
        {**GOOD, "speeds": [math.inf]},
    ],
    "not_a_map": [[1, 2]],
}


class Recorder(Node):
    def on_start(self) -> None:
        self.got: list[dict[str, Any]] = []

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        self.got.append(data)


def harness(port_type: str = "Cmd") -> NodeHarness:
    return NodeHarness(Recorder, ports={"in": ("subscribe", port_type)}, types=TYPES)


# ---- the decoders ------------------------------------------------------------------------
@pytest.mark.parametrize("reason", BAD)
def test_a_finite_decoder_refuses_each_bad_sample_for_its_reason(reason):
    cmd = SampleTypes(TYPES, finite=True).for_port("Cmd")
    for sample in BAD[reason]:
        got = cmd.decode("c.in", encode_data(sample))
        assert isinstance(got, Refusal) and got.reason == reason, (sample, got)


def test_a_non_finite_number_is_refused_with_where_it_is():
    cmd = SampleTypes(TYPES, finite=True).for_port("Cmd")
    got = cmd.decode("c.in", encode_data({**GOOD, "speeds": [1.0, math.nan]}))
    assert (got.reason, got.detail) == ("non_finite", "Cmd: $.speeds[1] is not finite")  # type: ignore[union-attr]


def test_only_the_fields_a_type_lists_as_non_finite_may_be_so():
    scan = SampleTypes(TYPES, finite=True).for_port("Scan")
    assert scan.decode("s", encode_data({"angle": 0.1, "ranges": [math.inf, 1.0]})) == {
        "angle": 0.1,
        "ranges": [math.inf, 1.0],
    }
    refused = scan.decode("s", encode_data({"angle": math.nan, "ranges": []}))
    assert getattr(refused, "reason", None) == "non_finite"


def test_the_monitor_s_decoders_leave_non_finite_numbers_to_its_measurements():
    cmd = SampleTypes(TYPES).for_port("Cmd")  # finite=False, as the Context Monitor's
    got = cmd.decode("c.in", encode_data({**GOOD, "speeds": [math.nan]}))
    assert isinstance(got, dict) and math.isnan(got["speeds"][0])


def test_nested_types_are_what_a_reader_of_the_ports_needs():
    assert [t.name for t in nested(TYPES, ["Cmd", "Twist"])] == ["Pose", "Cmd"]
    assert nested(TYPES, []) == []
    listed = DataType(name="Path", fields={"poses": "list[list[Pose]]"})
    assert [t.name for t in nested([*TYPES, listed], ["Path"])] == ["Pose", "Path"]


# ---- the node's inputs -------------------------------------------------------------------
def test_a_typed_input_hands_the_node_only_samples_of_its_type_and_counts_the_rest():
    h = harness()
    for samples in BAD.values():
        for sample in samples:
            h.send("in", sample)
    h.send_raw("in", b"\xc1")  # not msgpack
    assert h.node.got == []
    counters = h.core.counters
    assert counters.received == 0
    assert counters.dropped == 2  # not a map, not msgpack
    assert counters.rejected == sum(len(v) for r, v in BAD.items() if r != "not_a_map")
    assert {r: counters.extra.get(r) for r in BAD} == {r: len(v) for r, v in BAD.items()}
    assert counters.extra["malformed"] == 1
    # the first refusal of each reason at once (then rate-limited), saying what was wrong
    assert h.logs == [
        "[node] refused sample on in: Cmd: Object missing required field `pose`",
        "[node] refused sample on in: Cmd: Expected `int`, got `str` - at `$.seq`",
        "[node] refused sample on in: Cmd: $.speeds[1] is not finite",
        "[node] dropped sample on in: Cmd: Expected `object`, got `array`",
    ]
    h.send("in", {**GOOD, "extra": 3, "note": "hi"})
    assert h.node.got == [{**GOOD, "note": "hi"}]  # undeclared fields are not delivered
    assert h.core.counters.received == 1


def test_an_input_of_an_undeclared_type_takes_any_map():
    h = harness("NotDeclared")
    h.send("in", {"anything": math.nan})
    h.send("in", [1])
    assert len(h.node.got) == 1 and h.core.counters.dropped == 1


def test_the_harness_reads_the_data_types_of_a_package_folder():
    h = NodeHarness(
        Recorder, ports={"in": ("subscribe", "MotorCommand")}, types=ROOT / "scenarios/quadcopter"
    )
    h.send("in", {"speeds": [math.nan] * 4, "controller": "pid"})
    h.send("in", {"speeds": [400.0] * 4, "controller": "pid"})
    assert h.node.got == [{"speeds": [400.0] * 4, "controller": "pid"}]
    assert h.core.counters.extra["non_finite"] == 1


class _Transport:
    def publish(self, port: str, payload: bytes, stamp: float) -> None:
        pass

    def rebind(self, port: str, direction: str, keys: list[str], standby=None) -> None:
        pass

    def subscribe(self, key_expr: str, callback: Any) -> None:
        pass


def test_a_forged_sample_on_a_hot_standby_s_key_never_displaces_its_held_one():
    """The hostile client's NaN on the standby's output key, between its last good sample
    and the switch: the switch delivers the good one (on the old code, the NaN)."""
    spec = m.NodeSpec(
        system="t", name="sink", host="h", implementation=f"{__name__}.Recorder",
        ports={"in": m.PortSpec(direction="subscribe", type="Cmd", keys=["a"], standby=["b"])},
        types=TYPES,
    )  # fmt: skip
    core = NodeCore(spec, Recorder, _Transport(), monotonic=lambda: 0.0)
    core.start()
    core.hold("in", "b", encode_data(GOOD), None)
    core.hold("in", "b", encode_data({**GOOD, "speeds": [math.nan]}), None)
    assert core.counters.extra["non_finite"] == 1
    assert isinstance(core.handle(m.Rewire(port="in", keys=["b"])), m.Ok)
    assert core.node.got == [GOOD]


# ---- from the model, not from the request -----------------------------------------------
PACKAGE = ROOT / "tests" / "data" / "hosttest"


def test_the_host_agent_gives_a_node_the_port_types_and_data_types_of_its_model():
    catalog = Catalog.of(deploy(PACKAGE), "h1")
    lying = m.NodeSpec(
        system="hosttest", name="relay", host="h1", implementation="rra_agent.nodes.generic.Relay",
        ports={"in": m.PortSpec(direction="subscribe", type="Anything", keys=["k"]),
               "out": m.PortSpec(direction="publish", type="Anything", keys=["o"])},
    )  # fmt: skip
    admitted = catalog.admit(lying)
    assert {n: p.type for n, p in admitted.ports.items()} == {"in": "Sample", "out": "Sample"}
    assert [t.name for t in admitted.types] == ["Sample"]
    assert admitted.types[0].optional == ["relay", "count"]
    extra = msgspec.structs.replace(
        lying, ports={**lying.ports, "aux": m.PortSpec(direction="subscribe", type="Sample")}
    )
    with pytest.raises(Refused, match="port 'aux' is not one the model declares"):
        catalog.admit(extra)


def test_a_container_gives_its_members_the_types_its_host_agent_s_model_declares():
    deployed = deploy(PACKAGE)
    catalog = Catalog.of(deployed, "h1")
    container = ContainerRuntime(catalog.container_spec("box"), BusConfig())
    member = next(
        c for c in deployed.configured.components
        if c.name in container.members and any(p.direction == "subscribe" for p in c.ports)
    )  # fmt: skip
    name = member.name
    lying = m.NodeSpec(
        system="hosttest", name=name, host="elsewhere",
        implementation=container.members[name].implementations[0],
        ports={p.name: m.PortSpec(direction=p.direction, type="Anything") for p in member.ports},
    )  # fmt: skip
    admitted = container._admit(lying)
    assert {n: p.type for n, p in admitted.ports.items()} == {p.name: p.type for p in member.ports}
    assert "Anything" not in {p.type for p in admitted.ports.values()}
    assert [t.name for t in admitted.types] == [t.name for t in catalog.types_of(member)]
    assert admitted.types, "the member's inputs carry a declared data type"
    unknown = msgspec.structs.replace(
        lying, ports={"aux": m.PortSpec(direction="publish", type="X")}
    )
    with pytest.raises(NodeError, match="port 'aux' is not one the model declares"):
        container._admit(unknown)


def test_what_the_host_agent_adds_is_not_a_difference_reconciliation_acts_on():
    """The engines' spec has no data types (the host agent derives them): the digest of
    what the host runs must equal the engines' own, or reconciliation restarts the node."""
    from rra_agent.bus.keys import Keys
    from rra_agent.engines.executor import spec_for

    deployed = deploy(PACKAGE)
    catalog = Catalog.of(deployed, "h1")
    relay = deployed.configured.component("relay")
    assert relay is not None
    asked = spec_for(Keys("hosttest"), relay, {"in": ("src",)}, {}, default_host="h1")
    admitted = catalog.admit(asked)
    assert admitted.types and not asked.types
    assert m.spec_digest(admitted) == m.spec_digest(asked)


def test_a_reload_s_catalog_keeps_the_ros2_side_and_the_data_types(tmp_path):
    """The catalog a reload prepares is made as the first one: on the old code it lost the
    package's ``ros2:`` section, so a ROS 2 component started after a reload had no ROS 2
    side."""
    from rra_agent.bus.config import BusConfig as Bus
    from rra_agent.bus.config import free_port
    from rra_agent.host.agent import HostAgent
    from rra_agent.package.bundle import bundle_of

    rover = ROOT / "scenarios" / "ros2_rover"
    dep = deploy(rover)
    agent = HostAgent(
        dep.system, "local", Bus(connect=[f"tcp/127.0.0.1:{free_port()}"]), tmp_path,
        hub=True, catalog=Catalog.of(dep, "local", default_host=True), models=dep,
    )  # fmt: skip
    assert isinstance(agent.prepare_models(bundle_of(dep.package)), m.Ok)
    assert agent._next is not None
    prepared = agent._next[1]
    assert prepared.ros2 == agent.catalog.ros2 is not None
    assert prepared.data_types == agent.catalog.data_types


# ---- what is logged -----------------------------------------------------------------------
def test_a_flood_of_one_source_s_junk_never_hides_another_source_s_first_refusal():
    """Under a hostile client, junk on an engine's control endpoint came first and took the
    monitor's one "dropped (malformed)" line per 10 s: source.out's went unlogged."""
    lines: list[str] = []
    now = [0.0]
    log = RateLimitedLog(lines.append, period=10.0, clock=lambda: now[0])
    for _ in range(100):
        log("dropped (malformed)", "process request: junk", "request")
    log("dropped (malformed)", "source.out: not msgpack", "source.out")
    assert lines == [
        "dropped (malformed): process request: junk",
        "dropped (malformed): source.out: not msgpack",
    ]
    now[0] = 11.0
    log("dropped (malformed)", "process request: junk", "request")
    assert lines[-1] == "dropped (malformed): process request: junk (100 since the last report)"


def test_a_sample_over_the_size_limit_is_dropped_and_counted_as_too_large():
    h = harness()
    h.send_raw("in", b"\x80" * (h.core.max_data + 1))
    assert h.node.got == [] and h.core.counters.dropped == 1
    assert h.core.counters.extra["too_large"] == 1
