"""Getting a version of the models into a running engine (``rra reload``).

A replica gets the models of a digest from, in turn: what it prepared (`PrepareModels`), the
run's record (``<run>/record/models/<digest>/``, written by the Run-time Resolution Engine
leader before it switches), or the leader itself (`GetModels` on ``engine/resolution/ctl``).
`deploy_bundle` loads them as the running deployment's next version: the same deployment-time
selection, the package's own folder kept as its root (its Python modules are not reloaded).
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.client import oks
from rra_agent.bus.keys import Keys
from rra_agent.deployment import Deployment, deploy_package
from rra_agent.errors import RraError
from rra_agent.package.bundle import ModelBundle, load_bundle, write_bundle
from rra_agent.record.run import models_folder, read_models

_REQ = m.Codec[m.EngineRequest](m.EngineRequest)


def deploy_bundle(bundle: ModelBundle, current: Deployment) -> Deployment:
    """The deployment of ``bundle`` with ``current``'s deployment-time selection (RraError
    if the models do not load, or complete that selection differently)."""
    folder = Path(tempfile.mkdtemp(prefix=f"rra-models-{bundle.digest}-"))
    try:
        write_bundle(bundle.verified(), folder)
        pkg = load_bundle(folder, root=current.package.root)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    new = deploy_package(pkg, sorted(current.selection), bundle)
    if new.selection != current.selection:
        gained = sorted(new.selection - current.selection)
        lost = sorted(current.selection - new.selection)
        raise RraError(
            "the deployment-time selection would change (+"
            f"{', '.join(gained) or 'nothing'}, -{', '.join(lost) or 'nothing'}): "
            "it cannot change while the system runs"
        )
    return new


def find_bundle(
    digest: str, run_dir: Path | None, session: zenoh.Session | None, keys: Keys
) -> ModelBundle:
    """The models ``digest`` from the run's record, else from the Resolution Engine leader."""
    if run_dir is not None and models_folder(run_dir, digest).is_dir():
        return read_models(run_dir, digest)
    if session is None:
        raise RraError(f"models {digest}: not in the record and no bus to ask")
    for answer in oks(session.get(
        keys.engine_ctl("resolution"), payload=_REQ.encode(m.GetModels(digest=digest)),
        timeout=2.0,
    )):  # fmt: skip
        if answer.result:
            try:
                bundle = msgspec.convert(answer.result, ModelBundle)
            except msgspec.ValidationError:
                continue
            if bundle.digest == digest:
                return bundle.verified()
    raise RraError(f"models {digest}: the Resolution Engine leader did not give them")
