"""The Adaptation Engine's explanations on the wire: why a selection is what it is.

The pure core explains each change of a tick (`rra_agent.core.adaptation.Why`: the action
that made it, the values it read, what it overruled) and reasons about the configurations
the rules can reach (`rra_agent.core.reachable`); this module turns both into what
`Selection.why`, the adaptation events and ``rra why`` carry (`rra_agent.bus.messages.Why`),
and back for a replica that follows its leader.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from types import MappingProxyType
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.core.adaptation import FiredRule, Overruled, Why
from rra_agent.core.reachable import Reachability
from rra_agent.models.features import Span

#: Configurations listed in an answer about what is reachable (the count is always given).
LISTED = 32
_NONE: Mapping[tuple[str, float], str] = MappingProxyType({})


def _where(span: Span | None) -> str:
    return f"{span.file}:{span.line}:{span.col}" if span else ""


def _span(where: str) -> Span | None:
    file, _, rest = where.rpartition(":")
    file, _, line = file.rpartition(":")
    try:
        return Span(file, int(line), int(rest)) if file else None
    except ValueError:
        return None


def _name(rule: str, ruleset: str | None) -> str:
    return rule if ruleset is None else f"{ruleset}.{rule}"


def wire_fired(
    f: FiredRule,
    reads: dict[str, tuple[Any, float]],
    overrides: Mapping[tuple[str, float], str] = _NONE,
) -> m.FiredRule:
    """A fired action as the wire names it, with the stamps and values it read, and which of
    them an operator set (``overrides``: (measurement, stamp) -> who)."""
    seen = {n: reads[n] for n in f.reads if n in reads}
    return m.FiredRule(
        rule=_name(f.rule, f.ruleset),
        action=f.action,
        where=_where(f.span),
        reads={n: float(s) for n, (_, s) in seen.items()},
        values={n: v for n, (v, _) in seen.items() if isinstance(v, float | int | bool | str)},
        overrides={n: who for n, (_, s) in seen.items() if (who := overrides.get((n, s)))},
    )


def wire_why(w: Why, overrides: Mapping[tuple[str, float], str] = _NONE) -> m.Why:
    return m.Why(
        target=w.target,
        kind=w.kind,
        value=w.value,
        since=w.since,
        reason=w.reason,
        by=[wire_fired(f, w.reads, overrides) for f in w.by],
        detail=w.detail,
        overruled=[
            m.Overruled(
                rule=_name(o.rule, o.ruleset),
                action=o.action,
                where=_where(o.span),
                wants=o.wants,
                why=o.why,
                detail=o.detail,
            )
            for o in w.overruled
        ],
    )


def core_why(w: m.Why) -> Why:
    """A leader's explanation as this replica's engine keeps it (`AdaptationEngine.note`)."""

    def split(name: str) -> tuple[str, str | None]:
        ruleset, _, rule = name.rpartition(".")
        return (rule, ruleset or None)

    reads: dict[str, tuple[Any, float]] = {}
    by = []
    for f in w.by:
        rule, ruleset = split(f.rule)
        for n, stamp in f.reads.items():
            reads[n] = (f.values.get(n), stamp)
        span = _span(f.where)
        by.append(FiredRule(rule=rule, action=f.action, span=span, ruleset=ruleset,
                            reads=tuple(f.reads)))  # fmt: skip
    return Why(
        target=w.target,
        kind=w.kind,
        value=w.value,
        since=w.since,
        reason=w.reason,  # type: ignore[arg-type]
        by=tuple(by),
        reads=reads,
        detail=w.detail,
        overruled=tuple(
            Overruled(
                rule=split(o.rule)[0],
                ruleset=split(o.rule)[1],
                action=o.action,
                span=_span(o.where),
                wants=o.wants,
                why=o.why,  # type: ignore[arg-type]
                detail=o.detail,
            )
            for o in w.overruled
        ),
    )


def causes(why: Iterable[m.Why]) -> list[m.FiredRule]:
    """The rules that made the changes ``why`` explains, each once, in order."""
    out: dict[tuple[str, str, str], m.FiredRule] = {}
    for w in why:
        for f in w.by:
            out.setdefault((f.rule, f.action, f.where), f)
    return list(out.values())


def reachable_summary(r: Reachability) -> dict[str, Any]:
    """What ``rra why`` shows of `rra_agent.core.reachable.reachable` from the current
    configuration: how many configurations, the first `LISTED`, what each family of
    features can change to, and the selectable features the rules never select."""
    return {
        "count": r.count,
        "complete": r.complete,
        "current": sorted(r.start),
        "configurations": [sorted(c) for c in r.configurations(LISTED)],
        "families": [
            {"features": list(features), "states": [sorted(s) for s in states]}
            for features, states in r.alternatives()
        ],
        "never": list(r.never),
    }
