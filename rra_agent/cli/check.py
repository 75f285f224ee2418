"""``rra check PKG``: the static conflict analysis of a package's adaptation rules."""

from __future__ import annotations

import argparse
import sys

from rra_agent.package.loader import (
    load_package,
)


# ---- the command table and main ----------------------------------------------------------
# ---- rra check ---------------------------------------------------------------------------
def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("package", metavar="PKG", help="system package folder (or its rra.yaml)")


def run(args: argparse.Namespace) -> int:
    """Pairs of rules outside one rule set that can fire together with opposite effects."""
    from rra_agent.core.conflicts import check_conflicts

    pkg = load_package(args.package)
    if pkg.adaptation is None:
        print(f"{args.package}: no adaptation model to check")
        return 0
    conflicts = check_conflicts(pkg.adaptation, pkg.features)
    for c in conflicts:
        print(c.render())
    certain = sum(c.certain for c in conflicts)
    print(
        f"{args.package}: {certain} conflict(s), {len(conflicts) - certain} possible "
        "conflict(s) the analysis could not rule out",
        file=sys.stderr,
    )
    return 1 if certain else 0
