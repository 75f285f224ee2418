"""Deployment-time and Run-time Resolution Models (paper Sec. II and III-E).

Both map features to the transformations applied to a system model when the feature is
selected, in one transformation language (the paper: the run-time meta-model extends the
deployment-time one). The run-time model adds parameters set from a Continuous Variability
attribute (``from_attribute``) and the replacement strategy used when a component is swapped.

In YAML each transformation is a one-key mapping::

    Manipulation:
      - include_component: arm_controller
      - set_implementation: {component: local_navigation, implementation: dwa}
      - set_parameter: {component: local_navigation, parameter: max_vel, from_attribute: MaxVel}
      - add_connection: {from: radio_driver_a.rx, to: radio_switch.radio_in}
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from rra_agent.models.base import FrozenModel
from rra_agent.models.system import ParamValue, parse_endpoint

Strategy = Literal["stop-then-start", "start-then-stop", "standby", "hot-standby"]
#: Strategies whose components are pre-started at deployment and kept for the way back.
PRE_STARTED = frozenset({"standby", "hot-standby"})


class SetImplementation(FrozenModel, frozen=True):
    component: str
    #: A key of the component's ``implementations``.
    implementation: str


class SetParameter(FrozenModel, frozen=True):
    component: str
    parameter: str
    value: ParamValue | None = None
    #: Name of a Continuous Variability attribute whose current value is used (run-time only).
    from_attribute: str | None = None

    def __post_init__(self) -> None:
        if (self.value is None) == (self.from_attribute is None):
            raise ValueError("set_parameter needs exactly one of 'value' and 'from_attribute'")


class ConnectionRef(FrozenModel, frozen=True):
    source: str = msgspec.field(name="from")
    target: str = msgspec.field(name="to")

    def __post_init__(self) -> None:
        parse_endpoint(self.source)
        parse_endpoint(self.target)

    @property
    def key(self) -> tuple[str, str]:
        return (self.source, self.target)


class Transformation(FrozenModel, frozen=True):
    """Exactly one of the fields is set."""

    include_component: str | None = None
    remove_component: str | None = None
    set_implementation: SetImplementation | None = None
    set_parameter: SetParameter | None = None
    add_connection: ConnectionRef | None = None
    remove_connection: ConnectionRef | None = None

    def __post_init__(self) -> None:
        n = sum(getattr(self, f) is not None for f in self.__struct_fields__)
        if n != 1:
            raise ValueError(
                "a transformation has exactly one of: " + ", ".join(self.__struct_fields__)
            )

    @property
    def op(self) -> str:
        """The name of the one field that is set."""
        return next(f for f in self.__struct_fields__ if getattr(self, f) is not None)


class ResolutionModel(FrozenModel, frozen=True):
    """Feature name -> transformations, applied in the feature model's order when selected."""

    features: dict[str, list[Transformation]] = {}


class DeploymentResolutionModel(ResolutionModel, frozen=True):
    pass


class StateTransfer(FrozenModel, frozen=True):
    """Copy the exported state of ``from`` into ``to`` when one replaces the other."""

    source: str = msgspec.field(name="from")
    target: str = msgspec.field(name="to")


class Replacement(FrozenModel, frozen=True):
    """How components are replaced at run time (the paper's second future-work item)."""

    default: Strategy = "stop-then-start"
    #: Per-component override, keyed by the component being started.
    components: dict[str, Strategy] = {}
    state_transfer: list[StateTransfer] = []
    #: Seconds a node swapped out by a ``stop-then-start`` swap may take to stop (its
    #: ``on_stop``, its session's close) before its host agent kills it, keyed by the
    #: component being stopped; 0: killed at once (its state exported first). Without an
    #: entry it stops with the host agent's grace periods (SIGINT, SIGTERM, SIGKILL after
    #: 2 s each). The replacement starts only once it is gone: a deadline shortens the
    #: gap in which neither runs.
    stop_deadline: dict[str, Annotated[float, msgspec.Meta(ge=0.0, le=60.0)]] = {}

    def strategy_for(self, component: str) -> Strategy:
        return self.components.get(component, self.default)

    def pre_started(self, component: str) -> bool:
        """Whether ``component`` runs before it is swapped in (``standby``, ``hot-standby``)
        and stays running after it is swapped out, for the way back."""
        return self.strategy_for(component) in PRE_STARTED

    def hot(self, component: str) -> bool:
        """Whether ``component`` is a hot standby: pre-started *active*, computing and
        publishing on its own keys, which its consumers listen to without delivering until
        the switch selects them (switch = one request to each consumer)."""
        return self.strategy_for(component) == "hot-standby"


class RuntimeResolutionModel(ResolutionModel, frozen=True):
    replacement: Replacement = Replacement()
