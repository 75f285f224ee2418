"""``rra status`` and ``rra events``: look at a running system from another terminal.

``rra status`` asks the resolution engine for the current run-time selection and CV values,
and every host agent for its nodes (host, state, pid, implementation, active flag, restarts);
``--watch S`` redraws it every S seconds. ``rra events`` follows the adaptation events and
node-state transitions live (or prints a saved ``events.jsonl`` with ``--log``).
"""

from __future__ import annotations

import argparse
import contextlib
import threading
import time
from typing import Any

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply, wait_until
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.errors import RraError

_EVT = m.Codec[m.EventMessage](m.EventMessage)


def configure_status(p: argparse.ArgumentParser) -> None:
    p.add_argument("--system", required=True, help="system name (the package's)")
    p.add_argument("--watch", type=float, metavar="S", help="refresh every S seconds")
    p.add_argument("--json", action="store_true", help="machine-readable output")
    add_bus_arguments(p)


def gather(client: BusClient, timeout: float = 2.0) -> dict[str, Any]:
    """The engine's status and every host agent's node list, as plain data."""
    out: dict[str, Any] = {"engine": None, "nodes": []}
    # A client just connected has not been told about the engine yet: query it once its
    # token has reached this session (its queryable was declared before the token).
    engine_token = f"{client.keys.prefix}/alive/*/resolution"
    with contextlib.suppress(TimeoutError):
        wait_until(
            lambda: list(client.session.liveliness().get(engine_token, timeout=0.5)),
            timeout,
            "the resolution engine",
            interval=0.02,
        )
    try:
        reply = client.request(client.keys.engine_ctl("resolution"), m.Status(), timeout)
        if isinstance(reply, m.Ok):
            out["engine"] = reply.result
    except NoReply:
        pass
    hosts = sorted(
        str(r.ok.key_expr).rsplit("/", 1)[-1]
        for r in client.session.liveliness().get(f"{client.keys.prefix}/hostagent/*", timeout=1)
        if r.ok is not None
    )
    for host in hosts:
        try:
            reply = client.host(host, m.ListNodes(), timeout)
        except NoReply:
            continue
        if isinstance(reply, m.Ok):
            out["nodes"].extend(reply.result)
    out["hosts"] = hosts
    return out


def render(status: dict[str, Any]) -> str:
    lines = []
    eng = status.get("engine")
    if eng:
        lines.append(f"system      {eng['system']}   deployment: {', '.join(eng['deployment'])}")
        lines.append(f"selection   {', '.join(eng['selection']) or '-'}")
        cv = ", ".join(f"{k}={v:.3g}" for k, v in sorted(eng["cv"].items()))
        lines.append(f"cv          {cv or '-'}")
        if eng.get("failed"):
            lines.append("last adaptation FAILED (rolled back); see `rra events`")
    else:
        lines.append("resolution engine: not reachable")
    running = (eng or {}).get("running", {})
    standby = set((eng or {}).get("standby", []))
    lines.append("")
    lines.append(
        f"{'NODE':<24} {'HOST':<10} {'STATE':<9} {'PID':>7} {'ACTIVE':<7} "
        f"{'RESTARTS':>8}  IMPLEMENTATION"
    )
    for n in sorted(status["nodes"], key=lambda n: (n["host"], n["node"])):
        active = n.get("active", True)
        if n["node"] in running:
            active = running[n["node"]]["active"]
        role = " (standby)" if n["node"] in standby else ""
        pid = str(n.get("pid") or "-")
        lines.append(
            f"{n['node']:<24} {n['host']:<10} {n['state']:<9} {pid:>7} "
            f"{'yes' if active else 'no':<7} {n.get('restarts', 0):>8}  "
            f"{n.get('implementation', '')}{role}"
        )
    return "\n".join(lines)


def run_status(args: argparse.Namespace) -> int:
    with BusClient(bus_from_args(args), args.system) as client:
        while True:
            status = gather(client)
            if not status["hosts"] and status["engine"] is None:
                raise RraError(f"no running system {args.system!r} reachable on the bus")
            if args.json:
                print(msgspec.json.encode(status).decode(), flush=True)
            else:
                if args.watch:
                    print("\033[2J\033[H", end="")
                print(render(status), flush=True)
            if not args.watch:
                return 0
            time.sleep(args.watch)


def configure_events(p: argparse.ArgumentParser) -> None:
    p.add_argument("--system", help="system name (to follow live)")
    p.add_argument("--log", metavar="FILE", help="print a saved events.jsonl instead")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    add_bus_arguments(p)


def format_event(ev: m.AdaptationEvent | m.NodeState) -> str:
    t = time.strftime("%H:%M:%S", time.localtime(ev.stamp)) + f".{int(ev.stamp % 1 * 1000):03d}"
    match ev:
        case m.NodeState():
            why = f" ({ev.reason})" if ev.reason else ""
            return f"{t} node  {ev.host}/{ev.node}: {ev.previous} -> {ev.state}{why}"
        case m.AdaptationEvent():
            cause = "; ".join(f"{c.rule}: {c.action}" for c in ev.cause)
            dur = " ".join(f"{k}={v * 1e3:.1f}ms" for k, v in ev.durations.items())
            out = f"{t} {ev.level.upper():<7} {ev.kind}: {ev.message}"
            if cause:
                out += f"\n    cause: {cause}"
            for step in ev.plan:
                out += f"\n    - {step}"
            if dur:
                out += f"\n    durations: {dur}"
            return out
    return repr(ev)


def run_events(args: argparse.Namespace) -> int:
    enc = msgspec.json.Encoder()
    if args.log:
        from rra_agent.engines.events import read_events

        for ev in read_events(args.log):
            print(enc.encode(ev).decode() if args.json else format_event(ev), flush=True)
        return 0
    if not args.system:
        raise RraError("give --system to follow a running system, or --log FILE")
    done = threading.Event()
    with BusClient(bus_from_args(args), args.system) as client:

        def on_event(sample: zenoh.Sample) -> None:
            try:
                ev = _EVT.decode(sample.payload.to_bytes())
            except (msgspec.DecodeError, msgspec.ValidationError):
                return
            print(enc.encode(ev).decode() if args.json else format_event(ev), flush=True)

        client.session.declare_subscriber(client.keys.events, on_event)
        try:
            done.wait()
        except KeyboardInterrupt:
            return 0
    return 0


def configure_param(p: argparse.ArgumentParser) -> None:
    p.add_argument("--system", required=True, help="system name (the package's)")
    p.add_argument("node", help="node name")
    p.add_argument("values", nargs="*", metavar="NAME=VALUE", help="values are YAML scalars")
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
    with BusClient(bus_from_args(args), args.system) as client:
        try:  # the router may still be telling this new client about the tokens
            wait_until(
                lambda: any(n == args.node for _, n in client.alive()),
                2.0,
                f"node {args.node}",
                interval=0.05,
            )
        except TimeoutError:
            raise RraError(f"no running node {args.node!r} in system {args.system!r}") from None
        reply = client.node(args.node, m.SetParams(params=values) if values else m.Describe())
    if isinstance(reply, m.Err):
        raise RraError(f"{args.node}: {reply.message}")
    params = values or reply.result["params"]
    for name, value in sorted(params.items()):
        print(f"{name} = {value!r}")
    return 0
