"""Measurement functions: how a measurement's ``function`` becomes a callable, in every process.

A measurement of ``measurements.yaml`` names its function either by a key of its source data
type's ``functions`` (``workingMotors``) or by a dotted Python path
(``rra_agent.library.motors.working_motors``); the package folder is on the import path, so a
package may ship its own. The Context Monitor resolves every measurement this way, and a node
that evaluates a reflex (`rra_agent.node.reflex`) resolves the measurements the reflex names
the same way, from its own copy of the package: what a reflex computes is what the monitor
computes, and no code ever travels on the bus.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from rra_agent.errors import RraError
from rra_agent.models.manifest import MANIFEST, Manifest
from rra_agent.models.measurements import Measurement, MeasurementsModel
from rra_agent.models.system import parse_endpoint
from rra_agent.package.contents import SystemPackage
from rra_agent.package.imports import add_package_path, import_dotted
from rra_agent.package.yamlload import load_yaml


def function_path(
    model: MeasurementsModel, meas: Measurement, port_types: list[str | None]
) -> str | None:
    """The dotted path of ``meas``'s function (None: it has none): its ``function`` itself,
    or the entry of that name in the ``functions`` of its sources' data types
    (``port_types``: the type each source port declares, in order)."""
    dotted = meas.function
    if dotted is None or "." in dotted:
        return dotted
    for port_type in port_types:
        dt = model.data_type(port_type) if port_type else None
        if dt is not None and dotted in dt.functions:
            return dt.functions[dotted]
    return dotted


def load_function(dotted: str, folders: list[str] | None = None) -> Callable[..., Any]:
    """The callable at ``dotted`` (``folders``: package folders put on the import path)."""
    if folders:
        add_package_path(folders)
    fn = import_dotted(dotted)
    if not callable(fn):
        raise RraError(f"function {dotted!r} is not callable")
    return fn  # type: ignore[no-any-return]


def load_measurements(root: str | Path) -> MeasurementsModel:
    """The measurements model of the package in folder ``root`` (its manifest names the
    file), without loading the other models."""
    folder = Path(root)
    manifest = Manifest(name=folder.name)
    if (folder / MANIFEST).is_file():
        manifest = load_yaml(folder / MANIFEST, Manifest)[0]
    model: MeasurementsModel = load_yaml(folder / manifest.measurements, MeasurementsModel)[0]
    return model


def measurement_functions(pkg: SystemPackage) -> dict[str, Callable[..., Any]]:
    """Measurement name -> its function, for every measurement of ``pkg`` that has one (the
    package folder put on the import path first): the Context Monitor's and the replay's."""
    add_package_path([pkg.root])
    out = {}
    for meas in pkg.measurements.measurements:
        dotted = function_path(pkg.measurements, meas, _port_types(pkg, meas))
        if dotted is None:
            continue
        fn = import_dotted(dotted)
        if not callable(fn):
            raise RraError(f"function {dotted!r} of measurement {meas.name} is not callable")
        out[meas.name] = fn
    return out


def _port_types(pkg: SystemPackage, meas: Measurement) -> list[str | None]:
    """The type each source port of ``meas`` declares (a ROS 2 topic's measurement: none)."""
    out: list[str | None] = []
    for src in meas.inputs if meas.ros2_topic is None else ():
        ep = parse_endpoint(src)
        comp = pkg.system.component(ep.component)
        port = comp.port(ep.port) if comp else None
        out.append(port.type if port else None)
    return out
