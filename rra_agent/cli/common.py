"""What the ``rra`` commands share: the width they fit (``--wide``), the ``--system`` option."""

from __future__ import annotations

import argparse

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
