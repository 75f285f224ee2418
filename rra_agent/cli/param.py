"""``rra param NODE [name=value ...]``: print or set a node's parameters (through the
Run-time Resolution Engine, which checks them against their declarations and knows the
model: an unknown node is refused at once). A node that is not running takes a value as the
one it will start with, and its read shows the values it will start with; both say so."""

from __future__ import annotations

import argparse
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.bus.client import (
    BusClient,
    NoReply,
    connect_system,
    node_params,
    set_params,
    wait_until,
)
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
    """``NAME=VALUE`` items, each value a YAML scalar (``1e-3`` a float)."""
    import yaml

    from rra_agent.package.yamlload import scalar

    out: dict[str, Any] = {}
    for item in items:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise RraError(f"expected NAME=VALUE, got {item!r}")
        try:
            out[name] = scalar(text)
        except yaml.YAMLError as e:
            raise RraError(f"{item!r}: not a YAML value: {e}") from None
    return out


def run_param(args: argparse.Namespace) -> int:
    """Set parameters of a node, or print them all when none is given. The same rule both
    ways for a node that is not running (not selected now, or stopped): a write is accepted
    as a value it will start with, a read prints the values it will start with, and both
    say that it is not running."""
    values = parse_assignments(args.values)
    with connect_system(bus_from_args(args), args.system) as client:
        if values or args.reset:
            result = set_params(client, args.node, values, args.reset)
            params = {**result.get("params", {}), **{n: "(model value)" for n in args.reset}}
            state = result.get("state", "running")
        else:
            info = node_params(client, args.node)  # an unknown node: refused at once
            state, params = info["state"], info["params"]
            if state != "stopped" and not client.restricted:  # what the node itself runs with
                params = _described(client, args.node, params)
    if state == "stopped":
        print(f"{args.node} is not running; it will start with:")
    for name, value in sorted(params.items()):
        print(
            f"{name} = {value!r}"
            if not isinstance(value, str) or "(" not in value
            else f"{name} = {value}"
        )
    return 0


def _described(client: BusClient, node: str, fallback: dict[str, Any]) -> dict[str, Any]:
    """The parameters ``node`` reports (``Describe``); ``fallback`` (the engine's) if it
    does not answer (an operator may not call a node)."""
    try:  # the router may still be telling this new client about the node's token
        wait_until(lambda: any(n == node for _, n in client.alive()), 2.0, f"node {node}",
                   interval=0.05)  # fmt: skip
        reply = client.node(node, m.Describe())
    except (TimeoutError, NoReply):
        return fallback
    if isinstance(reply, m.Err):
        raise RraError(f"{node}: {reply.message}")
    return dict(reply.result["params"])
