"""The ``rra`` command line (also ``python -m rra_agent``).

Each subcommand is a `Command` in `COMMANDS`: a help text, a function adding its arguments
and a handler returning the exit status. Every `RraError` ends the command with its message
on stderr and status 1 (no traceback), a model or DSL error as one ``file:line:col: message``
line as ``rra validate`` prints it; Ctrl-C ends it quietly with status 130.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from rra_agent import __version__
from rra_agent.errors import LocatedError, RraError
from rra_agent.package.loader import error_line, flatten_errors


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


COMMANDS: dict[str, Command] = {
    "validate": Command(
        "check every model of a package and their cross-references",
        lambda p: _configure("rra_agent.cli.validate:configure", p),
        lazy("rra_agent.cli.validate:run"),
    ),
    "resolve": Command(
        "print the Deployment-time Configured System Model for a feature selection",
        lambda p: _configure("rra_agent.cli.resolve:configure", p),
        lazy("rra_agent.cli.resolve:run"),
    ),
    "check": Command(
        "static analysis of the rules: conflicts (exit 1 if certain), unreachable features",
        lambda p: _configure("rra_agent.cli.check:configure", p),
        lazy("rra_agent.cli.check:run"),
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
        lambda p: _configure("rra_agent.cli.events:configure_events", p),
        lazy("rra_agent.cli.events:run_events"),
    ),
    "watch": Command(
        "print measurements as they change (MEASUREMENT ...; none: all) until Ctrl-C",
        lambda p: _configure("rra_agent.cli.watch:configure", p),
        lazy("rra_agent.cli.watch:run"),
    ),
    "inject": Command(
        "inject a fault, set parameters or override a measurement in a running system",
        lambda p: _configure("rra_agent.cli.inject:configure", p),
        lazy("rra_agent.cli.inject:run"),
    ),
    "why": Command(
        "why the run-time features and CV values are what they are, and what can be reached",
        lambda p: _configure("rra_agent.cli.why:configure", p),
        lazy("rra_agent.cli.why:run"),
    ),
    "demo": Command(
        "the paper's evaluation: a quadcopter loses a motor, RRA swaps its controller",
        lambda p: _configure("rra_agent.demo:configure", p),
        lazy("rra_agent.demo:run"),
    ),
    "param": Command(
        "print or set the parameters of a running node (NAME=VALUE ...)",
        lambda p: _configure("rra_agent.cli.param:configure_param", p),
        lazy("rra_agent.cli.param:run_param"),
    ),
    "select": Command(
        "force run-time features on or off (FEATURE=on|off|auto), or print the forced ones",
        lambda p: _configure("rra_agent.cli.select:configure", p),
        lazy("rra_agent.cli.select:run"),
    ),
    "retry": Command(
        "re-admit unavailable implementations (COMPONENT ...; none: all) and try them again",
        lambda p: _configure("rra_agent.cli.retry:configure_retry", p),
        lazy("rra_agent.cli.retry:run_retry"),
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
        lambda p: _configure("rra_agent.cli.test:configure", p),
        lazy("rra_agent.cli.test:run"),
    ),
    "replay": Command(
        "re-run a recorded run's decisions offline (--package EDITED: what-if)",
        lambda p: _configure("rra_agent.cli.replay:configure", p),
        lazy("rra_agent.cli.replay:run"),
    ),
    "reload": Command(
        "take edited models into the running system without restarting it (--undo)",
        lambda p: _configure("rra_agent.cli.reload:configure", p),
        lazy("rra_agent.cli.reload:run"),
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
        for err in flatten_errors(e):  # one format: `file:line:col: message` (`rra validate`'s)
            located = isinstance(err, LocatedError) and err.location is not None
            print(error_line(err) if located else f"rra {args.command}: {err}", file=sys.stderr)
        return 1
    except BrokenPipeError:  # e.g. `rra resolve PKG | head`: stop quietly
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    sys.exit(main())
