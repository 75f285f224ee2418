"""The Adaptation Engine process (paper Sec. III-D).

It listens to every Context Dependent Measurement on ``rra/<system>/ctx/*``, evaluates the
Adaptation Model with the pure engine (`rra_agent.core.rules.Engine`) on each new measurement
(rules with ``period 0``) and periodically (rules with a period, every ``tick`` seconds), and
publishes the run-time feature selection and the Continuous Variability values on
``rra/<system>/selection``: at once when they change, and as a heartbeat every
``heartbeat`` seconds so a late joiner (a restarted resolution engine) learns the current
state. Each selection names its cause: the rules that fired and the stamps of the
measurements they read. Conflicting actions in one tick are published as `ConflictReport`s.
"""

from __future__ import annotations

import sys
import threading
import time

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.keys import Keys
from rra_agent.bus.loop import MainLoop
from rra_agent.bus.runtime import open_session
from rra_agent.core.rules import Engine, TickResult
from rra_agent.deployment import Deployment
from rra_agent.viz.rerun_log import Logger, open_logger

NAME = "adaptation"
_CTX = m.Codec[m.CtxMessage](m.CtxMessage)
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)


class AdaptationProcess:
    def __init__(
        self,
        dep: Deployment,
        bus: BusConfig,
        *,
        host: str = "local",
        name: str = NAME,
        tick: float = 0.05,
        heartbeat: float = 1.0,
    ) -> None:
        if dep.package.adaptation is None:
            raise ValueError(f"package {dep.package.name!r} has no adaptation model")
        self.dep = dep
        self.bus = bus
        self.host = host
        self.name = name
        self.tick_period = tick
        self.heartbeat = heartbeat
        self.keys = Keys(dep.system)
        self.engine = Engine(dep.package.features, dep.selection, dep.package.adaptation)
        self.loop = MainLoop(time.monotonic)
        self.lock = threading.Lock()
        self.measurements: dict[str, tuple[object, float]] = {}
        self.changed: set[str] = set()
        self.dropped = 0
        self.seq = 0
        self.last_sent = 0.0
        self.publisher: zenoh.Publisher | None = None
        self.viz: Logger | None = None  # Rerun, when RRA_RERUN says so

    # ---- bus (Zenoh thread) ------------------------------------------------------------
    def _on_ctx(self, sample: zenoh.Sample) -> None:
        try:
            msg = _CTX.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            with self.lock:
                self.dropped += 1
            return
        with self.lock:
            self.measurements[msg.name] = (msg.value, msg.stamp)
            self.changed.add(msg.name)
        self.loop.post(self.evaluate)

    # ---- evaluation (main thread) ------------------------------------------------------
    def evaluate(self) -> TickResult | None:
        with self.lock:
            values, changed = dict(self.measurements), self.changed
            self.changed = set()
        now = time.time()
        result = self.engine.tick(now, values, changed=changed)
        if result.changed or now - self.last_sent >= self.heartbeat:
            self.publish(result, values, now)
        for c in result.conflicts:
            self._send(
                m.ConflictReport(
                    stamp=now,
                    target=c.target,
                    rules=[c.winner.rule, c.loser.rule],
                    resolution=f"{c.kind}: {c.winner.rule} wins (written later)",
                )
            )
        return result

    def publish(self, result: TickResult, values: dict, now: float) -> None:
        self.seq += 1
        cause = [
            m.FiredRule(
                rule=f.rule if f.ruleset is None else f"{f.ruleset}.{f.rule}",
                action=f.action,
                where=f"{f.span.file}:{f.span.line}:{f.span.col}" if f.span else "",
                reads={n: values[n][1] for n in f.reads if n in values},
            )
            for f in result.fired
        ]
        self._send(
            m.Selection(
                seq=self.seq,
                stamp=now,
                deployment=sorted(self.dep.selection),
                features=sorted(result.selection),
                cv=dict(result.cv),
                changed=result.changed,
                cause=cause,
                rejected=[f"{r.rule}: {r.action}: {r.reason}" for r in result.rejected],
            )
        )
        self.last_sent = now
        if self.viz:
            self.viz.selection(
                result.selection,
                result.cv,
                now,
                universe=self.dep.package.features.runtime_features(),
                fired=[f"{c.rule}: {c.action}" for c in cause],
                changed=result.changed,
            )

    def _send(self, msg: m.Selection | m.ConflictReport) -> None:
        if self.publisher is not None:
            self.publisher.put(_SEL.encode(msg))

    # ---- lifecycle ---------------------------------------------------------------------
    def run(self, *, install_signals: bool = True) -> int:
        if install_signals:
            self.loop.install_signals()
        self.viz = open_logger(self.name)
        session = open_session(self.bus)
        try:
            self.publisher = session.declare_publisher(
                self.keys.selection, congestion_control=zenoh.CongestionControl.BLOCK, express=True
            )
            entities = [
                session.declare_subscriber(self.keys.ctx_all, self._on_ctx),
                session.liveliness().declare_token(self.keys.alive(self.host, self.name)),
            ]
            self.evaluate()  # the initial selection, before any measurement
            self.loop.run(lambda _now: self.evaluate(), self.tick_period)
            del entities
            return 0
        finally:
            self.publisher = None
            session.close()
            if self.viz:
                self.viz.close()


def main(argv: list[str] | None = None) -> int:
    """``python -m rra_agent.engines.adaptation --package PKG --select F,...``."""
    from rra_agent.engines.launch import engine_arguments, engine_setup

    parser = engine_arguments("rra adaptation", __doc__)
    parser.add_argument("--tick", type=float, default=0.05, help="periodic evaluation (s)")
    parser.add_argument("--heartbeat", type=float, default=1.0, help="selection heartbeat (s)")
    args = parser.parse_args(argv)
    setup = engine_setup(args, NAME)
    if setup is None:
        return 2
    dep, bus, host, name = setup
    try:
        proc = AdaptationProcess(
            dep, bus, host=host, name=name, tick=args.tick, heartbeat=args.heartbeat
        )
    except ValueError as e:
        print(f"rra adaptation: {e}", file=sys.stderr)
        return 2
    return proc.run()


if __name__ == "__main__":
    sys.exit(main())
