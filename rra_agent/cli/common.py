"""What the ``rra`` commands share: the width they fit, the ``--system`` option."""

from __future__ import annotations

import argparse

#: ``rra status`` fits this many columns unless ``--wide`` is given.
WIDTH = 100


def add_system_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--system",
        help="system name (the package's); needed only when several systems run at the endpoint",
    )


def cut(text: str, width: int, wide: bool) -> str:
    """``text`` at most ``width`` characters (its end replaced by ``~``) unless ``wide``."""
    return text if wide or len(text) <= width else text[: width - 1] + "~"
