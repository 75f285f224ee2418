"""Plan execution: strategies, ordering, state transfer and rollback, with a fake actuator."""

from __future__ import annotations

from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

import msgspec
import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.bus.messages import NodeSpec
from rra_agent.core import resolution as r
from rra_agent.core.effect import effective_model
from rra_agent.core.features import complete_deployment
from rra_agent.core.plan import Plan, diff, standby_subscriptions
from rra_agent.engines.executor import (
    Ctl,
    Executor,
    StepFailed,
    describe_step,
    plan_units,
    spec_for,
)
from rra_agent.models.resolution import Replacement, StateTransfer
from rra_agent.models.system import SystemModel
from rra_agent.package.loader import load_package

ROOT = Path(__file__).resolve().parents[1]
K = Keys("quadcopter")


class FakeActuator:
    def __init__(self) -> None:
        self.calls: list[tuple] = []
        self.batches: list[int] = []
        self.fail_on: set[tuple[str, str]] = set()
        #: (node, implementation) that cannot start (a restart with another one can).
        self.broken: set[tuple[str, str]] = set()
        self.states: dict[str, Any] = {"controller": {"integral": 1.5}}
        self.deadlines: dict[str, float] = {}

    def _do(self, op: str, name: str, *rest: Any) -> None:
        self.calls.append((op, name, *rest))
        if (op, name) in self.fail_on:
            raise StepFailed(f"{op} {name} failed")

    def start(self, specs: list[NodeSpec]) -> None:
        failed = {}
        for s in specs:
            try:
                self._do("start", s.name, s.active, s.state)
                if (s.name, s.implementation) in self.broken:
                    raise StepFailed(f"start {s.name} failed: implementation broken")
            except StepFailed as e:
                failed[s.name] = str(e)
        if failed:
            raise StepFailed("start failed", failed)

    def stop(self, specs: list[NodeSpec], deadlines: dict[str, float] | None = None) -> None:
        for s in specs:
            self._do("stop", s.name)
            if deadlines and s.name in deadlines:
                self.deadlines[s.name] = deadlines[s.name]

    def replace(
        self,
        pairs: list[tuple[NodeSpec, NodeSpec]],
        deadlines: dict[str, float] | None = None,
        on_stopped: Callable[[], None] | None = None,
        export: Collection[str] = (),
    ) -> None:
        """As the real one: each old node's state exported if asked (by its host agent),
        the old node stopped, then its new one started with that state (not if the old one
        did not stop or export)."""
        failed: dict[str, str] = {}
        for old, new in pairs:
            if old.name in export:
                try:
                    self._do("export", old.name)
                except StepFailed as e:
                    failed[old.name] = failed[new.name] = str(e)
                    continue
                new = msgspec.structs.replace(new, state=self.states.get(old.name))
            try:
                self.stop([old], deadlines)
            except StepFailed as e:
                failed[old.name] = str(e)
                failed[new.name] = f"not started: {old.name} did not stop"
                continue
            if on_stopped is not None:
                on_stopped()
            try:
                self.start([new])
            except StepFailed as e:
                failed.update(e.nodes or {new.name: str(e)})
        if failed:
            raise StepFailed("replace failed", failed)

    def control(
        self, batch: list[Ctl], meanwhile: Callable[[], None] | None = None
    ) -> list[m.Reply]:
        replies = self._control(batch)
        if meanwhile is not None:  # the real one: after sending, before reading the replies
            meanwhile()
        return replies

    def _control(self, batch: list[Ctl]) -> list[m.Reply]:
        self.batches.append(len(batch))
        replies: list[m.Reply] = []
        for c in batch:
            name = c.spec.name
            match c.request:
                case m.SetParams(params=p):
                    call = ("params", name, dict(p))
                case m.Rewire(port=port, keys=keys):
                    call = ("rewire", name, port, tuple(keys))
                case m.Activate(state=st):
                    if st is not None:  # the state is taken over first, in the same request
                        self.calls.append(("import", name, st))
                    call = ("active", name, True)
                case m.Deactivate():
                    call = ("active", name, False)
                case m.ExportState():
                    call = ("export", name)
                case m.ImportState(state=st):
                    call = ("import", name, st)
                case _:
                    raise AssertionError(c.request)
            self.calls.append(call)
            if (call[0], name) in self.fail_on:
                replies.append(m.Err(message=f"{call[0]} {name} failed", code="refused"))
            elif call[0] == "export":
                replies.append(m.Ok(result=self.states.get(name)))
            else:
                replies.append(m.Ok())
        return replies


@pytest.fixture(scope="module")
def quad():
    pkg = load_package(ROOT / "scenarios" / "quadcopter")
    dep = complete_deployment(pkg.features, pkg.manifest.default_selection)
    configured = r.resolve_deployment(pkg.system, pkg.deployment, pkg.features, dep)
    fm = pkg.features

    def target(*features: str) -> SystemModel:
        sel = {"Quadcopter", "Controller", *features}
        return r.resolve_runtime(configured, pkg.runtime, fm, sel, {})

    return configured, target


def make(
    strategy: str, transfer: bool = True, deadlines: dict[str, float] | None = None
) -> tuple[Executor, FakeActuator]:
    act = FakeActuator()
    rep = Replacement(
        default="stop-then-start",
        components={"proploss_controller": strategy},  # type: ignore[dict-item]
        state_transfer=[StateTransfer(source="controller", target="proploss_controller")]
        if transfer
        else [],
        stop_deadline=deadlines or {},
    )
    return Executor(act, K, rep, default_host="local"), act


def deploy(ex: Executor, act: FakeActuator, target: SystemModel) -> None:
    empty = msgspec.structs.replace(target, components=[], connections=[])
    assert ex.execute(diff(empty, target)).ok
    act.calls.clear()


def swap_plan(target) -> Plan:
    plan = diff(target("Standard"), target("Proploss"))
    kinds = [type(s).__name__ for s in plan.steps]
    assert kinds == ["SwapComponent", "Rewire"], kinds
    return plan


def test_deploy_starts_everything_at_once_and_tracks_specs(quad):
    _, target = quad
    ex, act = make("stop-then-start")
    empty = msgspec.structs.replace(target("Standard"), components=[], connections=[])
    out = ex.execute(diff(empty, target("Standard")))
    assert out.ok and [c[0] for c in act.calls] == ["start"] * 4
    assert set(ex.running) == {
        "trajectory_generator",
        "estimator",
        "controller",
        "vehicle_simulator",
    }
    sim = ex.running["vehicle_simulator"]
    assert sim.ports["motor_cmd"].keys == [K.data("controller/motor_cmd")]


def cold_swap(target, *fail_on: tuple[str, str]) -> tuple[Any, Executor, FakeActuator]:
    """The quadcopter deployed as Standard, then swapped to Proploss cold (stop-then-start)
    with the actions ``fail_on`` failing: the outcome, the executor and its actuator."""
    ex, act = make("stop-then-start")
    deploy(ex, act, target("Standard"))
    act.fail_on.update(fail_on)
    return ex.execute(swap_plan(target)), ex, act


def test_stop_then_start_swap_transfers_state_in_the_spec(quad):
    out, ex, act = cold_swap(quad[1])
    assert out.ok, out.error
    assert act.calls == [
        # the simulator's rewire is sent first and is in flight while the host agent exports
        # the old controller's state, stops it and starts the new one with it
        ("rewire", "vehicle_simulator", "motor_cmd", (K.data("proploss_controller/motor_cmd"),)),
        ("export", "controller"),
        ("stop", "controller"),
        ("start", "proploss_controller", True, {"integral": 1.5}),
    ]
    assert act.batches == [1]  # the export is the agent's: no round trip of the engine's
    assert "controller" not in ex.running and "proploss_controller" in ex.running


def test_a_cold_swap_whose_rewire_failed_meanwhile_is_undone_newest_first(quad):
    """The rewire fails while the replacement (beside it) succeeded: the unit is undone,
    the new controller stopped before the old one is started again (it may hold what the
    old one needs), and the simulator keeps listening to the old one."""
    out, ex, act = cold_swap(quad[1], ("rewire", "vehicle_simulator"))
    assert not out.ok
    assert act.calls[-2:] == [("stop", "proploss_controller"),
                              ("start", "controller", True, None)]  # fmt: skip
    assert "controller" in ex.running and "proploss_controller" not in ex.running
    sim = ex.running["vehicle_simulator"]
    assert sim.ports["motor_cmd"].keys == [K.data("controller/motor_cmd")]


def test_a_cold_swap_whose_old_node_cannot_export_stops_nothing(quad):
    out, ex, act = cold_swap(quad[1], ("export", "controller"))
    assert not out.ok
    assert ("stop", "controller") not in act.calls
    assert not [c for c in act.calls if c[:2] == ("start", "proploss_controller")]
    assert "controller" in ex.running and "proploss_controller" not in ex.running
    assert act.calls[-1] == (  # the simulator's rewire undone
        "rewire", "vehicle_simulator", "motor_cmd", (K.data("controller/motor_cmd"),))


def test_a_replacement_s_plan_lines_time_the_stop_and_the_start_apart(quad):
    """One `ReplaceNode` does both: the stop's line lasts until the old node is gone, the
    start's from then until the new one is ready (not both the whole request)."""
    _, target = quad
    now = [0.0]
    act = FakeActuator()
    took = {"stop": 0.010, "start": 0.030}
    real_do = act._do

    def timed(op: str, name: str, *rest: Any) -> None:
        real_do(op, name, *rest)
        now[0] += took.get(op, 0.001)

    act._do = timed  # type: ignore[method-assign]
    rep = Replacement(default="stop-then-start")
    ex = Executor(act, K, rep, default_host="local", clock=lambda: now[0])
    deploy(ex, act, target("Standard"))
    out = ex.execute(swap_plan(target))
    assert out.ok, out.error
    lines = {(r.action, r.node): r.seconds for r in out.records}
    assert lines[("stop", "controller")] == pytest.approx(0.010)
    assert lines[("start", "proploss_controller")] == pytest.approx(0.030)
    # the rewire was in flight during the replacement: its line leaves those 40 ms out (the
    # fake answers it in no time)
    assert lines[("rewire motor_cmd of vehicle_simulator", "")] == pytest.approx(0.0)


def test_a_stop_then_start_swap_stops_the_old_node_with_its_deadline(quad):
    """runtime.yaml ``stop_deadline: {controller: 0}``: the cold swap's stop of the old
    controller carries it (its host agent kills it at once); other stops do not."""
    _, target = quad
    ex, act = make("stop-then-start", deadlines={"controller": 0.0, "estimator": 0.5})
    deploy(ex, act, target("Standard"))
    assert ex.execute(swap_plan(target)).ok
    assert act.deadlines == {"controller": 0.0}
    ex, act = make("start-then-stop", deadlines={"controller": 0.0})
    deploy(ex, act, target("Standard"))
    assert ex.execute(swap_plan(target)).ok  # after the switch: off the critical path
    assert ("stop", "controller") in act.calls and act.deadlines == {}


def test_start_then_stop_makes_before_break(quad):
    _, target = quad
    ex, act = make("start-then-stop")
    deploy(ex, act, target("Standard"))
    assert ex.execute(swap_plan(target)).ok
    ops = [c[:2] for c in act.calls]
    assert ops == [
        ("start", "proploss_controller"),
        # connect: the simulator listens to the new node before it is activated (its first
        # command is published on activation); no deactivation of controller: it publishes
        # elsewhere and the rewire cuts it off
        ("rewire", "vehicle_simulator"),
        ("export", "controller"),
        ("import", "proploss_controller"),
        ("active", "proploss_controller"),
        ("stop", "controller"),  # last: after the simulator listens to the new node
    ]
    assert act.calls[0][2] is False  # started inactive


def test_standby_switch_is_activate_rewire_and_no_start(quad):
    _, target = quad
    ex, act = make("standby")
    deploy(ex, act, target("Standard"))
    plan = swap_plan(target)
    swap = plan.steps[0]
    pre = spec_for(K, swap.definition, dict(swap.inputs), dict(swap.outputs), default_host="l")
    assert ex.prestart_standby([pre]).ok
    assert act.calls == [("start", "proploss_controller", False, None)]
    act.calls.clear()
    out = ex.execute(plan)
    assert out.ok and out.first_switch is not None
    assert [c[0] for c in act.calls] == ["rewire", "export", "import", "active", "stop"]
    assert act.calls[3] == ("active", "proploss_controller", True)
    assert not ex.standby and ex.running["proploss_controller"].active


def test_failed_start_rolls_back_to_the_previous_configuration(quad):
    _, target = quad
    ex, act = make("stop-then-start", transfer=False)
    deploy(ex, act, target("Standard"))
    before = dict(ex.running)
    act.fail_on = {("start", "proploss_controller")}
    out = ex.execute(swap_plan(target))
    assert not out.ok and out.rolled_back and "proploss_controller" in out.error
    # undone in reverse order: the old one is back, then the simulator listens to it again
    assert act.calls[-2:] == [
        ("start", "controller", True, None),
        ("rewire", "vehicle_simulator", "motor_cmd", (K.data("controller/motor_cmd"),)),
    ]
    assert ex.running == before
    assert any(not rec.ok for rec in out.records)


def test_failed_rewire_undoes_the_swap_in_reverse_order(quad):
    _, target = quad
    ex, act = make("start-then-stop", transfer=False)
    deploy(ex, act, target("Standard"))
    act.fail_on = {("rewire", "vehicle_simulator")}
    out = ex.execute(swap_plan(target))
    assert out.rolled_back
    failed = (
        "rewire",
        "vehicle_simulator",
        "motor_cmd",
        (K.data("proploss_controller/motor_cmd"),),
    )
    undo = act.calls[act.calls.index(failed) + 1 :]
    assert undo == [("stop", "proploss_controller")]  # it was never activated
    assert set(ex.running) >= {"controller"} and "proploss_controller" not in ex.running


def two_components(v: float, w: int) -> SystemModel:
    def comp(name: str, param: str, type_: str, value: object) -> dict:
        return {
            "name": name,
            "implementation": f"x.{name.upper()}",
            "parameters": {param: {"type": type_, "value": value}},
        }

    return msgspec.convert(
        {"system": "s", "components": [comp("a", "v", "float", v), comp("b", "w", "int", w)]},
        SystemModel,
    )


def test_parameters_of_two_components_are_applied_each_on_its_own():
    """Two parameter changes depend on nothing: the one refused is reported and undone,
    the other stays applied (it is in effect)."""
    sysm, tgt = two_components(1.0, 1), two_components(2.0, 5)
    ex, act = make("stop-then-start")
    deploy(ex, act, sysm)
    act.fail_on = {("params", "b")}
    out = ex.execute(diff(sysm, tgt))
    assert not out.ok and out.partial and out.rolled_back
    assert act.calls == [("params", "a", {"v": 2.0}), ("params", "b", {"w": 5})]
    assert ex.running["a"].params == {"v": 2.0} and ex.running["b"].params == {"w": 1}
    [failure] = out.failures
    assert failure.parameters == {"b"} and not failure.structure
    assert failure.steps == ["set b w=5"] and "params b failed" in failure.error
    act.fail_on = set()
    assert ex.execute(diff(effective_model(sysm, tgt, (), {"b"}), tgt)).ok
    assert ex.running["a"].params == {"v": 2.0} and ex.running["b"].params == {"w": 5}


def test_standby_switch_is_connect_then_activate_and_the_host_learns_new_specs(quad):
    _, target = quad
    ex, act = make("standby", transfer=False)
    deploy(ex, act, target("Standard"))
    swap = swap_plan(target).steps[0]
    pre = spec_for(K, swap.definition, dict(swap.inputs), dict(swap.outputs), default_host="l")
    ex.prestart_standby([pre])
    act.calls.clear()
    act.batches.clear()
    assert ex.execute(swap_plan(target)).ok
    # rewire the simulator, then activate proploss: its first command (published on
    # activation) finds the simulator listening
    assert act.batches == [1, 1]
    assert [c[0] for c in act.calls] == ["rewire", "active", "stop"]
    sim = ex.running["vehicle_simulator"]
    assert sim.ports["motor_cmd"].keys == [K.data("proploss_controller/motor_cmd")]


def test_swapped_out_node_kept_as_standby_is_deactivated_for_the_way_back(quad):
    _, target = quad
    act = FakeActuator()
    rep = Replacement(components={"proploss_controller": "standby", "controller": "standby"})
    ex = Executor(act, K, rep, default_host="local")
    deploy(ex, act, target("Standard"))
    swap = swap_plan(target).steps[0]
    pre = spec_for(K, swap.definition, dict(swap.inputs), dict(swap.outputs), default_host="l")
    ex.prestart_standby([pre])
    act.calls.clear()
    assert ex.execute(swap_plan(target)).ok
    assert ("active", "controller", False) in act.calls
    assert not any(c[0] == "stop" for c in act.calls)
    assert set(ex.standby) == {"controller"} and not ex.standby["controller"].active
    # and back: the controller is switched to again without a start
    act.calls.clear()
    back = diff(target("Proploss"), target("Standard"))
    assert ex.execute(back).ok
    assert not any(c[0] == "start" for c in act.calls)
    assert ("active", "controller", True) in act.calls
    assert set(ex.standby) == {"proploss_controller"}


def test_an_outgoing_standby_node_is_kept_when_its_replacement_starts_cold(quad):
    """The controller is a standby replacement, Proploss is not: swapping to Proploss (its
    strategy stop-then-start) must not stop the controller, which stays for the way back;
    Proploss then starts inactive and takes over in the switch."""
    _, target = quad
    act = FakeActuator()
    rep = Replacement(components={"controller": "standby"})
    ex = Executor(act, K, rep, default_host="local")
    deploy(ex, act, target("Standard"))
    act.calls.clear()
    assert ex.execute(swap_plan(target)).ok
    assert not any(c[:2] == ("stop", "controller") for c in act.calls), act.calls
    assert ("start", "proploss_controller", False, None) in act.calls
    assert ("active", "proploss_controller", True) in act.calls
    assert ("active", "controller", False) in act.calls
    assert set(ex.standby) == {"controller"}


def hot_executor(
    quad, transfer: bool = True, hot: tuple[str, ...] = ("proploss_controller",)
) -> tuple[Executor, FakeActuator]:
    """Proploss (and ``hot``) as hot standbys, deployed with Proploss pre-started: the
    simulator's spec listens to their outputs in advance."""
    configured, target = quad
    act = FakeActuator()
    rep = Replacement(
        components=dict.fromkeys(hot, "hot-standby"),
        state_transfer=[StateTransfer(source="controller", target="proploss_controller")]
        if transfer
        else [],
    )
    held = standby_subscriptions(configured, hot)
    ex = Executor(act, K, rep, default_host="local", standby_inputs=held)
    deploy(ex, act, target("Standard"))
    swap = swap_plan(target).steps[0]
    pre = spec_for(K, swap.definition, dict(swap.inputs), dict(swap.outputs), default_host="l")
    assert ex.prestart_standby([pre]).ok
    return ex, act


def test_a_hot_standby_runs_active_and_its_consumer_listens_in_advance(quad):
    ex, act = hot_executor(quad)
    assert act.calls == [("start", "proploss_controller", True, None)]
    sim = ex.running["vehicle_simulator"].ports["motor_cmd"]
    assert sim.keys == [K.data("controller/motor_cmd")]
    assert sim.standby == [K.data("proploss_controller/motor_cmd")]
    # only the consumers of the hot standby's outputs listen in advance
    assert not ex.running["estimator"].ports["state"].standby


def test_a_hot_standby_switch_is_the_consumer_s_rewire_then_the_state(quad):
    """No activation (it runs already): the simulator's rewire is the switch; the state of
    the controller follows as an import; the controller is stopped, not deactivated."""
    _, target = quad
    ex, act = hot_executor(quad)
    act.calls.clear()
    act.batches.clear()
    assert ex.execute(swap_plan(target)).ok
    assert [c[0] for c in act.calls] == ["rewire", "export", "import", "stop"], act.calls
    assert act.calls[0] == ("rewire", "vehicle_simulator", "motor_cmd",
                            (K.data("proploss_controller/motor_cmd"),))  # fmt: skip
    assert act.calls[2] == ("import", "proploss_controller", {"integral": 1.5})
    sim = ex.running["vehicle_simulator"].ports["motor_cmd"]
    assert sim.standby == [K.data("proploss_controller/motor_cmd")]  # kept for restarts
    assert ex.running["proploss_controller"].active and not ex.standby


def test_a_hot_standby_swapped_out_stays_active_for_the_way_back(quad):
    _, target = quad
    ex, act = hot_executor(quad, transfer=False, hot=("proploss_controller", "controller"))
    act.calls.clear()
    assert ex.execute(swap_plan(target)).ok
    assert not any(c[0] in ("stop", "active") for c in act.calls), act.calls
    assert set(ex.standby) == {"controller"} and ex.standby["controller"].active
    act.calls.clear()
    assert ex.execute(diff(target("Proploss"), target("Standard"))).ok
    assert [c[0] for c in act.calls] == ["rewire"], act.calls
    assert set(ex.standby) == {"proploss_controller"}


# ---- plans that degrade, not block ---------------------------------------------------------
AGV = msgspec.convert(
    {
        "system": "agv",
        "components": [
            {"name": "lidar", "implementation": "x.Lidar", "optional": True, "binding": "runtime",
             "ports": [{"name": "scan", "direction": "publish", "type": "Scan"}]},
            {"name": "camera", "implementation": "x.Camera", "optional": True,
             "binding": "runtime", "ports": [{"name": "scan", "direction": "publish",
                                              "type": "Scan"}]},
            {"name": "perception", "implementation": "x.Perception",
             "ports": [{"name": "scan", "direction": "subscribe", "type": "Scan"},
                       {"name": "obstacles", "direction": "publish", "type": "Obstacles"}]},
            {"name": "motion", "implementation": "x.Motion",
             "parameters": {"max_speed": {"type": "float", "value": 1.4}},
             "ports": [{"name": "obstacles", "direction": "subscribe", "type": "Obstacles"}]},
            {"name": "beacon", "implementation": "x.Beacon", "optional": True,
             "binding": "runtime"},
        ],
        "connections": [
            {"from": "lidar.scan", "to": "perception.scan", "optional": True,
             "binding": "runtime"},
            {"from": "camera.scan", "to": "perception.scan", "optional": True,
             "binding": "runtime"},
            {"from": "perception.obstacles", "to": "motion.obstacles"},
        ],
    },
    SystemModel,
)  # fmt: skip


def agv(camera: bool, human_zone: bool) -> SystemModel:
    """The AGV with the lidar or the camera feeding perception, and in the human zone the
    speed limit and the beacon."""
    sensor = "camera" if camera else "lidar"
    comps = [
        c if c.name != "motion" or not human_zone
        else msgspec.structs.replace(c, parameters={
            "max_speed": msgspec.structs.replace(c.parameters["max_speed"], value=0.5)})
        for c in AGV.components
        if c.name in ("perception", "motion", sensor) or (human_zone and c.name == "beacon")
    ]  # fmt: skip
    conns = [c for c in AGV.connections if c.source.split(".")[0] in ("perception", sensor)]
    return msgspec.structs.replace(AGV, components=comps, connections=conns)


def test_a_component_that_cannot_start_does_not_hold_back_the_speed_limit():
    """The warehouse AGV enters the human zone while switching to a camera that is not
    plugged in: the camera's swap (its start, perception's rewire, the lidar's stop) fails
    and is undone as one unit; the speed limit and the beacon are applied."""
    ex, act = make("stop-then-start")
    deploy(ex, act, agv(camera=False, human_zone=False))
    act.fail_on = {("start", "camera")}
    before, after = agv(camera=False, human_zone=False), agv(camera=True, human_zone=True)
    out = ex.execute(diff(before, after))
    assert not out.ok and out.partial and out.rolled_back
    # the speed limit first: it never waits for a start (seconds, or a timeout)
    assert act.calls[0] == ("params", "motion", {"max_speed": 0.5})
    assert ex.running["motion"].params["max_speed"] == 0.5
    assert "beacon" in ex.running and "lidar" in ex.running and "camera" not in ex.running
    assert ex.running["perception"].ports["scan"].keys == [K.data("lidar/scan")]
    [failure] = out.failures
    assert failure.structure == {"lidar", "camera", "perception"}
    assert failure.nodes == {"camera": "start camera failed"}
    effective = effective_model(before, after, failure.structure, failure.parameters)
    assert {c.name for c in effective.components} == set(ex.running)
    assert diff(effective, after).steps  # the camera is still to come


def test_units_of_a_plan_follow_its_dependencies():
    ex, act = make("stop-then-start")
    deploy(ex, act, agv(camera=False, human_zone=False))
    plan = diff(agv(camera=False, human_zone=False), agv(camera=True, human_zone=True))
    units = plan_units(plan.steps, ex.running, K.data)
    by_unit: dict[int, set[str]] = {}
    for step, u in zip(plan.steps, units, strict=True):
        by_unit.setdefault(u, set()).add(describe_step(step))
    assert sorted(map(sorted, by_unit.values())) == [
        ["rewire perception.scan", "swap lidar -> camera"],
        ["set motion max_speed=0.5"],
        ["start beacon"],
    ]


def test_an_unavailable_component_is_not_tried():
    ex, act = make("stop-then-start")
    deploy(ex, act, agv(camera=False, human_zone=False))
    out = ex.execute(
        diff(agv(camera=False, human_zone=False), agv(camera=True, human_zone=True)),
        skip={"camera"},
    )
    assert not any(c[:2] == ("start", "camera") for c in act.calls), act.calls
    assert ("params", "motion", {"max_speed": 0.5}) in act.calls
    [failure] = out.failures
    assert failure.skipped and failure.nodes == {"camera": "unavailable"}
