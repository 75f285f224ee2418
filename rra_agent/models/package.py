"""The system-package manifest (``rra.yaml``): names the model files of one system package.

Every path is relative to the package folder. A package without ``rra.yaml`` uses the
default file names below.
"""

from __future__ import annotations

from rra_agent.models.base import Model

MANIFEST = "rra.yaml"


class Manifest(Model, frozen=True):
    name: str
    description: str | None = None
    features: str = "features.uvl"
    system: str = "system.yaml"
    deployment: str = "deployment.yaml"
    runtime: str = "runtime.yaml"
    measurements: str = "measurements.yaml"
    adaptation: str | None = "adaptation.rra"
    #: The deployment-time selection used when none is given on the command line.
    default_selection: list[str] = []
