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

import contextlib
import os
import pickle
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any

import msgspec

from rra_agent.core.features import complete_deployment
from rra_agent.core.resolution import resolve_deployment
from rra_agent.errors import RraError
from rra_agent.models.system import SystemModel
from rra_agent.package.bundle import ModelBundle, bundle_of
from rra_agent.package.contents import SystemPackage
from rra_agent.package.loader import load_package, package_root


@dataclass(frozen=True)
class Deployment:
    package: SystemPackage
    selection: frozenset[str]
    configured: SystemModel
    #: The package's model files as they were loaded, and their digest (the *models
    #: version*: `rra_agent.package.bundle`); None when a model file cannot be bundled.
    bundle: ModelBundle | None = None

    @property
    def models(self) -> str:
        """The digest of the models this deployment runs ("" when unknown)."""
        return self.bundle.digest if self.bundle is not None else ""

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
        Engine starts from (its value, else its lower bound, clamped by active NFRs).
        Computed once per deployment (by `prepare`, in the fork server, for every engine
        forked after it: building an Adaptation Engine for it copied ~3 MiB of the fork
        server's pages into each Resolution Engine)."""
        return dict(self._initial_cv)

    @cached_property
    def _initial_cv(self) -> dict[str, float]:
        pkg = self.package
        if pkg.adaptation is not None:
            from rra_agent.core.adaptation import AdaptationEngine

            return AdaptationEngine(pkg.features, self.selection, pkg.adaptation).cv
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
#: The model files a manifest names (they may lie outside the package's folder).
_MODELS = ("manifest", "features", "system", "deployment", "runtime", "measurements")
#: Deployments made by `prepare`: (package folder, names) -> (the files' stamp, deployment).
_prepared: dict[tuple[Path, tuple[str, ...]], tuple[Stamp, Deployment]] = {}


def package_stamp(pkg: SystemPackage) -> Stamp:
    """Every file under the package's folder (but hidden ones and ``__pycache__``) and every
    model file its manifest names, as they are now (a missing one has only its path)."""
    paths: set[str] = {str(pkg.file(m)) for m in _MODELS}
    if pkg.manifest.adaptation is not None:
        paths.add(str(pkg.file("adaptation")))
    for parent, dirs, files in os.walk(pkg.root):
        dirs[:] = [d for d in dirs if not d.startswith(".") and d != "__pycache__"]
        paths.update(os.path.join(parent, name) for name in files)
    out: list[tuple[str, int, int, int, int]] = []
    for path in sorted(paths):
        try:
            st = os.stat(path)
        except OSError:
            out.append((path, -1, -1, -1, -1))
            continue
        out.append((path, st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino))
    return tuple(out)


def prepare(path: str | Path, names: Sequence[str] = ()) -> Deployment:
    """`deploy` now, and keep the result for the next `deploy` of the same package and
    names in this process or a fork of it (while the package's files stay as they are)."""
    dep = _deploy(path, names)
    with contextlib.suppress(Exception):  # a model error is the engine's to report
        dep.initial_cv()
    # Stamped after loading: a file changed while it was being loaded may go unnoticed
    # (prepare runs in the fork server as the run starts, not while a package is edited).
    _prepared[_key(path, names)] = (package_stamp(dep.package), dep)
    return dep


def deploy(path: str | Path, names: Sequence[str] = ()) -> Deployment:
    """Load and resolve; ``names`` default to the manifest's ``default_selection``. A
    deployment `prepare`d in this process (or the one it was forked from) is returned as it
    is if the package's files have not changed since."""
    if _prepared:
        kept = _prepared.get(_key(path, names))
        if kept is not None and kept[0] == package_stamp(kept[1].package):
            return kept[1]
    return _deploy(path, names)


def deploy_apart(path: str | Path, names: Sequence[str] = ()) -> Deployment:
    """`deploy` in a forked child, whose result this process takes (pickled, its msgspec
    Structs as msgpack: `_StructPickler`): a long-lived caller (``rra up``'s host agent)
    then never imports the model parsers (lark and the DSLs) nor keeps what loading left in
    its heap, only the deployment (-3.5 MiB private, docs/performance.md). A model error, or a
    child that cannot deliver, is loaded again here: its message is `deploy`'s own. With
    threads running it is `deploy` (a fork copies only the calling thread)."""
    if threading.active_count() > 1 or not hasattr(os, "fork"):
        return deploy(path, names)
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover (the child)
        code = 1
        try:
            os.close(read)
            with os.fdopen(write, "wb") as out:
                _StructPickler(out, protocol=pickle.HIGHEST_PROTOCOL).dump(_deploy(path, names))
            code = 0
        finally:
            os._exit(code)
    os.close(write)
    with os.fdopen(read, "rb") as got:
        data = got.read()
    _, status = os.waitpid(pid, 0)
    if status == 0 and data:
        with contextlib.suppress(Exception):
            dep = pickle.loads(data)
            if isinstance(dep, Deployment):
                return dep
    return _deploy(path, names)


def _struct(data: bytes, cls: type[msgspec.Struct]) -> msgspec.Struct:
    return msgspec.msgpack.decode(data, type=cls)


class _StructPickler(pickle.Pickler):
    """Pickles a msgspec Struct as its msgpack: msgspec omits a field equal to its default
    only when it *is* the default object, and an unpickled ``"deployment"`` or
    ``Supervision()`` is a new one (node specs would encode, and hash, otherwise than the
    engines'); decoded, a field left out takes the class's own default. A Struct that does
    not come back equal from msgpack is pickled as usual."""

    def reducer_override(self, obj: Any) -> Any:
        if isinstance(obj, msgspec.Struct):
            with contextlib.suppress(Exception):
                data = msgspec.msgpack.encode(obj)
                if msgspec.msgpack.decode(data, type=type(obj)) == obj:
                    return _struct, (data, type(obj))
        return NotImplemented


def _key(path: str | Path, names: Sequence[str]) -> tuple[Path, tuple[str, ...]]:
    try:
        return package_root(path).resolve(), tuple(names)
    except RraError:
        return Path(path), tuple(names)  # never prepared: deploying it says what is wrong


def _deploy(path: str | Path, names: Sequence[str]) -> Deployment:
    pkg = load_package(path)
    try:
        bundle: ModelBundle | None = bundle_of(pkg)
    except RraError:
        bundle = None  # a model file outside the package folder: not recorded, not reloadable
    return deploy_package(pkg, names, bundle)


def deploy_package(
    pkg: SystemPackage, names: Sequence[str], bundle: ModelBundle | None = None
) -> Deployment:
    """Complete the deployment-time selection (``names``, default the manifest's) and resolve
    a loaded package (a reload: the models of ``bundle``)."""
    selection = complete_deployment(pkg.features, list(names) or pkg.manifest.default_selection)
    configured = resolve_deployment(pkg.system, pkg.deployment, pkg.features, selection)
    return Deployment(pkg, selection, configured, bundle)
