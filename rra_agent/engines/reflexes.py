"""Reflexes, the engines' side: compile, install, confirm, roll back.

The Run-time Resolution Engine leader keeps, in the nodes that would have to switch, the
reflexes the current configuration allows (`ReflexCompiler`): for every branch of a rule the
static analysis admits (`rra_agent.core.reflex.candidates`), it asks what the Adaptation
Engine would decide if that branch fired now (`AdaptationEngine.outcome`, with the forced and
unavailable features), what the plan from the running system to that decision is, and
compiles it into a reflex when the plan's switch is made only of rewires and activations of
nodes that already run (hot standbys, standbys), every node that switches receives the
measured output, no operator forced a feature of the family it changes and no NFR of the
features it changes constrains a CV (which would change parameters). Each such node gets an
`InstallReflex` (fenced, like every control request) with its part of the switch.

`ReflexKeeper` holds what is installed and what fired. After every change of the desired
state it installs what is newly possible and withdraws what no longer is (a conflict in
force, an override, a new configuration). A node whose reflex fires switches at once and
reports it (`ReflexFired` on ``reflex/<node>``). The engines then decide as always: when the
Adaptation Engine's selection makes the reflex's change, the keeper *confirms* it (an event
with both times) and the plan executes, finding the switch done. When a selection changes the
reflex's features otherwise, or none comes within ``confirm_ms``, it *rolls it back* (the
inverse requests, an event) and does not arm it again in that configuration. Every replica
records the fires it hears and mirrors the leader's installed reflexes, so a new leader
confirms or rolls back what its predecessor installed: a reflex survives a failover and
switches once.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from typing import Any

import msgspec

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.core.adaptation import AdaptationEngine, feature_families
from rra_agent.core.cv import cv_table
from rra_agent.core.plan import Plan, Rewire, StopComponent, SwapComponent, diff, topic_of
from rra_agent.core.reflex import Candidate, NotEligible, candidates
from rra_agent.deployment import Deployment
from rra_agent.engines.executor import Ctl, describe_step, must_deactivate
from rra_agent.errors import RraError, SelectionError
from rra_agent.models.resolution import PRE_STARTED
from rra_agent.models.system import SystemModel

#: Reflexes withdrawn lately, kept for a report of one that fired just before.
_RECENT = 32


@dataclass(frozen=True)
class Situation:
    """What the Run-time Resolution Engine knows of the running system."""

    selection: frozenset[str]
    cv: Mapping[str, float]
    forced: Mapping[str, bool]
    #: Run-time feature -> why it is unavailable.
    unavailable: Mapping[str, str]
    #: Rules (``rule`` or ``ruleset.rule``) in a conflict in force.
    conflicts: frozenset[str]
    runtime_model: SystemModel
    running: Mapping[str, m.NodeSpec]
    standby: Mapping[str, m.NodeSpec]
    reachable: Callable[[str], bool]
    target: Callable[[frozenset[str], dict[str, float]], SystemModel]
    #: What is in effect is not what was decided (a plan applied in part, a retry due).
    degraded: bool = False


@dataclass
class Planned:
    """A reflex compiled for the current configuration: one part per node that switches."""

    id: str
    rule: str
    before: frozenset[str]
    features: frozenset[str]
    parts: dict[str, m.Reflex]

    def record(self) -> m.ReflexRecord:
        return m.ReflexRecord(
            id=self.id,
            rule=self.rule,
            nodes=sorted(self.parts),
            features=sorted(self.features),
            actions={n: list(p.actions) for n, p in sorted(self.parts.items())},
            before=sorted(self.before),
        )


class ReflexCompiler:
    """The reflexes a configuration allows (see the module doc); pure but for its mirror of
    the Adaptation Engine, which it resets for each question."""

    def __init__(self, dep: Deployment) -> None:
        pkg = dep.package
        self.keys = Keys(dep.system)
        self.system = pkg.system
        self.replacement = pkg.runtime.replacement
        self.families = feature_families(pkg.features)
        self.candidates: list[Candidate] = []
        #: Rule (branch) -> why it can never be a reflex.
        self.never: dict[str, str] = {}
        self.engine: AdaptationEngine | None = None
        if pkg.adaptation is not None:
            self.candidates, self.never = candidates(
                pkg.adaptation, pkg.features, pkg.measurements, self.families
            )
            self.engine = AdaptationEngine(pkg.features, dep.selection, pkg.adaptation)
        #: Features whose NFRs constrain a CV: changing them may change parameters.
        self.nfr_owners = {
            owner for c in cv_table(pkg.features) for owner, _ in (*c.nfr_min, *c.nfr_max)
        }

    def compile(self, s: Situation) -> tuple[dict[str, Planned], dict[str, str]]:
        """The reflexes of this situation by id, and why each other candidate is none now."""
        out: dict[str, Planned] = {}
        why: dict[str, str] = {}
        for c in self.candidates:
            try:
                planned = self._plan(c, s)
            except NotEligible as e:
                why[_key(c)] = str(e)
                continue
            out[planned.id] = planned
        return out, why

    # ---- one candidate ---------------------------------------------------------------------
    def _plan(self, c: Candidate, s: Situation) -> Planned:
        if c.label in s.conflicts or c.rule.name in s.conflicts:
            raise NotEligible("it is in a conflict in force")
        after = self._outcome(c, s)
        changed = after ^ s.selection
        families = {self.families[f] for f in changed if f in self.families}
        forced = sorted(f for f in s.forced if self.families.get(f) in families)
        if forced:
            raise NotEligible(f"an operator forced {', '.join(forced)}")
        nfr = sorted(changed & self.nfr_owners)
        if nfr:
            raise NotEligible(f"an NFR of {', '.join(nfr)} constrains a CV")
        try:
            plan = diff(s.runtime_model, s.target(after, dict(s.cv)))
        except RraError as e:
            raise NotEligible(f"its decision does not resolve: {e}") from None
        actions = self._actions(plan, s)
        if not actions:
            raise NotEligible("its plan switches nothing a node can do")
        key = self._source_key(c.source)
        for node in actions:
            spec = s.running.get(node) or s.standby[node]
            if not _sees(spec, key):
                raise NotEligible(f"{node} does not receive {c.source}")
            if not s.reachable(spec.host):
                raise NotEligible(f"host {spec.host} of {node} is unreachable")
        tests = [[m.ReflexTest(measurement=t.measurement, op=t.op, value=t.value)  # type: ignore[arg-type]
                  for t in clause] for clause in c.condition]  # fmt: skip
        ident = _ident(c.label, c.branch, after, actions, tests, key)
        parts = {node: self._part(ident, c, key, tests, acts, after)
                 for node, acts in actions.items()}  # fmt: skip
        return Planned(ident, c.label, s.selection, after, parts)

    @staticmethod
    def _part(
        ident: str, c: Candidate, key: str, tests: list[list[m.ReflexTest]],
        actions: list[m.ReflexAction], after: frozenset[str],
    ) -> m.Reflex:  # fmt: skip
        return m.Reflex(
            id=ident, rule=c.label, branch=c.branch, source=c.source, key=key,
            measurements=list(c.measurements), any_of=tests, actions=actions,
            features=sorted(after),
        )  # fmt: skip

    def _outcome(self, c: Candidate, s: Situation) -> frozenset[str]:
        """What the Adaptation Engine decides if only this branch fires now."""
        engine = self.engine
        assert engine is not None
        try:
            engine.adopt(s.selection, s.cv)
        except SelectionError as e:
            raise NotEligible(f"the selection is not valid: {e}") from None
        engine.forced = dict(s.forced)
        engine.set_unavailable(s.unavailable)
        after = engine.outcome(c.rule.name, c.branch)
        if after == s.selection:
            raise NotEligible("it changes nothing in this configuration")
        return after

    def _actions(self, plan: Plan, s: Situation) -> dict[str, list[m.ReflexAction]]:
        """Node -> what it does, for a plan made only of switches of running nodes."""
        out: dict[str, list[m.ReflexAction]] = {}
        for step in plan.steps:
            match step:
                case SwapComponent(component=old, replacement=new, inputs=inputs):
                    self._swap(old, new, inputs, s, out)
                case Rewire(component=node, port=port, topics=topics):
                    spec = s.running.get(node)
                    if spec is None or port not in spec.ports:
                        raise NotEligible(f"{node} does not run")
                    _rewire(out, node, spec, port, [self.keys.data(t) for t in topics])
                case StopComponent():
                    pass  # after the switch, by the engines
                case _:
                    raise NotEligible(f"its plan does more than switch: {describe_step(step)}")
        return {n: acts for n, acts in out.items() if acts}

    def _swap(
        self,
        old: str,
        new: str,
        inputs: Mapping[str, Collection[str]],
        s: Situation,
        out: dict[str, list[m.ReflexAction]],
    ) -> None:
        strategy = self.replacement.strategy_for(new)
        if strategy not in PRE_STARTED or new not in s.standby or old not in s.running:
            raise NotEligible(f"{new} does not run yet ({strategy})")
        spec = s.standby[new]
        for port, topics in inputs.items():
            _rewire(out, new, spec, port, [self.keys.data(t) for t in topics])
        if not spec.active:
            out.setdefault(new, []).append(m.ReflexAction(kind="activate"))
        if must_deactivate(self.replacement, s.running[old], spec):
            out.setdefault(old, []).append(m.ReflexAction(kind="deactivate"))

    def _source_key(self, source: str) -> str:
        component, _, port = source.partition(".")
        return self.keys.data(topic_of(self.system, component, port))


def _key(c: Candidate) -> str:
    return c.label if len(c.rule.branches) == 1 else f"{c.label}[{c.branch}]"


def _rewire(
    out: dict[str, list[m.ReflexAction]], node: str, spec: m.NodeSpec, port: str, keys: list[str]
) -> None:
    if port in spec.ports and list(spec.ports[port].keys) != keys:
        out.setdefault(node, []).append(m.ReflexAction(kind="rewire", port=port, keys=keys))


def _sees(spec: m.NodeSpec, key: str) -> bool:
    """Whether a node publishes on ``key`` or listens to it (selected or held)."""
    return any(
        (p.direction == "publish" and list(p.keys) == [key])
        or (p.direction == "subscribe" and (key in p.keys or key in p.standby))
        for p in spec.ports.values()
    )


def _ident(label: str, branch: int, after: frozenset[str], actions: Any, tests: Any, key: str):
    blob = msgspec.msgpack.encode([label, branch, sorted(after), actions, tests, key])
    return f"{label}-{hashlib.blake2b(blob, digest_size=6).hexdigest()}"


# ---- the live part ------------------------------------------------------------------------
@dataclass
class Fired:
    """A reflex that fired and is neither confirmed nor rolled back yet."""

    record: m.ReflexRecord
    stamp: float
    nodes: set[str]
    values: dict[str, Any]
    #: When it is rolled back if not confirmed (``time.monotonic``).
    deadline: float
    failed: list[str] = field(default_factory=list)


#: Sends control requests (the actuator's batch: fenced, one reply each).
Send = Callable[[list[Ctl]], list[m.Reply]]
#: An adaptation event: kind, text, and the event's fields.
Emit = Callable[..., None]


class ReflexKeeper:
    """What is installed and what fired (see the module doc)."""

    def __init__(
        self,
        compiler: ReflexCompiler,
        send: Send,
        emit: Emit,
        spec_of: Callable[[str], m.NodeSpec | None],
        *,
        enabled: bool = True,
        confirm_s: float = 0.5,
        log: Callable[[str], None] = print,
        refuse: Callable[[str, str], None] = lambda kind, detail: None,
    ) -> None:
        self.compiler = compiler
        self.send, self.emit, self.spec_of = send, emit, spec_of
        self.log, self.refuse = log, refuse
        self.enabled = enabled
        self.confirm_s = confirm_s
        #: Installed, by id (the leader's: every part armed in its node; a standby's: as its
        #: leader publishes them).
        self.installed: dict[str, m.ReflexRecord] = {}
        self.fired: dict[str, Fired] = {}
        #: Withdrawn lately (a fire reported late still names one of these).
        self.recent: dict[str, m.ReflexRecord] = {}
        #: Fired and rolled back: not armed again in the configuration it was made for.
        self.spent: set[str] = set()
        #: Candidate -> why it is not installed now (``rra status``).
        self.why: dict[str, str] = dict(compiler.never)
        self.confirmed = 0
        self.rolled_back = 0

    # ---- installing -------------------------------------------------------------------------
    def sync(self, s: Situation) -> None:
        """Install what this situation allows and withdraw what it does not (the leader)."""
        desired = self._desired(s)
        gone = [r for i, r in self.installed.items() if i not in desired]
        new = [p for i, p in desired.items() if i not in self.installed]
        if not gone and not new:
            return
        batch = [Ctl(spec, m.WithdrawReflex(id=r.id))
                 for r in gone for spec in self._specs(r.nodes)]  # fmt: skip
        for r in gone:
            self._forget(r.id)
        wanted = [(p, node, self.spec_of(node)) for p in new for node in sorted(p.parts)]
        installs = [Ctl(spec, m.InstallReflex(reflex=p.parts[node]))
                    for p, node, spec in wanted if spec is not None]  # fmt: skip
        replies = self.send(batch + installs) if batch or installs else []
        self._installed(new, wanted, replies[len(batch) :])

    def _desired(self, s: Situation) -> dict[str, Planned]:
        why = dict(self.compiler.never)
        desired: dict[str, Planned] = {}
        labels = [_key(c) for c in self.compiler.candidates]
        if not self.enabled:
            why.update({k: "reflexes are off" for k in labels})
        elif s.degraded:
            why.update({k: "what runs is not what was decided" for k in labels})
        else:
            desired, now = self.compiler.compile(s)
            why.update(now)
            for ident in [i for i in desired if i in self.spent]:
                why[desired.pop(ident).rule] = "rolled back in this configuration"
        self.why = why
        return desired

    def _installed(self, new: list[Planned], wanted, replies: list[m.Reply]) -> None:
        """Keep the reflexes every part of which was armed; withdraw the others' parts."""
        refused: dict[str, list[str]] = {}
        it = iter(replies)
        for p, node, spec in wanted:
            reply = next(it) if spec is not None else m.Err(message=f"{node} does not run")
            if isinstance(reply, m.Err):
                refused.setdefault(p.id, []).append(f"{node}: {reply.message}")
        undo = []
        for p in new:
            if p.id not in refused:
                self.installed[p.id] = p.record()
                self.log(f"reflex {p.rule} installed in {', '.join(sorted(p.parts))}")
                continue
            self.why[p.rule] = "not installed: " + "; ".join(refused[p.id])
            self.log(f"reflex {p.rule} not installed: {'; '.join(refused[p.id])}")
            undo += [Ctl(spec, m.WithdrawReflex(id=p.id)) for spec in self._specs(p.parts)]
        if undo:
            self.send(undo)

    def _specs(self, nodes: Collection[str]) -> list[m.NodeSpec]:
        return [spec for n in sorted(nodes) if (spec := self.spec_of(n)) is not None]

    def _forget(self, ident: str) -> None:
        record = self.installed.pop(ident, None)
        if record is not None:
            self.recent[ident] = record
            while len(self.recent) > _RECENT:
                del self.recent[next(iter(self.recent))]

    # ---- firing ------------------------------------------------------------------------------
    def on_fired(self, msg: m.ReflexFired) -> Fired | None:
        """A node reports a fire (every replica records it); None if it names no reflex the
        engines installed there (refused and counted)."""
        record = self.installed.get(msg.id) or self.recent.get(msg.id)
        if record is None or msg.node not in record.nodes:
            self.refuse("reflex", f"{msg.node} reports reflex {msg.id}, which it was not given")
            return None
        f = self.fired.get(msg.id)
        if f is None:
            f = Fired(record, msg.stamp, set(), dict(msg.values), time.monotonic() + self.confirm_s)
            self.fired[msg.id] = f
        f.nodes.add(msg.node)
        f.failed += [f"{msg.node}: {x}" for x in msg.failed]
        f.stamp = min(f.stamp, msg.stamp)
        return f

    def decided(self, selection: frozenset[str]) -> None:
        """The engines decided ``selection`` (the leader, before it applies it): confirm the
        reflexes that made this change; roll back those whose features it changed otherwise."""
        for ident, f in list(self.fired.items()):
            verdict = _verdict(f.record, selection)
            if verdict == "confirmed":
                self._confirm(ident, f)
            elif verdict == "contradicted":
                self._roll_back(ident, f, f"the engines decided {', '.join(sorted(selection))}")

    def tick(self) -> None:
        """Roll back what was not confirmed in time (the leader)."""
        now = time.monotonic()
        for ident, f in list(self.fired.items()):
            if now >= f.deadline:
                self._roll_back(ident, f, f"not confirmed within {self.confirm_s * 1000:g} ms")

    def _confirm(self, ident: str, f: Fired) -> None:
        del self.fired[ident]
        self.confirmed += 1
        now = time.time()
        rec = f.record
        values = ", ".join(f"{k} = {v}" for k, v in sorted(f.values.items()))
        change = ", ".join(_change(rec))
        text = (
            f"reflex {rec.rule} fired in {', '.join(sorted(f.nodes))} at {_clock(f.stamp)}"
            f" ({values}); the engines decided {change} and confirmed it at {_clock(now)}, "
            f"{(now - f.stamp) * 1000:.1f} ms later"
        )
        self.log(text)
        self.emit("reflex", text, outcome="ok", node=min(f.nodes), context=dict(f.values),
                  durations={"confirm": now - f.stamp})  # fmt: skip

    def _roll_back(self, ident: str, f: Fired, why: str) -> None:
        del self.fired[ident]
        self.rolled_back += 1
        self.spent.add(ident)
        rec = f.record
        batch = []
        for spec in self._specs(rec.nodes):
            batch.append(Ctl(spec, m.WithdrawReflex(id=ident)))
            if spec.name in f.nodes:
                batch += [Ctl(spec, req) for req in _inverse(rec.actions.get(spec.name, []), spec)]
        replies = self.send(batch) if batch else []
        bad = [r.message for r in replies if isinstance(r, m.Err)]
        self._forget(ident)
        text = (
            f"reflex {rec.rule} fired in {', '.join(sorted(f.nodes))} at {_clock(f.stamp)}; "
            f"not confirmed ({why}): rolled back" + (f", but {'; '.join(bad)}" if bad else "")
        )
        self.log(text)
        took = {"rollback": time.time() - f.stamp}
        self.emit("reflex", text, outcome="rolled_back", level="warning", node=min(f.nodes),
                  context=dict(f.values), durations=took)  # fmt: skip

    # ---- state ---------------------------------------------------------------------------
    def state(self) -> list[m.ReflexRecord]:
        """The installed reflexes and those fired and pending, for the published state."""
        out = dict(self.installed)
        for ident, f in self.fired.items():
            base = out.get(ident, f.record)
            out[ident] = msgspec.structs.replace(base, fired=f.stamp, fired_by=sorted(f.nodes))
        return [out[i] for i in sorted(out)]

    def mirror(self, records: list[m.ReflexRecord]) -> None:
        """A standby keeps what its leader installed."""
        known = {r.id: msgspec.structs.replace(r, fired=0.0, fired_by=[]) for r in records}
        for ident in [i for i in self.installed if i not in known]:
            self._forget(ident)
        self.installed.update(known)
        for r in records:
            if r.fired and r.id not in self.fired:
                self.fired[r.id] = Fired(known[r.id], r.fired, set(r.fired_by), {},
                                         time.monotonic() + self.confirm_s)  # fmt: skip

    def take_over(self) -> None:
        """This replica leads now: what fired and is pending gets its deadline from now."""
        deadline = time.monotonic() + self.confirm_s
        for f in self.fired.values():
            f.deadline = max(f.deadline, deadline)

    def status(self) -> dict[str, Any]:
        return {
            "installed": [msgspec.to_builtins(r) for r in self.state()],
            "not_installed": dict(sorted(self.why.items())),
            "confirmed": self.confirmed,
            "rolled_back": self.rolled_back,
        }


def _change(record: m.ReflexRecord) -> list[str]:
    before, after = set(record.before), set(record.features)
    return [f"+{f}" for f in sorted(after - before)] + [f"-{f}" for f in sorted(before - after)]


def _verdict(record: m.ReflexRecord, selection: frozenset[str]) -> str:
    """``confirmed``: the decision makes the reflex's change; ``contradicted``: it changes
    the features the reflex changes to something else; ``pending`` otherwise."""
    before, after = frozenset(record.before), frozenset(record.features)
    on, off = after - before, before - after
    if on <= selection and not off & selection:
        return "confirmed"
    touched = on | off
    if touched & selection != touched & before:
        return "contradicted"
    return "pending"


def _inverse(actions: list[m.ReflexAction], spec: m.NodeSpec) -> list[m.NodeRequest]:
    """The requests that undo a node's reflex actions (its spec: what the engines gave it)."""
    out: list[m.NodeRequest] = []
    for a in reversed(actions):
        if a.kind == "rewire" and a.port in spec.ports:
            out.append(m.Rewire(port=a.port, keys=list(spec.ports[a.port].keys)))
        elif a.kind in ("activate", "deactivate"):  # back to what the engines gave it
            out.append(m.Activate() if spec.active else m.Deactivate())
    return out


def _clock(t: float) -> str:
    return time.strftime("%H:%M:%S", time.localtime(t)) + f".{int(t * 1000) % 1000:03d}"
