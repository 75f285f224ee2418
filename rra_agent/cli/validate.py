"""``rra validate PKG``: every problem of a system package as ``file:line:col: message``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from rra_agent.errors import RraError
from rra_agent.package.contents import SystemPackage
from rra_agent.package.loader import error_line, flatten_errors, load_package, package_root


# ---- rra validate ------------------------------------------------------------------------
def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("package", metavar="PKG", help="system package folder (or its rra.yaml)")


def run(args: argparse.Namespace) -> int:
    """Print every problem of a package as ``file:line:col: message``; 1 if there is any."""
    from rra_agent.package.validate import validate_package

    package_root(args.package)  # a missing folder is a plain error, not a model problem
    try:
        pkg = load_package(args.package, validate=False)
    except RraError as e:
        errors = flatten_errors(e)
    else:
        errors = list(validate_package(pkg))
    for err in errors:
        print(error_line(err))
    if errors:
        print(f"{args.package}: {len(errors)} error(s)", file=sys.stderr)
        return 1
    from rra_agent.dsl.uvl import uvl_warnings
    from rra_agent.package.validate import measurement_warnings

    for warning in uvl_warnings(pkg.features):  # UVL that the feature reasoning ignores
        print(warning)
    for mwarning in measurement_warnings(pkg):  # sources whose samples cannot be typed
        print(mwarning)
    print(f"{args.package}: ok ({_summary(pkg)})")
    return 0


def _summary(pkg: SystemPackage) -> str:
    fm, system, meas = pkg.features, pkg.system, pkg.measurements
    parts = [
        _n(len(fm.features), "feature") + f" ({len(fm.runtime_features())} run-time)",
        _n(len(system.components), "component"),
        _n(len(system.connections), "connection"),
        _n(len(meas.data_types), "data type"),
        _n(len(meas.measurements), "measurement"),
    ]
    if pkg.adaptation is not None:
        rules = _count_rules(pkg.adaptation)
        parts.append(_n(rules, "rule") if rules is not None else "adaptation rules")
    return ", ".join(parts)


def _count_rules(adaptation: object) -> int | None:
    rules = getattr(adaptation, "rules", None)
    if callable(rules):
        return sum(1 for _ in rules())
    return len(rules) if isinstance(rules, Sequence) else None


def _n(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"
