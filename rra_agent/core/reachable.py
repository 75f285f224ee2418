"""Which run-time configurations the adaptation rules can reach: a static analysis.

From a run-time selection (the default at start, or the current one), which selections can
the rules' actions lead to, whatever the measurements? Each condition is taken as free: any
branch of any rule may fire on any tick, so every feature action of the model is a possible
step, applied as the Adaptation Engine applies it (`rra_agent.core.features.apply_requests`:
a step the feature model refuses changes nothing). A tick applies its fired actions one after
the other, so the selections reachable one action at a time include every selection a
sequence of ticks can reach: what is *not* reached here, no run can select (a feature no rule
activates, nor a feature below it, and that is not a default, is the usual case). The search
may find more than a run reaches, as the measurements do not really vary independently.

The search runs per *family* (`rra_agent.core.adaptation.request_families`: requests on
features of different families never interact), so its cost is the sum over the families,
not their product; a family whose search exceeds ``max_states`` is cut short and said to be
(``complete`` False): no feature of it is called unreachable then.

A ``select_feature_from_variants_of`` step activates its best variant that is selectable
and not ``unavailable``; features an operator forced keep their state (steps that would
change them are skipped), as in the engine. Pure: no I/O.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping
from dataclasses import dataclass, field
from math import prod

from rra_agent.core.adaptation import request_families
from rra_agent.core.conflicts import ranked_variants
from rra_agent.core.features import (
    Request,
    apply_requests,
    complete_deployment,
    default_runtime_selection,
    selectable_runtime,
)
from rra_agent.models.adaptation import Activate, AdaptationModel, Deactivate, SelectVariant
from rra_agent.models.features import FeatureModel

#: A family's search stops after this many distinct states of its features.
MAX_STATES = 512


@dataclass(frozen=True)
class Family:
    """The states one family of run-time features can reach (each: its selected members)."""

    features: tuple[str, ...]
    states: tuple[frozenset[str], ...]
    complete: bool


@dataclass(frozen=True)
class Reachability:
    """What the rules can reach from ``start`` (see the module doc)."""

    start: frozenset[str]
    families: tuple[Family, ...]
    #: Selectable run-time features selected in no reachable configuration (only from
    #: families whose search completed).
    never: tuple[str, ...]
    #: Whether every family's search completed.
    complete: bool
    #: Run-time features selectable under the deployment (the others never are).
    selectable: frozenset[str] = field(default_factory=frozenset)

    @property
    def count(self) -> int:
        """How many configurations are reachable (the start included)."""
        return prod(len(f.states) for f in self.families)

    def configurations(self, limit: int = 64) -> list[frozenset[str]]:
        """Up to ``limit`` reachable configurations, the start first (a family varies
        at a time: the first family's states, then the next's, ...)."""
        out = [self.start]
        for fam in self.families:
            members = frozenset(fam.features)
            for state in fam.states:
                config = (self.start - members) | state
                if config not in out:
                    out.append(config)
                if len(out) >= limit:
                    return out
        return out

    def alternatives(self) -> list[tuple[tuple[str, ...], list[frozenset[str]]]]:
        """Per family that can change: its features and its reachable states."""
        return [(f.features, list(f.states)) for f in self.families if len(f.states) > 1]


def rule_requests(
    model: AdaptationModel,
    fm: FeatureModel,
    selectable: Collection[str],
    unavailable: Collection[str] = (),
) -> list[Request]:
    """Every (de)activation request an action of ``model`` can make, in file order, once."""
    out: dict[Request, None] = {}
    for rule in model.rules():
        for branch in rule.branches:
            for action in branch.actions:
                out.update(dict.fromkeys(_requests(action, fm, selectable, unavailable)))
    return list(out)


def _requests(
    action: object, fm: FeatureModel, selectable: Collection[str], unavailable: Collection[str]
) -> Iterable[Request]:
    match action:
        case Activate(features=fs):
            return [("activate", f.name) for f in fs]
        case Deactivate(features=fs):
            return [("deactivate", f.name) for f in fs]
        case SelectVariant():
            best = [
                v for v in ranked_variants(fm, action) if v in selectable and v not in unavailable
            ]
            return [("activate", best[0])] if best else []
    return []


def reachable(
    fm: FeatureModel,
    deployment: Collection[str],
    model: AdaptationModel,
    start: Collection[str] | None = None,
    *,
    forced: Mapping[str, bool] | None = None,
    unavailable: Collection[str] = (),
    max_states: int = MAX_STATES,
) -> Reachability:
    """The run-time configurations the rules of ``model`` can reach from ``start`` (default:
    the default run-time selection) under ``deployment`` (may be partial)."""
    dep = complete_deployment(fm, deployment)
    selectable = selectable_runtime(fm, dep)
    begin = frozenset(start) if start is not None else default_runtime_selection(fm, dep)
    requests = [
        (kind, f)
        for kind, f in rule_requests(model, fm, selectable, unavailable)
        if not (kind == "activate" and f in unavailable)
    ]
    family_of = request_families(fm)
    groups: dict[object, list[str]] = {}
    for name in fm.features:
        if name in family_of:
            groups.setdefault(family_of[name], []).append(name)
    families = []
    for fam, members in groups.items():
        steps = [r for r in requests if family_of.get(r[1]) == fam]
        families.append(
            _search(fm, dep, begin, tuple(members), steps, dict(forced or {}), max_states)
        )
    reached = {f for fam in families if fam.complete for state in fam.states for f in state}
    searched = {f for fam in families if fam.complete for f in fam.features}
    never = tuple(f for f in fm.features if f in selectable & searched and f not in reached)
    return Reachability(
        start=begin,
        families=tuple(families),
        never=never,
        complete=all(f.complete for f in families),
        selectable=selectable,
    )


def _search(
    fm: FeatureModel,
    deployment: frozenset[str],
    start: frozenset[str],
    members: tuple[str, ...],
    steps: list[Request],
    forced: dict[str, bool],
    max_states: int,
) -> Family:
    """Breadth-first over the states of one family's features (the rest stays ``start``)."""
    own = frozenset(members)
    seen = {start & own: start}
    frontier = [start]
    while frontier:
        state = frontier.pop(0)
        for step in steps:
            after, refused = apply_requests(fm, deployment, state, [step])
            if refused or any((f in after) != on for f, on in forced.items()):
                continue
            key = after & own
            if key in seen:
                continue
            if len(seen) >= max_states:
                return Family(members, tuple(seen), complete=False)
            seen[key] = after
            frontier.append(after)
    return Family(members, tuple(seen), complete=True)
