"""Load a system package: the manifest and every model file, with all errors collected.

A package is a folder holding ``rra.yaml`` (optional: without it the default file names are
used and the package is named after the folder), ``features.uvl``, ``system.yaml``,
``deployment.yaml``, ``runtime.yaml``, ``measurements.yaml`` and optionally an adaptation
model (``adaptation.rra``). Every file is loaded even when another one fails, so one run
reports every problem; cross-references are then checked by `validate_package`.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rra_agent.errors import ErrorGroup, LocatedError, ModelError, RraError
from rra_agent.models.features import FeatureModel
from rra_agent.models.manifest import MANIFEST, Manifest
from rra_agent.models.measurements import MeasurementsModel
from rra_agent.models.resolution import DeploymentResolutionModel, RuntimeResolutionModel
from rra_agent.models.system import SystemModel
from rra_agent.package.contents import SystemPackage
from rra_agent.package.yamlload import YamlDoc, load_yaml

if TYPE_CHECKING:
    from rra_agent.models.adaptation import AdaptationModel

#: The YAML models of a package: manifest field -> Struct.
YAML_MODELS: dict[str, type] = {
    "system": SystemModel,
    "deployment": DeploymentResolutionModel,
    "runtime": RuntimeResolutionModel,
    "measurements": MeasurementsModel,
}


def package_root(path: str | Path) -> Path:
    """The package folder for ``path`` (a folder, or its ``rra.yaml``); RraError if none."""
    p = Path(path)
    if p.is_file() and p.name == MANIFEST:
        p = p.parent
    if not p.exists():
        raise RraError(f"{path}: no such system package (folder not found)")
    if not p.is_dir():
        raise RraError(f"{path}: not a system package (expected a folder or its {MANIFEST})")
    if not any((p / n).is_file() for n in (MANIFEST, "system.yaml", "features.uvl")):
        raise RraError(f"{path}: not a system package (no {MANIFEST}, system.yaml or features.uvl)")
    return p


def load_package(path: str | Path, *, validate: bool = True) -> SystemPackage:
    """Load every model of the package at ``path``.

    Raises the error (or an `ErrorGroup` of all errors) of every file that fails to load;
    with ``validate`` (the default) then also those of `validate_package`, except the
    resolution of implementations (``rra validate`` does that; running a package does not
    import another host's node classes).
    """
    root = package_root(path)
    errors: list[RraError] = []
    manifest, mdoc = _load_manifest(root, errors)
    docs: dict[str, YamlDoc] = {"manifest": mdoc} if mdoc is not None else {}
    models: dict[str, Any] = {}
    for kind, type_ in YAML_MODELS.items():
        file = _model_file(root, manifest, mdoc, kind, errors)
        if file is not None:
            models[kind] = _collect(errors, lambda f=file, t=type_: load_yaml(f, t))
    uvl = _model_file(root, manifest, mdoc, "features", errors)
    features = _collect(errors, lambda: _load_features(uvl)) if uvl is not None else None
    adaptation = None
    if features is not None and models.get("measurements") is not None:
        adaptation = _collect(
            errors, lambda: _load_adaptation(root, manifest, mdoc, features, models)
        )
    ErrorGroup.raise_if_any(errors)
    # No features means a missing or broken features file, whose error(s) were just raised.
    assert features is not None
    pkg = SystemPackage(
        root=root,
        manifest=manifest,
        features=features,
        adaptation=adaptation,
        docs=docs | {k: doc for k, (_, doc) in models.items()},
        **{k: model for k, (model, _) in models.items()},
    )
    if validate:
        from rra_agent.package.validate import validate_package

        ErrorGroup.raise_if_any(validate_package(pkg, implementations=False))
    return pkg


def _collect(errors: list[RraError], load: Any) -> Any:
    """``load()``, or None after adding its error(s) to ``errors``."""
    try:
        return load()
    except ErrorGroup as e:
        errors.extend(e.errors)
    except RraError as e:
        errors.append(e)
    return None


def _load_manifest(root: Path, errors: list[RraError]) -> tuple[Manifest, YamlDoc | None]:
    file = root / MANIFEST
    default = Manifest(name=root.resolve().name)
    if not file.is_file():
        return default, None
    loaded = _collect(errors, lambda: load_yaml(file, Manifest))
    return loaded if loaded is not None else (default, None)


def _model_file(
    root: Path, manifest: Manifest, mdoc: YamlDoc | None, kind: str, errors: list[RraError]
) -> Path | None:
    """The path of a model file, or None after reporting that it does not exist."""
    file = root / getattr(manifest, kind)
    if file.is_file():
        return file
    errors.append(_missing(file, kind, mdoc))
    return None


def _missing(file: Path, kind: str, mdoc: YamlDoc | None) -> ModelError:
    named = mdoc is not None and mdoc.node(kind) is not None
    if named:
        assert mdoc is not None
        return mdoc.error(f"no such file: {file} (the {kind} model)", mdoc.loc(kind))
    return ModelError(f"{file}: no such file (the {kind} model)", None)


def _load_features(file: Path) -> FeatureModel:
    try:
        from rra_agent.dsl.uvl import load_uvl
    except ModuleNotFoundError as e:
        if e.name != "rra_agent.dsl.uvl":
            raise
        msg = f"{file}: cannot load UVL feature models (no rra_agent.dsl.uvl)"
        raise ModelError(msg, None) from None
    return load_uvl(file)


def _load_adaptation(
    root: Path,
    manifest: Manifest,
    mdoc: YamlDoc | None,
    features: FeatureModel,
    models: dict[str, Any],
) -> AdaptationModel | None:
    """Parse the adaptation rules when the package has them and the rule DSL is available."""
    if manifest.adaptation is None:
        return None
    file = root / manifest.adaptation
    if not file.is_file():
        if mdoc is not None and mdoc.node("adaptation") is not None:
            raise _missing(file, "adaptation", mdoc)
        return None  # the default name, and no such file: a package without rules
    try:
        rules = importlib.import_module("rra_agent.dsl.rules")
    except ModuleNotFoundError as e:
        if e.name != "rra_agent.dsl.rules":
            raise
        return None
    measurements, _ = models["measurements"]
    try:
        text = file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise ModelError(f"{file}: cannot read: {e}", None) from None
    return rules.parse_rules(text, str(file), features, measurements)


def flatten_errors(error: RraError) -> list[RraError]:
    """The errors inside an `ErrorGroup` (recursively), or the error itself."""
    if isinstance(error, ErrorGroup):
        return [e for sub in error.errors for e in flatten_errors(sub)]
    return [error]


def error_line(error: RraError) -> str:
    """One line for an error: ``file:line:col: message`` when located."""
    if isinstance(error, LocatedError):
        return error.headline
    return str(error)
