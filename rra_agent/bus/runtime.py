"""Run a `NodeCore` on Zenoh: ports as publishers/subscribers, a control queryable, a token.

Threading: Zenoh delivers samples and queries on its own thread; `NodeCore` serialises them
with the node's lock, so data and control are handled inline (no hand-off latency). The main
thread only sleeps in ``select`` until the next periodic ``step`` or a wake-up byte on a
self-pipe, written by SIGINT/SIGTERM (``signal.set_wakeup_fd``) and by a Shutdown request.

Ready handshake: the liveliness token ``rra/<system>/alive/<host>/<node>`` is declared last,
after every port is bound and ``on_start`` has run; its appearance means "ready", its
disappearance (undeclared, process gone, or lease expired for a frozen process) "gone".
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
import time
from typing import Any

import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.keys import Keys
from rra_agent.errors import RraError
from rra_agent.node import Node, NodeCore

_CTL = m.Codec[m.NodeRequest](m.NodeRequest)
_REPLY = m.Codec[m.Reply](m.Reply)
#: The data samples' send-time attachment (as `messages.pack_stamp`), inlined on the hot path.
_STAMP = struct.Struct("<d")


def open_session(bus: BusConfig, *, wait_connected: bool = False) -> zenoh.Session:
    """Open a Zenoh session. With ``wait_connected``, return only once the hub is linked
    (``scouting/delay=0`` makes open return before the connect endpoints are reached, so a
    query sent at once would find nobody); raise `NoPeer` after ``connect_timeout_ms``."""
    session = zenoh.open(bus.to_zenoh())
    if wait_connected and bus.connect:
        deadline = time.monotonic() + bus.connect_timeout_ms / 1000.0
        while not (session.info.routers_zid() or session.info.peers_zid()):
            if time.monotonic() >= deadline:
                session.close()
                raise NoPeer(f"nothing reachable at {', '.join(bus.connect)}")
            time.sleep(0.002)
    return session


class NoPeer(RraError):
    """Nothing answered at the bus endpoints (is the system running? right --connect?)."""


def data_publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """Reliable, blocking (never silently dropping), express (unbatched) publisher."""
    return session.declare_publisher(
        key,
        congestion_control=zenoh.CongestionControl.BLOCK,
        express=True,
    )


class ZenohTransport:
    """Binds a node's ports to key expressions and rebinds them at run time."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.core: NodeCore | None = None
        self.publishers: dict[str, zenoh.Publisher] = {}
        self.subscribers: dict[str, list[Any]] = {}
        #: Raw subscriptions (`NodeContext.subscribe`), undeclared when the session closes.
        self.raw: list[Any] = []

    def publish(self, port: str, payload: bytes, stamp: float) -> None:
        self.publishers[port].put(payload, attachment=_STAMP.pack(stamp))

    def rebind(self, port: str, direction: str, keys: list[str]) -> None:
        if direction == "publish":
            old = self.publishers.pop(port, None)
            self.publishers[port] = data_publisher(self.session, keys[0])
            if old is not None:
                old.undeclare()
            return
        for sub in self.subscribers.pop(port, []):
            sub.undeclare()
        self.subscribers[port] = [
            self.session.declare_subscriber(k, self._on_sample(port)) for k in keys
        ]

    def subscribe(self, key_expr: str, callback) -> None:
        unpack = _STAMP.unpack

        def on_sample(sample: zenoh.Sample) -> None:
            att = sample.attachment
            stamp = unpack(att.to_bytes())[0] if att is not None and len(att) == 8 else None
            callback(str(sample.key_expr), sample.payload.to_bytes(), stamp)

        self.raw.append(self.session.declare_subscriber(key_expr, on_sample))

    def _on_sample(self, port: str):
        unpack = _STAMP.unpack

        def callback(sample: zenoh.Sample) -> None:
            core = self.core
            if core is None:
                return
            att = sample.attachment
            stamp = unpack(att.to_bytes())[0] if att is not None and len(att) == 8 else None
            core.deliver(port, sample.payload.to_bytes(), stamp)

        return callback


class NodeRuntime:
    """One node process on the bus."""

    def __init__(self, spec: m.NodeSpec, node_cls: type[Node], bus: BusConfig) -> None:
        self.spec = spec
        self.node_cls = node_cls
        self.bus = bus
        self.keys = Keys(spec.system)
        self._rsock, self._wsock = socket.socketpair()
        self._rsock.setblocking(False)
        self._wsock.setblocking(False)
        self._signalled = False

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
        token = None
        core: NodeCore | None = None
        try:
            transport = ZenohTransport(session)
            core = NodeCore(
                self.spec,
                self.node_cls,
                transport,
                logger=lambda s: print(s, file=sys.stderr, flush=True),
                pid=os.getpid(),
            )
            for name, port in core.ports.items():
                transport.rebind(name, port.direction, list(port.keys))
            queryable = session.declare_queryable(
                self.keys.node_ctl(self.spec.name), self._on_query(core)
            )
            core.start()
            # Only now: a sample delivered before on_start would meet a half-set-up node
            # (samples arriving earlier are dropped, as if they had come before the ports).
            transport.core = core
            token = session.liveliness().declare_token(
                self.keys.alive(self.spec.host, self.spec.name)
            )
            self._loop(core)
            queryable.undeclare()
            return 0
        finally:
            if core is not None:
                core.stop()
            if token is not None:
                token.undeclare()
            session.close()
            signal.set_wakeup_fd(-1)

    def _on_query(self, core: NodeCore):
        def callback(query: zenoh.Query) -> None:
            payload = query.payload
            request: m.NodeRequest | None = None
            try:
                request = _CTL.decode(payload.to_bytes() if payload is not None else b"")
            except Exception as e:  # malformed control request: refuse, count, carry on
                with core.lock:
                    core.dropped += 1
                reply: m.Reply = m.Err(message=f"malformed request: {e}", code="malformed")
            else:
                reply = core.handle(request)
            query.reply(query.key_expr, _REPLY.encode(reply))
            if core.stop_requested.is_set() or (
                isinstance(request, m.SetParams) and "rate_hz" in request.params
            ):
                self.wake()  # the main loop re-reads the stop flag and rate_hz

        return callback

    def _loop(self, core: NodeCore) -> None:
        rate = core.rate_hz
        period = 1.0 / rate if rate > 0 else None
        next_step = time.time() + (period or 0.0)
        while not (self._signalled or core.stop_requested.is_set()):
            timeout = None if period is None else max(0.0, next_step - time.time())
            ready, _, _ = select.select([self._rsock], [], [], timeout)
            if ready:
                self._drain()
                new_rate = core.rate_hz
                if new_rate != rate:
                    rate, period = new_rate, (1.0 / new_rate if new_rate > 0 else None)
                    next_step = time.time() + (period or 0.0)
                continue
            if period is not None:
                now = time.time()
                core.step(now)
                next_step += period
                if next_step < now:  # fell behind: skip, don't burst
                    next_step = now + period

    def _drain(self) -> None:
        with contextlib.suppress(BlockingIOError, OSError):
            while self._rsock.recv(64):
                pass
