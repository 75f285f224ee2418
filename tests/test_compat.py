"""Old import paths of 0.1 keep working for one release, with a warning naming the new one
(docs/api.md, `rra_agent._compat`)."""

from __future__ import annotations

import importlib
import sys

import pytest

from rra_agent import _compat


@pytest.mark.parametrize("old", sorted(_compat.MOVED))
def test_an_old_module_path_imports_and_warns(old: str) -> None:
    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match="moved to"):
        importlib.import_module(old)


@pytest.mark.parametrize(
    ("old", "name", "new"),
    [
        ("rra_agent.core.rules", "Engine", "rra_agent.core.adaptation.AdaptationEngine"),
        ("rra_agent.core.rules", "clamp_cv", "rra_agent.core.cv.clamp_cv"),
        ("rra_agent.bus.runtime", "NodeRuntime", "rra_agent.node.runtime.NodeRuntime"),
        ("rra_agent.bus.runtime", "open_session", "rra_agent.bus.session.open_session"),
        ("rra_agent.models.loader", "load_package", "rra_agent.package.loader.load_package"),
        ("rra_agent.node", "NodeCore", "rra_agent.node.core.NodeCore"),
        ("rra_agent.node", "decode_data", "rra_agent.bus.data.decode_data"),
        ("rra_agent.core.resolution", "diff", "rra_agent.core.plan.diff"),
        ("rra_agent.engines.monitor", "MonitorProcess",
         "rra_agent.engines.monitor.ContextMonitorProcess"),
        ("rra_agent.engines.resolution", "ResolutionEngine",
         "rra_agent.engines.resolution.ResolutionEngineProcess"),
        ("rra_agent.cli.status", "set_params", "rra_agent.bus.client.set_params"),
    ],
)  # fmt: skip
def test_an_old_name_is_the_new_object_and_warns_naming_it(old: str, name: str, new: str):
    module, _, attr = new.rpartition(".")
    with pytest.warns(DeprecationWarning, match=attr):
        got = getattr(importlib.import_module(old), name)
    assert got is getattr(importlib.import_module(module), attr)


def test_the_public_node_sdk_needs_no_warning() -> None:
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        from rra_agent.node import Node, NodeContext, NodeError, NodeHarness  # noqa: F401


def test_an_unknown_name_is_still_an_attribute_error() -> None:
    with pytest.raises(AttributeError):
        importlib.import_module("rra_agent.node").NoSuchThing  # noqa: B018
