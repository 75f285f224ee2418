"""Run-time conflicts as they start and end: pure logic, no I/O, no clock.

The engine (`rra_agent.core.adaptation.Engine`) reports, on every tick, the conflicts *in force*
(``TickResult.active``): two evaluation units whose latest wishes on one target (a feature,
the alternatives of a group, a CV attribute) differ, a wish lasting until its unit runs
again. `ConflictTracker` turns that per-tick set into transitions: a conflict *starts* the
first tick it is in force and *ends* the first tick it is not, so an Adaptation Engine
reports each once when it starts and once when it ends, however many ticks it lasts.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import msgspec

from rra_agent.core.adaptation import ConflictRecord, FiredRule


class LiveConflict(msgspec.Struct, frozen=True, kw_only=True):
    """A conflict in force: who wants what on which target, since when, and why."""

    #: Stable identity: kind, target and the two rules.
    id: str
    kind: str
    target: str
    #: The rule that applied (written later) and the one overruled, qualified by rule set.
    winner: str
    loser: str
    #: What each rule wants (``on``/``off``, an alternative, a CV value), by rule.
    wants: dict[str, str]
    #: The actions as written.
    actions: dict[str, str]
    #: ``file:line:col`` of each action.
    where: dict[str, str] = {}
    #: When it started (the tick's ``now``).
    since: float
    #: The measurement values the two rules read when it started.
    context: dict[str, Any] = {}

    def describe(self) -> str:
        """One line: ``rules A and B on T: A wants x, B wants y (m=v, ...); A applies``."""
        wants = ", ".join(f"{r} wants {self.wants.get(r, '?')}" for r in (self.winner, self.loser))
        ctx = ", ".join(f"{k}={v!r}" for k, v in sorted(self.context.items()))
        return (
            f"rules {self.winner} and {self.loser} on {self.target}: {wants}"
            + (f" (context {ctx})" if ctx else "")
            + f"; {self.winner} applies (written later)"
        )


def rule_name(f: FiredRule) -> str:
    return f.rule if f.ruleset is None else f"{f.ruleset}.{f.rule}"


def conflict_id(record: ConflictRecord) -> str:
    return f"{record.kind}:{record.target}:{rule_name(record.winner)}|{rule_name(record.loser)}"


def _where(f: FiredRule) -> str:
    return f"{f.span.file}:{f.span.line}:{f.span.col}" if f.span else ""


def live(record: ConflictRecord, now: float, context: Mapping[str, Any]) -> LiveConflict:
    """A conflict in force from its record; ``context`` holds the measurement values (by
    name) this tick read; those the two rules read are kept."""
    w, lo = record.winner, record.loser
    names = dict.fromkeys((*w.reads, *lo.reads))
    wants = dict(zip((rule_name(w), rule_name(lo)), record.values, strict=False))
    return LiveConflict(
        id=conflict_id(record),
        kind=record.kind,
        target=record.target,
        winner=rule_name(w),
        loser=rule_name(lo),
        wants=wants,
        actions={rule_name(w): w.action, rule_name(lo): lo.action},
        where={rule_name(f): _where(f) for f in (w, lo) if f.span},
        since=now,
        context={n: context[n] for n in names if n in context},
    )


class ConflictTracker:
    """The conflicts announced so far; `update` says which started and which ended."""

    def __init__(self) -> None:
        self.known: dict[str, LiveConflict] = {}

    def adopt(self, conflicts: Iterable[LiveConflict]) -> None:
        """Continue from a set announced elsewhere (the leader's, the saved state's)."""
        self.known = {c.id: c for c in conflicts}

    def update(
        self, active: Sequence[ConflictRecord], now: float, context: Mapping[str, Any]
    ) -> tuple[list[LiveConflict], list[tuple[LiveConflict, float]]]:
        """The conflicts that started (in force now, not known) and those that ended (known,
        no longer in force, with how long they lasted in seconds); the known set becomes the
        set in force."""
        current = {conflict_id(r): r for r in active}
        started = [live(r, now, context) for cid, r in current.items() if cid not in self.known]
        ended = [
            (c, max(0.0, now - c.since)) for cid, c in self.known.items() if cid not in current
        ]
        for c, _ in ended:
            del self.known[c.id]
        for c in started:
            self.known[c.id] = c
        return started, ended

    @property
    def current(self) -> list[LiveConflict]:
        return sorted(self.known.values(), key=lambda c: (c.since, c.id))
