"""What is in effect after a plan applied in part (`rra_agent.core.effect`).

The invariant that matters: whatever fails, the nodes the executor runs are exactly the
effective model's components, with its implementations, parameters and wiring, so the next
plan (from the effective model to the target) is the right one.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rra_agent.core import resolution as r
from rra_agent.core.effect import effective_model, in_effect
from rra_agent.core.features import apply_requests, complete_deployment, default_runtime_selection
from rra_agent.core.plan import diff, subscriptions
from rra_agent.engines.executor import Executor
from rra_agent.models.resolution import Replacement
from rra_agent.package.loader import load_package
from tests.test_executor import FakeActuator, K

ROOT = Path(__file__).resolve().parents[1]
PKG = load_package(ROOT / "scenarios" / "object_storing")
FM = PKG.features
DEP = complete_deployment(FM, PKG.manifest.default_selection)
CONFIGURED = r.resolve_deployment(PKG.system, PKG.deployment, FM, DEP)
CHOICES = [
    (env, chan, rack, mat, vel)
    for env, chan, rack, mat, vel in itertools.product(
        ("Static", "Dynamic"), ("ChannelA", "ChannelB"), (None, "Small", "Large"),
        (None, "Fragile"), (0.4, 0.7),
    )
]  # fmt: skip


def selection(choice: tuple) -> tuple[frozenset[str], dict[str, float]]:
    env, chan, rack, mat, vel = choice
    wanted = [("activate", f) for f in (env, chan, rack, mat) if f is not None]
    if rack is None:
        wanted.append(("deactivate", "RackSize"))
    if mat is None:
        wanted.append(("deactivate", "Material"))
    sel, refused = apply_requests(FM, DEP, default_runtime_selection(FM, DEP), wanted)
    assert not refused, refused
    return sel, {"MaxVel": vel}


def target(choice: tuple) -> r.SystemModel:
    sel, cv = selection(choice)
    return r.resolve_runtime(CONFIGURED, PKG.runtime, FM, sel, cv)


def check_runs_as(ex: Executor, model: r.SystemModel) -> None:
    """The executor's running nodes are exactly ``model``'s, as ``model`` configures them."""
    assert set(ex.running) == {c.name for c in model.components}
    subs = subscriptions(model)
    for c in model.components:
        spec = ex.running[c.name]
        assert spec.implementation == c.implementation, c.name
        assert spec.params == {k: p.value for k, p in c.parameters.items()}, c.name
        for p in c.ports:
            if p.direction == "subscribe":
                want = sorted(K.data(t) for t in subs[(c.name, p.name)])
                assert sorted(spec.ports[p.name].keys) == want, (c.name, p.name)


NODES = sorted(c.name for c in CONFIGURED.components)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    a=st.sampled_from(CHOICES),
    b=st.sampled_from(CHOICES),
    start_fails=st.sets(st.sampled_from(NODES), max_size=3),
    params_fail=st.sets(st.sampled_from(NODES), max_size=2),
    strategy=st.sampled_from(["stop-then-start", "start-then-stop"]),
)
def test_whatever_fails_the_nodes_run_as_the_effective_model(
    a, b, start_fails, params_fail, strategy
):
    act = FakeActuator()
    ex = Executor(act, K, Replacement(default=strategy), default_host="local")
    empty = r.SystemModel(system=CONFIGURED.system, hosts=CONFIGURED.hosts)
    current = target(a)
    assert ex.execute(diff(empty, current)).ok
    goal = target(b)
    act.broken = {(c.name, c.implementation) for c in goal.components if c.name in start_fails}
    act.fail_on = {("params", n) for n in params_fail}
    out = ex.execute(diff(current, goal))
    effective = effective_model(current, goal, out.failed_structure, out.failed_parameters)
    check_runs_as(ex, effective)
    # and once nothing fails any more, the rest of the way is the plan from there
    act.fail_on, act.broken = set(), set()
    assert ex.execute(diff(effective, goal)).ok
    check_runs_as(ex, goal)


def from_a_to_b(a: tuple, b: tuple, fail_on: set[tuple[str, str]]):
    """Deploy ``a``, go to ``b`` with ``fail_on`` failing: (outcome, selection and CV in
    effect, CV values of ``b`` and of ``a``)."""
    act = FakeActuator()
    ex = Executor(act, K, Replacement(), default_host="local")
    empty = r.SystemModel(system=CONFIGURED.system, hosts=CONFIGURED.hosts)
    assert ex.execute(diff(empty, target(a))).ok
    act.fail_on = fail_on
    out = ex.execute(diff(target(a), target(b)))
    effective = effective_model(target(a), target(b), out.failed_structure, out.failed_parameters)
    (sel_a, cv_a), (sel_b, cv_b) = selection(a), selection(b)
    sel, cv = in_effect(FM, PKG.runtime, sel_b, sel_a, effective, target(b), cv_b, cv_a)
    return out, sel, cv, cv_b, cv_a


def test_what_is_in_effect_when_the_channel_cannot_start():
    """Channel B's radio driver does not start: Channel B is decided but not in effect,
    Channel A (still running) is; the rack size, applied, is in effect."""
    out, sel, cv, cv_b, _ = from_a_to_b(
        ("Static", "ChannelA", "Small", None, 0.4),
        ("Static", "ChannelB", "Large", None, 0.7),
        {("start", "radio_driver_b")},
    )
    assert out.partial
    assert "ChannelA" in sel and "ChannelB" not in sel
    assert "Large" in sel and "Small" not in sel
    assert cv == cv_b  # MaxVel's parameter (local navigation) was set


def test_a_parameter_refused_keeps_its_cv_out_of_effect():
    out, _, cv, _, cv_a = from_a_to_b(
        ("Static", "ChannelA", None, None, 0.4),
        ("Static", "ChannelA", None, None, 0.7),
        {("params", "local_navigation")},
    )
    assert not out.ok
    assert cv == cv_a


@pytest.mark.parametrize("choice", CHOICES[:4])
def test_nothing_failed_means_the_target_is_in_effect(choice):
    sel, cv = selection(choice)
    t = target(choice)
    assert effective_model(t, t, ()) == t
    got, got_cv = in_effect(FM, PKG.runtime, sel, frozenset(), t, t, cv, {})
    assert got == sel and got_cv == cv
