"""The Node SDK's public face: subclass `Node`, use the `NodeContext` it is given.

A node's logic only sees its context (parameters, ``publish``, clock, active flag) and
the events it is handed (``on_message``, ``step``, ``on_params``...), so the same class
runs in its own process on the bus (`rra_agent.node.runtime`), inside a component
container (`rra_agent.node.container`) and in a unit test (`rra_agent.node.NodeHarness`).
docs/nodes.md is the guide."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, ClassVar, Protocol

from rra_agent.errors import RraError


class _Core(Protocol):
    """What a `NodeContext` reads and calls of the node's core (`rra_agent.node.core`)."""

    spec: Any
    params: dict[str, Any]
    active: bool

    def clock(self) -> float: ...

    def publish(self, port: str, data: Any) -> bool: ...

    def log(self, message: str) -> None: ...

    def subscribe_raw(self, key_expr: str, callback: RawCallback) -> None: ...


#: A raw subscription's callback: (key, payload, sender's stamp or None).
RawCallback = Callable[[str, bytes, "float | None"], None]


class NodeContext:
    """The node's view of the world: its name, parameters, clock, ``publish`` and active flag."""

    def __init__(self, core: _Core) -> None:
        self._core = core

    @property
    def name(self) -> str:
        return self._core.spec.name

    @property
    def system(self) -> str:
        return self._core.spec.system

    @property
    def params(self) -> dict[str, Any]:
        """Current parameter values (read-only view; changes come through `Node.on_params`)."""
        return dict(self._core.params)

    def param(self, name: str, default: Any = None) -> Any:
        return self._core.params.get(name, default)

    @property
    def active(self) -> bool:
        return self._core.active

    def now(self) -> float:
        return self._core.clock()

    def publish(self, port: str, data: Any) -> bool:
        """Publish ``data`` (a map of the port's data type) on an output port.

        Returns False (and publishes nothing) while the node is inactive.
        """
        return self._core.publish(port, data)

    def log(self, message: str) -> None:
        self._core.log(message)

    def subscribe(self, key_expr: str, callback: RawCallback) -> None:
        """Listen on a key expression outside the node's data ports, e.g.
        ``Keys(self.system).inject_all`` (fault injections).

        ``callback(key, payload, stamp)`` gets the raw payload (decode it yourself) and runs
        under the node's lock, like `Node.on_message`; an exception in it is counted and
        logged. Call it from `Node.on_start`; the subscription lasts as long as the node and
        is not a port (no Rewire, not in Describe).
        """
        self._core.subscribe_raw(key_expr, callback)


class Node:
    """Base class of a component's logic. Override what you need; all hooks are optional.

    ``rate_hz`` > 0 makes the runtime call `step` periodically; a ``rate_hz`` parameter in
    the node's spec overrides the class attribute.
    """

    rate_hz: ClassVar[float] = 0.0

    def __init__(self, ctx: NodeContext) -> None:
        self.ctx = ctx

    @classmethod
    def warm_up(cls) -> None:
        """Expensive set-up that does not depend on the node's spec (tables, gains, models),
        done once per host: the host agent's fork server calls it after importing the class,
        and every node forked from it inherits what it cached at module or class level. A
        cold start (stop-then-start) then costs a fork, not a computation. Must not open
        files, threads or sessions (they would be shared by every forked node)."""

    @classmethod
    def rehearse(cls) -> None:
        """Run, on scratch objects, the code the node needs at once once it runs (a
        controller's first command): called in the node's own process before its
        constructor, while a replacement waits for the node it replaces to stop. A process
        forked from the fork server copies the pages a code path writes the first time it
        runs it (reference counts, specialised bytecode: 0.3-2 ms for a controller's update);
        rehearsed, that is paid before the node is on the critical path. Must have no effect
        outside its own objects (publish nothing, open nothing). An exception is logged; the
        node starts anyway."""

    def on_start(self) -> None:
        """Called once, after ports and parameters are set up and before the node is ready."""

    def on_message(self, port: str, data: dict[str, Any], stamp: float | None) -> None:
        """A sample arrived on input ``port`` (``stamp``: the sender's wall-clock send time)."""

    def step(self, now: float) -> None:
        """Periodic work at ``rate_hz``."""

    def on_params(self, changed: dict[str, Any]) -> None:
        """Parameters changed at run time (``ctx.params`` already holds the new values)."""

    def on_active(self, active: bool) -> None:
        """The node was activated or deactivated."""

    def export_state(self) -> Any:
        """State handed to a replacement node (msgpack-encodable); None = nothing."""
        return None

    def import_state(self, state: Any) -> None:
        """Take over the state exported by the node this one replaces."""

    def on_stop(self) -> None:
        """Called once when the node shuts down."""


class NodeError(RraError):
    """A control request a node refuses (unknown port or parameter, bad value)."""
