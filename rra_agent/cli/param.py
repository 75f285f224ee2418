"""``rra param NODE [name=value ...]``: print or set a running node's parameters (through
the Run-time Resolution Engine, which checks them against their declarations)."""

from __future__ import annotations

import argparse
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.bus.client import connect_system, engine_params, set_params, wait_until
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.cli.common import add_system_argument
from rra_agent.errors import RraError


def configure_param(p: argparse.ArgumentParser) -> None:
    add_system_argument(p)
    p.add_argument("node", help="node name")
    p.add_argument("values", nargs="*", metavar="NAME=VALUE", help="values are YAML scalars")
    p.add_argument(
        "--reset", action="append", default=[], metavar="NAME", help="back to the model's value"
    )
    add_bus_arguments(p)


def parse_assignments(items: list[str]) -> dict[str, Any]:
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise RraError(f"expected NAME=VALUE, got {item!r}")
        try:
            out[name] = yaml.safe_load(text)
        except yaml.YAMLError as e:
            raise RraError(f"{item!r}: not a YAML value: {e}") from None
    return out


def run_param(args: argparse.Namespace) -> int:
    """Set parameters of a running node (or print them all when none is given)."""
    values = parse_assignments(args.values)
    with connect_system(bus_from_args(args), args.system) as client:
        if values or args.reset:
            result = set_params(client, args.node, values, args.reset)
            params = {**result.get("params", {}), **{n: "(model value)" for n in args.reset}}
        elif client.restricted:  # an operator may not call a node: the engine's model
            params = engine_params(client, args.node)
        else:
            try:  # the router may still be telling this new client about the tokens
                wait_until(
                    lambda: any(n == args.node for _, n in client.alive()),
                    2.0,
                    f"node {args.node}",
                    interval=0.05,
                )
            except TimeoutError:
                system = client.keys.system
                raise RraError(f"no running node {args.node!r} in system {system!r}") from None
            reply = client.node(args.node, m.Describe())
            if isinstance(reply, m.Err):
                raise RraError(f"{args.node}: {reply.message}")
            params = reply.result["params"]
    for name, value in sorted(params.items()):
        print(
            f"{name} = {value!r}"
            if not isinstance(value, str) or "(" not in value
            else f"{name} = {value}"
        )
    return 0
