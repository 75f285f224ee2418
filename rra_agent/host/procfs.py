"""What the kernel says of a process in ``/proc/PID/stat``: its state, its parent and when it
started (with its pid, a process's identity: a pid is reused, the pair is not)."""

from __future__ import annotations


def stat(pid: int) -> list[str] | None:
    """The fields of ``/proc/PID/stat`` after the command name (the state first); None if
    the process is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            raw = f.read()
    except OSError:
        return None
    return raw[raw.rindex(")") + 2 :].split()


def state(pid: int) -> str:
    """The kernel's state letter of a process (``R``, ``S``, ``T`` stopped, ``Z`` ended and
    not reaped...), '' if gone."""
    fields = stat(pid)
    return fields[0] if fields else ""


def parent(pid: int) -> int | None:
    """The pid of the parent of process ``pid``; None if it is gone."""
    fields = stat(pid)
    return int(fields[1]) if fields else None


def start_time(pid: int) -> int | None:
    """When process ``pid`` started (clock ticks after boot); None if it is gone."""
    fields = stat(pid)
    return int(fields[19]) if fields else None
