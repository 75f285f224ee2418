"""Command-line output that fits `WIDTH` (100) columns: tables, labelled fields, wrapped lines.

Every table and banner the ``rra`` command prints goes through here, so that nothing is wider
than 100 columns unless the user asks for it (``--wide``: one line per row or field, nothing
wrapped or cut). Cells and fields are wrapped at spaces; a word longer than its column (a
path, a URL) is broken inside.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

#: Columns every table, banner and line of the ``rra`` command fits, unless ``--wide``.
WIDTH = 100
#: The narrowest a wrapped table column becomes.
MIN_COLUMN = 12


def cut(text: str, width: int, wide: bool = False) -> str:
    """``text`` at most ``width`` characters (its end replaced by ``~``) unless ``wide``."""
    return text if wide or len(text) <= width else text[: width - 1] + "~"


def wrap(text: str, width: int = WIDTH, indent: str = "", *, wide: bool = False) -> list[str]:
    """``text`` in lines of at most ``width`` columns, the later ones indented by ``indent``
    (``wide``: one line)."""
    if wide or len(text) <= width:
        return [text]
    return textwrap.wrap(
        text, width, subsequent_indent=indent, break_on_hyphens=False, drop_whitespace=True
    ) or [text]


def field(label: str, text: str, *, width: int = WIDTH, wide: bool = False, pad: int = 8) -> str:
    """``label`` and ``text`` in two columns (``text`` wrapped under itself), as lines."""
    head = f"{label:<{pad}} "
    return "\n".join(wrap(head + text, width, " " * len(head), wide=wide))


def table(
    rows: Sequence[Sequence[str]],
    *,
    wrapping: Sequence[int] = (),
    width: int = WIDTH,
    wide: bool = False,
    gap: int = 2,
) -> str:
    """``rows`` (the first one the header) as aligned columns at most ``width`` wide: the
    columns whose index is in ``wrapping`` are narrowed (the widest first, not below
    `MIN_COLUMN`) and their cells wrapped onto more lines; the others keep their width.
    ``wide``: every row on one line, nothing wrapped."""
    if not rows:
        return ""
    n = len(rows[0])
    natural = [max(len(r[i]) for r in rows) for i in range(n)]
    widths = list(natural) if wide else _fit(natural, set(wrapping), width, gap)
    out = []
    for row in rows:
        cells = [
            wrap(cell, widths[i], wide=wide) if i in wrapping else [cell]
            for i, cell in enumerate(row)
        ]
        for k in range(max(len(c) for c in cells)):
            parts = [(c[k] if k < len(c) else "").ljust(widths[i]) for i, c in enumerate(cells)]
            out.append((" " * gap).join(parts).rstrip())
    return "\n".join(out)


def _fit(natural: list[int], wrapping: set[int], width: int, gap: int) -> list[int]:
    """Column widths: ``natural`` narrowed, wrapping columns first and widest first."""
    widths = list(natural)
    total = sum(widths) + gap * (len(widths) - 1)
    while total > width:
        shrinkable = [i for i in wrapping if widths[i] > MIN_COLUMN]
        if not shrinkable:
            break
        widest = max(shrinkable, key=lambda i: widths[i])
        widths[widest] -= 1
        total -= 1
    return widths
