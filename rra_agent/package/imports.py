"""Importing a system package's own Python modules (node classes, measurement functions).

A package may ship Python modules in its folder: node classes named by ``system.yaml``
(``rover_nodes.GnssReceiver``) and measurement functions named by ``measurements.yaml``
(``rover_functions.speed``). Every process that imports them (the node processes, the host
agent's fork server, a component container, the Context Monitor, ``rra validate``) puts the
package folder on ``sys.path`` the same way, with `add_package_path`:

- the folder goes **after** every other entry (the standard library, the installed packages,
  rra_agent itself), so a module of the package can never replace one of those for the rest
  of the process (a package's ``platform.py`` does not become the ``platform`` that zenoh or
  the standard library import);
- a module of the package that *is* hidden that way (its top-level name is also a module of
  the standard library or of an installed package) is an error that says so
  (`shadowed_problem`), at ``rra validate`` and in the node's log, instead of the wrong module
  being used.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Iterable
from pathlib import Path
from types import ModuleType
from typing import Any

from rra_agent.errors import RraError


def add_package_path(folders: Iterable[str | Path]) -> None:
    """Append each package folder to ``sys.path`` (last) unless it is already there."""
    added = False
    for folder in folders:
        f = str(Path(folder).resolve())
        if f not in sys.path:
            sys.path.append(f)
            added = True
    if added:
        importlib.invalidate_caches()


def package_module_file(folder: str | Path, top: str) -> Path | None:
    """The file or folder of top-level module ``top`` in a package folder, or None."""
    root = Path(folder)
    for candidate in (root / f"{top}.py", root / top):
        if candidate.is_file() or candidate.is_dir():
            return candidate
    return None


def _origin(module: ModuleType) -> str:
    file = getattr(module, "__file__", None)
    if file:
        return str(file)
    paths = list(getattr(module, "__path__", []) or [])
    return paths[0] if paths else "built in"


def shadowed_problem(module: ModuleType, folders: Iterable[str | Path]) -> str | None:
    """Why ``module`` is not the package's module of that name (None when it is, or when no
    package folder has a module of its top-level name)."""
    top = module.__name__.split(".")[0]
    top_module = sys.modules.get(top, module)
    origin = _origin(top_module)
    for folder in folders:
        own = package_module_file(folder, top)
        if own is None:
            continue
        resolved = str(Path(folder).resolve())
        if origin.startswith(resolved + "/") or origin == resolved:
            return None
        return (
            f"module '{top}' of the package folder ({own.name}) is hidden by '{top}' from "
            f"{origin} (the standard library and installed packages come first); rename the "
            "package's module"
        )
    return None


def import_dotted(dotted: str) -> Any:
    """``pkg.module.attr`` -> the object (the longest importable module prefix is used)."""
    parts = dotted.split(".")
    for i in range(len(parts) - 1, 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)
        return obj
    raise RraError(f"cannot import {dotted!r}")
