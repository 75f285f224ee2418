"""``rra resolve PKG --select F,...``: the Deployment-time Configured System Model."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import msgspec
import yaml

from rra_agent.models.system import SystemModel
from rra_agent.package.loader import (
    load_package,
)


# ---- rra resolve -------------------------------------------------------------------------
def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("package", metavar="PKG", help="system package folder (or its rra.yaml)")
    p.add_argument(
        "--select",
        "-s",
        action="append",
        default=[],
        metavar="F1,F2",
        help="deployment-time features to select (default: the manifest's default_selection)",
    )
    p.add_argument("--format", "-f", choices=("yaml", "json"), default="yaml")
    p.add_argument("--output", "-o", metavar="FILE", help="write to FILE instead of stdout")


def run(args: argparse.Namespace) -> int:
    """Print the Deployment-time Configured System Model for a selection."""
    from rra_agent.core.features import complete_deployment
    from rra_agent.core.resolution import resolve_deployment

    pkg = load_package(args.package)
    names = split_selection(args.select) or list(pkg.manifest.default_selection)
    selection = complete_deployment(pkg.features, names)
    configured = resolve_deployment(pkg.system, pkg.deployment, pkg.features, selection)
    ordered = [f for f in pkg.features.features if f in selection]
    text = render_system(configured, args.format, f"selection: {', '.join(ordered)}")
    if args.output:
        Path(args.output).write_text(text, encoding="utf-8")
        print(f"wrote {args.output}", file=sys.stderr)
    else:
        sys.stdout.write(text)
    return 0


def split_selection(values: Sequence[str]) -> list[str]:
    """``["A,B", "C"]`` -> ``["A", "B", "C"]`` (blank items dropped)."""
    return [name.strip() for v in values for name in v.split(",") if name.strip()]


def render_system(system: SystemModel, fmt: str, note: str | None = None) -> str:
    """A system model as YAML (with ``note`` as a leading comment) or as JSON."""
    if fmt == "json":
        return msgspec.json.format(msgspec.json.encode(system), indent=2).decode() + "\n"
    body = yaml.safe_dump(
        msgspec.to_builtins(system), sort_keys=False, allow_unicode=True, width=100
    )
    header = f"# Deployment-time Configured System Model of '{system.system}'\n"
    return header + (f"# {note}\n" if note else "") + body
