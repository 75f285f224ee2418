"""Why a node failed, said where its user looks: the exception, its place in the node's own
code, and the report a node process leaves for its host agent.

`describe` turns an exception into a `Failure`: its type and message, the ``file:line`` of
the innermost frame of the node's own code (not rra-agent's runtime, not a library; relative
to the system package), and what the runtime was running (``during``: ``import``,
``constructor``, ``on_start``...; `tag` marks an exception with it where it is raised).

A node process that ends by an exception prints the whole traceback to its log and writes a
*report*, the `Failure` as JSON, to the file its host agent names in ``RRA_FAILURE_REPORT``
(``<log-dir>/<node>.failure``): to a temporary name, then renamed, so the host agent, which
reads and removes it when it reaps the process, finds a whole report or none. A file rather
than the bus (the process may be dying because its session failed) or the heartbeat's shared
memory (fixed 16-byte slots; a report has no fixed size): it costs nothing while the node
runs, and it is read once, after the writer is gone. An external command writes none; its
host agent takes the last lines of its log instead (`tail`).
"""

from __future__ import annotations

import contextlib
import os
import sys
import sysconfig
import time
import traceback
from collections.abc import Iterable
from pathlib import Path

import msgspec

from rra_agent.bus.messages import Failure
from rra_agent.errors import RraError

REPORT_ENV = "RRA_FAILURE_REPORT"
#: The longest message kept in a `Failure` (the log has the whole of it).
MESSAGE_MAX = 500
_ATTR = "rra_during"
_PACKAGE = Path(__file__).resolve().parent
#: rra-agent's own machinery around node code: never "where" a node failed if its own
#: code is on the stack.
_RUNTIME = tuple(
    str(_PACKAGE / p) for p in ("node.py", "failure.py", "trace.py", "bus", "host", "models")
)
_LIBRARY = tuple(
    {
        os.path.realpath(p)
        for k in ("stdlib", "platstdlib", "purelib", "platlib")
        if (p := sysconfig.get_paths().get(k))
    }
)


def tag(exc: BaseException, during: str) -> BaseException:
    """Mark ``exc`` with what the runtime was running (kept if already marked: the
    innermost runtime call knows best)."""
    if not getattr(exc, _ATTR, ""):
        with contextlib.suppress(AttributeError, TypeError):
            setattr(exc, _ATTR, during)
    return exc


def describe(exc: BaseException, during: str = "", roots: Iterable[str] = ()) -> Failure:
    """``exc`` as a `Failure`. An `RraError` raised ``from`` another exception (e.g. "cannot
    import X" from the `ImportError`) is described by that exception; ``roots``: the system
    package's folders (paths are shown relative to them)."""
    during = getattr(exc, _ATTR, "") or during
    shown = exc.__cause__ if isinstance(exc, RraError) and exc.__cause__ is not None else exc
    file, line, function = _user_frame(shown, list(roots))
    return Failure(
        type=type_name(shown),
        message=str(shown)[:MESSAGE_MAX],
        where=f"{file}:{line}" if file else "",
        function=function,
        during=during,
        stamp=time.time(),
    )


def type_name(exc: BaseException) -> str:
    cls = type(exc)
    return (
        cls.__qualname__ if cls.__module__ == "builtins" else f"{cls.__module__}.{cls.__qualname__}"
    )


def formatted(exc: BaseException) -> str:
    """The whole traceback of ``exc`` (with its causes), as Python prints it."""
    return "".join(traceback.format_exception(exc)).rstrip("\n")


def summary(f: Failure) -> str:
    """One line: ``RuntimeError: camera not found (nodes.py:42 in on_start)``; for an
    external command, its last line of output."""
    if not f.type:
        lines = f.message.strip().splitlines()
        return f"last output: {lines[-1].strip()}" if lines else "no output"
    lines = f.message.strip().splitlines()
    text = f"{f.type}: {lines[0]}" if lines else f.type
    place = f.where + (f" in {f.function}" if f.function else "")
    if f.during and f.during != f.function:
        place += f", during {f.during}" if place else f"during {f.during}"
    return f"{text} ({place})" if place else text


def reason(base: str, f: Failure | None) -> str:
    """A transition's reason with the failure's summary: ``exited with status 1: ...``."""
    return f"{base}: {summary(f)}" if f is not None else base


# ---- the report: node -> host agent ---------------------------------------------------
def write_report(f: Failure, path: str | None = None) -> None:
    """Leave ``f`` for the host agent (at ``path``, or ``$RRA_FAILURE_REPORT``; nothing
    without one: a node started by hand)."""
    path = path or os.environ.get(REPORT_ENV)
    if not path:
        return
    with contextlib.suppress(OSError):
        tmp = f"{path}.tmp"
        with open(tmp, "wb") as out:
            out.write(msgspec.json.encode(f))
        os.replace(tmp, path)


def take_report(path: str | Path) -> Failure | None:
    """Read and remove the report at ``path`` (None if there is none, or it is not one)."""
    try:
        raw = Path(path).read_bytes()
    except OSError:
        return None
    with contextlib.suppress(OSError):
        os.unlink(path)
    try:
        return msgspec.json.decode(raw, type=Failure)
    except (msgspec.DecodeError, msgspec.ValidationError):
        return None


def tail(path: str | Path, start: int = 0, lines: int = 3, window: int = 4096) -> str:
    """The last ``lines`` non-empty lines written to ``path`` after offset ``start`` (what a
    process wrote to its log since it started)."""
    try:
        with open(path, "rb") as f:
            size = f.seek(0, os.SEEK_END)
            f.seek(max(start, size - window))
            raw = f.read()
    except OSError:
        return ""
    text = [t.strip() for t in raw.decode(errors="replace").splitlines() if t.strip()]
    return "\n".join(text[-lines:])[-MESSAGE_MAX:]


# ---- where in the node's own code ----------------------------------------------------
def _user_frame(exc: BaseException, roots: list[str]) -> tuple[str, int, str]:
    """(file, line, function) of the innermost frame of the node's own code: in the package,
    else outside rra-agent's runtime and the libraries, else outside the runtime, else the
    innermost frame; a `SyntaxError` is where the bad line is."""
    if isinstance(exc, SyntaxError) and exc.filename:
        return _shown(exc.filename, roots), exc.lineno or 0, ""
    frames = [(f.filename, f.lineno or 0, f.name) for f in traceback.extract_tb(exc.__traceback__)]
    real = [
        (os.path.realpath(fn), line, name) for fn, line, name in frames if not fn.startswith("<")
    ]
    tests = (
        lambda fn: any(_under(fn, r) for r in roots),
        lambda fn: not fn.startswith(_RUNTIME) and not fn.startswith(_LIBRARY),
        lambda fn: not fn.startswith(_RUNTIME),
    )
    for test in tests:
        for fn, line, name in reversed(real):
            if test(fn):
                return _shown(fn, roots), line, name
    if frames:
        fn, line, name = frames[-1]
        return _shown(fn, roots), line, name
    return "", 0, ""


def _under(path: str, root: str) -> bool:
    root = os.path.realpath(root)
    return path == root or path.startswith(root.rstrip(os.sep) + os.sep)


def _shown(path: str, roots: list[str]) -> str:
    """``path`` relative to the package folder, else to the import path entry it is under
    (the module's own path), else as it is."""
    if path.startswith("<"):
        return path
    real = os.path.realpath(path)
    for root in roots:
        if _under(real, root):
            return os.path.relpath(real, os.path.realpath(root))
    entries = [os.path.realpath(p) for p in sys.path if p and os.path.isdir(p)]
    best = max((e for e in entries if e != os.sep and _under(real, e)), key=len, default=None)
    return os.path.relpath(real, best) if best else real


def details(f: Failure) -> list[str]:
    """The failure in a few short lines (``rra events``, the Rerun event log, ``rra test``):
    what was raised, where, and the log with the rest."""
    lines = f.message.strip().splitlines()
    if not f.type:
        out = [f"output: {line}" for line in lines] or ["no output"]
    else:
        out = [f"{f.type}: {lines[0]}" if lines else f.type, *(f"  {x}" for x in lines[1:3])]
        place = " ".join(
            part
            for part in (
                f"at {f.where}" if f.where else "",
                f"in {f.function}" if f.function else "",
                f"during {f.during}" if f.during and f.during != f.function else "",
            )
            if part
        )
        if place:
            out.append(place)
    if f.log:
        out.append(f"log: {f.log}")
    return out


def without_summary(reason: str, f: Failure | None) -> str:
    """``reason`` without the failure's summary `reason` appended to it."""
    tail = f": {summary(f)}" if f is not None else ""
    return reason[: -len(tail)] if tail and reason.endswith(tail) else reason
