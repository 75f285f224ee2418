"""Reflexes in process (no bus): which decisions may be delegated (`rra_agent.core.reflex`),
what the engines compile for the current configuration and how they confirm or roll back
(`rra_agent.engines.reflexes`), and how a node evaluates and fires one
(`rra_agent.node.reflex`, through `NodeHarness`). The real processes: tests/test_reflexes.py.
"""

from __future__ import annotations

import math
import shutil
import time
from pathlib import Path
from typing import Any

import msgspec
import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.core.adaptation import AdaptationEngine, feature_families
from rra_agent.core.reflex import Test as Cmp
from rra_agent.core.reflex import candidates, holds
from rra_agent.deployment import deploy
from rra_agent.dsl.rules import parse_rules
from rra_agent.engines.executor import Ctl
from rra_agent.engines.reflexes import ReflexKeeper, Situation
from rra_agent.engines.resolution import ResolutionEngineProcess
from rra_agent.node.harness import NodeHarness
from rra_agent.package.loader import load_package

ROOT = Path(__file__).resolve().parents[1]
PKG = Path(__file__).parent / "data" / "reflex_system"
QUAD = ROOT / "scenarios" / "quadcopter"


# ---- which branches may be reflexes --------------------------------------------------------
def _model(text: str, pkg: Path = PKG):
    p = load_package(pkg)
    model = parse_rules(text, "test.rra", p.features, p.measurements)
    return model, p


def _candidates(text: str, pkg: Path = PKG):
    model, p = _model(text, pkg)
    found, why = candidates(model, p.features, p.measurements, feature_families(p.features))
    return {f"{c.label}[{c.branch}]": c for c in found}, why


HEAD = "import reflex.contextDepMeasModel as cdm\n"


def test_a_branch_is_its_condition_and_the_negation_of_the_ones_before_it() -> None:
    found, _ = _candidates(HEAD + """
rule R period 0 ms:
    if (cdm.Level < 0) activate_feature(Backup)
    else if (NOT (cdm.Level >= 5 OR cdm.Level == 3)) activate_feature(Main)
""")  # fmt: skip
    assert found["R[0]"].condition == ((Cmp("Level", "<", 0.0),),)
    assert found["R[1]"].condition == (
        (Cmp("Level", ">=", 0.0), Cmp("Level", "<", 5.0), Cmp("Level", "!=", 3.0)),
    )
    assert found["R[0]"].source == "plant.out"


def test_the_condition_is_false_where_the_engine_would_be_undefined() -> None:
    cond = ((Cmp("Level", "<", 0.0),), (Cmp("Other", "==", "x"),))
    assert holds(cond, {"Level": -1.0, "Other": "y"})
    assert not holds(cond, {"Level": 1.0, "Other": "y"})
    assert not holds(cond, {"Level": math.nan, "Other": "x"})  # NaN: undefined, never fires
    assert not holds(cond, {"Level": -1.0})  # a measurement missing: never fires
    assert holds(((),), {})  # no test: holds
    assert not holds((), {})  # no clause: never


def test_the_quadcopter_rule_is_a_candidate() -> None:
    p = load_package(QUAD)
    assert p.adaptation is not None
    found, why = candidates(p.adaptation, p.features, p.measurements,
                            feature_families(p.features))  # fmt: skip
    assert [(c.label, c.branch, c.source, c.measurements) for c in found] == [
        ("MotorLoss", 0, "vehicle_simulator.telemetry", ("WorkingMotors",))
    ]
    assert why == {}


@pytest.mark.parametrize(
    ("rule", "reason"),
    [
        ("rule R period 0 ms reflex off: if (cdm.Level < 0) activate_feature(Backup)",
         "reflex off"),
        ("rule R period 100 ms: if (cdm.Level < 0) activate_feature(Backup)",
         "evaluated every 100 ms, not on each new sample"),
        ("rule R period 0 ms: if (cdm.Level * 2 < 0) activate_feature(Backup)",
         "its condition reads arithmetic"),
        ("rule R: activate_feature(Backup)", "its condition reads no measurement"),
    ],
)  # fmt: skip
def test_what_is_never_a_reflex(rule: str, reason: str) -> None:
    found, why = _candidates(HEAD + rule)
    assert not found
    assert why == {"R": reason}


def test_no_reflex_where_another_rule_or_a_higher_priority_may_overturn_it() -> None:
    found, why = _candidates(HEAD + """
ruleSet Mode:
    rule Fallback priority 2: if (cdm.Level < 0) activate_feature(Backup)
    rule Hold priority 1: if (cdm.Level < -50) activate_feature(Main)
""")  # fmt: skip
    assert "Mode.Fallback[0]" not in found
    assert why["Fallback"] == "rule Mode.Hold may overturn it (activate_feature(Main))"
    # Guards the analysis proves disjoint cannot overturn each other: both are reflexes.
    found, why = _candidates(HEAD + """
rule Down period 0 ms: if (cdm.Level < 0) activate_feature(Backup)
rule Up period 0 ms: if (cdm.Level > 10) activate_feature(Main)
""")  # fmt: skip
    assert set(found) == {"Down[0]", "Up[0]"}, why


def test_the_outcome_is_what_a_tick_would_decide_with_overrides_and_unavailability() -> None:
    dep = deploy(PKG)
    engine = AdaptationEngine(dep.package.features, dep.selection, dep.package.adaptation)
    assert engine.outcome("Fallback", 0) == {"Mode", "Backup"}
    engine.force({"Main": "on"})
    assert engine.outcome("Fallback", 0) == {"Mode", "Main"}  # forced: nothing changes
    engine.force({"Main": "auto"})
    engine.set_unavailable({"Backup": "backup cannot start"})
    assert engine.outcome("Fallback", 0) == {"Mode", "Main"}


# ---- what the engines compile for a configuration ------------------------------------------
def _engine(pkg: Path, **kw: Any) -> ResolutionEngineProcess:
    return ResolutionEngineProcess(deploy(pkg, kw.pop("names", [])), BusConfig(), **kw)


def _situation(re: ResolutionEngineProcess, **changes: Any) -> Situation:
    target = re.target(re.selection, re.cv)
    running = {s.name: s for s in re._specs(target, target.components)}
    rep = re.dep.package.runtime.replacement
    standby = {s.name: msgspec.structs.replace(s, active=rep.hot(s.name))
               for s in re.standby_specs(target)}  # fmt: skip
    fields: dict[str, Any] = dict(
        selection=re.selection, cv=re.cv, forced={}, unavailable={}, conflicts=frozenset(),
        runtime_model=target, running=running, standby=standby, reachable=lambda h: True,
        target=re.target,
    )  # fmt: skip
    return Situation(**{**fields, **changes})


def _strategy(tmp_path: Path, strategy: str, src: Path = QUAD) -> Path:
    pkg = tmp_path / "pkg"
    shutil.copytree(src, pkg, ignore=shutil.ignore_patterns("*.scenario.yaml"))
    runtime = pkg / "runtime.yaml"
    runtime.write_text(runtime.read_text().replace(
        "proploss_controller: hot-standby", f"proploss_controller: {strategy}"))  # fmt: skip
    return pkg


def test_a_hot_standby_switch_is_one_rewire_of_the_consumer() -> None:
    re = _engine(QUAD, names=["Hover"])
    planned, why = re.reflexes.compiler.compile(_situation(re))
    assert why == {}
    [p] = planned.values()
    assert p.rule == "MotorLoss" and p.features == {"Controller", "Proploss"}
    [(node, part)] = p.parts.items()
    assert node == "vehicle_simulator"
    assert part.key == "rra/quadcopter/data/vehicle_simulator/telemetry"
    proploss = "rra/quadcopter/data/proploss_controller/motor_cmd"
    assert part.actions == [m.ReflexAction(kind="rewire", port="motor_cmd", keys=[proploss])]
    assert part.any_of == [[m.ReflexTest(measurement="WorkingMotors", op="<", value=4.0)]]


def test_a_standby_switch_also_activates_the_standby(tmp_path: Path) -> None:
    re = _engine(_strategy(tmp_path, "standby"), names=["Hover"])
    planned, _ = re.reflexes.compiler.compile(_situation(re))
    [p] = planned.values()
    assert {n: [a.kind for a in part.actions] for n, part in p.parts.items()} == {
        "vehicle_simulator": ["rewire"],
        "proploss_controller": ["activate"],  # it receives the telemetry: it sees the source
    }


def test_a_cold_swap_is_no_reflex(tmp_path: Path) -> None:
    re = _engine(_strategy(tmp_path, "stop-then-start"), names=["Hover"])
    planned, why = re.reflexes.compiler.compile(_situation(re))
    assert planned == {}
    assert why == {"MotorLoss": "proploss_controller does not run yet (stop-then-start)"}


def test_no_reflex_under_an_override_a_conflict_or_a_partial_plan() -> None:
    re = _engine(QUAD, names=["Hover"])
    compile_ = re.reflexes.compiler.compile
    # Forced Standard: the rule changes nothing; forced anything of its family: no reflex.
    assert compile_(_situation(re, forced={"Standard": True}))[1] == {
        "MotorLoss": "it changes nothing in this configuration"
    }
    assert compile_(_situation(re, forced={"Controller": True}))[1] == {
        "MotorLoss": "an operator forced Controller"
    }
    assert compile_(_situation(re, conflicts=frozenset({"MotorLoss"})))[1] == {
        "MotorLoss": "it is in a conflict in force"
    }
    assert compile_(_situation(re, unavailable={"Proploss": "it cannot start"}))[1] == {
        "MotorLoss": "it changes nothing in this configuration"
    }
    sent: list[list[Ctl]] = []
    keeper = _keeper(re, sent)
    keeper.sync(_situation(re, degraded=True))
    assert keeper.installed == {} and sent == []
    assert keeper.why == {"MotorLoss": "what runs is not what was decided"}


# ---- installing, confirming, rolling back --------------------------------------------------
def _keeper(re: ResolutionEngineProcess, sent: list[list[Ctl]], events: list | None = None,
            replies=None, confirm_s: float = 0.5) -> ReflexKeeper:  # fmt: skip
    situation = _situation(re)
    specs = {**situation.running, **situation.standby}

    def send(batch: list[Ctl]) -> list[m.Reply]:
        sent.append(batch)
        return [replies(c) if replies else m.Ok() for c in batch]

    def emit(kind: str, text: str, **fields: Any) -> None:
        (events if events is not None else []).append((kind, text, fields))

    return ReflexKeeper(re.reflexes.compiler, send, emit, specs.get, confirm_s=confirm_s,
                        log=lambda text: None)  # fmt: skip


def _fired(ident: str, node: str = "vehicle_simulator", values=None) -> m.ReflexFired:
    return m.ReflexFired(node=node, id=ident, rule="MotorLoss", stamp=time.time(),
                         values=values or {"WorkingMotors": 3})  # fmt: skip


PROPLOSS = frozenset({"Controller", "Proploss"})
STANDARD = frozenset({"Controller", "Standard"})


def test_installed_once_then_confirmed_by_the_engines_decision() -> None:
    re = _engine(QUAD, names=["Hover"])
    sent: list[list[Ctl]] = []
    events: list = []
    keeper = _keeper(re, sent, events)
    keeper.sync(_situation(re))
    keeper.sync(_situation(re))  # nothing changed: nothing sent
    assert [[type(c.request).__name__ for c in b] for b in sent] == [["InstallReflex"]]
    [ident] = keeper.installed
    assert keeper.on_fired(_fired(ident)) is not None
    assert [r.fired_by for r in keeper.state()] == [["vehicle_simulator"]]
    keeper.decided(PROPLOSS)
    assert keeper.fired == {} and keeper.confirmed == 1
    [(kind, text, fields)] = events
    assert kind == "reflex" and fields["outcome"] == "ok" and "confirm" in fields["durations"]
    assert "the engines decided +Proploss, -Standard and confirmed it" in text


def test_rolled_back_when_not_confirmed_in_time_and_not_armed_again() -> None:
    re = _engine(QUAD, names=["Hover"])
    sent: list[list[Ctl]] = []
    events: list = []
    keeper = _keeper(re, sent, events, confirm_s=0.0)
    keeper.sync(_situation(re))
    [ident] = keeper.installed
    keeper.on_fired(_fired(ident))
    keeper.decided(STANDARD)  # a decision that does not touch Proploss yet: pending
    assert ident in keeper.fired
    keeper.tick()
    undo = sent[-1]
    assert [type(c.request).__name__ for c in undo] == ["WithdrawReflex", "Rewire"]
    controller = "rra/quadcopter/data/controller/motor_cmd"
    assert undo[1].request == m.Rewire(port="motor_cmd", keys=[controller])
    assert [f["outcome"] for _, _, f in events] == ["rolled_back"]
    assert keeper.installed == {} and keeper.rolled_back == 1
    keeper.sync(_situation(re))  # the same configuration: not armed again
    assert keeper.installed == {}
    assert keeper.why["MotorLoss"] == "rolled back in this configuration"


def test_rolled_back_at_once_when_the_engines_decide_otherwise() -> None:
    re = _engine(QUAD, names=["Hover"])
    sent: list[list[Ctl]] = []
    events: list = []
    keeper = _keeper(re, sent, events)
    keeper.sync(_situation(re))
    [ident] = keeper.installed
    keeper.on_fired(_fired(ident))
    record = keeper.fired[ident].record
    # A decision that changes the reflex's features to something it did not decide.
    keeper.decided(frozenset(record.before) - {"Standard"} | {"Other"})
    assert [f["outcome"] for _, _, f in events] == ["rolled_back"]


def test_a_report_of_a_reflex_not_installed_there_is_refused() -> None:
    re = _engine(QUAD, names=["Hover"])
    refused: list = []
    keeper = _keeper(re, [])
    keeper.refuse = lambda kind, detail: refused.append(detail)
    keeper.sync(_situation(re))
    [ident] = keeper.installed
    assert keeper.on_fired(_fired("forged-1")) is None
    assert keeper.on_fired(_fired(ident, node="estimator")) is None
    assert len(refused) == 2 and keeper.fired == {}


def test_a_node_that_refuses_its_part_leaves_no_reflex_installed(tmp_path: Path) -> None:
    re = _engine(_strategy(tmp_path, "standby"), names=["Hover"])
    sent: list[list[Ctl]] = []

    def replies(c: Ctl) -> m.Reply:
        if isinstance(c.request, m.InstallReflex) and c.spec.name == "proploss_controller":
            return m.Err(message="cannot import the function", code="refused")
        return m.Ok()

    keeper = _keeper(re, sent, replies=replies)
    keeper.sync(_situation(re))
    assert keeper.installed == {}
    assert [type(c.request).__name__ for c in sent[-1]] == ["WithdrawReflex", "WithdrawReflex"]
    assert keeper.why["MotorLoss"].startswith("not installed: proploss_controller: cannot import")


def test_a_new_leader_confirms_what_its_predecessor_installed() -> None:
    re = _engine(QUAD, names=["Hover"])
    leader = _keeper(re, [])
    leader.sync(_situation(re))
    standby_sent: list[list[Ctl]] = []
    events: list = []
    standby = _keeper(re, standby_sent, events)
    standby.mirror(leader.state())
    [ident] = standby.installed
    standby.on_fired(_fired(ident))  # every replica records the fire
    standby.take_over()
    standby.sync(_situation(re))  # the same reflex: nothing installed again
    assert standby_sent == []
    standby.decided(PROPLOSS)
    assert [f["outcome"] for _, _, f in events] == ["ok"]


# ---- the node's side ---------------------------------------------------------------------
def _plant(path: Path = PKG, value: float = 1.0) -> NodeHarness:
    import reflex_nodes  # the package's own module (its folder is on the path)

    return NodeHarness(reflex_nodes.Plant, name="plant", params={"value": value},
                       ports={"out": ("publish", "Level"), "cmd": ("subscribe", "Command")},
                       path=[str(path)])  # fmt: skip


def _reflex(**kw: Any) -> m.Reflex:
    fields: dict[str, Any] = dict(
        id="Fallback-1", rule="Fallback", source="plant.out", key="rra/test/data/plant/out",
        measurements=["Level"], any_of=[[m.ReflexTest(measurement="Level", op="<", value=0.0)]],
        actions=[m.ReflexAction(kind="rewire", port="cmd", keys=["rra/test/data/backup/out"])],
    )  # fmt: skip
    return m.Reflex(**{**fields, **kw})


@pytest.fixture
def package_on_path(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(PKG))


def test_a_node_fires_once_on_its_own_output_after_its_step(package_on_path) -> None:
    h = _plant()
    assert isinstance(h.request(m.InstallReflex(reflex=_reflex())), m.Ok)
    h.step(1.0)
    assert h.fired == []
    h.request(m.SetParams(params={"value": -1.0}))
    h.step(1.02)
    [fired] = h.fired
    assert (fired.node, fired.id, fired.values) == ("plant", "Fallback-1", {"Level": -1.0})
    assert h.core.ports["cmd"].keys == ["rra/test/data/backup/out"]
    h.step(1.04)
    assert len(h.fired) == 1  # once
    info = h.request(m.Describe())
    assert isinstance(info, m.Ok) and info.result["reflexes"] == {"Fallback-1": fired.stamp}


def test_a_node_fires_on_an_input_sample_after_on_message(package_on_path) -> None:
    from rra_agent.nodes.generic import Relay

    h = NodeHarness(Relay, name="backup", ports={"in": ("subscribe", "Level"),
                    "out": ("publish", "Command")}, active=False, path=[str(PKG)])  # fmt: skip
    reflex = _reflex(key="rra/test/data/backup/in", actions=[m.ReflexAction(kind="activate")])
    assert isinstance(h.request(m.InstallReflex(reflex=reflex)), m.Ok)
    h.send("in", {"seq": 1, "value": 2.0})
    assert h.fired == [] and not h.core.active
    h.send("in", {"seq": 2, "value": -3.0})
    assert len(h.fired) == 1 and h.core.active
    # Activated after the sample reached the node: its newest output goes out at once.
    assert h.outputs("out")[-1]["value"] == -3.0


def test_a_node_refuses_a_reflex_it_cannot_compute(package_on_path) -> None:
    h = _plant()
    bad = [
        (_reflex(measurements=["Nope"]), "the package declares no measurement Nope"),
        (_reflex(key="rra/test/data/other/out"), "no port of this node carries"),
        (_reflex(actions=[m.ReflexAction(kind="rewire", port="out", keys=[])]),
         "no input port 'out'"),
    ]  # fmt: skip
    for reflex, why in bad:
        reply = h.request(m.InstallReflex(reflex=reflex))
        assert isinstance(reply, m.Err) and why in reply.message, reply
    no_package = NodeHarness(type(h.node), name="plant", ports={"out": ("publish", "Level")})
    reply = no_package.request(m.InstallReflex(reflex=_reflex(actions=[])))
    assert isinstance(reply, m.Err) and "no package folder" in reply.message


def test_a_function_that_raises_never_fires_and_the_node_goes_on(
    tmp_path: Path, package_on_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    pkg = tmp_path / "pkg"
    shutil.copytree(PKG, pkg)
    meas = pkg / "measurements.yaml"
    meas.write_text(
        meas.read_text().replace(
            "reflex_functions.level", "reflex_functions.level_but_not_in_the_plant"
        )
    )
    h = _plant(pkg, value=-1.0)
    monkeypatch.setenv("RRA_NODE_SPEC", '{"name": "plant"}')
    assert isinstance(h.request(m.InstallReflex(reflex=_reflex())), m.Ok)
    for i in range(3):
        h.step(1.0 + i * 0.02)
    assert h.fired == [] and len(h.outputs("out")) == 3
    stats = h.request(m.Stats())
    assert isinstance(stats, m.Ok) and stats.result.counters["reflex_errors"] == 3


def test_rra_status_lists_the_installed_reflexes_in_100_columns() -> None:
    from rra_agent.cli.status import WIDTH, reflex_lines

    record = {"rule": "MotorLoss", "nodes": ["vehicle_simulator"], "before": ["Standard"],
              "features": ["Proploss"], "fired": 0.0}  # fmt: skip
    assert reflex_lines({}) == []
    assert reflex_lines({"reflexes": {"installed": [record]}}) == [
        "reflex      MotorLoss in vehicle_simulator: +Proploss, -Standard (armed)"
    ]
    fired = reflex_lines({"reflexes": {"installed": [{**record, "fired": time.time()}]}})
    assert " ".join(x.strip() for x in fired).endswith("awaiting confirmation)")
    many = {**record, "nodes": [f"node_with_a_long_name_{i}" for i in range(6)]}
    lines = reflex_lines({"reflexes": {"installed": [many]}})
    assert len(lines) > 1 and all(len(x) <= WIDTH for x in lines)


def test_no_reflexes_without_an_adaptation_engine_to_confirm_them() -> None:
    from rra_agent.cli.up import engine_specs

    dep = deploy(PKG)

    def resolution_cmd(**kw: Any) -> list[str]:
        specs = engine_specs(dep, [], Path("/tmp/run"), "local", **kw)
        [spec] = [s for s in specs if s.name.startswith("resolution")][:1]
        return list(spec.implementation.command)

    assert "--no-reflexes" not in resolution_cmd(adaptation=True)
    assert "--no-reflexes" in resolution_cmd(adaptation=False)
    assert "--no-reflexes" in resolution_cmd(adaptation=True, reflexes=False)
