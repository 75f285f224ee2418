"""A node's reflexes: decisions the engines compiled ahead, taken on the node's own samples.

The Run-time Resolution Engine leader installs a reflex (`rra_agent.bus.messages.Reflex`, in
a fenced `InstallReflex`) in a node that would have to switch when a rule fires: a condition
over measurements computed from the samples on one data key (an output of this node, or a key
one of its inputs listens to) and this node's part of the switch (rewires, activation). The
node computes those measurements exactly as the Context Monitor does
(`rra_agent.core.monitor.ContextMonitor`: the sample decoded against its port's data type,
non-finite and implausible values refused, the value coerced to its type) with the function
*its own copy of the package* names for each (``measurements.yaml``, resolved as the monitor
resolves it: `rra_agent.package.functions`); nothing executable comes from the bus. When the
condition holds (`rra_agent.core.reflex.holds`), the reflex fires once: the node does its
actions as the control requests of the same names would, and reports it (`ReflexFired`);
the engines confirm it or roll it back. It fires on a sample whose values *changed* (the
sample before it gave others), as the Context Monitor publishes a measurement when its value
changes and a rule runs on a new value: armed while its condition already holds, a reflex
waits for a change, and the engines decide on the monitor's next publication as before. A
function that raises, or a value that cannot be computed, never fires a reflex: the engines
make the switch as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.core.monitor import ContextMonitor
from rra_agent.core.reflex import Condition, Test, holds
from rra_agent.errors import RraError
from rra_agent.models.measurements import MeasurementsModel
from rra_agent.node.api import NodeError
from rra_agent.package.functions import function_path, load_function, load_measurements

#: Measurements models of package folders loaded by this process.
_MODELS: dict[str, MeasurementsModel] = {}


@dataclass
class Armed:
    """An installed reflex: what it computes, when it holds, and whether it fired."""

    spec: m.Reflex
    monitor: ContextMonitor
    condition: Condition
    #: When it fired (wall clock), 0 while armed: a reflex fires once.
    fired: float = 0.0
    #: The measurement values of the previous sample (None: no sample yet).
    last: dict[str, Any] | None = None


@dataclass(frozen=True)
class Fire:
    """A reflex whose condition held on a sample: to be acted on, then reported."""

    armed: Armed
    values: dict[str, Any]
    sample: float | None


class Reflexes:
    """The reflexes installed in one node, by id, and the keys they watch."""

    def __init__(self, folders: list[str]) -> None:
        self.folders = folders
        self.by_id: dict[str, Armed] = {}
        #: The data keys some armed reflex computes from (empty: none; the hot path checks it).
        self.watched: frozenset[str] = frozenset()
        self.fired = 0

    @property
    def errors(self) -> int:
        """Samples on which a measurement function raised or gave no usable value."""
        return sum(sum(a.monitor.failures.values()) for a in self.by_id.values())

    def install(self, spec: m.Reflex, ports: dict[str, m.PortSpec]) -> None:
        """Arm ``spec`` (replacing one of its id); `NodeError` saying why it cannot be."""
        port = _port_of(spec.key, ports)
        if port is None:
            raise NodeError(f"no port of this node carries {spec.key}")
        for action in spec.actions:
            if action.kind == "rewire":
                target = ports.get(action.port)
                if target is None or target.direction != "subscribe":
                    raise NodeError(f"reflex {spec.rule}: no input port {action.port!r}")
        monitor = self._monitor(spec, ports[port].type)
        condition: Condition = tuple(
            tuple(Test(t.measurement, t.op, t.value) for t in clause) for clause in spec.any_of
        )
        self.by_id[spec.id] = Armed(spec, monitor, condition)
        self._index()

    def withdraw(self, ident: str) -> None:
        """Disarm reflex ``ident`` ("": all)."""
        if ident:
            self.by_id.pop(ident, None)
        else:
            self.by_id.clear()
        self._index()

    def evaluate(
        self, key: str, payload: bytes | bytearray | memoryview, stamp: float | None
    ) -> list[Fire]:
        """The armed reflexes of ``key`` whose condition holds on this sample (disarmed)."""
        out = []
        for armed in list(self.by_id.values()):
            if armed.fired or armed.spec.key != key:
                continue
            computed = armed.monitor.on_raw(armed.spec.source, bytes(payload), stamp or 0.0)
            values = {c.name: c.value for c in computed}
            if len(values) < len(armed.spec.measurements):
                continue  # not computable from this sample: as if it had not come
            new, armed.last = armed.last is not None and values != armed.last, values
            if new and holds(armed.condition, values):
                out.append(Fire(armed, values, stamp))
        return out

    def state(self) -> dict[str, float]:
        return {i: a.fired for i, a in self.by_id.items()}

    def _index(self) -> None:
        self.watched = frozenset(a.spec.key for a in self.by_id.values() if not a.fired)

    def spent(self, armed: Armed, now: float) -> None:
        """``armed`` fired at ``now``: it stays installed (and listed), disarmed."""
        armed.fired = now
        self.fired += 1
        self._index()

    def _monitor(self, spec: m.Reflex, port_type: str) -> ContextMonitor:
        """A Context Monitor of only the reflex's measurements, from this node's package."""
        model = self._model()
        chosen = []
        functions = {}
        for name in spec.measurements:
            meas = next((x for x in model.measurements if x.name == name), None)
            if meas is None:
                raise NodeError(f"reflex {spec.rule}: the package declares no measurement {name}")
            if meas.inputs != [spec.source]:
                raise NodeError(f"reflex {spec.rule}: {name} is not computed from {spec.source}")
            dotted = function_path(model, meas, [port_type])
            if dotted is not None:
                try:
                    functions[name] = load_function(dotted, self.folders)
                except (RraError, ImportError, AttributeError) as e:
                    raise NodeError(f"reflex {spec.rule}: function of {name}: {e}") from None
            chosen.append(meas)
        subset = MeasurementsModel(data_types=model.data_types, measurements=chosen)
        return ContextMonitor(subset, functions, {spec.source: port_type})

    def _model(self) -> MeasurementsModel:
        folder = next(
            (f for f in self.folders
             if (Path(f) / "rra.yaml").is_file() or (Path(f) / "measurements.yaml").is_file()),
            None,
        )  # fmt: skip
        if folder is None:
            raise NodeError("no package folder: this node cannot compute measurements")
        if folder not in _MODELS:
            try:
                _MODELS[folder] = load_measurements(folder)
            except RraError as e:
                raise NodeError(f"cannot read the package's measurements: {e}") from None
        return _MODELS[folder]


def _port_of(key: str, ports: dict[str, m.PortSpec]) -> str | None:
    """The port of the node that carries ``key``: an output publishing on it, or an input
    listening to it (selected or held)."""
    for name, p in ports.items():
        if p.direction == "publish" and list(p.keys) == [key]:
            return name
        if p.direction == "subscribe" and (key in p.keys or key in p.standby):
            return name
    return None
