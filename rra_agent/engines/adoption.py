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
from rra_agent.models.resolution import ResolutionModel
from rra_agent.models.system import SystemModel


@dataclass
class Observed:
    """Nodes of this system running now, as specs, by name."""

    nodes: dict[str, m.NodeSpec] = field(default_factory=dict)
    #: Running by their host's account, but not answering: name -> host.
    silent: dict[str, str] = field(default_factory=dict)


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


def managed_parameters(model: ResolutionModel) -> set[tuple[str, str]]:
    """(component, parameter) pairs some transformation of ``model`` sets."""
    return {
        (t.set_parameter.component, t.set_parameter.parameter)
        for ts in model.features.values()
        for t in ts
        if t.set_parameter is not None
    }


def observe(
    client: BusClient, hosts: list[str], configured: SystemModel, timeout: float = 5.0
) -> Observed:
    """Every component of ``configured`` that a host agent reports RUNNING, described.

    A node that its host reports RUNNING but that does not answer ``Describe`` (twice) is
    recorded with ``silent``: it runs, in a state we cannot read, so it is restarted."""
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
            info = _describe(client, name, timeout)
            if info is None:
                out.silent[name] = host
                continue
            impl = components[name].implementation
            out.nodes[name] = spec_from_info(configured.system, info, impl)
    return out


def _describe(client: BusClient, name: str, timeout: float) -> dict[str, Any] | None:
    for _ in range(2):
        try:
            reply = client.node(name, m.Describe(), timeout)
        except NoReply:
            continue
        if isinstance(reply, m.Ok):
            return reply.result
    return None


def takeover_plan(
    observed: Observed,
    expected: dict[str, m.NodeSpec],
    target: SystemModel,
    keep_standby: set[str],
    managed: set[tuple[str, str]] | None = None,
) -> tuple[r.Plan, dict[str, m.NodeSpec], dict[str, m.NodeSpec]]:
    """The plan from what runs to ``target``, and the nodes to hand the executor as already
    running and as standby. ``expected``: the spec each target component should run with;
    ``keep_standby``: components that may stay running inactive as standby replacements;
    ``managed``: the (component, parameter) pairs the Run-time Resolution Model sets — only
    those are set back; any other parameter keeps the value it has (None: all are managed)."""
    subs = r.subscriptions(target)
    by_name = {c.name: c for c in target.components}
    running: dict[str, m.NodeSpec] = {}
    standby: dict[str, m.NodeSpec] = {}
    steps: list[r.PlanStep] = []
    for name, host in observed.silent.items():
        # It runs but we cannot read its state: restart it (or stop it if it should not run).
        want = expected.get(name)
        running[name] = want or m.NodeSpec(
            system=target.system, name=name, host=host, implementation=""
        )
        if want is not None:
            c = by_name[name]
            steps.append(
                r.SetImplementation(
                    component=name,
                    implementation=c.implementation,
                    previous=c.implementation,
                    definition=c,
                    **r.wiring(c, subs),
                )
            )
        else:
            steps.append(r.StopComponent(component=name))
    for name, seen in observed.nodes.items():
        if name in expected:
            running[name] = seen
            steps += _reconcile(seen, expected[name], by_name[name], subs, managed)
        elif name in keep_standby and not seen.active:
            standby[name] = seen
        else:
            running[name] = seen
            steps.append(r.StopComponent(component=name))
    starts = [
        r.StartComponent(component=n, definition=by_name[n], **r.wiring(by_name[n], subs))
        for n in expected
        if n not in observed.nodes and n not in observed.silent
    ]
    return r.Plan(steps=tuple(_canonical(starts + steps))), running, standby


def _reconcile(seen: m.NodeSpec, want: m.NodeSpec, c, subs, managed) -> list[r.PlanStep]:
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
                **r.wiring(c, subs),
            )
        ]
    steps: list[r.PlanStep] = []
    values = {
        k: v
        for k, v in want.params.items()
        if seen.params.get(k) != v and (managed is None or (c.name, k) in managed)
    }
    if values:
        steps.append(r.SetParameters(component=c.name, values=values))
    for port, spec in want.ports.items():
        if spec.direction == "subscribe" and seen.ports[port].keys != spec.keys:
            steps.append(r.Rewire(component=c.name, port=port, topics=subs[(c.name, port)]))
    return steps


_ORDER = (r.StartComponent, r.SetImplementation, r.SetParameters, r.Rewire, r.StopComponent)


def _canonical(steps: list[r.PlanStep]) -> list[r.PlanStep]:
    return sorted(steps, key=lambda s: next(i for i, t in enumerate(_ORDER) if isinstance(s, t)))
