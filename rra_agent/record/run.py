"""A run folder's ``record/``: the run, the models of each version, the record files, the seal.

::

    <run>/record/run.json                 RunInfo: system, deployment, host, start, models
    <run>/record/models/<digest>.json     the model files of one version (names)
    <run>/record/models/<digest>/...      their copy, as the package names them
    <run>/record/<replica>-<pid>.rec      one per engine process (`rra_agent.record.format`)
    <run>/record/SEAL.json                at a clean end: each record file's size and SHA-256

``rra up`` begins the record (`begin`: the info and the models it starts with) and seals it
when every process has stopped (`seal`); the Run-time Resolution Engine keeps each version
``rra reload`` brings (`keep_models`). A sealed record is checked whole (`check_seal`): a
truncated or changed file is an error; an unsealed one (a killed run) is read as far as it
goes.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import time
from pathlib import Path
from typing import TypeVar

import msgspec

from rra_agent.errors import RraError
from rra_agent.package.bundle import ModelBundle, check_relative, digest_of, write_bundle
from rra_agent.record.format import FORMAT, SUFFIX

RECORD = "record"
RUN_FILE = "run.json"
SEAL_FILE = "SEAL.json"
MODELS = "models"
T = TypeVar("T")


class RunInfo(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    system: str
    deployment: list[str]
    #: Wall-clock time the run began (``rra up`` started).
    started: float
    #: The digest of the models it started with.
    models: str
    host: str = ""
    #: The package folder it ran (for a reader: where its Python modules are).
    package: str = ""
    format: int = FORMAT


class Listing(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    digest: str
    files: list[str]


class SealEntry(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    size: int
    sha256: str


class Seal(msgspec.Struct, kw_only=True, forbid_unknown_fields=True):
    stamp: float
    files: dict[str, SealEntry]


def record_dir(run_dir: Path) -> Path:
    return Path(run_dir) / RECORD


def begin(run_dir: Path, info: RunInfo, bundle: ModelBundle) -> Path:
    """Start a new record in ``run_dir`` (an earlier run's record there is removed)."""
    folder = record_dir(run_dir)
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    keep_models(run_dir, bundle)
    _write_json(folder / RUN_FILE, info)
    return folder


def keep_models(run_dir: Path, bundle: ModelBundle) -> Path:
    """Copy one version of the models into the record (once per digest)."""
    models = record_dir(run_dir) / MODELS
    listing = models / f"{bundle.digest}.json"
    if not listing.exists():
        write_bundle(bundle, models / bundle.digest)
        _write_json(listing, Listing(digest=bundle.digest, files=sorted(bundle.files)))
    return models / bundle.digest


def read_models(run_dir: Path, digest: str) -> ModelBundle:
    """One version of the models from the record, checked against its digest (RraError)."""
    models = record_dir(run_dir) / MODELS
    listing = _read_json(models / f"{digest}.json", Listing)
    files = {}
    for name in listing.files:
        path = models / digest / check_relative(name)
        try:
            files[name] = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise RraError(f"{path}: cannot read: {e}") from None
    actual = digest_of(files)
    if actual != digest or listing.digest != digest:
        raise RraError(
            f"{models / digest}: digest mismatch (recorded {digest}, the files now {actual}): "
            "the recorded models were changed"
        )
    return ModelBundle(files=files, digest=digest)


def models_folder(run_dir: Path, digest: str) -> Path:
    return record_dir(run_dir) / MODELS / digest


def read_info(run_dir: Path) -> RunInfo:
    return _read_json(record_dir(run_dir) / RUN_FILE, RunInfo)


def record_files(run_dir: Path) -> list[Path]:
    return sorted(record_dir(run_dir).glob(f"*{SUFFIX}"))


def seal(run_dir: Path) -> Seal:
    """Write the seal: the size and SHA-256 of every record file, as they are now."""
    folder = record_dir(run_dir)
    entries = {p.name: SealEntry(size=p.stat().st_size, sha256=_sha256(p)) for p in
               record_files(run_dir)}  # fmt: skip
    out = Seal(stamp=time.time(), files=entries)
    _write_json(folder / SEAL_FILE, out)
    return out


def check_seal(run_dir: Path) -> Seal | None:
    """The seal, after checking every file it names against it (RraError); None when the
    record was not sealed (the run was killed)."""
    path = record_dir(run_dir) / SEAL_FILE
    if not path.exists():
        return None
    sealed = _read_json(path, Seal)
    present = {p.name for p in record_files(run_dir)}
    for name, entry in sealed.files.items():
        file = record_dir(run_dir) / name
        if name not in present:
            raise RraError(f"{file}: missing (the sealed record had it)")
        size = file.stat().st_size
        if size != entry.size:
            what = "truncated" if size < entry.size else "grown"
            raise RraError(f"{file}: {what}: {size} bytes, {entry.size} when the run ended")
        if _sha256(file) != entry.sha256:
            raise RraError(f"{file}: digest mismatch: changed since the run ended")
    extra = sorted(present - set(sealed.files))
    if extra:
        raise RraError(f"{record_dir(run_dir) / extra[0]}: not in the sealed record")
    return sealed


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with path.open("rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _write_json(path: Path, obj: object) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_bytes(msgspec.json.encode(obj))
    tmp.replace(path)


def _read_json(path: Path, type_: type[T]) -> T:
    try:
        return msgspec.json.decode(path.read_bytes(), type=type_)
    except FileNotFoundError:
        raise RraError(f"{path}: missing: not a recorded run (or it was cut short)") from None
    except (OSError, msgspec.DecodeError, msgspec.ValidationError) as e:
        raise RraError(f"{path}: unreadable: {e}") from None
