"""What the ``rra`` commands share: the width they fit (``--wide``), the ``--system`` option."""

from __future__ import annotations

import argparse
import threading
from typing import Any

import zenoh

from rra_agent.bus.keys import Keys
from rra_agent.text import WIDTH, cut

__all__ = ["WIDTH", "add_system_argument", "add_wide_argument", "cut"]


def add_system_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--system",
        help="system name (the package's); needed only when several systems run at the endpoint",
    )


def add_wide_argument(p: argparse.ArgumentParser, what: str = "tables and banners") -> None:
    p.add_argument(
        "--wide", action="store_true", help=f"{what} on long lines, not fitted to {WIDTH} columns"
    )


class UntilStopped:
    """Following a running system (``rra events -f``, ``rra watch``) until its last host
    agent is gone, or Ctrl-C."""

    def __init__(self) -> None:
        self.done = threading.Event()
        self._hosts: set[str] = set()
        self._lock = threading.Lock()

    def on_host(self, sample: zenoh.Sample) -> None:
        """A host agent's liveliness token came or went: the last one gone ends following."""
        host = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._hosts.add(host)
            elif host in self._hosts:
                self._hosts.discard(host)
                if not self._hosts:
                    self.done.set()

    def follow(self, session: zenoh.Session, keys: Keys, entities: list[Any], quiet: bool) -> int:
        """Wait until the system stops (or Ctrl-C), then undeclare ``entities``; 0."""
        try:
            entities.append(session.liveliness().declare_subscriber(
                keys.host_alive_all, self.on_host, history=True))  # fmt: skip
            self.done.wait()
        except KeyboardInterrupt:
            return 0
        finally:
            for entity in entities:
                entity.undeclare()
        if not quiet:
            print(f"system {keys.system!r} stopped: no host agent is left", flush=True)
        return 0
