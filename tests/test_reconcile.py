"""Taking over a running system: the plan from what runs to the target (no bus)."""

from __future__ import annotations

from pathlib import Path

import msgspec
import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.core import resolution as r
from rra_agent.core.plan import Plan, subscriptions
from rra_agent.deployment import deploy
from rra_agent.engines.executor import spec_for
from rra_agent.engines.reconcile import Observed, spec_from_info, takeover_plan

DATA = Path(__file__).parent / "data" / "relay_system"
K = Keys("relay_system")


@pytest.fixture(scope="module")
def world():
    dep = deploy(DATA)
    pkg = dep.package

    def target(path: str, gain: float = 1.0):
        sel = {"Relay", "Path", "Tuning", path}
        return r.resolve_runtime(dep.configured, pkg.runtime, pkg.features, sel, {"Gain": gain})

    def expected(model):
        subs = subscriptions(model)
        out = {}
        for c in model.components:
            inputs = {p.name: subs.get((c.name, p.name), ()) for p in c.ports}
            outputs = {p.name: f"{c.name}/{p.name}" for p in c.ports if p.direction == "publish"}
            out[c.name] = spec_for(K, c, inputs, outputs, default_host="local")
        return out

    return target, expected


def kinds(plan: Plan) -> list[tuple[str, str]]:
    return [(type(s).__name__, s.component) for s in plan.steps]


def test_everything_running_as_it_should_is_adopted_without_a_step(world):
    target, expected = world
    tgt = target("Direct")
    want = expected(tgt)
    plan, running, standby = takeover_plan(Observed(dict(want)), want, tgt, set())
    assert plan.empty and set(running) == {"source", "direct", "sink"} and not standby


def test_nothing_running_is_a_deployment(world):
    target, expected = world
    tgt = target("Direct")
    plan, running, _ = takeover_plan(Observed(), expected(tgt), tgt, set())
    assert kinds(plan) == [("StartComponent", n) for n in ("source", "direct", "sink")]
    assert not running


def test_differences_become_ordinary_steps(world):
    target, expected = world
    tgt = target("Filtered", gain=7.0)
    want = expected(tgt)
    seen = dict(want)
    seen["sink"] = msgspec.structs.replace(
        want["sink"],
        params={"offset": 1.0},  # an old CV value
        ports={**want["sink"].ports, "in": msgspec.structs.replace(
            want["sink"].ports["in"], keys=[K.data("direct/out")])},  # the old wiring
    )  # fmt: skip
    del seen["filtered"]  # not started yet
    seen["direct"] = spec_for(  # still running from before
        K, next(c for c in target("Direct").components if c.name == "direct"),
        {"in": ("source/out",)}, {"out": "direct/out"}, default_host="local",
    )  # fmt: skip
    seen["source"] = msgspec.structs.replace(want["source"], active=False)  # inactive
    plan, running, _ = takeover_plan(Observed(seen), want, tgt, set())
    assert kinds(plan) == [
        ("StartComponent", "filtered"),
        ("SetImplementation", "source"),  # inactive where it should run: restarted
        ("SetParameters", "sink"),
        ("Rewire", "sink"),
        ("StopComponent", "direct"),
    ]
    assert plan.steps[2].values == {"offset": 7.0}
    assert plan.steps[3].topics == ("filtered/out",)
    assert set(running) == {"source", "sink", "direct"}


def test_an_inactive_standby_candidate_stays_on_standby(world):
    target, expected = world
    tgt = target("Direct")
    want = expected(tgt)
    filtered = spec_for(
        K, next(c for c in target("Filtered").components if c.name == "filtered"),
        {"in": ("source/out",)}, {"out": "filtered/out"}, default_host="local", active=False,
    )  # fmt: skip
    plan, _, standby = takeover_plan(Observed({**want, "filtered": filtered}), want, tgt,
                                     {"filtered"})  # fmt: skip
    assert plan.empty and set(standby) == {"filtered"}


def test_an_active_hot_standby_stays_on_standby_and_an_active_plain_one_is_stopped(world):
    """A hot standby runs active (it publishes on keys its consumers do not select yet): a
    new leader adopts it as a standby. An active node that should be a plain standby is not
    one (it would publish), nor is an inactive node that should be hot (its consumers would
    wait for samples that never come)."""
    target, expected = world
    tgt = target("Direct")
    want = expected(tgt)
    comp = next(c for c in target("Filtered").components if c.name == "filtered")

    def filtered(active: bool) -> m.NodeSpec:
        return spec_for(K, comp, {"in": ("source/out",)}, {"out": "filtered/out"},
                        default_host="local", active=active)  # fmt: skip

    seen = Observed({**want, "filtered": filtered(True)})
    plan, _, standby = takeover_plan(seen, want, tgt, {"filtered"}, {"filtered"})
    assert plan.empty and set(standby) == {"filtered"}
    plan, _, standby = takeover_plan(seen, want, tgt, {"filtered"})
    assert kinds(plan) == [("StopComponent", "filtered")] and not standby
    seen = Observed({**want, "filtered": filtered(False)})
    plan, _, standby = takeover_plan(seen, want, tgt, {"filtered"}, {"filtered"})
    assert kinds(plan) == [("StopComponent", "filtered")] and not standby


def test_spec_from_describe_round_trips(world):
    target, expected = world
    want = expected(target("Direct"))["sink"]
    info = {
        "name": "sink", "implementation": want.implementation, "host": "local",
        "active": True, "params": dict(want.params),
        "ports": [{"name": n, "direction": p.direction, "type": p.type, "keys": p.keys}
                  for n, p in want.ports.items()],
    }  # fmt: skip
    assert spec_from_info(info, want) == want
    live = spec_from_info({**info, "params": {"offset": 5.0}, "active": False}, want)
    assert live.params == {"offset": 5.0} and not live.active and live.decl == want.decl


def test_a_running_node_that_does_not_answer_is_left_to_its_host_agent(world):
    """Only the host agent decides that a process is frozen (heartbeat and probe): a node
    that does not answer the engine now is neither restarted nor started a second time."""
    target, expected = world
    tgt = target("Direct")
    want = expected(tgt)
    seen = {n: s for n, s in want.items() if n != "sink"}
    plan, running, _ = takeover_plan(Observed(seen, silent={"sink": "local"}), want, tgt, set())
    assert plan.empty and "sink" in running


def test_nodes_the_host_is_restarting_are_its_business(world):
    target, expected = world
    tgt = target("Direct")
    want = expected(tgt)
    seen = {n: s for n, s in want.items() if n != "sink"}
    backoff = m.NodeState(stamp=0.0, node="sink", host="local", state="BACKOFF")
    observed = Observed(seen, pending={"sink": backoff}, states={"sink": backoff})
    plan, running, _ = takeover_plan(observed, want, tgt, set())
    assert plan.empty and running["sink"] == want["sink"]


def test_a_stopped_node_is_started_again(world):
    target, expected = world
    tgt = target("Direct")
    want = expected(tgt)
    seen = {n: s for n, s in want.items() if n != "sink"}
    stopped = m.NodeState(stamp=0.0, node="sink", host="local", state="STOPPED")
    plan, _, _ = takeover_plan(Observed(seen, states={"sink": stopped}), want, tgt, set())
    assert kinds(plan) == [("StartComponent", "sink")]


def test_nothing_is_done_on_an_unreachable_host(world):
    target, expected = world
    tgt = target("Direct")
    want = expected(tgt)
    seen = {n: s for n, s in want.items() if n != "sink"}
    plan, running, _ = takeover_plan(Observed(seen, unreachable={"local"}), want, tgt, set())
    assert plan.empty and "sink" in running


def test_every_parameter_that_drifted_from_the_desired_model_is_set_back(world):
    """Operators' values are part of the desired model (the engine's overrides); anything
    else that differs on a running node (set behind the engine's back) is drift."""
    target, expected = world
    tgt = target("Direct", gain=3.0)
    want = expected(tgt)
    seen = dict(want)
    seen["source"] = msgspec.structs.replace(want["source"], params={"rate_hz": 20.0, "value": 7.0})
    seen["sink"] = msgspec.structs.replace(want["sink"], params={"offset": 9.0})
    plan, _, _ = takeover_plan(Observed(seen), want, tgt, set())
    assert kinds(plan) == [("SetParameters", "source"), ("SetParameters", "sink")]
    assert [s.values for s in plan.steps] == [{"value": 1.0}, {"offset": 3.0}]
