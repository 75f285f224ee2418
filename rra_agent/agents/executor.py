"""Execute a reconfiguration `Plan` on the running system, transactionally.

The Run-time Resolution Engine computes a `Plan` (`rra_agent.core.resolution.diff`); this
module carries it out through an `Actuator` (host agents and node control endpoints on the
bus, or a fake in unit tests). Every action that changed the running system is recorded
with its inverse; if a step fails (a node not ready in time, a control request refused),
the inverses run in reverse order and the system is back in its previous configuration.

Order of execution (from the plan's canonical order):

1. new components start, all at once, and are waited for together;
2. swaps, each with the replacement strategy of the Run-time Resolution Model for the
   component swapped in:
   - ``stop-then-start``: stop the old node, start the new one;
   - ``start-then-stop`` (make before break): start the new node inactive, wait until it is
     ready, transfer state, activate it, deactivate the old one (stopped in phase 5);
   - ``standby``: the new node is already running inactive (pre-started at deployment);
     switching is transfer state, activate it, deactivate the old one (stopped in phase 5,
     or kept as a standby itself when its own strategy is ``standby``);
3. restarts (`SetImplementation`): stop, then start with the new definition (a node's name is
   its identity on the bus, so old and new cannot overlap);
4. parameter changes, then rewires (subscribers of swapped or restarted peers included);
5. components that go stop, all at once, with the nodes swapped out by ``start-then-stop``
   and ``standby`` (an inactive old node publishes nothing, so stopping it last costs the
   switch nothing).

State transfer (`Replacement.state_transfer`): the old node's exported state is handed to
the new one (import_state on a running node, or in the spec of a node being started).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import msgspec

from rra_agent.bus.keys import Keys
from rra_agent.bus.messages import NodeSpec, PortSpec
from rra_agent.core import resolution as r
from rra_agent.errors import RraError
from rra_agent.models.resolution import Replacement
from rra_agent.models.system import Component


class StepFailed(RraError):
    """An action on the running system failed; the plan is rolled back."""


class Actuator(Protocol):
    """What the executor needs from the running system."""

    def start(self, specs: list[NodeSpec]) -> None:
        """Start the nodes and return once all are ready; raise StepFailed otherwise."""
        ...

    def stop(self, nodes: list[NodeSpec]) -> None:
        """Stop the nodes and return once all are gone; raise StepFailed otherwise."""
        ...

    def set_params(self, spec: NodeSpec, values: dict[str, Any]) -> None: ...

    def rewire(self, spec: NodeSpec, port: str, keys: list[str]) -> None: ...

    def set_active(self, spec: NodeSpec, active: bool) -> None: ...

    def export_state(self, spec: NodeSpec) -> Any: ...

    def import_state(self, spec: NodeSpec, state: Any) -> None: ...


@dataclass
class StepRecord:
    """What one action did and how long it took (the adaptation event's plan lines)."""

    action: str
    node: str
    seconds: float
    ok: bool = True
    detail: str = ""

    def line(self) -> str:
        status = "ok" if self.ok else f"FAILED: {self.detail}"
        return f"{self.action} {self.node} ({self.seconds * 1e3:.1f} ms) {status}"


@dataclass
class Outcome:
    ok: bool
    records: list[StepRecord] = field(default_factory=list)
    error: str = ""
    rolled_back: bool = False
    rollback_error: str = ""
    seconds: float = 0.0
    #: Time from the start of execution until the first swapped-in node was active.
    first_switch: float | None = None


def spec_for(
    keys: Keys,
    c: Component,
    inputs: dict[str, tuple[str, ...]],
    outputs: dict[str, str],
    *,
    default_host: str,
    active: bool = True,
    state: Any = None,
) -> NodeSpec:
    """The `NodeSpec` that runs component ``c`` with the given wiring (topics -> keys)."""
    ports: dict[str, PortSpec] = {}
    for p in c.ports:
        if p.direction == "publish":
            topic = outputs.get(p.name, p.topic or f"{c.name}/{p.name}")
            ports[p.name] = PortSpec(direction="publish", type=p.type, keys=[keys.data(topic)])
        else:
            topics = inputs.get(p.name, ())
            ports[p.name] = PortSpec(
                direction="subscribe", type=p.type, keys=[keys.data(t) for t in topics]
            )
    return NodeSpec(
        system=keys.system,
        name=c.name,
        host=c.host or default_host,
        implementation=c.implementation,
        params={k: p.value for k, p in c.parameters.items()},
        ports=ports,
        active=active,
        state=state,
    )


class Transaction:
    """Runs actions, remembers how to undo each, and undoes them all on failure."""

    def __init__(self, clock: Callable[[], float]) -> None:
        self.clock = clock
        self.records: list[StepRecord] = []
        self.undo: list[tuple[str, Callable[[], None]]] = []

    def run(self, action: str, node: str, do: Callable[[], Any], undo: Callable[[], None] | None):
        t0 = self.clock()
        try:
            result = do()
        except StepFailed as e:
            self.records.append(StepRecord(action, node, self.clock() - t0, False, str(e)))
            raise
        self.records.append(StepRecord(action, node, self.clock() - t0))
        if undo is not None:
            self.undo.append((f"undo {action} {node}", undo))
        return result

    def rollback(self) -> str:
        """Undo in reverse order; returns the first undo failure ('' when all went well)."""
        first = ""
        for what, fn in reversed(self.undo):
            try:
                fn()
            except Exception as e:  # keep undoing the rest
                first = first or f"{what}: {e}"
        self.undo.clear()
        return first


class Executor:
    """Holds the running nodes' specs and applies plans to them."""

    def __init__(
        self,
        actuator: Actuator,
        keys: Keys,
        replacement: Replacement,
        *,
        default_host: str,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.actuator = actuator
        self.keys = keys
        self.replacement = replacement
        self.default_host = default_host
        self.clock = clock
        #: Nodes of the Run-time Configured System Model, by name.
        self.running: dict[str, NodeSpec] = {}
        #: Pre-started, inactive replacements (``standby`` strategy), by name.
        self.standby: dict[str, NodeSpec] = {}

    # ---- public ------------------------------------------------------------------------
    def prestart_standby(self, specs: list[NodeSpec]) -> Outcome:
        """Start standby replacements inactive (at deployment time)."""
        specs = [msgspec.structs.replace(s, active=False) for s in specs]
        tx = Transaction(self.clock)
        t0 = self.clock()
        try:
            if specs:
                tx.run(
                    "prestart",
                    ",".join(s.name for s in specs),
                    lambda: self.actuator.start(specs),
                    None,
                )
        except StepFailed as e:
            return Outcome(False, tx.records, str(e), seconds=self.clock() - t0)
        for s in specs:
            self.standby[s.name] = s
        return Outcome(True, tx.records, seconds=self.clock() - t0)

    def execute(self, plan: r.Plan) -> Outcome:
        t0 = self.clock()
        tx = Transaction(self.clock)
        running_before = dict(self.running)
        standby_before = dict(self.standby)
        self._first_switch: float | None = None
        self._retired: list[NodeSpec] = []
        try:
            self._apply(plan, tx)
        except StepFailed as e:
            rollback_error = tx.rollback()
            self.running, self.standby = running_before, standby_before
            return Outcome(
                False,
                tx.records,
                str(e),
                rolled_back=not rollback_error,
                rollback_error=rollback_error,
                seconds=self.clock() - t0,
            )
        first = None if self._first_switch is None else self._first_switch - t0
        return Outcome(True, tx.records, seconds=self.clock() - t0, first_switch=first)

    # ---- plan phases -------------------------------------------------------------------
    def _apply(self, plan: r.Plan, tx: Transaction) -> None:
        steps = plan.steps
        starts = [s for s in steps if isinstance(s, r.StartComponent)]
        if starts:
            specs = [self._spec(s.definition, s.inputs, s.outputs) for s in starts]
            self._start(tx, specs)
        for s in steps:
            if isinstance(s, r.SwapComponent):
                self._swap(tx, s)
        for s in steps:
            if isinstance(s, r.SetImplementation):
                self._restart(tx, s)
        for s in steps:
            if isinstance(s, r.SetParameters):
                self._set_params(tx, s.component, dict(s.values))
        for s in steps:
            if isinstance(s, r.Rewire):
                self._rewire(tx, s.component, s.port, [self.keys.data(t) for t in s.topics])
        stops = [self.running[s.component] for s in steps if isinstance(s, r.StopComponent)]
        stops += [self.running[spec.name] for spec in self._retired]
        if stops:
            self._stop(tx, stops)

    def _spec(self, c: Component, inputs, outputs, *, active=True, state=None) -> NodeSpec:
        return spec_for(
            self.keys,
            c,
            dict(inputs),
            dict(outputs),
            default_host=self.default_host,
            active=active,
            state=state,
        )

    # ---- actions (each with its inverse) -----------------------------------------------
    def _start(self, tx: Transaction, specs: list[NodeSpec]) -> None:
        names = ",".join(s.name for s in specs)

        def undo() -> None:
            self.actuator.stop(specs)
            for s in specs:
                self.running.pop(s.name, None)

        tx.run("start", names, lambda: self.actuator.start(specs), undo)
        for s in specs:
            self.running[s.name] = s

    def _stop(self, tx: Transaction, specs: list[NodeSpec]) -> None:
        names = ",".join(s.name for s in specs)

        def undo() -> None:
            self.actuator.start(specs)
            for s in specs:
                self.running[s.name] = s

        tx.run("stop", names, lambda: self.actuator.stop(specs), undo)
        for s in specs:
            self.running.pop(s.name, None)

    def _set_active(self, tx: Transaction, spec: NodeSpec, active: bool) -> NodeSpec:
        tx.run(
            "activate" if active else "deactivate",
            spec.name,
            lambda: self.actuator.set_active(spec, active),
            lambda: self.actuator.set_active(spec, not active),
        )
        return msgspec.structs.replace(spec, active=active)

    def _set_params(self, tx: Transaction, name: str, values: dict[str, Any]) -> None:
        spec = self.running[name]
        old = {k: spec.params.get(k) for k in values}
        tx.run(
            "set_params",
            name,
            lambda: self.actuator.set_params(spec, values),
            lambda: self.actuator.set_params(spec, old),
        )
        self.running[name] = msgspec.structs.replace(spec, params={**spec.params, **values})

    def _rewire(self, tx: Transaction, name: str, port: str, keys: list[str]) -> None:
        spec = self.running.get(name) or self.standby[name]
        old = list(spec.ports[port].keys)
        if old == keys:
            return
        tx.run(
            f"rewire {port} of",
            name,
            lambda: self.actuator.rewire(spec, port, keys),
            lambda: self.actuator.rewire(spec, port, old),
        )
        ports = dict(spec.ports)
        ports[port] = msgspec.structs.replace(ports[port], keys=keys)
        new = msgspec.structs.replace(spec, ports=ports)
        (self.running if name in self.running else self.standby)[name] = new

    def _transfer(self, old: NodeSpec, new_name: str) -> Any:
        wanted = any(
            t.source == old.name and t.target == new_name for t in self.replacement.state_transfer
        )
        return self.actuator.export_state(old) if wanted else None

    def _swap(self, tx: Transaction, s: r.SwapComponent) -> None:
        old = self.running[s.component]
        strategy = self.replacement.strategy_for(s.replacement)
        if strategy == "standby" and s.replacement in self.standby:
            self._swap_standby(tx, s, old)
        elif strategy in ("start-then-stop", "standby"):
            self._swap_make_before_break(tx, s, old)
        else:
            self._swap_stop_then_start(tx, s, old)

    def _swap_stop_then_start(self, tx: Transaction, s: r.SwapComponent, old: NodeSpec) -> None:
        state = self._transfer(old, s.replacement)
        self._stop(tx, [old])
        self._start(tx, [self._spec(s.definition, s.inputs, s.outputs, state=state)])
        self._first_switch = self.clock()

    def _swap_make_before_break(self, tx: Transaction, s: r.SwapComponent, old: NodeSpec):
        new = self._spec(s.definition, s.inputs, s.outputs, active=False)
        self._start(tx, [new])
        self._hand_over(tx, old, new)
        self._retired.append(old)  # stopped last, once its subscribers are rewired

    def _swap_standby(self, tx: Transaction, s: r.SwapComponent, old: NodeSpec) -> None:
        # Bookkeeping (running/standby) is restored from snapshots on rollback.
        self.running[s.replacement] = self.standby.pop(s.replacement)
        for port, topics in s.inputs.items():
            self._rewire(tx, s.replacement, port, [self.keys.data(t) for t in topics])
        self._hand_over(tx, old, self.running[s.replacement])
        if self.replacement.strategy_for(old.name) == "standby":
            self.standby[old.name] = self.running.pop(old.name)  # warm for the way back
        else:
            self._retired.append(old)

    def _hand_over(self, tx: Transaction, old: NodeSpec, new: NodeSpec) -> None:
        """State transfer, then activate the new node and deactivate the old one."""
        state = self._transfer(old, new.name)
        if state is not None:
            tx.run("import_state", new.name, lambda: self.actuator.import_state(new, state), None)
        self.running[new.name] = self._set_active(tx, new, True)
        self._first_switch = self.clock()
        self.running[old.name] = self._set_active(tx, old, False)

    def _restart(self, tx: Transaction, s: r.SetImplementation) -> None:
        old = self.running[s.component]
        self._stop(tx, [old])
        self._start(tx, [self._spec(s.definition, s.inputs, s.outputs)])
