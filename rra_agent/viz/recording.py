"""The ``rra up`` side of Rerun logging: the ``--rerun`` option, merging and verifying.

Nothing here imports rerun: the ``rerun`` command-line tool is run as a process. It is the
native binary shipped in the ``rerun_cli`` package (found without importing it), called
directly: the ``rerun`` console script is a Python wrapper that starts that binary as a
child and would orphan it when killed. ``RERUN_CLI_PATH`` overrides the binary, and a
``rerun`` on ``PATH`` is the last resort (then run in its own process group, killed as a
group on timeout).

``--rerun`` forms (put the option after PKG)::

    --rerun                    save to <run-dir>/recording.rrd
    --rerun save [PATH]        save to PATH (default <run-dir>/recording.rrd)
    --rerun PATH.rrd           the same as ``save PATH.rrd``
    --rerun connect [URL]      stream to a running viewer (default rerun+http://127.0.0.1:9876/proxy)
    --rerun off                no logging (the default)

With ``save``, each logging process writes ``<run-dir>/rerun/<recording-id>/<process>.rrd``
and `rra_agent.viz.blueprint.send` the views (``blueprint.rrd``); once every child has
exited, `finish` merges them into PATH (``rerun rrd optimize``: merged and compacted), checks
the result (``rerun rrd verify``) and names it in ``<run-dir>/rerun/recording.txt``. The
per-process files are kept.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from rra_agent.viz.rerun_log import DEFAULT_URL, ENV_VAR, RerunConfig, viewer_reachable

if TYPE_CHECKING:
    from rra_agent.package.contents import SystemPackage

SUBDIR = "rerun"
#: In a run folder: the path of the merged recording when ``--rerun save PATH`` put it
#: elsewhere (read by ``rra view RUN_DIR``).
POINTER = f"{SUBDIR}/recording.txt"


class RecordingError(Exception):
    """The rerun tool failed on a recording (message: what and why)."""


def rerun_option(
    values: Sequence[str] | None, system: str, run_dir: Path
) -> tuple[RerunConfig, Path | None]:
    """(configuration for the children, path of the merged recording or None) of the
    ``--rerun`` values; ValueError for a malformed option or an unreachable viewer."""
    vals = list(values) if values is not None else ["off"]
    mode, rest = (vals[0], vals[1:]) if vals else ("save", [])
    if mode.endswith(".rrd") and not rest:
        mode, rest = "save", [mode]
    if len(rest) > 1 or mode not in ("off", "save", "connect") or (mode == "off" and rest):
        raise ValueError(
            f"expected `off`, `save [PATH]` or `connect [URL]`, got {' '.join(vals)!r}"
        )
    if mode == "off":
        return RerunConfig(), None
    if mode == "connect":
        url = rest[0] if rest else DEFAULT_URL
        if not viewer_reachable(url):
            raise ValueError(
                f"no Rerun viewer at {url} (start one first: `{venv_rerun() or 'rerun'}`)"
            )
        return RerunConfig.new("connect", system, url=url), None
    out = Path(rest[0]) if rest else run_dir / "recording.rrd"
    out = out.resolve()
    if out.suffix != ".rrd":
        raise ValueError(f"{out}: a recording file ends with .rrd")
    out.parent.mkdir(parents=True, exist_ok=True)
    config = RerunConfig.new("save", system)
    # One folder per recording: a reused run folder never mixes two runs' files.
    config.dir = str(run_dir / SUBDIR / config.recording_id)
    return config, out


#: The blueprint children of `attach_blueprint` (their waiters); `finish` waits for them.
_blueprints: list[threading.Thread] = []


def attach_blueprint(config: RerunConfig, package: SystemPackage) -> None:
    """Give the recording its views: the package's limits and choices into ``config``
    (`rra_agent.viz.blueprint.describe`) and the blueprint sent by a child process (it
    imports rerun, which this process must not: the processes it forks would inherit it).
    The child runs while the system starts (~1 s); `finish` waits for it. A failure is a
    warning on stderr: the run goes on without the designed views."""
    if config.mode == "off":
        return
    from rra_agent.viz import blueprint

    blueprint.describe(config, blueprint.layout_of(package))
    cmd = [sys.executable, "-m", "rra_agent.viz.blueprint", str(package.root)]
    env = {**os.environ, ENV_VAR: config.to_env(), "RERUN_ANALYTICS": "0"}
    proc = subprocess.Popen(
        cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE, text=True,
    )  # fmt: skip

    def wait() -> None:
        try:
            _, err = proc.communicate(timeout=60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            print("rra up: rerun: no blueprint (timed out after 60 s)", file=sys.stderr)
            return
        if proc.returncode != 0:
            why = (err.strip().splitlines() or [f"exit status {proc.returncode}"])[-1]
            print(f"rra up: rerun: no blueprint ({why})", file=sys.stderr)

    waiter = threading.Thread(target=wait, name="rerun-blueprint", daemon=True)
    waiter.start()
    _blueprints.append(waiter)


def export(config: RerunConfig) -> None:
    """Put ``config`` in this process' environment, which every child inherits (mode off:
    remove any inherited one)."""
    if config.mode == "off":
        os.environ.pop(ENV_VAR, None)
    else:
        os.environ[ENV_VAR] = config.to_env()


def venv_rerun() -> str | None:
    """The rerun binary this Python environment installed (``RERUN_CLI_PATH`` overrides):
    the native one of the ``rerun_cli`` package, else the ``rerun`` script next to the
    interpreter; None if there is neither (PATH is not searched)."""
    override = os.environ.get("RERUN_CLI_PATH")
    if override:
        return override
    exe_name = "rerun.exe" if os.name == "nt" else "rerun"
    spec = importlib.util.find_spec("rerun_cli")
    folders = [Path(f) for f in ((spec.submodule_search_locations or []) if spec else [])]
    for exe in [*(f / exe_name for f in folders), Path(sys.executable).parent / exe_name]:
        if exe.is_file() and os.access(exe, os.X_OK):
            return str(exe)
    return None


def rerun_cli() -> list[str]:
    """The command that runs the rerun CLI (the venv's, else one on PATH)."""
    own = venv_rerun()
    if own is not None:
        return [own]
    found = shutil.which("rerun")
    if found:
        return [found]
    raise RecordingError("the rerun CLI is not installed (pip install rerun-sdk)")


def run_cli(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess[str]:
    """Run ``rerun ARGS`` to completion (output captured); RecordingError on timeout."""
    cmd = [*rerun_cli(), *args]
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    proc = subprocess.Popen(
        cmd,
        env=env,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # a wrapper's child is killed with it (the group)
    )
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise RecordingError(
            f"`rerun {' '.join(args[:2])}` timed out after {timeout:g} s"
        ) from None
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def _why(proc: subprocess.CompletedProcess[str]) -> str:
    lines = [ln for ln in (proc.stderr + proc.stdout).splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error" in ln.lower() or "missing" in ln.lower()]
    return "; ".join((errors or lines)[-3:]) or f"exit status {proc.returncode}"


def verify(path: Path) -> None:
    """``rerun rrd verify PATH``; RecordingError saying why if it does not verify."""
    proc = run_cli("rrd", "verify", str(path))
    if proc.returncode != 0:
        raise RecordingError(f"{path} does not verify: {_why(proc)}")


def merge(sources: Sequence[Path], out: Path) -> list[str]:
    """Merge ``sources`` into ``out``, compacting the many small chunks the processes wrote
    into few large ones (``rerun rrd optimize``: the viewer then loads the recording several
    times faster). A source that cannot be read completely (a process killed while writing)
    is merged as far as it can be read: the warnings say so."""
    if not sources:
        raise RecordingError("no process wrote a recording")
    srcs = [str(p) for p in sources]
    proc = run_cli("rrd", "optimize", *srcs, "-o", str(out))
    if proc.returncode == 0:
        return []
    warning = f"merge: {_why(proc)}; merged again skipping unreadable data"
    proc = run_cli("rrd", "optimize", "--continue-on-error", *srcs, "-o", str(out))
    if proc.returncode != 0:
        raise RecordingError(f"cannot merge {', '.join(srcs)}: {_why(proc)}")
    return [warning]


def finish(config: RerunConfig, out: Path) -> list[str]:
    """After a ``save`` run: merge every process' file (and the blueprint's) into ``out``,
    verify it, and name it in the run folder's ``rerun/recording.txt`` (for ``rra view
    RUN_DIR``).

    Returns warnings; raises RecordingError (the per-process files stay for a manual
    ``rerun rrd merge``)."""
    while _blueprints:
        _blueprints.pop().join(timeout=65)
    folder = Path(config.dir)
    warnings = merge(sorted(folder.glob("*.rrd")), out)
    verify(out)
    (folder.parent / "recording.txt").write_text(f"{out}\n")
    return warnings


#: An entity path in ``rrd print``: escaped characters (``Communic.\ Channel``) included.
_CHUNK = re.compile(r" - (/(?:\\.|[^\s\\])*) - data columns")


def entity_paths(path: Path) -> set[str]:
    """The entity paths that hold data in a recording (from ``rerun rrd print``)."""
    proc = run_cli("rrd", "print", str(path))
    if proc.returncode != 0:
        raise RecordingError(f"cannot print {path}: {_why(proc)}")
    return set(_CHUNK.findall(proc.stdout))
