"""Reconciliation: what runs, compared with what should run, as an ordinary plan.

The Run-time Configured System Model is the desired state; the host agents report the
observed one. The Run-time Resolution Engine leader compares them whenever it takes over and
then periodically (a reconcile loop, as a Kubernetes controller runs), and turns the
difference into a `Plan` its executor carries out:

- a node its host reports RUNNING is *described* (``Describe``: implementation, parameters,
  port bindings, active flag) when the engine does not know its live configuration yet
  (a new process, a new leader); one whose configuration is known (``verified``) is not
  asked again. Parameters, wiring and activation that differ are set; a wrong
  implementation is restarted;
- a node the host is (re)starting, backing off, probing or holding FATAL is the host's to
  handle (its restart policy, its cool-down): nothing is done but telling the host the
  right spec if its copy differs;
- a node its host reports RUNNING but that does not answer is left alone this round (the
  host agent decides whether it is frozen: heartbeat and probe); the engine never restarts
  a process for not answering it;
- a desired node that is STOPPED, EXITED or unknown on a reachable host is started;
- a node that runs but should not is stopped;
- nothing is done on a host that does not answer (a partition is context, not a crash).

The first deployment is the case where nothing runs yet.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field
from typing import Any

import msgspec

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply
from rra_agent.core.plan import (
    Plan,
    PlanStep,
    Rewire,
    SetImplementation,
    SetParameters,
    StartComponent,
    StopComponent,
    subscriptions,
    wiring,
)
from rra_agent.models.system import SystemModel

#: Observed states in which the host agent is handling the node itself.
HOST_HANDLES = frozenset({"STARTING", "BACKOFF", "UNRESPONSIVE", "FATAL", "STOPPING"})


@dataclass
class Observed:
    """What the host agents report for the components of a system."""

    #: Running and described (or already verified): the spec it runs with.
    nodes: dict[str, m.NodeSpec] = field(default_factory=dict)
    #: Being handled by its host agent (starting, backing off, probed, FATAL): name -> state.
    pending: dict[str, m.NodeState] = field(default_factory=dict)
    #: RUNNING by its host's account but not answering now: name -> host.
    silent: dict[str, str] = field(default_factory=dict)
    #: Every state the hosts reported, by node.
    states: dict[str, m.NodeState] = field(default_factory=dict)
    #: Hosts that did not answer.
    unreachable: set[str] = field(default_factory=set)
    #: Nodes described this round: name -> pid (their live configuration is now known).
    described: dict[str, int] = field(default_factory=dict)

    def forget(self, name: str) -> None:
        """Leave a node out of this round (a probe's: not the model's to start or stop)."""
        for table in (self.nodes, self.pending, self.silent, self.states, self.described):
            table.pop(name, None)


def spec_from_info(info: dict[str, Any], template: m.NodeSpec) -> m.NodeSpec:
    """What a node runs with, from its ``Describe`` reply: ``template`` (the spec the model
    gives it: declarations, supervision, import path) with the live implementation, host,
    parameters, port bindings and active flag."""
    ports = {
        p["name"]: m.PortSpec(
            direction=p["direction"],
            type=p["type"],
            keys=list(p["keys"]),
            standby=list(p.get("standby", ())),
        )
        for p in info["ports"]
    }
    reported = info["implementation"]
    impl = template.implementation
    return msgspec.structs.replace(
        template,
        host=info["host"],
        implementation=impl if reported == m.implementation_id(impl) else reported,
        params=dict(info["params"]),
        ports=ports,
        active=bool(info["active"]),
        state=None,
    )


def observe(
    client: BusClient,
    hosts: list[str],
    templates: dict[str, m.NodeSpec],
    *,
    known: dict[str, tuple[int, m.NodeSpec]] | None = None,
    timeout: float = 2.0,
) -> Observed:
    """The observed state of every component with a spec in ``templates`` (what the model
    would run it with; `spec_from_info`). ``known``: nodes whose live configuration the
    caller already knows, as (pid, spec): not described again while their pid is the same."""
    known = known or {}
    out = Observed()
    for host in hosts:
        try:
            reply = client.host(host, m.ListNodes(), timeout)
        except NoReply:
            out.unreachable.add(host)
            continue
        if not isinstance(reply, m.Ok):
            out.unreachable.add(host)
            continue
        for raw in reply.result:
            try:
                st = msgspec.convert(raw, m.NodeState)
            except msgspec.ValidationError:
                continue
            if st.node not in templates:
                continue  # an engine, or a node of another model
            out.states[st.node] = st
            if st.state in HOST_HANDLES:
                out.pending[st.node] = st
            elif st.state == "RUNNING":
                _running(client, out, st, templates[st.node], known, timeout)
    return out


def _running(client, out: Observed, st: m.NodeState, template, known, timeout) -> None:
    have = known.get(st.node)
    if have is not None and have[0] == st.pid:
        out.nodes[st.node] = have[1]
        return
    info = _describe(client, st.node, timeout)
    if info is None or info.get("pid") != st.pid:
        out.silent[st.node] = st.host
        return
    out.nodes[st.node] = spec_from_info(info, template)
    out.described[st.node] = st.pid  # type: ignore[assignment]


def _describe(client: BusClient, name: str, timeout: float) -> dict[str, Any] | None:
    try:
        reply = client.node(name, m.Describe(), timeout)
    except NoReply:
        return None
    return reply.result if isinstance(reply, m.Ok) else None


def takeover_plan(
    observed: Observed,
    expected: dict[str, m.NodeSpec],
    target: SystemModel,
    keep_standby: set[str],
    hot: Collection[str] = (),
) -> tuple[Plan, dict[str, m.NodeSpec], dict[str, m.NodeSpec]]:
    """The plan from what runs to ``target``, and the nodes to hand the executor as already
    running and as standby. ``expected``: the spec each target component should run with;
    ``keep_standby``: components that may stay running inactive as standby replacements, or
    active if they are in ``hot`` (hot standbys)."""
    subs = subscriptions(target)
    by_name = {c.name: c for c in target.components}
    running: dict[str, m.NodeSpec] = {}
    standby: dict[str, m.NodeSpec] = {}
    steps: list[PlanStep] = []
    unreachable = {n for n, st in observed.states.items() if st.host in observed.unreachable} | {
        n for n, s in expected.items() if s.host in observed.unreachable
    }
    for name in [*observed.pending, *observed.silent, *unreachable]:
        # The host handles it, or cannot be asked now: count it as what it should be.
        if name in expected:
            running[name] = expected[name]
        elif name in keep_standby:
            st = observed.states.get(name)
            if st is not None and st.active == (name in hot):
                standby[name] = _placeholder(target.system, st)
        elif name in observed.states and name not in unreachable:
            st = observed.states[name]
            if st.state != "STOPPING":
                running[name] = _placeholder(target.system, st)
                steps.append(StopComponent(component=name))
    for name, seen in observed.nodes.items():
        if name in expected:
            running[name] = seen
            steps += _reconcile(seen, expected[name], by_name[name], subs)
        elif name in keep_standby and seen.active == (name in hot):
            standby[name] = seen
        else:
            running[name] = seen
            steps.append(StopComponent(component=name))
    present = {*observed.nodes, *observed.pending, *observed.silent, *unreachable}
    starts = [
        StartComponent(component=n, definition=by_name[n], **wiring(by_name[n], subs))
        for n in expected
        if n not in present
    ]
    return Plan(steps=tuple(_canonical(starts + steps))), running, standby


def _placeholder(system: str, st: m.NodeState) -> m.NodeSpec:
    return m.NodeSpec(
        system=system,
        name=st.node,
        host=st.host,
        implementation=st.implementation,
        active=st.active,
    )


def _reconcile(seen: m.NodeSpec, want: m.NodeSpec, c, subs) -> list[PlanStep]:
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
            SetImplementation(
                component=c.name,
                implementation=c.implementation,
                previous=seen.implementation,
                definition=c,
                **wiring(c, subs),
            )
        ]
    steps: list[PlanStep] = []
    values = {k: v for k, v in want.params.items() if seen.params.get(k) != v}
    if values:
        steps.append(SetParameters(component=c.name, values=values))
    for port, spec in want.ports.items():
        if spec.direction == "subscribe" and seen.ports[port].keys != spec.keys:
            steps.append(Rewire(component=c.name, port=port, topics=subs[(c.name, port)]))
    return steps


_ORDER = (StartComponent, SetImplementation, SetParameters, Rewire, StopComponent)


def _canonical(steps: list[PlanStep]) -> list[PlanStep]:
    return sorted(steps, key=lambda s: next(i for i, t in enumerate(_ORDER) if isinstance(s, t)))
