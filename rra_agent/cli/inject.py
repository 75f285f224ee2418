"""``rra inject``: an injection a scenario can make, from the terminal, against a running system.

- ``rra inject KIND [--target T] [key=value ...]``: a fault or context change for the nodes
  that take injections (the quadcopter simulator's ``break_motor``, ``degrade_motor``,
  ``sensor_noise``, ``clear_faults``), as a scenario's ``inject:`` step; ``rra inject
  break_motor 2`` is short for ``rra inject break_motor motor=2``. The Context Monitor leader
  publishes it (refused when no process of the system takes injections).
- ``rra inject set_params NODE name=value ...``: a node's parameters, as ``rra param``
  (checked against their declarations, kept in the Run-time Configured System Model).
- ``rra inject measurement NAME=VALUE [--for 5s]``: the Context Monitor publishes VALUE for
  measurement NAME instead of the computed one until the time is up (default 10 s), marked
  as an override; ``NAME=auto`` ends it early. Refused for an unknown measurement or a value
  its declaration does not admit.

Each is recorded as an ``injection`` event naming the operator (``user@host``); the command
prints what is now in effect, in one line.
"""

from __future__ import annotations

import argparse
import re
import time
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, connect_system, engine_request
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.cli.common import add_system_argument
from rra_agent.cli.param import parse_assignments
from rra_agent.cli.select import operator_name
from rra_agent.errors import RraError

#: Kinds whose first bare argument names a motor (``rra inject break_motor 2``).
MOTOR_KINDS = ("break_motor", "degrade_motor")
#: How long an override lasts when ``--for`` is not given.
DEFAULT_FOR = 10.0
_DURATION = re.compile(r"^\s*(\d+(?:\.\d*)?|\.\d+)\s*(ms|s|min|m|h)?\s*$")
_UNIT = {"ms": 0.001, "s": 1.0, None: 1.0, "m": 60.0, "min": 60.0, "h": 3600.0}


def configure(p: argparse.ArgumentParser) -> None:
    add_system_argument(p)
    p.add_argument(
        "kind",
        metavar="KIND",
        help="an injection kind (e.g. break_motor), set_params or measurement",
    )
    p.add_argument(
        "args",
        nargs="*",
        metavar="ARG",
        help="key=value arguments (YAML scalars); set_params: NODE first; measurement: "
        "NAME=VALUE (NAME=auto ends an override); break_motor N: motor N",
    )
    p.add_argument("--target", default="", help="the node the injection is for (default: any)")
    p.add_argument(
        "--for",
        dest="duration",
        metavar="DURATION",
        help=f"how long a measurement override lasts (5s, 500ms, 2m; default {DEFAULT_FOR:g}s)",
    )
    p.add_argument("--timeout", type=float, default=5.0, metavar="S", help="wait for the engine")
    add_bus_arguments(p)


def parse_duration(text: str) -> float:
    """``5s``, ``500ms``, ``2m``, ``1.5`` (seconds) -> seconds; RraError otherwise."""
    match = _DURATION.match(text)
    if match is None:
        raise RraError(f"--for {text!r}: expected a duration such as 5s, 500ms or 2m")
    return float(match.group(1)) * _UNIT[match.group(2)]


def injection(kind: str, target: str, args: list[str]) -> m.Inject:
    """The `Inject` of ``rra inject KIND [--target T] ARGS``."""
    bare = [a for a in args if "=" not in a]
    values = parse_assignments([a for a in args if "=" in a])
    if bare:
        if kind not in MOTOR_KINDS or len(bare) > 1 or "motor" in values:
            raise RraError(f"expected key=value arguments, got {' '.join(bare)!r}")
        values["motor"] = parse_assignments([f"motor={bare[0]}"])["motor"]
    return m.Inject(kind=kind, target=target, args=values, operator=operator_name())


def override(args: list[str], duration: str | None) -> m.OverrideMeasurement:
    """The `OverrideMeasurement` of ``rra inject measurement NAME=VALUE [--for D]``."""
    if len(args) != 1 or "=" not in args[0]:
        raise RraError("expected one NAME=VALUE (e.g. BattLev=10; NAME=auto ends an override)")
    name, _, text = args[0].partition("=")
    if not name.strip():
        raise RraError(f"expected NAME=VALUE, got {args[0]!r}")
    seconds = 0.0 if text.strip() == "auto" else parse_duration(duration or f"{DEFAULT_FOR}s")
    if text.strip() != "auto" and not 0 < seconds <= 86400:
        raise RraError(f"--for {duration}: between 0 s and 24 h, please")
    return m.OverrideMeasurement(
        name=name.strip(), value=text.strip(), duration=seconds, operator=operator_name()
    )


def _set_params(client: BusClient, args: list[str], timeout: float) -> str:
    if not args or "=" in args[0]:
        raise RraError("expected: rra inject set_params NODE name=value ...")
    node, values = args[0], parse_assignments(args[1:])
    if not values:
        raise RraError(f"no name=value to set on {node}")
    request = m.SetParam(node=node, params=values, operator=operator_name(), injection=True)
    result = engine_request(client, "resolution", request, timeout)
    done = " ".join(f"{k}={v!r}" for k, v in sorted((result.get("params") or values).items()))
    return f"set {node}: {done}"


def _measurement(client: BusClient, request: m.OverrideMeasurement, timeout: float) -> str:
    result = engine_request(client, "monitor", request, timeout)
    if request.duration == 0:
        ended = "ended" if result.get("ended") else "was not overridden"
        return f"override of {request.name} {ended}: computed values again"
    until = time.strftime("%H:%M:%S", time.localtime(float(result.get("until", 0))))
    value: Any = result.get("value")
    return f"{request.name} = {value!r} (override) until {until} ({request.duration:g} s)"


def run(args: argparse.Namespace) -> int:
    kind = args.kind
    if kind == "measurement":
        request: m.EngineRequest = override(args.args, args.duration)
    elif args.duration is not None:
        raise RraError("--for applies to `rra inject measurement` only")
    elif kind != "set_params":
        request = injection(kind, args.target, args.args)
    with connect_system(bus_from_args(args), args.system) as client:
        if kind == "set_params":
            text = _set_params(client, args.args, args.timeout)
        elif isinstance(request, m.OverrideMeasurement):
            text = _measurement(client, request, args.timeout)
        else:
            result = engine_request(client, "monitor", request, args.timeout)
            text = f"injected {result.get('injected', kind)}"
    print(text, flush=True)
    return 0
