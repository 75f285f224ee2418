"""Run a `NodeCore` on Zenoh: ports as publishers/subscribers, a control queryable, a token.

Threading: zenoh-python hands the samples and queries of each subscriber and queryable from
Zenoh's network threads to a Python thread of that callback's own (its default, *indirect*
callbacks); there `NodeCore` serialises them with the node's lock, so data and control are
handled inline (no further hand-off). A direct callback (``indirect=False``) would save that
hop, ~14 µs of a round trip on one CPU, but would run node code on the network thread that
also reads the link's keep-alives, and pyo3 makes and drops a Python thread state per call
there, which costs more than the hop (issue 12: the raw echo of ``tools/bench_roundtrip.py``
run in a node process both ways).

The main thread only sleeps in ``select`` until the next periodic ``step`` or a wake-up byte on
a self-pipe, written by SIGINT/SIGTERM (``signal.set_wakeup_fd``) and by a Shutdown request.

Ready handshake: the liveliness token ``rra/<system>/alive/<host>/<node>`` is declared last,
after every port is bound and ``on_start`` has run; then the ready flag of the heartbeat is
set. Heartbeat (`rra_agent.bus.heartbeat`): the main loop writes it four times per
``heartbeat_timeout``, holding the node's lock, so a node whose callbacks are stuck stops
beating and its host agent probes it.
Shutdown: ``on_stop``, token undeclared, session closed in ``finally`` (a session left open
with callbacks declared keeps the interpreter from exiting).
"""

from __future__ import annotations

import contextlib
import os
import select
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Mapping
from typing import Any

import msgspec
import zenoh

from rra_agent import trace
from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import Refused, receive
from rra_agent.bus.heartbeat import Heartbeat
from rra_agent.bus.keys import Keys
from rra_agent.bus.session import CONTROL_QOS, beat_period, data_publisher, open_session
from rra_agent.node.api import Node
from rra_agent.node.core import REPLAY_MAX_AGE, NodeCore

_CTL = m.Codec[m.NodeRequest](m.NodeRequest)
_REPLY = m.Codec[m.Reply](m.Reply)
_REFLEX = m.Codec[m.ReflexMessage](m.ReflexMessage)
#: The data samples' send-time attachment (as `messages.pack_stamp`), inlined on the hot path.
_STAMP = struct.Struct("<d")


def control_callback(core: NodeCore, wake: Callable[[], None]):
    """The Zenoh callback of a node's control endpoint: decode (refusing and counting what is
    too large or malformed), let the core answer, reply; ``wake`` the main loop when it must
    re-read the stop flag or ``rate_hz``. A node process and a container use the same."""

    def callback(query: zenoh.Query) -> None:
        got = receive(query.payload, "node_ctl", _CTL)
        request: m.NodeRequest | None = None
        if isinstance(got, Refused):
            core.counters.dropped += 1
            reply: m.Reply = got.err()
        else:
            request = got
            core.counters.received += 1
            reply = core.handle(request)
            if trace.enabled():
                trace.mark(f"node:{request.__struct_config__.tag}", core.spec.name)
        query.reply(query.key_expr, _REPLY.encode(reply), **CONTROL_QOS)
        if must_wake(core, request):
            wake()

    return callback


def reflex_reporter(session: zenoh.Session, key: str) -> Callable[[m.ReflexFired], None]:
    """How a node reports a reflex that fired: on ``reflex/<node>``, ahead of data (the
    engines confirm it or roll it back)."""

    def report(msg: m.ReflexFired) -> None:
        session.put(key, _REFLEX.encode(msg), **CONTROL_QOS)

    return report


#: Node classes whose rehearsal this process has run (a spare runs them while it waits).
_rehearsed: set[type[Node]] = set()


def rehearse_class(node_cls: type[Node], name: str) -> None:
    """The node class's `Node.rehearse`, before its constructor, unless this process ran it
    already (`rehearse_ahead`); a failure is a log line."""
    error = rehearse_ahead(node_cls)
    if error is not None:  # the node's own code: it starts anyway (and does not retry it)
        print(f"[{name}] rehearse failed: {type(error).__name__}: {error}", file=sys.stderr,
              flush=True)  # fmt: skip
        _rehearsed.add(node_cls)
    trace.mark("node:rehearsed", name)


def rehearses(node_cls: type[Node]) -> bool:
    """Whether the class has a rehearsal of its own (`Node.rehearse` overridden)."""
    return "rehearse" in {name for k in node_cls.__mro__[:-1] if k is not Node for name in vars(k)}


def rehearse_ahead(node_cls: type[Node]) -> Exception | None:
    """The class's rehearsal, once per process (a spare runs it before it knows its node,
    so that a node of that class starts with it done); what it raised, if anything (a
    rehearsal that failed runs again in the node that needs it, which says so)."""
    if node_cls in _rehearsed:
        return None
    try:
        node_cls.rehearse()
    except Exception as e:
        return e
    _rehearsed.add(node_cls)
    return None


def must_wake(core: NodeCore, request: m.NodeRequest | None) -> bool:
    """Whether the main loop running ``core`` must wake after ``request``: to see the stop
    flag, or to re-read ``rate_hz``."""
    return core.stop_requested.is_set() or (
        isinstance(request, m.SetParams) and "rate_hz" in request.params
    )


class ZenohTransport:
    """Binds a node's ports to key expressions and rebinds them at run time."""

    def __init__(
        self, session: zenoh.Session, monotonic: Callable[[], float] = time.monotonic
    ) -> None:
        self.session = session
        self.monotonic = monotonic
        self.core: NodeCore | None = None
        self.publishers: dict[str, zenoh.Publisher] = {}
        #: port -> key -> (held?, subscriber): a standby key's subscriber hands its samples
        #: to `NodeCore.hold`, the others to `NodeCore.deliver`.
        self.subscribers: dict[str, dict[str, tuple[bool, Any]]] = {}
        #: (port, key) -> held?, read by the subscriber's callback at each sample: a switch
        #: between a key and its hot standby flips these flags and declares nothing (it runs
        #: under the node's lock, on a reflex in the node's own thread; a declaration there
        #: waits on Zenoh while Zenoh's threads wait on the lock). A key no longer bound has
        #: none: what its subscriber still delivers, the node refuses and counts.
        self.held: dict[tuple[str, str], bool] = {}
        #: Raw subscriptions (`NodeContext.subscribe`), undeclared when the session closes.
        self.raw: list[Any] = []
        #: Until the node's code has started (`start_delivery`): the newest sample of each
        #: (port, key) that came meanwhile, as (payload, stamp, arrival on the monotonic
        #: clock); None once delivering.
        self._early: dict[tuple[str, str], tuple[bytes, float | None, float]] | None = {}
        self._early_lock = threading.Lock()

    def start_delivery(self, core: NodeCore) -> None:
        """Deliver to ``core`` from now on, after the newest sample of each key that came
        while the node was starting (if younger than `REPLAY_MAX_AGE`), as a subscription
        queue of depth one would: a replacement started between two samples of a 500 Hz
        topic acts on the one it missed, not on the next. Under the node's lock, so that a
        newer sample is delivered after them."""
        with self._early_lock, core.lock:
            early, self._early = self._early or {}, None
            self.core = core
            now = self.monotonic()
            for (port, key), (payload, stamp, t) in early.items():
                if now - t <= REPLAY_MAX_AGE and (port, key) in self.held:
                    self._hand(core, port, key, payload, stamp)

    def _hand(
        self, core: NodeCore, port: str, key: str, payload: bytes, stamp: float | None
    ) -> None:
        """A sample to the node: delivered, or held while ``key`` is a standby key of
        ``port`` (one no longer bound has no flag: the core refuses and counts it)."""
        if not self.held.get((port, key), False):
            core.deliver(port, payload, stamp, key)
        else:
            core.hold(port, key, payload, stamp)

    def _keep_early(self, port: str, key: str, payload: bytes, stamp: float | None) -> bool:
        """Keep a sample that came before the node's code started; False: it has started."""
        with self._early_lock:
            if self._early is None:
                return False
            self._early[(port, key)] = (payload, stamp, self.monotonic())
            return True

    def publish(self, port: str, payload: bytes, stamp: float) -> None:
        try:
            self.publishers[port].put(payload, attachment=_STAMP.pack(stamp))
        except zenoh.ZError:
            if self.session.is_closed():  # the node is stopping: a sample that was being
                return  # delivered as its session closed has nowhere to go, and no fault
            raise

    def rebind(
        self, port: str, direction: str, keys: list[str], standby: list[str] | None = None
    ) -> None:
        if direction == "publish":
            old = self.publishers.pop(port, None)
            self.publishers[port] = data_publisher(self.session, keys[0])
            if old is not None:
                old.undeclare()
            return
        held = set(standby or ())
        old_subs = self.subscribers.pop(port, {})
        subs: dict[str, tuple[bool, Any]] = {}
        for k in dict.fromkeys([*keys, *held]):
            self.held[(port, k)] = k in held
            prev = old_subs.pop(k, None)
            if prev is not None:
                subs[k] = (k in held, prev[1])  # listening already: no gap, no declaration
                continue
            subs[k] = (k in held, self.session.declare_subscriber(k, self._on_sample(port, k)))
        for k, (_, sub) in old_subs.items():
            self.held.pop((port, k), None)
            sub.undeclare()
        self.subscribers[port] = subs

    def close(self) -> None:
        """Undeclare every publisher and subscriber (a component unloaded from a container;
        a node process closes its session instead)."""
        self.core = None
        for pub in self.publishers.values():
            pub.undeclare()
        for sub in [s for subs in self.subscribers.values() for _, s in subs.values()] + self.raw:
            sub.undeclare()
        self.publishers.clear()
        self.subscribers.clear()
        self.held.clear()
        self.raw.clear()

    def subscribe(self, key_expr: str, callback) -> None:
        unpack = _STAMP.unpack

        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment
            stamp = unpack(att.to_bytes())[0] if att is not None and len(att) == 8 else None
            callback(str(sample.key_expr), sample.payload.to_bytes(), stamp)

        self.raw.append(self.session.declare_subscriber(key_expr, on_sample))

    def _on_sample(self, port: str, key: str):
        """The callback of the subscription of ``port`` to ``key``: its samples are
        delivered, or, while ``key`` is a held (standby) key of ``port``, handed to
        `NodeCore.hold` (`held`); one still on its way once ``key`` is unbound is refused
        and counted by `NodeCore.deliver` (``unselected``)."""
        unpack = _STAMP.unpack

        def callback(sample: zenoh.Sample) -> None:
            att = sample.attachment
            stamp = unpack(att.to_bytes())[0] if att is not None and len(att) == 8 else None
            payload = sample.payload.to_bytes()
            core = self.core
            if core is None:
                if self._keep_early(port, key, payload, stamp):
                    return
                core = self.core
                if core is None:  # closed
                    return
            self._hand(core, port, key, payload, stamp)

        return callback


def bind_ports(transport: Any, ports: Mapping[str, m.PortSpec]) -> None:
    """Bind every port of a node to its keys (and a subscriber port to its standby keys)."""
    for name, port in ports.items():
        transport.rebind(name, port.direction, list(port.keys), list(port.standby))


def rehearse(session: zenoh.Session, tag: str, bus: BusConfig) -> None:
    """Run what a node runs as it starts, up to its own code, on a throwaway spec and keys
    ``rra/_spare/<tag>/...``: the spec's decoding, the runtime's set-up, the declarations of
    a subscriber port, a publisher port, a control queryable and a token (each undeclared).
    A spare does it while it waits, so that the node it becomes pays neither zenoh-python's
    first-declaration set-up nor the copy of the pages that path writes (measured beside a
    running system: a node's preparation 2.6 -> 1.7 ms median)."""
    base = f"rra/_spare/{tag}"
    spec = m.NodeSpec(
        system="_spare", name=tag, host="_spare", implementation="rra_agent.node.Node",
        ports={"in": m.PortSpec(direction="subscribe", type="X", keys=[f"{base}/in"]),
               "out": m.PortSpec(direction="publish", type="X", keys=[f"{base}/out"])},
    )  # fmt: skip
    spec = msgspec.convert(msgspec.to_builtins(spec), m.NodeSpec)
    msgspec.json.decode(bus.to_env(), type=BusConfig)
    runtime = NodeRuntime(spec, Node, bus)
    runtime.close_wakeup()
    transport = ZenohTransport(session)
    bind_ports(transport, spec.ports)
    transport.close()
    session.declare_queryable(f"{base}/ctl", lambda query: None).undeclare()
    session.liveliness().declare_token(f"{base}/alive").undeclare()


class NodeRuntime:
    """One node process on the bus."""

    def __init__(
        self,
        spec: m.NodeSpec,
        node_cls: type[Node],
        bus: BusConfig,
        *,
        gate: Callable[[Callable[[], bool]], bool] | None = None,
    ) -> None:
        self.spec = spec
        #: A replacement's start gate (`rra_agent.host.gate`): nothing of the node's code
        #: runs before it opens.
        self.gate = gate
        self.node_cls = node_cls
        self.bus = bus
        self.keys = Keys(spec.system)
        self._rsock, self._wsock = socket.socketpair()
        self._rsock.setblocking(False)
        self._wsock.setblocking(False)
        self._signalled = False
        self.heartbeat = Heartbeat.from_env()
        #: The node's core once made (`rra_agent.node.run_node` reads its failures).
        self.core: NodeCore | None = None

    def close_wakeup(self) -> None:
        """Close the wake-up socket pair (a runtime that will not run: `rehearse`)."""
        self._rsock.close()
        self._wsock.close()

    def wake(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):  # a wake-up is already pending
            self._wsock.send(b"\0")

    def _on_signal(self, signum: int, _frame: Any) -> None:
        self._signalled = True

    def run(self) -> int:
        signal.set_wakeup_fd(self._wsock.fileno(), warn_on_full_buffer=False)
        signal.signal(signal.SIGINT, self._on_signal)
        signal.signal(signal.SIGTERM, self._on_signal)
        session = open_session(self.bus)
        trace.mark("node:session", self.spec.name)
        token = None
        core: NodeCore | None = None
        try:
            transport = self.make_transport(session)
            # The data ports first: declared before the node's code runs (the core delivers
            # nothing until `on_start` has returned), so that a gated start has them ready.
            bind_ports(transport, self.spec.ports)
            rehearse_class(self.node_cls, self.spec.name)  # a replacement: while the old stops
            if self.gate is not None and not self._pass_gate():
                return 0
            core = self.make_core(transport)
            self.core = core
            core.on_reflex = reflex_reporter(session, self.keys.reflex(self.spec.name))
            queryable = session.declare_queryable(
                self.keys.node_ctl(self.spec.name), self._on_query(core)
            )
            trace.mark("node:declared", self.spec.name)
            core.start()
            trace.mark("node:on_start", self.spec.name)
            # Only now: a sample delivered before on_start would meet a half-set-up node
            # (of those that came earlier, the newest of each key follows at once).
            transport.start_delivery(core)
            token = session.liveliness().declare_token(
                self.keys.alive(self.spec.host, self.spec.name)
            )
            self.heartbeat.beat(ready=True)
            trace.mark("node:token", self.spec.name)
            self._loop(core)
            queryable.undeclare()
            return 0
        finally:
            if core is not None:
                core.stop()
            if token is not None:
                token.undeclare()
            self.release()
            session.close()
            signal.set_wakeup_fd(-1)

    def _pass_gate(self) -> bool:
        """Wait for the start gate; False if the node was told to stop meanwhile."""
        trace.mark("node:prepared", self.spec.name)
        assert self.gate is not None
        passed = self.gate(lambda: self._signalled)
        trace.mark("node:gate", self.spec.name)
        return passed

    # ---- what a runtime of another kind (`rra_agent.node.ros2`) changes ------------------
    def make_transport(self, session: zenoh.Session) -> Any:
        """The node's transport: its ports on Zenoh, and on ROS 2 too where they have a
        ROS 2 type (`rra_agent.node.ros2mirror.Ros2Mirror`)."""
        transport = ZenohTransport(session)
        if self.spec.ros2 is not None:
            from rra_agent.node.ros2mirror import Ros2Mirror

            self._ros2 = Ros2Mirror(transport, self.spec)
            return self._ros2
        return transport

    def make_core(self, transport: Any) -> NodeCore:
        return NodeCore(
            self.spec,
            self.node_cls,
            transport,
            logger=lambda s: print(s, file=sys.stderr, flush=True),
            pid=os.getpid(),
            max_data=self.bus.max_data_bytes,
        )

    def release(self) -> None:
        """Before the session closes: undeclare what is not the transport's (ROS 2)."""
        ros2 = getattr(self, "_ros2", None)
        if ros2 is not None:
            ros2.close()

    def _on_query(self, core: NodeCore):
        return control_callback(core, self.wake)

    def _loop(self, core: NodeCore) -> None:
        rate = core.rate_hz
        period = 1.0 / rate if rate > 0 else None
        next_step = time.time() + (period or 0.0)
        beat_every = beat_period(self.spec.supervision.heartbeat_timeout)
        next_beat = time.monotonic()
        while not (self._signalled or core.stop_requested.is_set()):
            if time.monotonic() >= next_beat:
                self._beat(core, beat_every)
                next_beat = time.monotonic() + beat_every
            timeout = next_beat - time.monotonic()
            if period is not None:
                timeout = min(timeout, next_step - time.time())
            ready, _, _ = select.select([self._rsock], [], [], max(0.0, timeout))
            if ready:
                self._drain()
                new_rate = core.rate_hz
                if new_rate != rate:
                    rate, period = new_rate, (1.0 / new_rate if new_rate > 0 else None)
                    next_step = time.time() + (period or 0.0)
                continue
            if period is not None and time.time() >= next_step:
                now = time.time()
                core.step(now)
                next_step += period
                if next_step < now:  # fell behind: skip, don't burst
                    next_step = now + period

    def _beat(self, core: NodeCore, wait: float) -> None:
        """Beat while holding the node's lock: a node stuck in a callback does not beat."""
        if core.lock.acquire(timeout=wait):
            try:
                self.heartbeat.beat()
            finally:
                core.lock.release()

    def _drain(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            while self._rsock.recv(64):
                pass
