"""A deployed system: its package, the deployment-time selection and the configured model.

Every engine process and the CLI start from the same three steps (paper Fig. 1, left):
load the package, complete the deployment-time selection, and resolve the Template System
Model into the Deployment-time Configured System Model.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from rra_agent.core.features import complete_deployment
from rra_agent.core.resolution import resolve_deployment
from rra_agent.models.loader import SystemPackage, load_package
from rra_agent.models.system import SystemModel


@dataclass(frozen=True)
class Deployment:
    package: SystemPackage
    selection: frozenset[str]
    configured: SystemModel

    @property
    def system(self) -> str:
        return self.configured.system

    @property
    def implementations(self) -> frozenset[str]:
        """Every implementation the configured model may run (what host agents accept)."""
        out: set[str] = set()
        for c in self.configured.components:
            for impl in (c.implementation, *c.implementations.values()):
                out.add(impl if isinstance(impl, str) else " ".join(impl.command))
        return frozenset(out)

    def initial_cv(self) -> dict[str, float]:
        """Continuous Variability values before the first adaptation: what the Adaptation
        Engine starts from (its value, else its lower bound, clamped by active NFRs)."""
        pkg = self.package
        if pkg.adaptation is not None:
            from rra_agent.core.rules import Engine

            return Engine(pkg.features, self.selection, pkg.adaptation).cv
        out = {}
        for name, (_, attr) in pkg.features.attributes.items():
            if attr.kind == "cv":
                value = attr.rra_value
                if isinstance(value, bool) or not isinstance(value, int | float):
                    value = attr.lower if attr.lower is not None else attr.upper
                if value is not None:
                    out[name] = float(value)
        return out

    @property
    def hosts(self) -> list[str]:
        return sorted({c.host for c in self.configured.components if c.host})


def deploy(path: str | Path, names: Sequence[str] = ()) -> Deployment:
    """Load and resolve; ``names`` default to the manifest's ``default_selection``."""
    pkg = load_package(path)
    selection = complete_deployment(pkg.features, list(names) or pkg.manifest.default_selection)
    configured = resolve_deployment(pkg.system, pkg.deployment, pkg.features, selection)
    return Deployment(pkg, selection, configured)
