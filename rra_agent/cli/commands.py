"""The ``rra`` command line (also ``python -m rra_agent``).

Each subcommand is a `Command` in `COMMANDS`: a help text, a function adding its arguments
and a handler returning the exit status. Every `RraError` ends the command with its message
on stderr and status 1 (no traceback); Ctrl-C ends it quietly with status 130.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import msgspec
import yaml

from rra_agent import __version__
from rra_agent.errors import LocatedError, RraError
from rra_agent.models.loader import (
    SystemPackage,
    error_line,
    flatten_errors,
    load_package,
    package_root,
)
from rra_agent.models.system import SystemModel


@dataclass(frozen=True)
class Command:
    """One subcommand: ``configure`` adds its arguments, ``run`` returns the exit status.

    A new subcommand is one more entry in `COMMANDS`; its handler may live in another module
    (``run=lazy("rra_agent.cli.up:run")``).
    """

    help: str
    configure: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


def lazy(target: str) -> Callable[[argparse.Namespace], int]:
    """A handler ``"package.module:function"`` imported only when its command runs, so that
    ``rra validate`` does not pay for zenoh, mujoco or rerun."""
    module, _, name = target.partition(":")

    def run(args: argparse.Namespace) -> int:
        return getattr(importlib.import_module(module), name)(args)

    return run


# ---- rra validate ------------------------------------------------------------------------
def _configure_validate(p: argparse.ArgumentParser) -> None:
    p.add_argument("package", metavar="PKG", help="system package folder (or its rra.yaml)")


def _run_validate(args: argparse.Namespace) -> int:
    """Print every problem of a package as ``file:line:col: message``; 1 if there is any."""
    from rra_agent.models.validate import validate_package

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
    from rra_agent.models.validate import measurement_warnings

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


# ---- rra resolve -------------------------------------------------------------------------
def _configure_resolve(p: argparse.ArgumentParser) -> None:
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


def _run_resolve(args: argparse.Namespace) -> int:
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


# ---- the command table and main ----------------------------------------------------------
# ---- rra check ---------------------------------------------------------------------------
def _configure_check(p: argparse.ArgumentParser) -> None:
    p.add_argument("package", metavar="PKG", help="system package folder (or its rra.yaml)")


def _run_check(args: argparse.Namespace) -> int:
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


COMMANDS: dict[str, Command] = {
    "validate": Command(
        "check every model of a package and their cross-references",
        _configure_validate,
        _run_validate,
    ),
    "resolve": Command(
        "print the Deployment-time Configured System Model for a feature selection",
        _configure_resolve,
        _run_resolve,
    ),
    "check": Command(
        "static conflict analysis of the adaptation rules (exit 1 on a certain conflict)",
        _configure_check,
        _run_check,
    ),
    "up": Command(
        "run a system on this machine until Ctrl-C (engines and nodes as Zenoh peers)",
        lambda p: _configure("rra_agent.cli.up:configure", p),
        lazy("rra_agent.cli.up:run"),
    ),
    "status": Command(
        "show a running system: selection, CV values, nodes with their state",
        lambda p: _configure("rra_agent.cli.status:configure_status", p),
        lazy("rra_agent.cli.status:run_status"),
    ),
    "events": Command(
        "follow the adaptation events of a running system (or print an events.jsonl)",
        lambda p: _configure("rra_agent.cli.status:configure_events", p),
        lazy("rra_agent.cli.status:run_events"),
    ),
    "demo": Command(
        "the paper's evaluation: a quadcopter loses a motor, RRA swaps its controller",
        lambda p: _configure("rra_agent.demo:configure", p),
        lazy("rra_agent.demo:run"),
    ),
    "param": Command(
        "print or set the parameters of a running node (NAME=VALUE ...)",
        lambda p: _configure("rra_agent.cli.status:configure_param", p),
        lazy("rra_agent.cli.status:run_param"),
    ),
    "select": Command(
        "force run-time features on or off (FEATURE=on|off|auto), or print the forced ones",
        lambda p: _configure("rra_agent.cli.select:configure", p),
        lazy("rra_agent.cli.select:run"),
    ),
    "retry": Command(
        "re-admit unavailable implementations (COMPONENT ...; none: all) and try them again",
        lambda p: _configure("rra_agent.cli.select:configure_retry", p),
        lazy("rra_agent.cli.select:run_retry"),
    ),
    "view": Command(
        "open a recording (FILE.rrd or a run folder) in the Rerun viewer of this environment",
        lambda p: _configure("rra_agent.cli.view:configure", p),
        lazy("rra_agent.cli.view:run"),
    ),
    "agent": Command(
        "serve this machine as a host of a system: start and supervise its nodes",
        lambda p: _configure("rra_agent.host.agent:configure", p),
        lazy("rra_agent.host.agent:run"),
    ),
    "test": Command(
        "run scenarios (*.scenario.yaml) headless and print the verdict of each expectation",
        lambda p: _configure("rra_agent.scenario.cli:configure", p),
        lazy("rra_agent.scenario.cli:run"),
    ),
    "certs": Command(
        "make the system CA and the mTLS certificates of every host and role",
        lambda p: _configure("rra_agent.cli.certs:configure", p),
        lazy("rra_agent.cli.certs:run"),
    ),
}


def _configure(target: str, parser: argparse.ArgumentParser) -> None:
    """Call a subcommand's ``configure`` living in another module."""
    module, _, name = target.partition(":")
    getattr(importlib.import_module(module), name)(parser)


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``rra`` argument parser. With ``only`` (a command name) just that command's
    arguments are configured: the others' modules (zenoh, cryptography, ...) are not imported,
    which keeps ``rra validate`` quick to start."""
    parser = argparse.ArgumentParser(
        prog="rra", description="RRA: Robotics Run-time Adaptation (IROS 2015) on Zenoh."
    )
    parser.add_argument("--version", action="version", version=f"rra {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, cmd in COMMANDS.items():
        p = sub.add_parser(name, help=cmd.help, description=cmd.help)
        if only is None or name == only:
            cmd.configure(p)
    return parser


def _command_of(argv: Sequence[str]) -> str | None:
    """The subcommand ``argv`` names (its first non-option word), if it is a known one."""
    word = next((a for a in argv if not a.startswith("-")), None)
    return word if word in COMMANDS else None


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``rra`` with ``argv`` (default: the process arguments); returns the exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(_command_of(argv))
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    try:
        return COMMANDS[args.command].run(args)
    except KeyboardInterrupt:
        return 130
    except RraError as e:
        for err in flatten_errors(e):
            located = isinstance(err, LocatedError) and err.location is not None
            print(str(err) if located else f"rra {args.command}: {err}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `rra resolve PKG | head`: stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    sys.exit(main())
