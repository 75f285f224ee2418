"""What the Adaptation Engine keeps when its models change (``rra reload``).

`carry_over` moves the state of a running `AdaptationEngine` onto one built from the new
models: the run-time selection and the CV values (when the new feature model allows them,
else the new default selection), the operators' forced features that are still selectable,
and the unavailable features as the new models map them. Rule schedules and the conflicts in
force start again: the new engine's first tick runs every rule, so the new rules are in
effect at once. The engine process and the offline replay (``rra replay``) both call it, so a
replay switches models exactly as the run did. Pure: no I/O.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

from rra_agent.core.adaptation import AdaptationEngine
from rra_agent.errors import SelectionError
from rra_agent.models.adaptation import AdaptationModel
from rra_agent.models.features import FeatureModel


def carry_over(
    old: AdaptationEngine,
    new: AdaptationEngine,
    unavailable: Mapping[str, str] | None = None,
) -> AdaptationEngine:
    """``new`` (built from the new models, never ticked) continuing from ``old``."""
    runtime = set(new.fm.runtime_features())
    selection = frozenset(f for f in old.selection if f in runtime)
    try:
        new.adopt(selection, old.cv)
    except SelectionError:
        new.adopt(new.selection, old.cv)  # the new default selection, the CV values kept
    new.forced = {f: on for f, on in old.forced.items() if f in new.selectable}
    if unavailable is not None:
        new.set_unavailable(unavailable)
    return new


def engine_for(
    fm: FeatureModel, deployment: Collection[str], model: AdaptationModel
) -> AdaptationEngine:
    """A new engine for the new models (what a replica prepares before the switch)."""
    return AdaptationEngine(fm, deployment, model)
