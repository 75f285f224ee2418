"""``rra check PKG``: the static analysis of a package's adaptation rules.

- Conflicts (`rra_agent.core.conflicts`): pairs of rules outside one rule set that can fire
  together with opposite effects; exit status 1 if one is certain.
- Reachability (`rra_agent.core.reachable`): a warning per run-time feature, selectable under
  the deployment-time selection (``--select``, default the manifest's ``default_selection``),
  that no sequence of the rules' actions selects from the default run-time selection (the
  conditions taken as free): no rule activates it nor a feature below it, and it is no
  default. Warnings do not change the exit status.
"""

from __future__ import annotations

import argparse
import sys

from rra_agent.cli.resolve import split_selection
from rra_agent.package.loader import load_package


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("package", metavar="PKG", help="system package folder (or its rra.yaml)")
    p.add_argument(
        "--select",
        action="append",
        default=[],
        metavar="F1,F2",
        help="deployment-time features (default: the manifest's default_selection)",
    )


def run(args: argparse.Namespace) -> int:
    """Conflicts, then the run-time features the rules can never select."""
    from rra_agent.core.conflicts import check_conflicts
    from rra_agent.core.reachable import reachable

    pkg = load_package(args.package)
    if pkg.adaptation is None:
        print(f"{args.package}: no adaptation model to check")
        return 0
    conflicts = check_conflicts(pkg.adaptation, pkg.features)
    for c in conflicts:
        print(c.render())
    selection = split_selection(args.select) or list(pkg.manifest.default_selection)
    found = reachable(pkg.features, selection, pkg.adaptation)
    for name in found.never:
        feature = pkg.features.features[name]
        where = f"{feature.span.location()}: " if feature.span else ""
        print(f"{where}warning: no rule can ever select run-time feature {name}")
    certain = sum(c.certain for c in conflicts)
    cut = "" if found.complete else " (search cut short)"
    print(
        f"{args.package}: {certain} conflict(s), {len(conflicts) - certain} possible "
        f"conflict(s), {len(found.never)} feature(s) never selected{cut}",
        file=sys.stderr,
    )
    return 1 if certain else 0
