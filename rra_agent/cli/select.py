"""``rra select``: an operator forces run-time features on or off.

``rra select [--system NAME] FEATURE=on|off|auto ...`` asks the Adaptation Engine leader
(`ForceFeatures` on ``engine/adaptation/ctl``) to force each FEATURE on or off, or to release
it (``auto``: the rules decide again). The engine checks the choices against the feature
model (a refused one changes nothing and is printed as one line), records an ``override``
adaptation event, and from then on its rules cannot change a forced feature. Without
choices, ``rra select`` prints the features forced now.
"""

from __future__ import annotations

import argparse
import getpass
import socket
from collections.abc import Sequence
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply, connect_system, wait_until
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.cli.common import add_system_argument
from rra_agent.core.overrides import CHOICES
from rra_agent.errors import RraError


def configure(p: argparse.ArgumentParser) -> None:
    add_system_argument(p)
    p.add_argument(
        "choices",
        nargs="*",
        metavar="FEATURE=on|off|auto",
        help="force a run-time feature on or off; auto releases it (none: print the forced)",
    )
    p.add_argument("--timeout", type=float, default=5.0, metavar="S", help="wait for the engine")
    add_bus_arguments(p)


def parse_choices(items: Sequence[str]) -> dict[str, str]:
    """``["Light=on", "Eco=auto"]`` -> ``{"Light": "on", "Eco": "auto"}``; RraError if bad."""
    out: dict[str, str] = {}
    for item in items:
        name, sep, choice = item.partition("=")
        name, choice = name.strip(), choice.strip().lower()
        if not sep or not name or choice not in CHOICES:
            raise RraError(f"expected FEATURE=on|off|auto, got {item!r}")
        out[name] = choice
    return out


def operator_name() -> str:
    """Who asks, for the ``override`` event: ``user@host``."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):
        user = "unknown"
    return f"{user}@{socket.gethostname()}"


def _ask(client: BusClient, request: m.EngineRequest, timeout: float) -> dict[str, Any]:
    """One request to the Adaptation Engine leader, once its token has reached us."""
    system = client.keys.system
    try:
        wait_until(
            lambda: list(
                client.session.liveliness().get(f"{client.keys.lead('adaptation')}/**", timeout=0.5)
            ),
            timeout,
            "the adaptation engine",
            interval=0.02,
        )
        reply = client.request(client.keys.engine_ctl("adaptation"), request, timeout)
    except (TimeoutError, NoReply):
        raise RraError(
            f"no Adaptation Engine leads system {system!r} on this bus "
            "(is it running with an adaptation model? right --system and --connect?)"
        ) from None
    if isinstance(reply, m.Err):
        raise RraError(reply.message)
    return reply.result if isinstance(reply.result, dict) else {}


def run(args: argparse.Namespace) -> int:
    choices = parse_choices(args.choices)
    with connect_system(bus_from_args(args), args.system) as client:
        if choices:
            request = m.ForceFeatures(features=choices, operator=operator_name())  # type: ignore[arg-type]
            result = _ask(client, request, args.timeout)
        else:
            result = _ask(client, m.Status(), args.timeout)
    forced = result.get("forced") or {}
    if not forced:
        print("no run-time feature is forced (the rules decide)")
    for name, state in sorted(forced.items()):
        print(f"{name} = {state}")
    if choices and "selection" in result:
        print(f"selection: {', '.join(result['selection']) or '-'}")
    return 0
