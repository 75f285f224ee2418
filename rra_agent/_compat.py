"""Old import paths, kept for one release: the one place that knows where things moved.

Release 0.2 re-laid the package out (CHANGELOG.md). Importing a module by its old path
still works and warns (`DeprecationWarning` naming the new path): a finder on
``sys.meta_path`` makes the old name an alias of a module that forwards each attribute to
where it lives now. A class or function renamed in place is forwarded by its module's
``__getattr__`` (`renamed`). Public API: docs/api.md.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import types
import warnings
from collections.abc import Callable, Sequence
from typing import Any

#: Old module -> the modules its names live in now (searched in order).
MOVED: dict[str, tuple[str, ...]] = {
    "rra_agent.core.rules": ("rra_agent.core.adaptation", "rra_agent.core.cv"),
    "rra_agent.core.context": ("rra_agent.core.monitor",),
    "rra_agent.models.loader": ("rra_agent.package.loader",),
    "rra_agent.models.validate": ("rra_agent.package.validate",),
    "rra_agent.models.yamlload": ("rra_agent.package.yamlload",),
    "rra_agent.models.pkgimport": ("rra_agent.package.imports",),
    "rra_agent.models.package": ("rra_agent.models.manifest",),
    "rra_agent.bus.runtime": ("rra_agent.node.runtime", "rra_agent.bus.session"),
    "rra_agent.host.container": ("rra_agent.node.container",),
    "rra_agent.host.heartbeat": ("rra_agent.bus.heartbeat",),
    "rra_agent.scenario.cli": ("rra_agent.cli.test",),
}  # fmt: skip
#: Names renamed where they live: (module, old name) -> new name.
RENAMED: dict[tuple[str, str], str] = {
    ("rra_agent.core.adaptation", "Engine"): "AdaptationEngine",
    ("rra_agent.engines.monitor", "MonitorProcess"): "ContextMonitorProcess",
    ("rra_agent.engines.adaptation", "AdaptationProcess"): "AdaptationEngineProcess",
    ("rra_agent.engines.resolution", "ResolutionEngine"): "ResolutionEngineProcess",
}  # fmt: skip
#: Names that left a module that stays: (module, name) -> the module it lives in now.
LEFT: dict[tuple[str, str], str] = {
    **{
        ("rra_agent.core.resolution", n): "rra_agent.core.plan"
        for n in (
            "Plan", "PlanStep", "Step", "StartComponent", "StopComponent", "SwapComponent",
            "SetImplementation", "SetParameters", "Rewire", "diff", "peers_of", "topic_of",
            "subscriptions", "standby_subscriptions", "wiring",
        )
    },
    **{
        ("rra_agent.node", n): m
        for n, m in [
            ("NodeCore", "rra_agent.node.core"), ("Transport", "rra_agent.node.core"),
            ("REPLAY_MAX_AGE", "rra_agent.node.core"),
            ("load_node_class", "rra_agent.node.loading"),
            ("read_spec", "rra_agent.node.process"), ("run_node", "rra_agent.node.process"),
            ("main", "rra_agent.node.process"), ("SPEC_ENV", "rra_agent.node.process"),
            ("EXIT_CONFIG", "rra_agent.node.process"), ("CONTAINER", "rra_agent.node.process"),
            ("encode_data", "rra_agent.bus.data"), ("decode_data", "rra_agent.bus.data"),
        ]
    },
    **{
        ("rra_agent.cli.status", n): m
        for n, m in [
            ("gather", "rra_agent.bus.client"), ("set_params", "rra_agent.bus.client"),
            ("engine_params", "rra_agent.bus.client"), ("process_stats", "rra_agent.bus.client"),
            ("wait_for_leader", "rra_agent.bus.client"), ("WIDTH", "rra_agent.cli.common"),
            ("add_system_argument", "rra_agent.cli.common"),
            ("format_event", "rra_agent.cli.events"), ("in_time_order", "rra_agent.cli.events"),
            ("EventFilter", "rra_agent.cli.events"),
            ("parse_assignments", "rra_agent.cli.param"),
        ]
    },
}  # fmt: skip


def _warn(old: str, new: str) -> None:
    warnings.warn(f"{old} moved to {new}; the old name goes in the next release",
                  DeprecationWarning, stacklevel=3)  # fmt: skip


def renamed(module: str) -> Callable[[str], Any]:
    """A module's ``__getattr__`` forwarding the names that were renamed in it or that left
    it (`RENAMED`, `LEFT`), with a warning."""

    def getattr_(name: str) -> Any:
        new = RENAMED.get((module, name))
        if new is not None:
            _warn(f"{module}.{name}", f"{module}.{new}")
            return getattr(sys.modules[module], new)
        where = LEFT.get((module, name))
        if where is not None:
            _warn(f"{module}.{name}", f"{where}.{name}")
            return getattr(importlib.import_module(where), name)
        raise AttributeError(f"module {module!r} has no attribute {name!r}")

    return getattr_


class _Alias(types.ModuleType):
    """An old module: each attribute is looked up where it lives now (and warns)."""

    def __init__(self, name: str, targets: Sequence[str]) -> None:
        super().__init__(name, f"Moved to {', '.join(targets)}.")
        self.__targets = tuple(targets)

    def __getattr__(self, attr: str) -> Any:
        if attr.startswith("__"):
            raise AttributeError(attr)
        for target in self.__targets:
            name = RENAMED.get((target, attr), attr)
            module = importlib.import_module(target)
            if name in vars(module):
                _warn(f"{self.__name__}.{attr}", f"{target}.{name}")
                return vars(module)[name]
        raise AttributeError(f"module {self.__name__!r} has no attribute {attr!r}")


class _Finder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    def find_spec(self, fullname: str, path: Any, target: Any = None):
        if fullname not in MOVED:
            return None
        return importlib.machinery.ModuleSpec(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> types.ModuleType:
        return _Alias(spec.name, MOVED[spec.name])

    def exec_module(self, module: types.ModuleType) -> None:
        _warn(module.__name__, " / ".join(MOVED[module.__name__]))


def install() -> None:
    """Put the finder in front of the others (once)."""
    if not any(isinstance(f, _Finder) for f in sys.meta_path):
        sys.meta_path.insert(0, _Finder())
