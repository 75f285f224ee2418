"""The plan (paper Sec. III-E): the steps that turn one running system into another.

`diff` compares two configured system models and produces the `Plan` that turns the
running system of one into the other's; `topic_of`, `subscriptions`, `wiring` and
`standby_subscriptions` define how connections map onto topics. Pure."""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Mapping

import msgspec

from rra_agent.errors import ResolutionError
from rra_agent.models.system import (
    Component,
    Implementation,
    ParamValue,
    SystemModel,
    parse_endpoint,
)


def same_value(a: object, b: object) -> bool:
    """Value equality that tells booleans from numbers (``True != 1`` here)."""
    if isinstance(a, bool) or isinstance(b, bool):
        return type(a) is type(b) and a == b
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same_value(x, y) for x, y in zip(a, b, strict=True))
    return a == b


# ---------------------------------------------------------------------------------------------
# Topics: how connections map onto the bus
# ---------------------------------------------------------------------------------------------
def topic_of(system: SystemModel, component: str, port: str) -> str:
    """The topic a publisher port writes: ``Port.topic``, else ``<component>/<port>``."""
    comp = system.component(component)
    if comp is None:
        raise ResolutionError(f"no component {component!r} in system {system.system!r}")
    p = comp.port(port)
    if p is None:
        raise ResolutionError(f"component {component!r} has no port {port!r}")
    if p.direction != "publish":
        raise ResolutionError(f"port '{component}.{port}' does not publish")
    return p.topic or f"{component}/{port}"


def subscriptions(system: SystemModel) -> dict[tuple[str, str], tuple[str, ...]]:
    """(component, subscriber port) -> the sorted topics it listens on, from the connections.

    Every subscriber port of every component is a key (an unconnected one maps to ``()``), in
    model order. A connection whose endpoints are not a present publisher and subscriber port
    raises `ResolutionError`.
    """
    topics: dict[tuple[str, str], set[str]] = {
        (c.name, p.name): set()
        for c in system.components
        for p in c.ports
        if p.direction == "subscribe"
    }
    for conn in system.connections:
        src, dst = parse_endpoint(conn.source), parse_endpoint(conn.target)
        key = (dst.component, dst.port)
        if key not in topics:
            raise ResolutionError(
                f"connection {conn.source} -> {conn.target}: {conn.target!r} is not a "
                f"subscriber port of a component of {system.system!r}"
            )
        topics[key].add(topic_of(system, src.component, src.port))
    return {k: tuple(sorted(v)) for k, v in topics.items()}


def standby_subscriptions(
    system: SystemModel, hot: Iterable[str]
) -> dict[str, dict[str, tuple[str, ...]]]:
    """component -> subscriber port -> the sorted topics of the ``hot`` components connected
    to it in ``system`` (the deployment-time configured model, optional connections included):
    what each consumer listens to in advance, without delivering, so that switching it to a
    hot standby is a selection, not a new subscription."""
    hot = set(hot)
    out: dict[str, dict[str, set[str]]] = {}
    for conn in system.connections:
        src, dst = parse_endpoint(conn.source), parse_endpoint(conn.target)
        if src.component in hot and dst.component not in hot:
            topics = out.setdefault(dst.component, {}).setdefault(dst.port, set())
            topics.add(topic_of(system, src.component, src.port))
    return {c: {p: tuple(sorted(t)) for p, t in ports.items()} for c, ports in out.items()}


# ---------------------------------------------------------------------------------------------
# The plan: steps turning one running system into another
# ---------------------------------------------------------------------------------------------
class Step(msgspec.Struct, frozen=True, kw_only=True, tag_field="op"):
    """Base of the plan steps; ``component`` names the component acted on."""

    component: str


class StartComponent(Step, frozen=True, tag="start_component"):
    """Launch ``component`` from ``definition``; ``inputs`` maps each subscriber port to its
    topics, ``outputs`` each publisher port to its topic."""

    definition: Component
    inputs: dict[str, tuple[str, ...]] = {}
    outputs: dict[str, str] = {}


class StopComponent(Step, frozen=True, tag="stop_component"):
    """Shut ``component`` down."""


class SwapComponent(Step, frozen=True, tag="swap_component"):
    """Replace ``component`` (stopped) by ``replacement`` (started from ``definition``), which
    is connected to the same peers: the executor applies the replacement strategy (and state
    transfer) of the Run-time Resolution Model for ``replacement``."""

    replacement: str
    definition: Component
    inputs: dict[str, tuple[str, ...]] = {}
    outputs: dict[str, str] = {}


class SetImplementation(Step, frozen=True, tag="set_implementation"):
    """Restart ``component`` from its new ``definition``: emitted when its implementation (or
    its host, ports or parameter declarations) changed."""

    implementation: Implementation
    previous: Implementation
    definition: Component
    inputs: dict[str, tuple[str, ...]] = {}
    outputs: dict[str, str] = {}


class SetParameters(Step, frozen=True, tag="set_parameters"):
    """Set the changed parameter ``values`` of a running component."""

    values: dict[str, ParamValue]


class Rewire(Step, frozen=True, tag="rewire"):
    """Make subscriber ``port`` of a running component listen on exactly ``topics``."""

    port: str
    topics: tuple[str, ...]


PlanStep = (
    StartComponent | StopComponent | SwapComponent | SetImplementation | SetParameters | Rewire
)


class Plan(msgspec.Struct, frozen=True, kw_only=True):
    """Ordered steps; see `diff` for the order."""

    steps: tuple[PlanStep, ...] = ()

    @property
    def empty(self) -> bool:
        return not self.steps

    @property
    def started(self) -> tuple[str, ...]:
        """Components launched (started, or swapped in)."""
        return tuple(_launched(self.steps))

    @property
    def stopped(self) -> tuple[str, ...]:
        """Components shut down (stopped, or swapped out)."""
        return tuple(
            s.component for s in self.steps if isinstance(s, StopComponent | SwapComponent)
        )


def _launched(steps: tuple[PlanStep, ...]) -> Iterator[str]:
    for s in steps:
        if isinstance(s, StartComponent):
            yield s.component
        elif isinstance(s, SwapComponent):
            yield s.replacement


def diff(current: SystemModel, target: SystemModel) -> Plan:
    """The plan turning the running system of ``current`` into that of ``target``.

    What runs is compared: for each component its implementation, host, ports, parameter
    declarations and values, and the topics each subscriber port listens on (descriptions,
    alternative ``implementations``, ``optional``/``binding`` flags and model order are
    metadata). The plan is empty iff the two running systems are equal; both models must be
    of the same system with the same hosts.

    Steps, in this canonical order (each group in target model order unless said otherwise):

    1. `StartComponent` for each component only in ``target`` (not part of a swap);
    2. `SwapComponent` for each swap pair, in ``current`` order. A component ``old`` only in
       ``current`` and ``new`` only in ``target`` form a pair when the peer endpoints ``old``
       is connected to in ``current`` equal (non-empty) those ``new`` is connected to in
       ``target``, as sets of (direction, ``peer.port``). Candidates are paired greedily,
       ``old`` in ``current`` order, each taking the first unpaired ``new`` in ``target`` order.
    3. `SetImplementation` (a restart) for each component in both whose implementation, host,
       ports or parameter declarations (names, types) changed;
    4. `SetParameters` with the changed values, for each other component in both;
    5. `Rewire` of each subscriber port, of a component in both and not restarted, whose topics
       changed (a started, swapped-in or restarted component gets its ``inputs`` with its step);
    6. `StopComponent` for each component only in ``current`` (not part of a swap), in
       ``current`` order.

    Starts come before rewires and stops so that a make-before-break executor can follow the
    order as is; a stop-then-start executor reorders.
    """
    _check_comparable(current, target)
    cur = {c.name: c for c in current.components}
    tgt = {c.name: c for c in target.components}
    cur_subs, tgt_subs = subscriptions(current), subscriptions(target)
    gone = [n for n in cur if n not in tgt]
    new = [n for n in tgt if n not in cur]
    swaps = _pair_swaps(current, target, gone, new)
    swapped_in, swapped_out = {n for _, n in swaps}, {o for o, _ in swaps}
    both = [n for n in tgt if n in cur]
    restarted = [n for n in both if _shape(cur[n]) != _shape(tgt[n])]
    running = [n for n in both if n not in restarted]

    steps: list[PlanStep] = [
        StartComponent(component=n, definition=tgt[n], **wiring(tgt[n], tgt_subs))
        for n in new
        if n not in swapped_in
    ]
    steps += [
        SwapComponent(component=o, replacement=n, definition=tgt[n], **wiring(tgt[n], tgt_subs))
        for o, n in swaps
    ]
    steps += _kept_steps(restarted, running, cur, tgt, cur_subs, tgt_subs)
    steps += [StopComponent(component=n) for n in gone if n not in swapped_out]
    return Plan(steps=tuple(steps))


def _kept_steps(
    restarted: list[str],
    running: list[str],
    cur: dict[str, Component],
    tgt: dict[str, Component],
    cur_subs: dict[tuple[str, str], tuple[str, ...]],
    tgt_subs: dict[tuple[str, str], tuple[str, ...]],
) -> list[PlanStep]:
    """For the components in both models: `SetImplementation` of the ``restarted``, then
    `SetParameters` and `Rewire` of those that keep ``running`` as they are."""
    steps: list[PlanStep] = [
        SetImplementation(
            component=n,
            implementation=tgt[n].implementation,
            previous=cur[n].implementation,
            definition=tgt[n],
            **wiring(tgt[n], tgt_subs),
        )
        for n in restarted
    ]
    for n in running:
        values = _changed_parameters(cur[n], tgt[n])
        if values:
            steps.append(SetParameters(component=n, values=values))
    steps += [
        Rewire(component=n, port=p.name, topics=tgt_subs[(n, p.name)])
        for n in running
        for p in tgt[n].ports
        if p.direction == "subscribe" and cur_subs[(n, p.name)] != tgt_subs[(n, p.name)]
    ]
    return steps


def _check_comparable(current: SystemModel, target: SystemModel) -> None:
    if current.system != target.system:
        raise ResolutionError(
            f"cannot diff system {current.system!r} against system {target.system!r}"
        )
    if current.hosts != target.hosts:
        raise ResolutionError(f"the hosts of system {current.system!r} differ between models")


def _shape(c: Component) -> tuple[object, ...]:
    """What a running component cannot change without a restart."""
    decls = {k: p.type for k, p in c.parameters.items()}
    return (c.implementation, c.host, tuple(c.ports), decls)


def _changed_parameters(cur: Component, tgt: Component) -> dict[str, ParamValue]:
    return {
        k: p.value
        for k, p in tgt.parameters.items()
        if not same_value(cur.parameters[k].value, p.value)
    }


def wiring(c: Component, subs: Mapping[tuple[str, str], tuple[str, ...]]) -> dict[str, dict]:
    """A component's ``inputs`` (subscriber port -> topics) and ``outputs`` (publisher port ->
    topic), as plan steps carry them; ``subs`` from `subscriptions`."""
    return {
        "inputs": {p.name: subs[(c.name, p.name)] for p in c.ports if p.direction == "subscribe"},
        "outputs": {
            p.name: p.topic or f"{c.name}/{p.name}" for p in c.ports if p.direction == "publish"
        },
    }


def peers_of(system: SystemModel, name: str) -> frozenset[tuple[str, str]]:
    """The endpoints a component is connected to: ("in", publisher) / ("out", subscriber)."""
    out = set()
    for conn in system.connections:
        src, dst = parse_endpoint(conn.source), parse_endpoint(conn.target)
        if src.component == name and dst.component != name:
            out.add(("out", conn.target))
        elif dst.component == name and src.component != name:
            out.add(("in", conn.source))
    return frozenset(out)


def _pair_swaps(
    current: SystemModel, target: SystemModel, gone: list[str], new: list[str]
) -> list[tuple[str, str]]:
    new_peers = {n: peers_of(target, n) for n in new}
    pairs: list[tuple[str, str]] = []
    taken: set[str] = set()
    for old in gone:
        peers = peers_of(current, old)
        match = next((n for n in new if n not in taken and peers and new_peers[n] == peers), None)
        if match is not None:
            taken.add(match)
            pairs.append((old, match))
    return pairs
