"""Command-line plumbing shared by the engine processes (monitor, adaptation, resolution).

An engine started by a host agent finds its name and host in ``RRA_NODE_SPEC`` and its bus in
``RRA_BUS_CONFIG``, like a node; started by hand it takes ``--name``/``--host`` and the bus
flags. Model errors are printed as ``file:line:col: message`` and the engine exits with 2
(the supervisor's "do not restart" status).

`warm_up` is each engine module's hook for the fork server (`rra_agent.host.forkserver`),
which runs the engines in forks of itself: it prepares the deployment there once
(`rra_agent.deployment.prepare`), and every engine forked after shares it.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import sys
from collections.abc import Callable
from pathlib import Path

import msgspec

from rra_agent.bus.config import BusConfig, add_bus_arguments, bus_from_args
from rra_agent.bus.messages import NodeSpec
from rra_agent.deployment import Deployment, deploy, prepare
from rra_agent.errors import RraError
from rra_agent.node.process import SPEC_ENV


def engine_arguments(prog: str, doc: str | None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog=prog, description=(doc or "").split("\n\n")[0])
    parser.add_argument("--package", required=True, help="system package folder")
    parser.add_argument(
        "--select", action="append", default=[], help="deployment-time features (comma list)"
    )
    parser.add_argument("--run-dir", help="where logs of this run go")
    parser.add_argument(
        "--no-record", action="store_true", help="do not record the run (<run-dir>/record/)"
    )
    parser.add_argument("--host", default=None, help="this process' host (default: local)")
    parser.add_argument("--name", default=None, help="this engine's name on the bus")
    add_bus_arguments(parser)
    return parser


def selection(args: argparse.Namespace) -> list[str]:
    """The ``--select`` names (each a comma list)."""
    return [n.strip() for v in args.select for n in v.split(",") if n.strip()]


def record_dir(args: argparse.Namespace) -> Path | None:
    """The run folder this engine records in (``<run-dir>/record/``), or None."""
    return Path(args.run_dir) if args.run_dir and not args.no_record else None


def warm_up(
    argv: list[str], arguments: Callable[[], argparse.ArgumentParser] | None = None
) -> None:
    """In the fork server, before it forks an engine with these arguments: load and resolve
    the package it will (a model error is left for the engine to report), and parse them
    with the engine's ``arguments`` (`parse_engine_args` then hands them over)."""
    args, _ = engine_arguments("rra engine", None).parse_known_args(argv)
    with contextlib.suppress(RraError):
        prepare(args.package, selection(args))
    if arguments is not None:
        _parse_ahead(arguments, argv)


#: Arguments parsed by `warm_up`, by (the engine's module, argv).
_parsed: dict[tuple[str, tuple[str, ...]], argparse.Namespace] = {}


def _parse_ahead(arguments: Callable[[], argparse.ArgumentParser], argv: list[str]) -> None:
    """Keep ``arguments().parse_args(argv)`` for the engines forked after (an error, printed
    by the engine itself, is not kept)."""
    with contextlib.suppress(Exception, SystemExit), contextlib.redirect_stderr(io.StringIO()):
        _parsed[(arguments.__module__, tuple(argv))] = arguments().parse_args(argv)


def parse_engine_args(
    arguments: Callable[[], argparse.ArgumentParser], argv: list[str] | None
) -> argparse.Namespace:
    """``arguments().parse_args(argv)``, or a copy of what `warm_up` parsed ahead: building
    and running an argparse parser wrote to ~1 MiB of the fork server's pages in each
    engine forked from it."""
    key = (arguments.__module__, tuple(sys.argv[1:] if argv is None else argv))
    kept = _parsed.get(key)
    if kept is not None:
        return argparse.Namespace(**vars(kept))
    return arguments().parse_args(argv)


def engine_setup(
    args: argparse.Namespace, default_name: str
) -> tuple[Deployment, BusConfig, str, str] | None:
    """(deployment, bus, host, name), or None after printing why the engine cannot run."""
    name, host = args.name or default_name, args.host or "local"
    raw = os.environ.get(SPEC_ENV)
    if raw:
        try:
            spec = msgspec.json.decode(raw, type=NodeSpec)
            name, host = args.name or spec.name, args.host or spec.host
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            print(f"{default_name}: bad {SPEC_ENV}: {e}", file=sys.stderr)
            return None
    try:
        dep = deploy(args.package, selection(args))
        bus = bus_from_args(args)
    except RraError as e:
        print(str(e), file=sys.stderr)
        return None
    return dep, bus, host, name
