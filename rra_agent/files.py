"""Writing a file whole, with its mode from the first byte: the one way rra-agent writes a
key, a certificate or a ROS 2 executable's session configuration."""

from __future__ import annotations

import os
from pathlib import Path


def write_atomic(path: str | Path, data: bytes, mode: int = 0o600) -> Path:
    """Write ``data`` to ``path`` under a temporary name created with ``mode`` (also when a
    file was there before: never readable by others, even briefly), then rename it over
    ``path``: a reader sees the old file or the whole new one. The path written."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, mode)
    try:
        os.fchmod(fd, mode)
        os.write(fd, data)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    return path
