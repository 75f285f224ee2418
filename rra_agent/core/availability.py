"""Failure as context: which run-time features an unavailable implementation takes away.

A component's implementation that cannot start, or keeps crashing, is *unavailable*
(`rra_agent.engines.resolution` decides that from what its host agents report, and re-admits
it after a successful probe or when an operator says so). The Adaptation Engine then decides
without the features that need it: a feature needs (component, implementation) when its
run-time transformations launch the component (``include_component``, with the component's
configured implementation) or switch it to an implementation (``set_implementation``).

Implementations are named by their key in the component's ``implementations`` (``""``: the
implementation the Deployment-time Configured System Model gives it). Pure.
"""

from __future__ import annotations

from collections.abc import Mapping

from rra_agent.models.features import FeatureModel
from rra_agent.models.resolution import ResolutionModel
from rra_agent.models.system import Component, Implementation, SystemModel

Need = tuple[str, str]


def implementation_key(component: Component, impl: Implementation) -> str:
    """The key of ``impl`` among ``component``'s alternatives ("" for its own)."""
    if impl == component.implementation:
        return ""
    return next((k for k, v in component.implementations.items() if v == impl), "")


def requirements(fm: FeatureModel, runtime: ResolutionModel) -> dict[str, frozenset[Need]]:
    """Run-time feature -> the (component, implementation key) its transformations launch."""
    out: dict[str, frozenset[Need]] = {}
    for key, steps in runtime.features.items():
        name = fm.resolve_name(key) or key
        switched = {
            t.set_implementation.component: t.set_implementation.implementation
            for t in steps
            if t.set_implementation is not None
        }
        needs = {(c, k) for c, k in switched.items()}
        needs |= {
            (t.include_component, "")
            for t in steps
            if t.include_component is not None and t.include_component not in switched
        }
        if needs:
            out[name] = frozenset(needs)
    return out


def unavailable_features(
    needs: Mapping[str, frozenset[Need]], unavailable: Mapping[Need, str]
) -> dict[str, str]:
    """Feature -> why it is unavailable (the first unavailable implementation it needs)."""
    out: dict[str, str] = {}
    for feature, wanted in needs.items():
        for need in sorted(wanted):
            if need in unavailable:
                component, key = need
                what = component if not key else f"{component} ({key})"
                out[feature] = f"{what} is unavailable: {unavailable[need]}"
                break
    return out


def needed_by(needs: Mapping[str, frozenset[Need]], features: set[str]) -> set[Need]:
    """What the given features need (to re-admit when an operator forces them on)."""
    return {n for f in features for n in needs.get(f, ())}


def component_needs(model: SystemModel, component: str, impl: Implementation) -> Need | None:
    """The (component, key) of a component of ``model`` running ``impl`` (None: unknown)."""
    c = model.component(component)
    return None if c is None else (component, implementation_key(c, impl))
