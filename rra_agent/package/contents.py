"""A loaded system package: every model, and the YAML trees that locate their errors."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from rra_agent.models.features import FeatureModel
from rra_agent.models.manifest import MANIFEST, Manifest
from rra_agent.models.measurements import MeasurementsModel
from rra_agent.models.resolution import DeploymentResolutionModel, RuntimeResolutionModel
from rra_agent.models.system import SystemModel
from rra_agent.package.yamlload import YamlDoc

if TYPE_CHECKING:
    from rra_agent.models.adaptation import AdaptationModel


@dataclass(frozen=True)
class SystemPackage:
    """Every model of one system package, loaded, plus the YAML trees to locate errors."""

    root: Path
    manifest: Manifest
    features: FeatureModel
    system: SystemModel
    deployment: DeploymentResolutionModel
    runtime: RuntimeResolutionModel
    measurements: MeasurementsModel
    #: The Adaptation Model from the rule DSL, or None when the package has none.
    adaptation: AdaptationModel | None = None
    #: ``"manifest"`` (when rra.yaml exists), ``"system"``, ``"deployment"``, ``"runtime"``,
    #: ``"measurements"`` -> the composed YAML file.
    docs: Mapping[str, YamlDoc] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.manifest.name

    def file(self, model: str) -> Path:
        """The path of a model file by its manifest field (``"system"``, ...; ``"manifest"``)."""
        return self.root / (MANIFEST if model == "manifest" else getattr(self.manifest, model))

    def doc(self, model: str) -> YamlDoc:
        """The composed YAML of a model (an empty one when there is none, e.g. no rra.yaml)."""
        return self.docs.get(model) or YamlDoc(str(self.file(model)), None)
