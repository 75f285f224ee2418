"""``rra view [RUN_DIR | FILE.rrd] [--web]``: open a recording in the Rerun viewer.

The viewer is the one this Python environment installed (``pip install rerun-sdk``): the
native ``rerun`` binary of the ``rerun_cli`` package, else the ``rerun`` script next to the
Python executable; never one found on PATH (another version may not read the recording).
``RERUN_CLI_PATH`` overrides it.

What is opened:

- ``FILE.rrd``: that file;
- ``RUN_DIR`` (a folder of ``rra up`` or ``rra demo``): its ``recording.rrd``, else the file
  named in ``rerun/recording.txt`` (written when ``--rerun save PATH`` put it elsewhere),
  else the newest ``*.rrd`` in the folder;
- nothing: the newest recording of the run folders under ``.rra/``, else ``demo.rrd``.

The viewer's servers listen on 127.0.0.1 only. ``--web`` serves the web viewer (``--port``,
default 9090; its gRPC server on a free port) and prints the address to open. The viewer
process replaces this one (``exec``), so Ctrl-C or a signal stops it and leaves nothing
behind. Without ``--web`` on Linux, a display must be there (`display_problem`: a Wayland
socket, or an X server answering at ``$DISPLAY``); if none is, the command says so in one
line naming the way out (``rra view --web``) instead of starting a viewer that fails with
its windowing library's error.
"""

from __future__ import annotations

import argparse
import os
import re
import socket
import sys
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import quote

from rra_agent.errors import RraError
from rra_agent.viz.recording import POINTER, venv_rerun

DEFAULT_WEB_PORT = 9090


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "target",
        nargs="?",
        metavar="RUN_DIR | FILE.rrd",
        help="a recording, or a run folder holding one (default: the newest under .rra/)",
    )
    p.add_argument("--web", action="store_true", help="serve the web viewer on 127.0.0.1")
    p.add_argument(
        "--port",
        type=int,
        default=DEFAULT_WEB_PORT,
        help=f"the web viewer's HTTP port with --web (default {DEFAULT_WEB_PORT})",
    )


def rerun_binary() -> str:
    """The venv's rerun viewer; RraError when this environment has none."""
    found = venv_rerun()
    if found is None:
        raise RraError(
            "the Rerun viewer is not installed in this Python environment "
            f"({sys.executable}); install it with `pip install rerun-sdk`"
        )
    return found


def _in_run_dir(folder: Path) -> Path | None:
    direct = folder / "recording.rrd"
    if direct.is_file():
        return direct
    pointer = folder / POINTER
    if pointer.is_file():
        named = Path(pointer.read_text().strip())
        if named.is_file():
            return named
    found = sorted(folder.glob("*.rrd"), key=lambda p: p.stat().st_mtime)
    return found[-1] if found else None


def resolve_recording(target: str | None, cwd: Path | None = None) -> Path:
    """The recording ``target`` names (see the module's docstring); RraError saying what is
    missing otherwise."""
    here = cwd or Path.cwd()
    if target is None:
        runs = [r for d in sorted((here / ".rra").glob("*/")) if (r := _in_run_dir(d))]
        if runs:
            return max(runs, key=lambda p: p.stat().st_mtime)
        if (here / "demo.rrd").is_file():
            return here / "demo.rrd"
        raise RraError(
            "no recording under .rra/ and no demo.rrd here: give a RUN_DIR or FILE.rrd "
            "(record one with `rra demo` or `rra up PKG --rerun save`)"
        )
    path = Path(target)
    path = path if path.is_absolute() else here / path
    if path.is_dir():
        found = _in_run_dir(path)
        if found is None:
            raise RraError(
                f"{target}: no recording in this run folder (run `rra up` with `--rerun save`)"
            )
        return found
    if not path.exists():
        raise RraError(f"{target}: no such file or folder")
    if path.suffix != ".rrd":
        raise RraError(f"{target}: not a Rerun recording (a .rrd file or a run folder)")
    return path


def viewer_command(recording: Path, *, web: bool, port: int, grpc_port: int) -> list[str]:
    """The command line that opens ``recording``."""
    # The viewer's own gRPC server (native too) listens on loopback only.
    cmd = [rerun_binary(), str(recording), "--bind", "127.0.0.1"]
    if web:
        cmd += [
            "--web-viewer",
            "--web-viewer-port",
            str(port),
            "--port",
            str(grpc_port),
        ]
    return cmd


def display_problem(environ: Mapping[str, str] | None = None) -> str | None:
    """Why a native viewer window cannot open here (None: a display is there, or this is not
    Linux, where the viewer finds its own): a Wayland socket (``$WAYLAND_DISPLAY``, relative
    to ``$XDG_RUNTIME_DIR``; or ``$WAYLAND_SOCKET``) or an X server accepting a connection at
    ``$DISPLAY`` (its Unix socket, or TCP port 6000 + N of its host)."""
    env = os.environ if environ is None else environ
    if not sys.platform.startswith(("linux", "freebsd", "openbsd", "netbsd")):
        return None
    if env.get("WAYLAND_SOCKET"):
        return None
    wayland = env.get("WAYLAND_DISPLAY")
    if wayland:
        path = os.path.join(env.get("XDG_RUNTIME_DIR", ""), wayland)
        if os.path.exists(path):
            return None
    display = env.get("DISPLAY")
    if not display:
        if wayland:
            return f"no Wayland display at {path}, and $DISPLAY is not set"
        return "no display here ($DISPLAY, $WAYLAND_DISPLAY unset)"
    return None if _x_answers(display) else f"no X server answers at DISPLAY={display}"


def _x_answers(display: str) -> bool:
    """Whether an X server accepts a connection at ``display`` (``:0``, ``host:10.0``)."""
    found = re.fullmatch(r"(?:(?P<host>[^:]*)/?)?(?::)(?P<n>\d+)(?:\.\d+)?", display)
    if found is None:
        return True  # a form this check does not know: let the viewer try
    host, n = found["host"] or "", int(found["n"])
    try:
        if host in ("", "unix"):
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
                s.settimeout(0.5)
                path = f"/tmp/.X11-unix/X{n}"
                try:
                    s.connect(path)
                except OSError:
                    s.connect("\0" + path)  # Linux: the abstract socket of the same name
            return True
        with socket.create_connection((host, 6000 + n), timeout=0.5):
            return True
    except OSError:
        return False


def web_address(port: int, grpc_port: int) -> str:
    source = quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")
    return f"http://127.0.0.1:{port}/?url={source}"


def run(args: argparse.Namespace) -> int:
    recording = resolve_recording(args.target)
    if not args.web and (why := display_problem()) is not None:
        raise RraError(f"{why}: try `rra view --web` (in a browser)")
    grpc_port = 0
    if args.web:
        from rra_agent.bus.config import free_port

        grpc_port = free_port()
    cmd = viewer_command(recording, web=args.web, port=args.port, grpc_port=grpc_port)
    if args.web:
        print(f"rra view: {recording} at {web_address(args.port, grpc_port)}", flush=True)
    else:
        print(f"rra view: {recording}", flush=True)
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    try:
        os.execve(cmd[0], cmd, env)
    except OSError as e:
        raise RraError(f"cannot start the Rerun viewer {cmd[0]}: {e.strerror}") from None
    return 1  # not reached
