"""Taking over a running system: what runs, compared with what should run.

A Run-time Resolution Engine that starts while nodes of its system already run (it was
killed and restarted by its host agent) must not restart them: it reads their state back
(the host agents' node lists, then each node's ``Describe``: implementation, parameters,
port bindings, active flag) and turns the difference to the target model into an ordinary
plan: nodes that match are adopted as they are, parameters and wiring that differ are set,
a node running the wrong implementation (or inactive where it should be active) is
restarted, missing nodes are started and nodes that should not run are stopped. The first
deployment is the case where nothing runs yet.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply
from rra_agent.core import resolution as r
from rra_agent.models.system import SystemModel


@dataclass
class Observed:
    """Nodes of this system running now, as specs, by name."""

    nodes: dict[str, m.NodeSpec] = field(default_factory=dict)


def spec_from_info(system: str, info: dict[str, Any], implementation: Any) -> m.NodeSpec:
    """A `NodeSpec` from a node's ``Describe`` reply (``implementation``: the model's, when
    the reported one is the same program)."""
    ports = {
        p["name"]: m.PortSpec(direction=p["direction"], type=p["type"], keys=list(p["keys"]))
        for p in info["ports"]
    }
    reported = info["implementation"]
    impl_id = (
        implementation if isinstance(implementation, str) else " ".join(implementation.command)
    )
    return m.NodeSpec(
        system=system,
        name=info["name"],
        host=info["host"],
        implementation=implementation if reported == impl_id else reported,
        params=dict(info["params"]),
        ports=ports,
        active=bool(info["active"]),
    )


def observe(
    client: BusClient, hosts: list[str], configured: SystemModel, timeout: float = 2.0
) -> Observed:
    """Every component of ``configured`` that a host agent reports RUNNING, described."""
    components = {c.name: c for c in configured.components}
    out = Observed()
    for host in hosts:
        try:
            reply = client.host(host, m.ListNodes(), timeout)
        except NoReply:
            continue
        if not isinstance(reply, m.Ok):
            continue
        for node in reply.result:
            name = node["node"]
            if name not in components or node["state"] != "RUNNING":
                continue
            try:
                info = client.node(name, m.Describe(), timeout)
            except NoReply:
                continue
            if isinstance(info, m.Ok):
                impl = components[name].implementation
                out.nodes[name] = spec_from_info(configured.system, info.result, impl)
    return out


def takeover_plan(
    observed: Observed,
    expected: dict[str, m.NodeSpec],
    target: SystemModel,
    keep_standby: set[str],
) -> tuple[r.Plan, dict[str, m.NodeSpec], dict[str, m.NodeSpec]]:
    """The plan from what runs to ``target``, and the nodes to hand the executor as already
    running and as standby. ``expected``: the spec each target component should run with;
    ``keep_standby``: components that may stay running inactive as standby replacements."""
    subs = r.subscriptions(target)
    by_name = {c.name: c for c in target.components}
    running: dict[str, m.NodeSpec] = {}
    standby: dict[str, m.NodeSpec] = {}
    steps: list[r.PlanStep] = []
    for name, seen in observed.nodes.items():
        if name in expected:
            running[name] = seen
            steps += _reconcile(seen, expected[name], by_name[name], subs)
        elif name in keep_standby and not seen.active:
            standby[name] = seen
        else:
            running[name] = seen
            steps.append(r.StopComponent(component=name))
    starts = [
        r.StartComponent(component=n, definition=by_name[n], **_wiring(by_name[n], subs))
        for n in expected
        if n not in observed.nodes
    ]
    return r.Plan(steps=tuple(_canonical(starts + steps))), running, standby


def _wiring(c, subs) -> dict[str, dict]:
    return {
        "inputs": {p.name: subs[(c.name, p.name)] for p in c.ports if p.direction == "subscribe"},
        "outputs": {
            p.name: p.topic or f"{c.name}/{p.name}" for p in c.ports if p.direction == "publish"
        },
    }


def _reconcile(seen: m.NodeSpec, want: m.NodeSpec, c, subs) -> list[r.PlanStep]:
    same_shape = (
        seen.implementation == want.implementation
        and seen.host == want.host
        and {n: (p.direction, p.type) for n, p in seen.ports.items()}
        == {n: (p.direction, p.type) for n, p in want.ports.items()}
        and set(seen.params) == set(want.params)
        and seen.active == want.active
    )
    if not same_shape:
        return [
            r.SetImplementation(
                component=c.name,
                implementation=c.implementation,
                previous=seen.implementation,
                definition=c,
                **_wiring(c, subs),
            )
        ]
    steps: list[r.PlanStep] = []
    values = {k: v for k, v in want.params.items() if seen.params.get(k) != v}
    if values:
        steps.append(r.SetParameters(component=c.name, values=values))
    for port, spec in want.ports.items():
        if spec.direction == "subscribe" and seen.ports[port].keys != spec.keys:
            steps.append(r.Rewire(component=c.name, port=port, topics=subs[(c.name, port)]))
    return steps


_ORDER = (r.StartComponent, r.SetImplementation, r.SetParameters, r.Rewire, r.StopComponent)


def _canonical(steps: list[r.PlanStep]) -> list[r.PlanStep]:
    return sorted(steps, key=lambda s: next(i for i, t in enumerate(_ORDER) if isinstance(s, t)))
