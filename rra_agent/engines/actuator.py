"""The executor's hands on the bus: host agents start and stop nodes, nodes obey control.

Starting and stopping go through the host agent of the node's host (``StartNode``,
``StopNode``). Termination is read from the `NodeState` events host agents publish;
readiness from those *and* from the node's liveliness token as seen by this session. The
node declares its token after its control queryable, so once the token has reached this
session through the router, so has the queryable, and a control request will find it
(the host agent seeing the token says nothing about what this session has been told).

Each event gets a local sequence number and a wait only accepts events that arrived after
its request, so an old RUNNING or STOPPED of an earlier instance is never mistaken for the
new one. A node that backs off or goes FATAL while starting fails the step at once (the
plan then rolls back) instead of waiting for the timeout.

Parameters, rewiring, activation and state go straight to the nodes' control queryables, a
whole batch in flight at once; the host agent is told the new spec asynchronously
(``UpdateSpec``) so a restart after a crash comes back with the current wiring and
parameters, without slowing the switch down.

Every request that changes something carries ``fence``, the term of the engine leader that
sends it (`claim` makes a new leader known to every host agent and node first). A node
already running with the requested spec counts as started, one already stopped as
stopped: a new leader may repeat what its predecessor had begun.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Collection, Mapping
from typing import Any

import msgspec
import zenoh

from rra_agent import trace
from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply, oks
from rra_agent.bus.keys import Keys
from rra_agent.bus.session import CONTROL_QOS
from rra_agent.engines.executor import Ctl, StepFailed, apply_request

_EVT = m.Codec[m.EventMessage](m.EventMessage)
_ANY = m.Codec[Any](Any)
_REPLY = m.Codec[m.Reply](m.Reply)
TERMINAL = frozenset({"STOPPED", "EXITED", "FATAL"})


class ZenohActuator:
    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        *,
        start_timeout: float = 15.0,
        stop_timeout: float = 10.0,
        request_timeout: float = 2.0,
        on_node_state: Any = None,
        reachable: Callable[[str], bool] = lambda host: True,
        container_of: Mapping[str, str] | None = None,
    ) -> None:
        self.session = session
        #: The component container each contained component runs in (from the model):
        #: several requests of one batch to one container travel as one `NodeBatch`.
        self.container_of = dict(container_of or {})
        self.keys = keys
        self.client = BusClient(None, keys.system, session=session)  # type: ignore[arg-type]
        self.start_timeout = start_timeout
        self.stop_timeout = stop_timeout
        self.request_timeout = request_timeout
        self.on_node_state = on_node_state
        #: Whether a host's agent can be asked now; steps for other hosts are not sent but
        #: listed in ``deferred`` as (host, what) (a partition is context, not a failure).
        self.reachable = reachable
        self.deferred: list[tuple[str, str]] = []
        self.cond = threading.Condition()
        self.seq = 0
        self.history: dict[str, list[tuple[int, m.NodeState]]] = {}
        #: Nodes whose liveliness token this session sees: a direct link to them exists.
        self.alive: set[str] = set()
        #: When each node's token last appeared (on the `seq` scale of the events): a node
        #: declares its token once it is ready, so a token newer than a start request says
        #: the node started, one hop before its host agent's ``RUNNING`` comes.
        self.appeared: dict[str, int] = {}
        self.dropped = 0
        #: The leader term put on every request that changes the system (None: not leading).
        self.fence: m.Fence | None = None
        #: A receiver refused a request as coming from a superseded leader (``stale_fence``):
        #: another leader has acted; this one must step down, not call its plan a failure.
        self.superseded = False
        self._pending: list[Any] = []
        self._subs = [
            session.declare_subscriber(keys.events, self._on_event),
            session.liveliness().declare_subscriber(keys.alive_all, self._on_alive, history=True),
        ]

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()

    def _on_alive(self, sample: zenoh.Sample) -> None:
        parsed = self.keys.parse_alive(str(sample.key_expr))
        if parsed is None:
            return
        with self.cond:
            if sample.kind == zenoh.SampleKind.PUT:
                self.alive.add(parsed[1])
                self.seq += 1
                self.appeared[parsed[1]] = self.seq
            else:
                self.alive.discard(parsed[1])
            self.cond.notify_all()

    # ---- NodeState bookkeeping (Zenoh thread) -------------------------------------------
    def _on_event(self, sample: zenoh.Sample) -> None:
        try:
            msg = _EVT.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            self.dropped += 1
            return
        if not isinstance(msg, m.NodeState):
            return
        with self.cond:
            self.seq += 1
            hist = self.history.setdefault(msg.node, [])
            hist.append((self.seq, msg))
            del hist[:-32]
            self.cond.notify_all()
        if self.on_node_state is not None:
            self.on_node_state(msg)

    def _mark(self) -> int:
        with self.cond:
            return self.seq

    def _since(self, node: str, mark: int) -> list[m.NodeState]:
        return [s for q, s in self.history.get(node, ()) if q > mark]

    def _wait(
        self, names: list[str], mark: int, done, failed, timeout: float, what: str
    ) -> dict[str, str]:
        """Wait until ``done(events)`` for every node, or until it ``failed`` or the timeout
        passed; the nodes that did not make it, and why (empty: all did)."""
        deadline = time.monotonic() + timeout
        out: dict[str, str] = {}
        with self.cond:
            while True:
                pending = []
                for n in names:
                    if n in out:
                        continue
                    evs = self._since(n, mark)
                    bad = failed(evs)
                    if bad is not None:
                        out[n] = f"{bad.state} ({bad.reason})" if bad.reason else bad.state
                    elif not done(n, evs):
                        pending.append(n)
                if not pending:
                    return out
                left = deadline - time.monotonic()
                if left <= 0:
                    out.update((n, f"{what} timed out after {timeout:g} s") for n in pending)
                    return out
                self.cond.wait(left)

    def _fenced(self, request: Any) -> Any:
        if self.fence is not None and "fence" in request.__struct_fields__:
            return msgspec.structs.replace(request, fence=self.fence)
        return request

    def claim(
        self, fence: m.Fence, hosts: list[str], nodes: list[str], timeout: float = 0.3
    ) -> int:
        """Make a new leader known to every host agent and node at once; the highest epoch
        any of them had accepted (above ``fence.epoch``: this leader is out of date)."""
        payload = _ANY.encode(m.Claim(fence=fence))
        keys = [self.keys.host_ctl(h) for h in hosts] + [self.keys.node_ctl(n) for n in nodes]
        handlers = [self.session.get(k, payload=payload, timeout=timeout) for k in keys]
        highest = fence.epoch
        for handler in handlers:
            for answer in oks(handler):
                if isinstance(answer.result, dict):
                    seen = answer.result.get("fence") or [0]
                    highest = max(highest, int(seen[0]))
        return highest

    # ---- Actuator ----------------------------------------------------------------------
    def _reachable(self, specs: list[m.NodeSpec], what: str) -> list[m.NodeSpec]:
        """The specs whose host can be asked; the others are deferred."""
        out = []
        for spec in specs:
            if self.reachable(spec.host):
                out.append(spec)
            else:
                self.deferred.append((spec.host, f"{what} {spec.name}"))
        return out

    def start(self, specs: list[m.NodeSpec], timeout: float | None = None) -> None:
        """Start the nodes at once; `StepFailed` naming those that did not become ready
        within ``timeout`` (default: the actuator's) (each stopped again, so no restart loop
        is left behind); the others run."""
        specs = self._reachable(specs, "start")
        trace.mark("engine:start", ",".join(s.name for s in specs))
        mark = self._mark()
        failed: dict[str, str] = {}
        waiting: list[m.NodeSpec] = []
        for spec in specs:
            try:
                result = self._host(spec, m.StartNode(spec=spec), "start")
            except (StepFailed, NoReply) as e:
                failed[spec.name] = str(e)
                continue
            if not _running_already(result):
                waiting.append(spec)
        failed.update(self._wait_started([s.name for s in waiting], mark, timeout))
        trace.mark("engine:started", ",".join(s.name for s in specs))
        if failed:
            self._abandon([s for s in specs if s.name in failed])
            first = next(iter(failed.items()))
            raise StepFailed(f"start {first[0]}: {first[1]}", failed)

    def _wait_started(
        self, names: list[str], mark: int, timeout: float | None = None
    ) -> dict[str, str]:
        """Wait until each node started after ``mark`` is ready (`_ready`), or failed (its
        host agent's BACKOFF, FATAL or EXITED); those that did not make it, and why."""
        return self._wait(
            names,
            mark,
            done=lambda n, evs: self._ready(n, evs, mark),
            failed=lambda evs: next(
                (e for e in evs if e.state in ("BACKOFF", "FATAL", "EXITED")), None
            ),
            timeout=self.start_timeout if timeout is None else timeout,
            what="start",
        )

    def _wait_stopped(self, names: list[str], mark: int) -> dict[str, str]:
        """Wait until each node stopped after ``mark`` has ended; those that did not."""
        return self._wait(
            names,
            mark,
            done=lambda n, evs: any(e.state in TERMINAL for e in evs),
            failed=lambda evs: None,
            timeout=self.stop_timeout,
            what="stop",
        )

    def _ready(self, node: str, evs: list[m.NodeState], mark: int) -> bool:
        """A node started after ``mark``: its token, declared once its declarations and
        ``on_start`` are done, seen here since (this session then also knows its control
        queryable, declared before it), or its host agent's ``RUNNING`` with the token."""
        if node not in self.alive:
            return False
        return self.appeared.get(node, 0) > mark or any(e.state == "RUNNING" for e in evs)

    def _abandon(self, specs: list[m.NodeSpec]) -> None:
        """Best-effort stop of nodes whose start failed (no restart loop left behind)."""
        for spec in specs:
            with contextlib.suppress(NoReply, StepFailed):
                self._host(spec, m.StopNode(node=spec.name), "stop")

    def stop(self, specs: list[m.NodeSpec], deadlines: Mapping[str, float] | None = None) -> None:
        specs = self._reachable(specs, "stop")
        trace.mark("engine:stop", ",".join(s.name for s in specs))
        mark = self._mark()
        waiting: list[m.NodeSpec] = []
        failed: dict[str, str] = {}
        deadlines = deadlines or {}
        for spec in specs:
            req = m.StopNode(node=spec.name, deadline=deadlines.get(spec.name))
            try:
                result = self._host(spec, req, "stop")
            except (StepFailed, NoReply) as e:
                failed[spec.name] = str(e)
                continue
            if not (isinstance(result, dict) and result.get("already")):
                waiting.append(spec)
        failed.update(self._wait_stopped([s.name for s in waiting], mark))
        trace.mark("engine:stopped", ",".join(s.name for s in specs))
        if failed:
            first = next(iter(failed.items()))
            raise StepFailed(f"stop {first[0]}: {first[1]}", failed)

    def replace(
        self,
        pairs: list[tuple[m.NodeSpec, m.NodeSpec]],
        deadlines: Mapping[str, float] | None = None,
        on_stopped: Callable[[], None] | None = None,
        export: Collection[str] = (),
    ) -> None:
        """Stop each ``(old, new)`` pair's old node and start its new one once the old is
        gone: one `ReplaceNode` to their host agent where both run on one host (the new
        process prepares while the old stops; all sent at once), else `stop` then `start`.
        The old nodes named in ``export`` hand their state to their new ones (exported by
        their host agent, or here first for a pair on two hosts). `StepFailed` naming the
        old nodes that did not stop (or export) and the new ones that did not start (a new
        one whose old one did not stop is not started, and is stopped). ``on_stopped`` is
        called as the old nodes are seen gone (once per kind of pair: the last call counts)."""
        deadlines = deadlines or {}
        stopped = on_stopped or (lambda: None)
        local = [(o, n) for o, n in pairs if o.host == n.host and self.reachable(o.host)]
        apart = [p for p in pairs if p not in local]
        failed = self._replace_apart(apart, deadlines, stopped, export)
        trace.mark("engine:replace", ",".join(n.name for _, n in local))
        mark = self._mark()
        sent: list[tuple[m.NodeSpec, m.NodeSpec]] = []
        running: set[str] = set()  # new nodes that ran already (as they are)
        requests = [
            (old, new, m.ReplaceNode(node=old.name, spec=new, deadline=deadlines.get(old.name),
                                     export=old.name in export))
            for old, new in local
        ]  # fmt: skip
        handlers = [(o, n, self._send_host(n.host, req)) for o, n, req in requests]
        for old, new, handler in handlers:
            try:
                result = self._ok(self._host_reply(handler, new.host), f"replace {new.name} "
                                  f"on {new.host}")  # fmt: skip
            except StepFailed as e:
                failed[old.name] = failed[new.name] = str(e)
                continue
            if _running_already(result):
                running.add(new.name)
            sent.append((old, new))
        failed.update(self._wait_replaced(sent, mark, running, stopped))
        if failed:
            self._abandon([n for o, n in sent if o.name in failed and n.name not in failed])
            for o, n in sent:
                if o.name in failed:
                    failed.setdefault(n.name, f"not started: {o.name} did not stop")
            first = next(iter(failed.items()))
            raise StepFailed(f"replace {first[0]}: {first[1]}", failed)

    def _wait_replaced(
        self,
        sent: list[tuple[m.NodeSpec, m.NodeSpec]],
        mark: int,
        running: set[str],
        stopped: Callable[[], None],
    ) -> dict[str, str]:
        """Wait for each old node's end (then ``stopped()``), then for each new one's
        readiness (but those ``running`` already)."""
        if not sent:
            return {}
        failed = self._wait_stopped([o.name for o, _ in sent], mark)
        trace.mark("engine:stopped", ",".join(o.name for o, _ in sent))
        stopped()
        news = [n.name for o, n in sent if o.name not in failed and n.name not in running]
        failed.update(self._wait_started(news, mark))
        trace.mark("engine:started", ",".join(n.name for _, n in sent))
        return failed

    def _replace_apart(
        self,
        pairs: list[tuple[m.NodeSpec, m.NodeSpec]],
        deadlines: Mapping[str, float],
        stopped: Callable[[], None],
        export: Collection[str],
    ) -> dict[str, str]:
        """`replace` of pairs on two hosts (or an unreachable one): the state of those in
        ``export`` exported, stop (then ``stopped()``), then start."""
        failed: dict[str, str] = {}
        if not pairs:
            return failed
        exporting = [(o, n) for o, n in pairs if o.name in export]
        replies = self.control([Ctl(o, m.ExportState()) for o, _ in exporting]) if exporting else []
        states: dict[str, Any] = {}
        for (o, n), rep in zip(exporting, replies, strict=True):
            if isinstance(rep, m.Ok):
                states[n.name] = rep.result
            else:
                failed[o.name] = failed[n.name] = f"export of its state: {rep.message}"
        pairs = [(o, msgspec.structs.replace(n, state=states.get(n.name, n.state)))
                 for o, n in pairs if o.name not in failed]  # fmt: skip
        try:
            self.stop([o for o, _ in pairs], deadlines)
        except StepFailed as e:
            failed.update(e.nodes or {o.name: str(e) for o, _ in pairs})
        stopped()
        news = [n for o, n in pairs if o.name not in failed]
        for o, n in pairs:
            if o.name in failed:
                failed[n.name] = f"not started: {o.name} did not stop"
        try:
            self.start(news)
        except StepFailed as e:
            failed.update(e.nodes or {n.name: str(e) for n in news})
        return failed

    def control(
        self, batch: list[Ctl], meanwhile: Callable[[], None] | None = None
    ) -> list[m.Reply]:
        """All requests in flight at once (each get returns at once; then drain the replies),
        so a batch costs about one round trip; ``meanwhile`` runs before the draining.
        Successful spec changes are forwarded to the host agents without waiting. A request
        to a node of an unreachable host is deferred (answered ``Ok`` with no result here)."""
        if trace.enabled():
            trace.mark("engine:control", ",".join(c.label for c in batch))
        groups = self._by_container(batch)
        grouped = {i for indices in groups.values() for i in indices}
        batches = {
            box: self.session.get(
                self.keys.node_ctl(box),
                payload=_ANY.encode(m.NodeBatch(calls=[
                    m.NodeCall(node=batch[i].spec.name, request=self._fenced(batch[i].request))
                    for i in indices
                ])),
                timeout=self.request_timeout,
                **CONTROL_QOS,
            )
            for box, indices in groups.items()
        }  # fmt: skip
        handlers = [
            self.session.get(
                self.keys.node_ctl(c.spec.name),
                payload=_ANY.encode(self._fenced(c.request)),
                timeout=self.request_timeout,
                **CONTROL_QOS,
            )
            if self.reachable(c.spec.host) and i not in grouped
            else None
            for i, c in enumerate(batch)
        ]
        if meanwhile is not None:
            meanwhile()
        replies = [
            self._first_reply(h, c) if h is not None else self._defer(c)
            for h, c in zip(handlers, batch, strict=True)
        ]
        for box, indices in groups.items():
            for i, rep in zip(indices, self._batch_replies(batches[box], box, len(indices)),
                              strict=True):  # fmt: skip
                replies[i] = rep
        if trace.enabled():
            trace.mark("engine:replied", ",".join(c.label for c in batch))
        if any(isinstance(r, m.Err) and r.code == "stale_fence" for r in replies):
            self.superseded = True
        latest: dict[str, m.NodeSpec] = {}
        for c, rep in zip(batch, replies, strict=True):
            if isinstance(rep, m.Ok) and c.inverse is not None:  # it changed the node
                name = c.spec.name
                latest[name] = apply_request(latest.get(name, c.spec), c.request)
        self._update(list(latest.values()))
        return replies

    def _by_container(self, batch: list[Ctl]) -> dict[str, list[int]]:
        """Indices of the requests that go to one container together (two or more to the
        same container of a reachable host), by container."""
        groups: dict[str, list[int]] = {}
        for i, c in enumerate(batch):
            box = self.container_of.get(c.spec.name)
            if box is not None and self.reachable(c.spec.host):
                groups.setdefault(box, []).append(i)
        return {box: indices for box, indices in groups.items() if len(indices) > 1}

    def _batch_replies(self, handler: Any, box: str, n: int) -> list[m.Reply]:
        """The ``n`` replies of a `NodeBatch` to container ``box`` (each the same `Err` if
        the container did not answer or answered something else)."""
        reply = self._first_reply(handler, f"container {box}")
        if isinstance(reply, m.Ok) and isinstance(reply.result, list) and len(reply.result) == n:
            try:
                return [msgspec.convert(r, m.Reply) for r in reply.result]
            except msgspec.ValidationError as e:
                reply = m.Err(message=f"malformed reply of container {box}: {e}", code="malformed")
        if isinstance(reply, m.Ok):
            reply = m.Err(message=f"container {box} answered {n} requests wrongly",
                          code="malformed")  # fmt: skip
        return [reply] * n

    def _defer(self, c: Ctl) -> m.Reply:
        self.deferred.append((c.spec.host, f"{c.request.__struct_config__.tag} {c.spec.name}"))
        return m.Ok()

    def _first_reply(self, handler: Any, c: Ctl | str) -> m.Reply:
        out: m.Reply | None = None
        for reply in handler:  # ends when the query is complete (or timed out)
            if out is not None:
                continue
            if reply.ok is not None:
                try:
                    out = _REPLY.decode(reply.ok.payload.to_bytes())
                except (msgspec.DecodeError, msgspec.ValidationError) as e:
                    out = m.Err(message=f"malformed reply: {e}", code="malformed")
            elif reply.err is not None:
                out = m.Err(message=reply.err.payload.to_string(), code="zenoh")
        who = c if isinstance(c, str) else f"node {c.spec.name}"
        return out or m.Err(
            message=f"no reply from {who} within {self.request_timeout:g} s", code="no_reply"
        )

    def _send_host(self, host: str, request: m.HostRequest) -> Any:
        """A request to a host agent put in flight (its replies: `_host_reply`)."""
        return self.session.get(
            self.keys.host_ctl(host),
            payload=_ANY.encode(self._fenced(request)),
            timeout=self.request_timeout,
        )

    def _host_reply(self, handler: Any, host: str) -> m.Reply:
        """The reply to a request `_send_host` sent (an `Err` if none came in time)."""
        reply = self._first_reply(handler, f"the host agent of {host}")
        if isinstance(reply, m.Err) and reply.code == "stale_fence":
            self.superseded = True
        return reply

    def _host(self, spec: m.NodeSpec, request: m.HostRequest, what: str) -> Any:
        reply = self.client.host(spec.host, self._fenced(request), self.request_timeout)
        if isinstance(reply, m.Err) and reply.code == "stale_fence":
            self.superseded = True
        return self._ok(reply, f"{what} {spec.name} on {spec.host}")

    @staticmethod
    def _ok(reply: m.Reply, what: str) -> Any:
        match reply:
            case m.Ok(result=result):
                return result
            case m.Err(message=message, code=code):
                raise StepFailed(f"{what}: {message} ({code})")
        raise StepFailed(f"{what}: unexpected reply {reply!r}")

    def _update(self, specs: list[m.NodeSpec]) -> None:
        """Tell the host agents the nodes' current specs: one request per host, not waited
        for (its handler is kept and drained at a later call)."""
        # forget answered ones (and, in case some never answer, all but the newest few)
        self._pending = [h for h in self._pending if h.try_recv() is None][-64:]
        by_host: dict[str, list[m.NodeSpec]] = {}
        for spec in specs:
            if self.reachable(spec.host):
                by_host.setdefault(spec.host, []).append(spec)
        for host, group in by_host.items():
            self._pending.append(
                self.session.get(
                    self.keys.host_ctl(host),
                    payload=_ANY.encode(m.UpdateSpec(specs=group, fence=self.fence)),
                    timeout=self.request_timeout,
                )
            )


def _running_already(result: Any) -> bool:
    """A start's reply says the node was running already (it is left as it is)."""
    return (
        isinstance(result, dict)
        and bool(result.get("already"))
        and result.get("state") == "RUNNING"
    )
