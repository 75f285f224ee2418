"""The system-package manifest (``rra.yaml``): names the model files of one system package.

Every path is relative to the package folder. A package without ``rra.yaml`` uses the
default file names below.
"""

from __future__ import annotations

from typing import Literal

from rra_agent.models.base import FrozenModel
from rra_agent.models.system import Scheduling
from rra_agent.ros2.errors import BadName
from rra_agent.ros2.names import check_domain, qualify

MANIFEST = "rra.yaml"


class ProcessSettings(FrozenModel, frozen=True):
    scheduling: Scheduling = Scheduling()


#: The largest CPU wake-up latency a host may be asked for (Linux's PM QoS takes an s32).
MAX_CPU_LATENCY_US = 2_000_000_000


class AgentSettings(ProcessSettings, frozen=True):
    """How the host agents run: their own scheduling, and what they ask of their host."""

    #: While a host agent runs, its host's CPUs are asked to wake within this many
    #: microseconds (Linux PM QoS, ``/dev/cpu_dma_latency``; needs root): 0 keeps idle CPUs
    #: polling instead of halting, which takes the idle exit (on a virtual machine, the
    #: hypervisor's) off every wake-up of the loop, at the cost of power. None: not asked.
    cpu_latency_us: int | None = None

    def __post_init__(self) -> None:
        us = self.cpu_latency_us
        if us is not None and not 0 <= us <= MAX_CPU_LATENCY_US:
            raise ValueError(f"agents: cpu_latency_us must be 0..{MAX_CPU_LATENCY_US}, got {us}")


class ReflexSettings(FrozenModel, frozen=True):
    """Reflexes (docs/architecture.md, Reflexes): rules whose decision the engines compile
    ahead into the node that has to switch, which then switches on the sample itself."""

    #: False: no reflex is ever installed for this package (``rra up --no-reflexes`` too).
    enabled: bool = True
    #: A reflex that fired must be confirmed by the engines' own decision within this long
    #: (milliseconds); otherwise they roll its switch back.
    confirm_ms: float = 500.0

    def __post_init__(self) -> None:
        if not self.confirm_ms > 0:
            raise ValueError("reflexes: confirm_ms must be positive")
class Ros2Settings(FrozenModel, frozen=True):
    """The ROS 2 side of a system (docs/ros2.md): the ROS domain its ROS 2 nodes share, the
    distribution whose message definitions they use, and the folder of the package's own
    interface files (``<interfaces>/<pkg>/msg/<Type>.msg``, ``.../srv/<Name>.srv``, ``*.idl``).
    With it, rra-agent's nodes and engines are ROS 2 nodes too (rmw_zenoh's tokens), and
    its adaptation events go on the ROS 2 topic ``events`` (None: not)."""

    domain: int = 0
    distro: Literal["humble", "iron", "jazzy", "kilted"] = "jazzy"
    interfaces: str | None = None
    events: str | None = "/rra/events"

    def __post_init__(self) -> None:
        try:
            check_domain(self.domain)
            if self.events is not None:
                qualify(self.events)
        except BadName as e:
            raise ValueError(str(e)) from None


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
    #: How the host agents (``rra up``, ``rra agent``) schedule themselves (each runs its
    #: host's Zenoh router, which every sample of the host passes through), and the CPU
    #: wake-up latency they ask of their host.
    agents: AgentSettings = AgentSettings()
    #: Whether and how the engines delegate decisions they have planned to nodes.
    reflexes: ReflexSettings = ReflexSettings()
    #: The system's ROS 2 side (None: it has none).
    ros2: Ros2Settings | None = None
