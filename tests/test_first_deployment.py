"""The run's first deployment, when another Run-time Resolution Engine replica led at the
same moment (real processes: a host agent, and a Run-time Resolution Engine started by
hand).

Two replicas started together can both see the role leaderless and both claim epoch 1; the
fence lets only one act. Once seen (a scenario run waited 60 s for a ``deploy`` event that
never came): the loser had started some nodes before the winner's claim reached the host,
so the winner reported its deployment as ``adopt``; and a replica that had mirrored the
state of a leader that had not deployed yet took that state as a deployment to continue.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import msgspec
import pytest
import zenoh
from conftest import RELAY, RELAY_KEYS, ok

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, wait_until
from rra_agent.core import resolution as r
from rra_agent.deployment import deploy
from rra_agent.engines.events import read_events
from rra_agent.engines.executor import spec_for

K = RELAY_KEYS


@pytest.fixture
def host(procs, bus, tmp_path):
    """The host agent of host ``local`` for relay_system (the bus's hub), and a client."""
    procs.python(
        "rra_agent.host.agent", "--package", str(RELAY), "--host", "local", "--hub",
        "--log-dir", str(tmp_path / "nodes"), "--connect", bus.connect[0], "--no-multicast",
        "--lease-ms", "500", name="agent",
    )  # fmt: skip
    client = BusClient(bus, "relay_system")
    try:
        wait_until(lambda: list(client.session.liveliness().get(K.host_alive("local"),
                                                               timeout=0.5)),
                   30, "the host agent's token")  # fmt: skip
        yield client
    finally:
        client.close()


def resolution_engine(procs, bus, tmp_path: Path, name: str = "resolution-a") -> Path:
    """``python -m rra_agent.engines.resolution`` by hand, alone of its role; its run folder."""
    run_dir = tmp_path / "run"
    run_dir.mkdir(exist_ok=True)
    procs.python(
        "rra_agent.engines.resolution", "--package", str(RELAY), "--name", name, "--host",
        "local", "--run-dir", str(run_dir), "--no-record", "--connect", bus.connect[0],
        "--no-multicast", "--lease-ms", "500", name="engine",
    )  # fmt: skip
    return run_dir


def first_deployment(run_dir: Path, procs) -> m.AdaptationEvent:
    """The engine's first event about the system as a whole (deploy, adopt or reconcile)."""

    def found() -> m.AdaptationEvent | None:
        log = run_dir / "events.jsonl"
        events = read_events(log) if log.exists() else []
        return next((e for e in events if isinstance(e, m.AdaptationEvent)
                     and e.kind in ("deploy", "adopt", "reconcile")), None)  # fmt: skip

    try:
        return wait_until(found, 60, "the engine's first deployment")
    except TimeoutError:
        raise AssertionError(procs.log("engine")) from None


def node_pid(client: BusClient, name: str) -> int | None:
    nodes = msgspec.convert(ok(client.host("local", m.ListNodes())), list[m.NodeState])
    return next((n.pid for n in nodes if n.node == name and n.state == "RUNNING"), None)


def source_spec(fence: m.Fence) -> m.NodeSpec:
    """``source`` as the deployment's model starts it."""
    dep = deploy(RELAY)
    pkg = dep.package
    model = r.resolve_runtime(dep.configured, pkg.runtime, pkg.features,
                              {"Relay", "Path", "Tuning", "Direct"}, {"Gain": 1.0})  # fmt: skip
    c = next(c for c in model.components if c.name == "source")
    spec = spec_for(K, c, {}, {"out": "source/out"}, default_host="local")
    return msgspec.structs.replace(spec, fence=fence)


def test_a_deployment_begun_by_a_superseded_rival_is_the_run_s_deploy(host, procs, bus, tmp_path):
    """The rival (``resolution-b``, epoch 1) acted first: it started ``source``. The engine
    claims epoch 1 too, which beats the rival's (same epoch, smaller name): it takes the
    rival's node over and reports the run's ``deploy``, not an ``adopt`` (the scenario
    runner's time 0), and the rival can no longer act."""
    rival = m.Fence(epoch=1, leader="resolution-b")
    ok(host.host("local", m.Claim(fence=rival)))
    ok(host.host("local", m.StartNode(spec=source_spec(rival), fence=rival)))
    pid = wait_until(lambda: node_pid(host, "source"), 30, "the rival's source RUNNING")
    run_dir = resolution_engine(procs, bus, tmp_path)
    ev = first_deployment(run_dir, procs)
    assert (ev.kind, ev.outcome) == ("deploy", "ok"), ev
    assert ev.fence is not None and (ev.fence.epoch, ev.fence.leader) == (1, "resolution-a")
    assert "(1 found running)" in ev.message, ev.message
    assert node_pid(host, "source") == pid  # taken over, not restarted
    late = host.host("local", m.StopNode(node="source", fence=rival))
    assert isinstance(late, m.Err) and late.code == "stale_fence", late


def test_the_state_of_a_leader_that_had_not_deployed_is_not_continued(host, procs, bus, tmp_path):
    """The engine starts while another replica leads but has not deployed yet: it mirrors
    that leader's answer, and when it leads in its stead (the other is gone) it deploys the
    system, rather than taking the empty state for a deployment to continue."""
    dep = deploy(RELAY)
    state = m.EngineState(
        fence=m.Fence(epoch=1, leader="resolution-0"), version=0,
        selection=["Direct"], cv={"Gain": 1.0}, models=dep.models, deployed=False,
    )  # fmt: skip
    answer = m.Codec(m.Reply).encode(m.Ok(result=msgspec.to_builtins(state)))
    on_query: Callable[[zenoh.Query], None] = lambda q: q.reply(q.key_expr, answer)  # noqa: E731
    leader = host.session.declare_queryable(K.engine_ctl("resolution"), on_query)
    try:
        run_dir = resolution_engine(procs, bus, tmp_path)
        ev = first_deployment(run_dir, procs)
    finally:
        leader.undeclare()
    assert (ev.kind, ev.outcome) == ("deploy", "ok"), ev
    assert ev.fence is not None and ev.fence.epoch == 2  # above the leader it had mirrored
    assert node_pid(host, "sink") is not None
