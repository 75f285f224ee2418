"""A package's models as data: their files' text, and the digest that names this version.

A `ModelBundle` holds the model files a package's manifest names (``rra.yaml``,
``features.uvl``, ``system.yaml``, ``deployment.yaml``, ``runtime.yaml``,
``measurements.yaml``, ``adaptation.rra``) by their path relative to the package folder, as
text. Its `digest` (16 hex digits of a SHA-256 over the sorted names and contents) is the
*models version*: every `Selection` and `EngineState` carries the digest of the models it was
made under, a run's record keeps a copy of each version it ran, and ``rra reload`` sends a
bundle to the running engines.

Only the models are in a bundle: the package's Python modules (node classes, measurement
functions) are not; a bundle written back into a folder (`write_bundle`) loads with
`load_bundle`, which keeps the package's own folder as its root so that its modules are still
found where they were.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Mapping
from pathlib import Path, PurePosixPath

import msgspec

from rra_agent.errors import RraError
from rra_agent.models.manifest import MANIFEST
from rra_agent.package.contents import SystemPackage
from rra_agent.package.loader import load_package

#: The model files a manifest names, by their manifest field.
MODEL_FIELDS = ("features", "system", "deployment", "runtime", "measurements", "adaptation")


class ModelBundle(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """The model files of a package (relative path -> text) and their digest."""

    files: dict[str, str]
    digest: str = ""

    @classmethod
    def of(cls, files: Mapping[str, str]) -> ModelBundle:
        for name in files:
            check_relative(name)
        return cls(files=dict(sorted(files.items())), digest=digest_of(files))

    def verified(self) -> ModelBundle:
        """This bundle, after checking that its digest is that of its files (RraError)."""
        for name in self.files:
            check_relative(name)
        actual = digest_of(self.files)
        if actual != self.digest:
            raise RraError(f"models {self.digest}: digest mismatch (the files hash to {actual})")
        return self


def digest_of(files: Mapping[str, str]) -> str:
    """16 hex digits of SHA-256 over every (name, content), sorted by name."""
    h = hashlib.sha256()
    for name in sorted(files):
        data = files[name].encode("utf-8")
        h.update(f"{name}\0{len(data)}\0".encode())
        h.update(data)
    return h.hexdigest()[:16]


def check_relative(name: str) -> str:
    """A model file's name: relative, no ``..``, no leading ``.`` part (RraError)."""
    path = PurePosixPath(name)
    if path.is_absolute() or not path.parts or any(
        part in ("..", "") or part.startswith(".") for part in path.parts
    ):
        raise RraError(f"model file {name!r}: not a plain path inside the package folder")
    return name


def model_files(pkg: SystemPackage) -> dict[str, str]:
    """The relative path of each model file the package's manifest names (those that exist)."""
    names = [MANIFEST] if (pkg.root / MANIFEST).is_file() else []
    for field in MODEL_FIELDS:
        name = getattr(pkg.manifest, field)
        if name is not None and (pkg.root / name).is_file():
            names.append(name)
    return {name: name for name in names}


def bundle_of(pkg: SystemPackage) -> ModelBundle:
    """The models of a loaded package as they are on disk now. A model file outside the
    package folder (``../shared/system.yaml``) cannot be bundled (RraError)."""
    files: dict[str, str] = {}
    for name in model_files(pkg):
        if ".." in PurePosixPath(name).parts:
            raise RraError(
                f"{pkg.root / MANIFEST}: the model file {name} lies outside the package folder; "
                "copy it into the folder to record or reload this package"
            )
        try:
            files[name] = (pkg.root / name).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise RraError(f"{pkg.root / name}: cannot read: {e}") from None
    return ModelBundle.of(files)


def write_bundle(bundle: ModelBundle, folder: Path) -> Path:
    """Write the bundle's files under ``folder`` (made; files already there replaced)."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in bundle.files.items():
        path = folder / check_relative(name)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(text, encoding="utf-8")
        tmp.replace(path)
    return folder


def read_bundle(folder: Path, names: list[str] | None = None) -> ModelBundle:
    """The model files under ``folder`` (all files below it, or ``names``), as a bundle."""
    if names is None:
        names = sorted(
            p.relative_to(folder).as_posix()
            for p in folder.rglob("*")
            if p.is_file() and not any(part.startswith(".") for part in p.relative_to(folder).parts)
        )
    files = {}
    for name in names:
        try:
            files[name] = (folder / check_relative(name)).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise RraError(f"{folder / name}: cannot read: {e}") from None
    return ModelBundle.of(files)


def load_bundle(folder: Path, root: Path | None = None) -> SystemPackage:
    """Load the package whose model files a bundle wrote to ``folder``; its ``root`` is
    ``root`` (the running package's folder, where its Python modules are) when given."""
    pkg = load_package(folder)
    return pkg if root is None else dataclasses.replace(pkg, root=root)
