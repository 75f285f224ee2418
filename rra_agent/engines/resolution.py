"""The Run-time Resolution Engine process (paper Sec. III-E).

It holds the Run-time Configured System Model. At start it deploys the Deployment-time
Configured System Model with the default run-time selection (and pre-starts the ``standby``
replacements, inactive); then, for each new run-time selection the Adaptation Engine
publishes on ``rra/<system>/selection``, it computes the target model (the configured model
plus the Run-time Resolution Model's transformations for the selected features, CV values
included), diffs it against the current model, and executes the plan transactionally
(`rra_agent.engines.executor`). Every plan becomes an `AdaptationEvent` (cause, steps,
outcome, phase durations), published and written to ``<run-dir>/events.jsonl`` together with
the host agents' `NodeState` transitions.

Failed adaptations are rolled back and not retried for the same selection before
``retry_after`` seconds. Selections arriving during an execution are coalesced: only the
newest is acted on next. On exit the engine leaves the nodes running: the host agents own
them, and a restarted engine can take over (``rra up`` stops everything through the host
agent). Status (selection, CV values, nodes) is served on ``rra/<system>/engine/resolution/ctl``.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig
from rra_agent.bus.keys import Keys
from rra_agent.bus.loop import MainLoop
from rra_agent.bus.runtime import open_session
from rra_agent.core import resolution as r
from rra_agent.core.features import default_runtime_selection
from rra_agent.deployment import Deployment
from rra_agent.engines.actuator import ZenohActuator
from rra_agent.engines.adoption import managed_parameters, observe, takeover_plan
from rra_agent.engines.events import EventSink
from rra_agent.engines.executor import Executor, Outcome, spec_for
from rra_agent.errors import RraError
from rra_agent.models.system import Component, SystemModel
from rra_agent.viz.rerun_log import Logger, open_logger

NAME = "resolution"
#: Benchmarks only (``tools/bench_recovery.py``): wait this long before executing a plan, to
#: emulate a slower adaptation pipeline such as the paper's 0.5 s.
EMULATED_DELAY = float(os.environ.get("RRA_EMULATED_SWAP_DELAY", "0") or 0)
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
_REQ = m.Codec[m.EngineRequest](m.EngineRequest)
_REPLY = m.Codec[m.Reply](m.Reply)


class ResolutionEngine:
    def __init__(
        self,
        dep: Deployment,
        bus: BusConfig,
        *,
        host: str = "local",
        name: str = NAME,
        run_dir: Path | None = None,
        retry_after: float = 5.0,
        start_timeout: float = 15.0,
    ) -> None:
        self.dep = dep
        self.bus = bus
        self.host = host
        self.name = name
        self.keys = Keys(dep.system)
        self.run_dir = run_dir
        self.retry_after = retry_after
        self.start_timeout = start_timeout
        self.loop = MainLoop()
        fm = dep.package.features
        self.selection = default_runtime_selection(fm, dep.selection)
        self.cv: dict[str, float] = dep.initial_cv()
        self.current = msgspec.structs.replace(dep.configured, components=[], connections=[])
        self.pending: m.Selection | None = None
        self.failed: tuple[frozenset[str], tuple, float] | None = None
        self.seq = 0
        self.dropped = 0
        self._status: dict[str, Any] = {}
        self._lock = threading.Lock()
        self.viz: Logger | None = None  # Rerun, when RRA_RERUN says so

    # ---- the model side (pure, on the main thread) ---------------------------------------
    def target(self, selection: frozenset[str], cv: dict[str, float]) -> SystemModel:
        pkg = self.dep.package
        return r.resolve_runtime(self.dep.configured, pkg.runtime, pkg.features, selection, cv)

    def standby_specs(self, target: SystemModel) -> list[m.NodeSpec]:
        """Run-time components with the ``standby`` strategy not in ``target``: pre-start
        them wired as the configured model connects them to what runs."""
        running = {c.name for c in target.components}
        rep = self.dep.package.runtime.replacement
        standby = [
            c
            for c in self.dep.configured.components
            if c.name not in running and rep.strategy_for(c.name) == "standby"
        ]
        return self._specs(self.dep.configured, standby)

    # ---- bus callbacks (Zenoh thread) ----------------------------------------------------
    def _on_selection(self, sample: zenoh.Sample) -> None:
        try:
            msg = _SEL.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            self.dropped += 1
            return
        if isinstance(msg, m.Selection):
            with self._lock:
                self.pending = msg
            self.loop.post(self._take_pending)

    def _on_status(self, query: zenoh.Query) -> None:
        payload = query.payload
        try:
            _REQ.decode(payload.to_bytes() if payload is not None else b"")
            with self._lock:
                reply: m.Reply = m.Ok(result=dict(self._status))
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            self.dropped += 1
            reply = m.Err(message=f"malformed request: {e}", code="malformed")
        query.reply(query.key_expr, _REPLY.encode(reply))

    # ---- adaptation (main thread) --------------------------------------------------------
    def _take_pending(self) -> None:
        with self._lock:
            msg, self.pending = self.pending, None
        if msg is not None:
            self.adapt(msg)

    def adapt(self, msg: m.Selection) -> Outcome | None:
        selection = frozenset(msg.features)
        cv = {**self.cv, **msg.cv}
        if selection == self.selection and cv == self.cv:
            return None  # a heartbeat, or nothing this engine acts on
        key = (selection, tuple(sorted(cv.items())))
        now = time.monotonic()
        if self.failed and self.failed[:2] == key and now - self.failed[2] < self.retry_after:
            return None
        t_recv = time.time()
        t0 = time.perf_counter()
        try:
            target = self.target(selection, cv)
            plan = r.diff(self.current, target)
        except RraError as e:
            self.failed = (*key, now)
            self._event(
                "adaptation",
                f"cannot resolve the selection: {e}",
                msg,
                level="error",
                outcome="failed",
            )
            return None
        t_plan = time.perf_counter()
        if EMULATED_DELAY > 0 and plan.steps:
            time.sleep(EMULATED_DELAY)  # benchmarks only: a slower pipeline, like the paper's
        outcome = self.executor.execute(plan)
        t_end = time.perf_counter()
        reads = [f.reads.values() for f in msg.cause]
        stamps = [t for rs in reads for t in rs]
        durations = {
            "decide": max(0.0, msg.stamp - max(stamps)) if stamps else 0.0,
            "deliver": max(0.0, t_recv - msg.stamp),
            "plan": t_plan - t0,
            "execute": t_end - t_plan,
        }
        if stamps:
            durations["total"] = max(0.0, t_recv + (t_end - t0) - min(stamps))
        if outcome.first_switch is not None:
            durations["switch"] = outcome.first_switch
        if outcome.ok:
            self.current, self.selection, self.cv, self.failed = target, selection, cv, None
            self._persist()
            text = f"applied selection {sorted(selection)}" + (
                f", {len(plan.steps)} step(s)" if plan.steps else " (no change to the system)"
            )
            self._event("adaptation", text, msg, outcome="ok", plan=outcome, durations=durations)
        else:
            self.failed = (*key, now)
            state = "rolled back" if outcome.rolled_back else "ROLLBACK FAILED"
            self._event(
                "adaptation",
                f"adaptation failed, {state}: {outcome.error}",
                msg,
                level="error",
                outcome="rolled_back" if outcome.rolled_back else "failed",
                plan=outcome,
                durations=durations,
            )
        self._publish_status()
        return outcome

    def _event(
        self,
        kind: str,
        text: str,
        msg: m.Selection | None,
        *,
        level: m.Level = "info",
        outcome: str = "",
        plan: Outcome | None = None,
        durations: dict[str, float] | None = None,
    ) -> None:
        self.seq += 1
        event = m.AdaptationEvent(
            stamp=time.time(),
            kind=kind,
            message=text,
            level=level,
            source=self.name,
            cause=list(msg.cause) if msg else [],
            plan=[rec.line() for rec in plan.records] if plan else [],
            outcome=outcome,  # type: ignore[arg-type]
            durations=durations or {},
            seq=self.seq,
        )
        self.sink.emit(event)
        if self.viz:
            self.viz.event(event)

    def _node_state(self, st: m.NodeState) -> None:
        self.sink.record(st)
        if self.viz:
            self.viz.node_state(st)

    def _publish_status(self) -> None:
        status = {
            "system": self.dep.system,
            "deployment": sorted(self.dep.selection),
            "selection": sorted(self.selection),
            "cv": dict(self.cv),
            "running": {
                n: {"host": s.host, "implementation": str(s.implementation), "active": s.active}
                for n, s in self.executor.running.items()
            },
            "standby": sorted(self.executor.standby),
            "seq": self.seq,
            "failed": bool(self.failed),
        }
        with self._lock:
            self._status = status

    # ---- lifecycle ---------------------------------------------------------------------
    def deploy(self) -> Outcome:
        """Make the running system match the target of the current selection: start it from
        nothing, or take over what already runs (after a restart of this engine)."""
        target = self.target(self.selection, self.cv)
        hosts = sorted({c.host or self.host for c in self.dep.configured.components})
        observed = observe(self.actuator.client, hosts, self.dep.configured)
        expected = {s.name: s for s in self._specs(target, target.components)}
        candidates = {s.name for s in self.standby_specs(target)}
        managed = managed_parameters(self.dep.package.runtime)
        plan, running, standby = takeover_plan(observed, expected, target, candidates, managed)
        self.executor.running, self.executor.standby = running, standby
        outcome = self.executor.execute(plan)
        if outcome.ok:
            self.current = target
            missing = [s for s in self.standby_specs(target) if s.name not in standby]
            if missing:
                pre = self.executor.prestart_standby(missing)
                outcome.records.extend(pre.records)
                if not pre.ok:
                    outcome.ok, outcome.error = False, pre.error
        adopted = len(observed.nodes)
        what = f"adopted {adopted} running node(s), " if adopted else ""
        self._event(
            "adopt" if adopted else "deploy",
            f"{what}{len(self.executor.running)} node(s) running, "
            f"{len(self.executor.standby)} on standby, {len(plan.steps)} step(s)"
            if outcome.ok
            else f"deployment failed: {outcome.error}",
            None,
            level="info" if outcome.ok else "error",
            outcome="ok" if outcome.ok else "failed",
            plan=outcome,
            durations={"execute": outcome.seconds},
        )
        if outcome.ok:
            self._persist()
        self._publish_status()
        return outcome

    def _specs(self, model: SystemModel, components: list[Component]) -> list[m.NodeSpec]:
        """The specs that run ``components`` wired as ``model`` connects them."""
        subs = r.subscriptions(model)
        return [
            spec_for(self.keys, c, **r.wiring(c, subs), default_host=self.host) for c in components
        ]

    # ---- the applied selection survives a restart of this engine -------------------------
    @property
    def state_file(self) -> Path | None:
        return self.run_dir / f"{self.name}-state.json" if self.run_dir else None

    def _persist(self) -> None:
        if self.state_file is not None:
            data = {"selection": sorted(self.selection), "cv": self.cv}
            tmp = self.state_file.with_suffix(".tmp")
            tmp.write_bytes(msgspec.json.encode(data))
            tmp.replace(self.state_file)

    def _restore(self) -> None:
        """The selection applied before this engine was restarted, if any."""
        if self.state_file is None or not self.state_file.exists():
            return
        try:
            data = msgspec.json.decode(self.state_file.read_bytes(), type=dict[str, Any])
            self.selection = frozenset(data["selection"])
            self.cv = {**self.cv, **data["cv"]}
        except (msgspec.DecodeError, msgspec.ValidationError, KeyError, TypeError) as e:
            print(f"rra resolution: ignoring {self.state_file}: {e}", file=sys.stderr)

    def _wait_for_hosts(self, session: zenoh.Session, timeout: float = 30.0) -> None:
        hosts = {c.host or self.host for c in self.dep.configured.components}
        for h in sorted(hosts):
            wait_until(
                lambda h=h: list(session.liveliness().get(self.keys.host_alive(h), timeout=0.5)),
                timeout,
                f"the host agent of {h!r}",
                interval=0.05,
            )

    def run(self, *, install_signals: bool = True) -> int:
        if install_signals:
            self.loop.install_signals()
        self.viz = open_logger(self.name)
        session = open_session(self.bus)
        token = None
        log = self.run_dir / "events.jsonl" if self.run_dir else None
        self.sink = EventSink(session, self.keys.events, log)
        self.actuator = ZenohActuator(
            session,
            self.keys,
            start_timeout=self.start_timeout,
            on_node_state=lambda st: self.loop.post(lambda: self._node_state(st)),
        )
        self.executor = Executor(
            self.actuator, self.keys, self.dep.package.runtime.replacement, default_host=self.host
        )
        try:
            entities = [
                session.declare_subscriber(self.keys.selection, self._on_selection),
                session.declare_queryable(self.keys.engine_ctl(self.name), self._on_status),
            ]
            self._wait_for_hosts(session)
            self._restore()
            outcome = self.deploy()
            if not outcome.ok:
                print(f"rra resolution: deployment failed: {outcome.error}", file=sys.stderr)
                return 1
            token = session.liveliness().declare_token(self.keys.alive(self.host, self.name))
            self.loop.run(self._tick, 0.5)
            del entities
            return 0
        finally:
            if token is not None:
                token.undeclare()
            self.actuator.close()
            self.sink.close()
            session.close()
            if self.viz:
                self.viz.close()

    def _tick(self, now: float) -> None:
        """Retry a failed adaptation once ``retry_after`` has passed."""
        if self.failed and now - self.failed[2] >= self.retry_after and self.pending is None:
            with self._lock:
                last = self._last_selection()
            if last is not None:
                self.adapt(last)

    def _last_selection(self) -> m.Selection | None:
        if self.failed is None:
            return None
        selection, cv_items, _ = self.failed
        return m.Selection(
            seq=0,
            stamp=time.time(),
            deployment=sorted(self.dep.selection),
            features=sorted(selection),
            cv=dict(cv_items),
            changed=True,
        )


def main(argv: list[str] | None = None) -> int:
    """``python -m rra_agent.engines.resolution --package PKG --select F,...``."""
    from rra_agent.engines.launch import engine_arguments, engine_setup

    parser = engine_arguments("rra resolution", __doc__)
    parser.add_argument("--retry-after", type=float, default=5.0)
    parser.add_argument("--start-timeout", type=float, default=15.0)
    args = parser.parse_args(argv)
    setup = engine_setup(args, NAME)
    if setup is None:
        return 2
    dep, bus, host, name = setup
    engine = ResolutionEngine(
        dep,
        bus,
        host=host,
        name=name,
        run_dir=Path(args.run_dir) if args.run_dir else None,
        retry_after=args.retry_after,
        start_timeout=args.start_timeout,
    )
    return engine.run()


if __name__ == "__main__":
    sys.exit(main())
