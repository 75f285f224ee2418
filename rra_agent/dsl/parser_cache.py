"""Built lark parsers cached on disk, so a command does not rebuild them at every start.

Building an LALR parser from a ``.lark`` grammar (and, in strict mode, proving that no two
terminals can match the same text) takes most of a second; loading the built tables takes a
few milliseconds. `cached_lark` builds a parser once, saves it with `Lark.save`, and later
processes load it back.

The cache file is keyed by a hash of everything the built parser depends on: the grammar
text, the build options, the postlexer's class, lark's version and Python's version. A
changed grammar therefore gets a new file, and a stale or damaged file is never used (it is
rebuilt). Files live in ``$RRA_CACHE_DIR``, else ``$XDG_CACHE_HOME/rra-agent``, else
``~/.cache/rra-agent``; when none can be written the parser is simply built in memory. Files
are written to a temporary name and renamed into place, so two processes starting together
never read a half-written file. A parser is stored as a pickle, so a file is loaded only when
this user owns it and no one else may write it.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import lark
from lark import Lark

__all__ = ["cache_dir", "cache_file", "cached_lark"]

#: Bumped when the way this module stores parsers changes.
_FORMAT = "1"


def cache_dir() -> Path:
    """Where built parsers are kept (see the module docstring)."""
    explicit = os.environ.get("RRA_CACHE_DIR")
    if explicit:
        return Path(explicit)
    xdg = os.environ.get("XDG_CACHE_HOME")
    base = Path(xdg) if xdg and Path(xdg).is_absolute() else Path.home() / ".cache"
    return base / "rra-agent"


def _key(grammar: str, postlex: object | None, options: dict[str, Any]) -> str:
    h = hashlib.sha256()
    h.update(grammar.encode("utf-8"))
    h.update(repr(sorted(options.items())).encode("utf-8"))
    if postlex is not None:
        cls = type(postlex)
        h.update(f"{cls.__module__}.{cls.__qualname__}".encode())
    h.update(f"{lark.__version__}|{sys.version_info[:2]}|{_FORMAT}".encode())
    return h.hexdigest()[:32]


def cache_file(name: str, grammar: str, postlex: object | None, options: dict[str, Any]) -> Path:
    """The cache file for a parser of ``grammar`` built with ``options``."""
    return cache_dir() / f"{name}-{_key(grammar, postlex, options)}.lark"


def _trusted(fd: int) -> bool:
    """Whether an open cache file may be unpickled: owned by this user and writable by no one
    else (a parser is a pickle, and unpickling runs code)."""
    st = os.fstat(fd)
    getuid = getattr(os, "getuid", None)
    return (getuid is None or st.st_uid == getuid()) and not st.st_mode & 0o022


def _load(path: Path, postlex: object | None) -> Lark | None:
    try:
        with path.open("rb") as f:
            if not _trusted(f.fileno()):
                return None  # rebuilt, and replaced by a file of ours
            inst = Lark.__new__(Lark)
            kwargs = {"postlex": postlex} if postlex is not None else {}
            return inst._load(f, **kwargs)  # lark's own cache loads parsers this way
    except FileNotFoundError:
        return None
    except Exception:  # a damaged or foreign file: rebuild and replace it
        return None


def _store(path: Path, parser: Lark) -> None:
    """Write ``parser`` to ``path`` atomically; an unwritable cache is silently skipped."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    except OSError:
        return
    try:
        with os.fdopen(fd, "wb") as f:
            parser.save(f, exclude_options={"postlex"})
        os.replace(tmp, path)
    except Exception:  # disk full, permissions, ...: the parser still works
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def cached_lark(name: str, grammar: str, *, postlex: object | None = None, **options: Any) -> Lark:
    """``Lark(grammar, postlex=postlex, **options)``, loaded from the cache when it is there.

    ``options`` must select ``parser="lalr"`` (lark saves only LALR parsers). Checks done while
    building (``strict``) run when the parser is built, i.e. once per grammar version.
    ``postlex`` is not saved: the given instance is attached to the loaded parser.
    """
    if options.get("parser") != "lalr":
        raise ValueError("only LALR parsers can be cached")
    try:
        path: Path | None = cache_file(name, grammar, postlex, options)
    except (RuntimeError, OSError, KeyError):  # no home folder to hold the cache
        path = None
    parser = _load(path, postlex) if path is not None else None
    if parser is not None:
        return parser
    parser = Lark(grammar, postlex=postlex, **options)
    if path is not None:
        _store(path, parser)
    return parser
