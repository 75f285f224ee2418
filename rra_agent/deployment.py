"""A deployed system: its package, the deployment-time selection and the configured model.

Every engine process and the CLI start from the same three steps (paper Fig. 1, left):
load the package, complete the deployment-time selection, and resolve the Template System
Model into the Deployment-time Configured System Model.

`prepare` does it ahead of time and keeps the result: the fork server does so for the
engines it forks (`rra_agent.engines.launch.warm_up`), so that six engines share one
deployment in memory instead of each loading and resolving the package again (~10 MiB of
private memory each). `deploy` returns a prepared deployment only while no file of the
package has changed since (their size, modification and change times, inode).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from rra_agent.core.features import complete_deployment
from rra_agent.core.resolution import resolve_deployment
from rra_agent.models.loader import SystemPackage, load_package
from rra_agent.models.system import SystemModel


@dataclass(frozen=True)
class Deployment:
    package: SystemPackage
    selection: frozenset[str]
    configured: SystemModel

    @property
    def system(self) -> str:
        return self.configured.system

    @property
    def implementations(self) -> frozenset[str]:
        """Every implementation the configured model may run (what host agents accept)."""
        out: set[str] = set()
        for c in self.configured.components:
            for impl in (c.implementation, *c.implementations.values()):
                out.add(impl if isinstance(impl, str) else " ".join(impl.command))
        return frozenset(out)

    def initial_cv(self) -> dict[str, float]:
        """Continuous Variability values before the first adaptation: what the Adaptation
        Engine starts from (its value, else its lower bound, clamped by active NFRs)."""
        pkg = self.package
        if pkg.adaptation is not None:
            from rra_agent.core.rules import Engine

            return Engine(pkg.features, self.selection, pkg.adaptation).cv
        out = {}
        for name, (_, attr) in pkg.features.attributes.items():
            if attr.kind == "cv":
                value = attr.rra_value
                if isinstance(value, bool) or not isinstance(value, int | float):
                    value = attr.lower if attr.lower is not None else attr.upper
                if value is not None:
                    out[name] = float(value)
        return out

    @property
    def hosts(self) -> list[str]:
        return sorted({c.host for c in self.configured.components if c.host})


#: A stamp of the files of a package: (path, size, mtime, ctime, inode) of each.
Stamp = tuple[tuple[str, int, int, int, int], ...]
#: Deployments made by `prepare`: (package folder, names) -> (the files' stamp, deployment).
_prepared: dict[tuple[str, tuple[str, ...]], tuple[Stamp, Deployment]] = {}


def _key(path: str | Path, names: Sequence[str]) -> tuple[str, tuple[str, ...]]:
    return str(Path(path).resolve()), tuple(names)


def package_stamp(folder: str | Path) -> Stamp:
    """Every file under a package folder (but hidden ones and ``__pycache__``), as it is now."""
    out = []
    for parent, dirs, files in os.walk(folder):
        dirs[:] = sorted(d for d in dirs if not d.startswith(".") and d != "__pycache__")
        for name in sorted(files):
            path = os.path.join(parent, name)
            try:
                st = os.stat(path)
            except OSError:
                continue
            out.append((path, st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino))
    return tuple(out)


def prepare(path: str | Path, names: Sequence[str] = ()) -> Deployment:
    """`deploy` now, and keep the result for the next `deploy` of the same package and
    names in this process or a fork of it (while the package's files stay as they are)."""
    key = _key(path, names)
    stamp = package_stamp(key[0])  # before loading: a change while loading is seen later
    dep = _deploy(path, names)
    _prepared[key] = (stamp, dep)
    return dep


def deploy(path: str | Path, names: Sequence[str] = ()) -> Deployment:
    """Load and resolve; ``names`` default to the manifest's ``default_selection``. A
    deployment `prepare`d in this process (or the one it was forked from) is returned as it
    is if the package's files have not changed since."""
    if _prepared:
        key = _key(path, names)
        kept = _prepared.get(key)
        if kept is not None and kept[0] == package_stamp(key[0]):
            return kept[1]
    return _deploy(path, names)


def _deploy(path: str | Path, names: Sequence[str]) -> Deployment:
    pkg = load_package(path)
    selection = complete_deployment(pkg.features, list(names) or pkg.manifest.default_selection)
    configured = resolve_deployment(pkg.system, pkg.deployment, pkg.features, selection)
    return Deployment(pkg, selection, configured)
