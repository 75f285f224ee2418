"""The system-package manifest (``rra.yaml``): names the model files of one system package.

Every path is relative to the package folder. A package without ``rra.yaml`` uses the
default file names below.
"""

from __future__ import annotations

from rra_agent.models.base import FrozenModel
from rra_agent.models.system import Scheduling

MANIFEST = "rra.yaml"


class ProcessSettings(FrozenModel, frozen=True):
    scheduling: Scheduling = Scheduling()


class Manifest(FrozenModel, frozen=True):
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
    #: How the engine processes (Context Monitor, Adaptation Engine, Run-time Resolution
    #: Engine) are scheduled: they are on every adaptation's critical path.
    engines: ProcessSettings = ProcessSettings()
    #: How the host agents (``rra up``, ``rra agent``) schedule themselves: each runs its
    #: host's Zenoh router, which every sample of the host passes through.
    agents: ProcessSettings = ProcessSettings()
