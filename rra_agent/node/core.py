"""The node's machinery, whatever carries it: `NodeCore` owns the node instance, its
parameters, ports (the key expressions each is bound to), the active flag and the counters,
and answers control requests (`rra_agent.bus.messages.NodeRequest`). The bus runtime
(`rra_agent.node.runtime`), a component container (`rra_agent.node.container`) and the test
harness (`rra_agent.node.harness`) each wrap one; node code never sees it (it sees its
`rra_agent.node.api.NodeContext`)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, Protocol

import msgspec

from rra_agent import trace
from rra_agent.bus import failure
from rra_agent.bus import messages as m
from rra_agent.bus.counters import MAX_PAYLOAD, Counters, RateLimitedLog
from rra_agent.bus.data import DATA_ENCODER
from rra_agent.core.election import Term, newer
from rra_agent.core.samples import MALFORMED, Decoder, Refusal, SampleTypes, not_a_map
from rra_agent.models.system import ParamType, coerce_parameter
from rra_agent.node.api import Node, NodeContext, NodeError, RawCallback
from rra_agent.node.reflex import Fire, Reflexes


class Transport(Protocol):
    """What `NodeCore` needs from the bus (or from a test harness)."""

    def publish(self, port: str, payload: bytes, stamp: float) -> None: ...

    def rebind(
        self, port: str, direction: str, keys: list[str], standby: list[str] | None = None
    ) -> None:
        """Bind ``port`` to ``keys``; a subscriber port also listens on its ``standby`` keys,
        whose samples go to `NodeCore.hold` instead of `NodeCore.deliver`."""
        ...

    def subscribe(self, key_expr: str, callback: RawCallback) -> None: ...


#: A hot standby's held sample older than this (seconds) is not delivered at the switch: a
#: consumer switched to a producer that went quiet must not act on a stale value.
REPLAY_MAX_AGE = 0.1


#: The node hook a control request runs (what a `Failure` says the node was doing).
_HOOKS: dict[type, str] = {
    m.SetParams: "on_params",
    m.ImportState: "import_state",
    m.ExportState: "export_state",
    m.Activate: "activate",
    m.Deactivate: "on_active",
}
#: Distinct places of exceptions whose whole traceback a node logs (then one line each).
_TRACED_SITES = 64


def _kind_of(value: Any) -> ParamType | None:
    """The declared type a value of a spec without declarations stands for."""
    for type_, cls in (
        ("bool", bool),
        ("int", int),
        ("float", float),
        ("str", str),
        ("list", list),
    ):
        if isinstance(value, cls):
            return type_  # type: ignore[return-value]
    return None


class NodeCore:
    """Transport-independent node machinery; every entry point holds one re-entrant lock."""

    def __init__(
        self,
        spec: m.NodeSpec,
        node_cls: type[Node],
        transport: Transport,
        *,
        clock: Callable[[], float] = time.time,
        logger: Callable[[str], None] | None = None,
        pid: int = 0,
        monotonic: Callable[[], float] = time.monotonic,
        contained: bool = False,
        max_data: int | None = None,
    ) -> None:
        self.spec = spec
        #: The largest data sample accepted (the system's largest port limit; the routers
        #: enforce each port's own first).
        self.max_data = max_data or MAX_PAYLOAD["data"]
        self.transport = transport
        self.clock = clock
        #: For ages (of held samples): never set back, unlike the wall ``clock``.
        self.monotonic = monotonic
        self.pid = pid
        self._logger = logger
        self.lock = threading.RLock()
        self.params: dict[str, Any] = dict(spec.params)
        self.ports: dict[str, m.PortSpec] = {
            name: msgspec.structs.replace(p, keys=list(p.keys)) for name, p in spec.ports.items()
        }
        #: Output port names (a port never changes direction; `publish` checks this set only).
        self._outputs = frozenset(n for n, p in self.ports.items() if p.direction == "publish")
        #: How each input port's samples are decoded: against its declared data type, finite
        #: numbers only but in the type's ``non_finite`` fields (a port of an undeclared type:
        #: any map).
        types = SampleTypes(spec.types, finite=True)
        self._decoders: dict[str, Decoder] = {
            n: types.for_port(p.type) for n, p in self.ports.items() if n not in self._outputs
        }
        self.active = spec.active
        #: Declared type and bounds per parameter (from the spec, else the initial values').
        self.decl: dict[str, m.ParamDecl] = dict(spec.decl)
        for name, value in spec.params.items():
            kind = _kind_of(value)
            if name not in self.decl and kind is not None:
                self.decl[name] = m.ParamDecl(type=kind)
        #: The newest sample of each standby key not selected: (port, key) -> (payload, stamp,
        #: arrival on ``monotonic``), delivered when a `Rewire` selects the key.
        self._held: dict[tuple[str, str], tuple[bytes, float | None, float]] = {}
        self.counters = Counters()
        self.published = 0
        self.errors = 0
        #: What node code may raise without ending the process: in a container
        #: (``contained``), a component's ``sys.exit`` too (it must not end its neighbours).
        self._catch: tuple[type[BaseException], ...] = (
            (Exception, SystemExit) if contained else (Exception,)
        )
        #: The newest exception of node code the node went on after (`Stats`), and the
        #: exception of ``on_stop`` if it raised (the node's last word to its host agent).
        self.last_error: m.Failure | None = None
        self.stop_failure: m.Failure | None = None
        #: Where node code raised already, (during, type, where): the first time the log gets
        #: the whole traceback, later times a rate-limited line.
        self._traced: set[tuple[str, str, str]] = set()
        #: The newest leader fence accepted (requests with older ones are refused).
        self.fence: Term | None = spec.fence.term if spec.fence else None
        self._refusals = RateLimitedLog(self.log)
        self.stop_requested = threading.Event()
        #: Reflexes the engines installed (`rra_agent.node.reflex`), fires not yet acted on
        #: (a sample of the node's own output fires after the node code that published it
        #: returns), and how deep in node code this thread is.
        self.reflexes = Reflexes(list(spec.path))
        self._due: list[Fire] = []
        self._inside = 0
        #: Reports a fired reflex (the runtime puts it on ``reflex/<node>``).
        self.on_reflex: Callable[[m.ReflexFired], None] | None = None
        try:
            self.node = node_cls(NodeContext(self))
        except BaseException as e:
            failure.tag(e, "constructor")
            raise

    # ---- lifecycle ---------------------------------------------------------------------
    def start(self) -> None:
        """``import_state`` (of the spec's state, if any) and ``on_start``; what they raise
        is marked with which it was and propagates (the node does not start)."""
        with self.lock:
            during = "import_state"
            try:
                if self.spec.state is not None:
                    self.node.import_state(self.spec.state)
                during = "on_start"
                self.node.on_start()
            except BaseException as e:
                failure.tag(e, during)
                raise

    def stop(self) -> None:
        with self.lock:
            self.stop_failure = self._guard("on_stop", self.node.on_stop)

    @property
    def rate_hz(self) -> float:
        rate = self.params.get("rate_hz", type(self.node).rate_hz)
        return float(rate) if isinstance(rate, int | float) else 0.0

    def step(self, now: float) -> None:
        with self.lock:
            self._inside += 1
            try:
                self._guard("step", self.node.step, now)
            finally:
                self._inside -= 1
            if self._due:
                self._fire_due()

    # ---- data --------------------------------------------------------------------------
    def deliver(
        self,
        port: str,
        payload: bytes | bytearray | memoryview,
        stamp: float | None,
        key: str | None = None,
    ):
        """A raw sample arrived for input ``port`` (on ``key``, if the transport says):
        decode, count, hand to the node.

        A sample on a key the port no longer listens to is not delivered (counted as
        ``unselected``): one that was on its way when a rewire dropped its producer (already
        in the subscription's queue, or waiting for this lock while the rewire ran) must not
        reach the node after the switch, as a command of the controller just swapped out
        would (seen in ``tools/bench_recovery.py``'s traces: one more physics step driven by
        the old controller).

        A sample that is not of the port's declared data type, or carries NaN or an infinity
        where the type does not allow one, never reaches the node: it is refused and counted
        (`_refuse_sample`).

        The per-sample hot path: decoding and the node call are inlined (no helper frames),
        and the lock is taken without ``with`` (half the cost).
        """
        if len(payload) > self.max_data:
            self._too_large(port, len(payload))
            return
        decoder = self._decoders.get(port)
        if decoder is None:
            self._drop(port, "not an input port of this node")
            return
        try:
            data = decoder.decoder.decode(payload)
        except msgspec.DecodeError as e:
            self._refuse_sample(port, decoder.refused(port, e))
            return
        if type(data) is not dict:  # a port of an undeclared type: any map
            self._refuse_sample(port, not_a_map(port, data))
            return
        lock = self.lock
        lock.acquire()
        delivered = False
        try:
            if key is not None and key not in self.ports[port].keys:
                self.counters.bump("unselected")
                return
            self.counters.received += 1
            delivered = True
            self._inside += 1
            try:
                self.node.on_message(port, data, stamp)
            finally:
                self._inside -= 1
        except self._catch as e:  # a bug in node code must not reach the bus callback
            self._error("on_message", e)
        finally:
            try:  # the node has seen the sample; then the reflexes computed from it
                if delivered and key in self.reflexes.watched:
                    self._due += self.reflexes.evaluate(key, payload, stamp)  # type: ignore[arg-type]
                if self._due and not self._inside:
                    self._fire_due()
            finally:
                lock.release()

    def hold(self, port: str, key: str, payload: bytes, stamp: float | None) -> None:
        """A sample on a standby key of ``port`` (a hot standby's output): delivered if the
        key is selected by now, else kept, the newest only, for the switch to it."""
        with self.lock:
            if key in self.ports[port].keys:
                self.deliver(port, payload, stamp, key)
            elif self._valid(port, payload):  # junk must not displace a good held sample
                self._held[(port, key)] = (payload, stamp, self.monotonic())
                if key in self.reflexes.watched:
                    self._due += self.reflexes.evaluate(key, payload, stamp)
                    if not self._inside:
                        self._fire_due()

    def _valid(self, port: str, payload: bytes) -> bool:
        """Whether ``payload`` is a data sample `deliver` would accept (else refused, counted)."""
        if len(payload) > self.max_data:
            self._too_large(port, len(payload))
            return False
        decoder = self._decoders.get(port)
        if decoder is None:
            self._drop(port, "not an input port of this node")
            return False
        decoded = decoder.decode(port, payload)
        if isinstance(decoded, Refusal):
            self._refuse_sample(port, decoded)
            return False
        return True

    def _replay(self, port: str, keys: Iterable[str]) -> None:
        """Deliver the held samples of newly selected ``keys`` (if young enough)."""
        for key in keys:
            held = self._held.pop((port, key), None)
            if held is not None and self.monotonic() - held[2] <= REPLAY_MAX_AGE:
                self.deliver(port, held[0], held[1])

    def _too_large(self, port: str, size: int) -> None:
        why = f"{size} bytes, more than the {self.max_data} allowed"
        self._refuse_sample(port, Refusal(port, "too_large", why))

    def _drop(self, port: str, why: str) -> None:
        with self.lock:
            self.counters.dropped += 1
        self._refusals(f"dropped sample on {port}", why)

    def _refuse_sample(self, port: str, refusal: Refusal) -> None:
        """A sample `deliver` does not hand to the node: one that is not even a msgpack map
        is dropped, one of another type or with a non-finite number is rejected; both are
        counted per reason (``wrong_type``, ``non_finite``...) and logged, rate-limited."""
        malformed = refusal.reason in MALFORMED
        with self.lock:
            self.counters.bump(refusal.reason)
            if malformed:
                self.counters.dropped += 1
            else:
                self.counters.rejected += 1
        if malformed:
            self._refusals(f"dropped sample on {port}", refusal.detail)
        else:
            self._refusals(f"refused sample on {port}", refusal.detail, refusal.reason)

    @property
    def received(self) -> int:
        return self.counters.received

    @property
    def dropped(self) -> int:
        return self.counters.dropped

    def publish(self, port: str, data: Any) -> bool:
        if port not in self._outputs:
            raise NodeError(f"node {self.spec.name} has no output port {port!r}")
        if not self.active:
            return False
        payload, stamp = DATA_ENCODER.encode(data), self.clock()
        self.transport.publish(port, payload, stamp)
        self.published += 1
        if self.reflexes.watched:
            self._own_sample(self.ports[port].keys[0], payload, stamp)
        return True

    # ---- reflexes ----------------------------------------------------------------------
    def _own_sample(self, key: str, payload: bytes, stamp: float) -> None:
        """A sample this node published: its reflexes on that key fire once the node code
        that published it has returned (never inside it)."""
        if key not in self.reflexes.watched:
            return
        with self.lock:
            self._due += self.reflexes.evaluate(key, payload, stamp)
            if self._due and not self._inside:
                self._fire_due()

    def _fire_due(self) -> None:
        """Act on the reflexes whose condition held (the lock held, no node code running):
        each does its actions as the control requests of the same names would, then is
        reported."""
        due, self._due = self._due, []
        for fire in due:
            armed, now = fire.armed, self.clock()
            self.reflexes.spent(armed, now)
            failed = []
            for action in armed.spec.actions:
                try:
                    self._reflex_action(action)
                except self._catch as e:  # NodeError is an Exception
                    failed.append(f"{action.kind} {action.port}: {type(e).__name__}: {e}".strip())
            trace.mark("node:reflex", self.spec.name)
            self.counters.bump("reflexes_fired")
            msg = m.ReflexFired(
                node=self.spec.name, id=armed.spec.id, rule=armed.spec.rule, stamp=now,
                sample=fire.sample, values=fire.values, failed=failed,
            )  # fmt: skip
            if self.on_reflex is not None:
                self._guard("reflex report", self.on_reflex, msg)
            values = ", ".join(f"{k} = {v}" for k, v in fire.values.items())
            self.log(f"reflex {armed.spec.rule} fired ({values})"
                     + (f"; failed: {'; '.join(failed)}" if failed else ""))  # fmt: skip

    def _reflex_action(self, action: m.ReflexAction) -> None:
        match action.kind:
            case "rewire":
                self._rewire(action.port, list(action.keys))
            case "activate":
                self._set_active(True)
            case "deactivate":
                self._set_active(False)

    def subscribe_raw(self, key_expr: str, callback: RawCallback) -> None:
        def guarded(key: str, payload: bytes, stamp: float | None) -> None:
            with self.lock:
                self._guard(f"subscription {key_expr}", callback, key, payload, stamp)

        self.transport.subscribe(key_expr, guarded)

    # ---- control -----------------------------------------------------------------------
    def handle(self, request: m.NodeRequest) -> m.Reply:
        """Answer one control request; never raises."""
        with self.lock:
            self._inside += 1
            try:
                return self._handle(request)
            except NodeError as e:
                return m.Err(message=str(e), code="refused")
            except self._catch as e:  # a bug in node code must not kill the control endpoint
                during = _HOOKS.get(type(request), request.__struct_config__.tag)
                f = self._error(str(during), e)
                return m.Err(message=f"{type(e).__name__}: {e}", code="node_error", failure=f)
            finally:
                self._inside -= 1
                if self._due and not self._inside:
                    self._fire_due()

    def _handle(self, request: m.NodeRequest) -> m.Reply:
        fence = getattr(request, "fence", None)
        if fence is not None and not isinstance(request, m.Claim) and not self._admit(fence):
            return self._refuse(
                "stale_fence",
                f"{request.__struct_config__.tag} from leader {fence.leader} (epoch "
                f"{fence.epoch}) refused: leader {self.fence[1]} (epoch {self.fence[0]}) "  # type: ignore[index]
                "has acted since",
            )
        match request:
            case m.Ping():
                return m.Ok(result={"name": self.spec.name, "pid": self.pid})
            case m.Stats():
                return m.Ok(result=self.stats())
            case m.Claim(fence=claim):
                accepted = self._admit(claim)
                return m.Ok(result={"accepted": accepted, "fence": list(self.fence or ())})
            case m.Describe():
                return m.Ok(result=msgspec.to_builtins(self.describe()))
            case m.SetParams(params=params, decl=decl):
                self._redeclare(decl)
                self._set_params(params)
                return m.Ok()
            case m.Rewire(port=port, keys=keys):
                self._rewire(port, keys)
                return m.Ok()
            case m.Activate(state=state):
                if state is not None:
                    self.node.import_state(state)
                self._set_active(True)
                return m.Ok()
            case m.Deactivate():
                self._set_active(False)
                return m.Ok()
            case m.ExportState():
                return m.Ok(result=self.node.export_state())
            case m.ImportState(state=state):
                self.node.import_state(state)
                return m.Ok()
            case m.Shutdown():
                self.stop_requested.set()
                return m.Ok()
            case m.InstallReflex(reflex=reflex):
                self.reflexes.install(reflex, self.ports)
                self.log(f"reflex {reflex.rule} installed ({reflex.id})")
                return m.Ok()
            case m.WithdrawReflex(id=ident):
                self.reflexes.withdraw(ident)
                return m.Ok()
        raise NodeError(f"unsupported request {type(request).__name__}")

    def _admit(self, fence: m.Fence) -> bool:
        """Accept requests of this leader from now on, unless a newer one has acted."""
        term = fence.term
        if not newer(term, self.fence):
            return False
        self.fence = term
        return True

    def _refuse(self, code: str, message: str) -> m.Err:
        self.counters.rejected += 1
        self._refusals(f"refused ({code})", message)
        return m.Err(message=message, code=code)

    def _redeclare(self, decl: dict[str, m.ParamDecl]) -> None:
        """New declarations of known parameters (a reload changed their bounds): the
        current values must fit them, else nothing changes."""
        for name, d in decl.items():
            if name not in self.params:
                self.counters.rejected += 1
                raise NodeError(f"node {self.spec.name} has no parameter {name!r}")
            value = self.params[name]
            if value is not None:
                try:
                    coerce_parameter(d.type, value, d.min, d.max)
                except ValueError as e:
                    self.counters.rejected += 1
                    raise NodeError(
                        f"parameter {name!r} of node {self.spec.name}: its value {value!r} "
                        f"does not fit the new declaration: {e}"
                    ) from None
        self.decl.update(decl)

    def _set_params(self, params: dict[str, Any]) -> None:
        """Check every value against its declaration first: all are set, or none."""
        values = {}
        for name, value in params.items():
            if name not in self.params:
                known = ", ".join(sorted(self.params)) or "none"
                self.counters.rejected += 1
                raise NodeError(f"node {self.spec.name} has no parameter {name!r} (known: {known})")
            decl = self.decl.get(name)
            if decl is None:  # undeclared and started as nil: anything goes
                values[name] = value
                continue
            try:
                values[name] = coerce_parameter(decl.type, value, decl.min, decl.max)
            except ValueError as e:
                self.counters.rejected += 1
                raise NodeError(f"parameter {name!r} of node {self.spec.name}: {e}") from None
        changed = {k: v for k, v in values.items() if self.params[k] != v}
        self.params.update(values)
        if changed:
            self.node.on_params(changed)

    def _rewire(self, port: str, keys: list[str]) -> None:
        p = self.ports.get(port)
        if p is None:
            known = ", ".join(sorted(self.ports)) or "none"
            raise NodeError(f"node {self.spec.name} has no port {port!r} (known: {known})")
        if p.direction == "publish" and len(keys) != 1:
            raise NodeError(f"output port {port!r} publishes on exactly one key, got {keys}")
        self.ports[port] = msgspec.structs.replace(p, keys=list(keys))
        try:
            # A switch to a hot standby: its held sample first (the reason it is hot), then
            # the bindings (dropping the old producer's key costs the switch nothing).
            self._replay(port, [k for k in keys if k not in p.keys])
            self.transport.rebind(port, p.direction, list(keys), list(p.standby))
        except Exception:
            self.ports[port] = p
            raise

    def _set_active(self, active: bool) -> None:
        if active != self.active:
            self.active = active
            self.node.on_active(active)

    def describe(self) -> m.NodeInfo:
        return m.NodeInfo(
            name=self.spec.name,
            implementation=m.implementation_id(self.spec.implementation),
            pid=self.pid,
            host=self.spec.host,
            active=self.active,
            params=dict(self.params),
            ports=[
                m.PortInfo(
                    name=n,
                    direction=p.direction,
                    type=p.type,
                    keys=list(p.keys),
                    standby=list(p.standby),
                )
                for n, p in self.ports.items()
            ],
            received=self.counters.received,
            published=self.published,
            dropped=self.counters.dropped,
            rejected=self.counters.rejected,
            reflexes=self.reflexes.state(),
        )

    def stats(self) -> m.ProcessStats:
        c = self.counters
        c.extra.update(published=self.published, errors=self.errors)
        if self.reflexes.by_id or self.reflexes.fired:
            c.extra.update(reflexes=len(self.reflexes.by_id), reflex_errors=self.reflexes.errors)
        if self.fence is not None:
            c.extra["fence_epoch"] = self.fence[0]
        return msgspec.structs.replace(
            c.stats(self.spec.name, "node", self.pid), failure=self.last_error
        )

    # ---- helpers -----------------------------------------------------------------------
    def _guard(self, what: str, fn: Callable[..., Any], *args: Any) -> m.Failure | None:
        """Run node code; an exception is counted and logged (its `Failure` returned), never
        propagated to the bus."""
        try:
            fn(*args)
        except self._catch as e:
            return self._error(what, e)
        return None

    def _error(self, what: str, e: BaseException) -> m.Failure:
        """Node code raised ``e`` in ``what`` and the node goes on: count it, keep it for
        `Stats`, log its traceback the first time it is raised there (then one line at most
        every 10 s, with the count)."""
        self.errors += 1
        f = self.last_error = failure.describe(e, what, self.spec.path)
        site = (f.during, f.type, f.where)
        if site in self._traced or len(self._traced) >= _TRACED_SITES:
            self._refusals(f"{what} raised", failure.summary(f))
        else:
            self._traced.add(site)
            self.log(f"{what} raised {failure.summary(f)}\n{failure.formatted(e)}")
        return f

    def log(self, message: str) -> None:
        """A line (or lines, each prefixed with the node's name) in the node's log."""
        if self._logger is not None:
            prefix = f"[{self.spec.name}] "
            self._logger(prefix + message.replace("\n", "\n" + prefix))

