"""``rra retry [COMPONENT ...]``: re-admit unavailable implementations and try them again."""

from __future__ import annotations

import argparse

from rra_agent.bus import messages as m
from rra_agent.bus.client import NoReply, connect_system, wait_until
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.cli.common import add_system_argument
from rra_agent.cli.select import operator_name
from rra_agent.errors import RraError


def configure_retry(p: argparse.ArgumentParser) -> None:
    add_system_argument(p)
    p.add_argument(
        "components",
        nargs="*",
        metavar="COMPONENT",
        help="re-admit these components' unavailable implementations (none: all of them)",
    )
    p.add_argument("--timeout", type=float, default=30.0, metavar="S", help="wait for the engine")
    add_bus_arguments(p)


def run_retry(args: argparse.Namespace) -> int:
    """``rra retry [COMPONENT...]``: the Run-time Resolution Engine forgets that these
    implementations failed and tries them again; the Adaptation Engine may select the
    features that need them again."""
    request = m.Retry(components=list(args.components), operator=operator_name())
    with connect_system(bus_from_args(args), args.system) as client:
        try:
            wait_until(
                lambda: list(client.session.liveliness().get(
                    f"{client.keys.lead('resolution')}/**", timeout=0.5)),
                min(args.timeout, 5.0), "the resolution engine", interval=0.02,
            )  # fmt: skip
            reply = client.request(client.keys.engine_ctl("resolution"), request, args.timeout)
        except (TimeoutError, NoReply):
            raise RraError(
                f"no Run-time Resolution Engine leads system {client.keys.system!r} on this bus "
                "(right --system and --connect?)"
            ) from None
    if isinstance(reply, m.Err):
        raise RraError(reply.message)
    result = reply.result if isinstance(reply.result, dict) else {}
    again = result.get("readmitted") or []
    print(f"re-admitted: {', '.join(again)}" if again else "nothing was unavailable")
    still = result.get("unavailable") or []
    if still:
        print(f"unavailable again: {', '.join(still)} (see `rra status`, `rra events`)")
    return 0
