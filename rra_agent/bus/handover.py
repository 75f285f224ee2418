"""The state a gated replacement starts with, handed over in a file by its host agent.

A `ReplaceNode` with ``export`` has the host agent ask the old node for its state while the
replacement's process is already prepared behind its start gate (`rra_agent.host.gate`). The
state comes after that process was spawned, so it cannot be in the spec it was given: the
agent writes it to the file named in the replacement's environment (`STATE_ENV`) before it
opens the gate, and the replacement takes it from there (`take`) before its code runs.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

import msgspec

#: The environment variable naming the file a gated replacement takes its state from.
STATE_ENV = "RRA_STATE_FILE"

_ENC = msgspec.msgpack.Encoder()
_DEC = msgspec.msgpack.Decoder()


def write(path: str | Path, state: Any) -> None:
    """Write ``state`` to ``path`` whole (a temporary file renamed), readable by its owner."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.write(fd, _ENC.encode(state))
    finally:
        os.close(fd)
    os.replace(tmp, path)


def take(path: str | Path) -> tuple[bool, Any]:
    """(True, the state) from ``path``, which is removed; (False, None) if there is none."""
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        return False, None
    discard(path)
    return True, _DEC.decode(data)


def discard(path: str | Path) -> None:
    """Remove a state file nobody will take (nothing if it is not there)."""
    with contextlib.suppress(FileNotFoundError):
        Path(path).unlink()
