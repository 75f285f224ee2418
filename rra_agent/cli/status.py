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
from collections.abc import Sequence
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
    p.add_argument("--wide", action="store_true", help="also show each node's implementation")
    add_bus_arguments(p)


def _leader_token(client: BusClient, role: str) -> str:
    return f"{client.keys.lead(role)}/*/*"


def wait_for_leader(client: BusClient, timeout: float) -> None:
    """Until the Resolution Engine leader's token has reached this session (TimeoutError)."""
    wait_until(
        lambda: list(
            client.session.liveliness().get(_leader_token(client, "resolution"), timeout=0.5)
        ),
        timeout,
        "the resolution engine",
        interval=0.02,
    )


def gather(client: BusClient, timeout: float = 2.0) -> dict[str, Any]:
    """The engine's status, every host's nodes and every process's counters. An operator
    with a certificate (``client.restricted``) may not call host or node control: its view
    is the engine's (what the host agents last reported to it) and the engines' counters."""
    engine = _engine_status(client, timeout)
    eng = engine or {}
    present = {
        str(r.ok.key_expr).rsplit("/", 1)[-1]
        for r in client.session.liveliness().get(client.keys.host_alive_all, timeout=1)
        if r.ok is not None
    }
    nodes = [] if client.restricted else _listed_nodes(client, sorted(present), timeout)
    listed = {n["node"] for n in nodes}
    unreachable = set(eng.get("unreachable", []))
    for name, st in (eng.get("observed") or {}).items():
        if name in listed:
            continue
        # On a host the engine cannot reach now: as it last heard of it.
        state = f"{st['state']}?" if st.get("host") in unreachable else st["state"]
        nodes.append({"node": name, **st, "state": state})
    families = ("engine",) if client.restricted else ("node", "host")
    return {
        "engine": engine,
        "nodes": nodes,
        # The model's hosts as the engine sees them (an unreachable one too), and any other.
        "hosts": sorted({*eng.get("hosts", {}), *present}),
        "stats": process_stats(client, timeout, families=families),
    }


def _engine_status(client: BusClient, timeout: float) -> dict[str, Any] | None:
    # A client just connected has not been told about the engine yet: query it once the
    # leader's token has reached this session (its queryable was declared before it).
    with contextlib.suppress(TimeoutError):
        wait_for_leader(client, timeout)
    try:
        reply = client.request(client.keys.engine_ctl("resolution"), m.Status(), timeout)
    except NoReply:
        return None
    return reply.result if isinstance(reply, m.Ok) else None


def _listed_nodes(client: BusClient, hosts: list[str], timeout: float) -> list[dict[str, Any]]:
    """Every node the host agents of ``hosts`` supervise (``ListNodes``)."""
    out: list[dict[str, Any]] = []
    for host in hosts:
        try:
            reply = client.host(host, m.ListNodes(), timeout)
        except NoReply:
            continue
        if isinstance(reply, m.Ok):
            out.extend(reply.result)
    return out


def process_stats(
    client: BusClient, timeout: float = 1.0, families: tuple[str, ...] = ("node", "host")
) -> dict[str, dict[str, Any]]:
    """Every process's counters (`ProcessStats`) by name: one query to all at once."""
    out: dict[str, dict[str, Any]] = {}
    codec = m.Codec[m.Reply](m.Reply)
    for key in (f"{client.keys.prefix}/{family}/*/ctl" for family in families):
        for reply in client.session.get(
            key,
            payload=m.Codec[Any](Any).encode(m.Stats()),
            timeout=timeout,
            consolidation=zenoh.ConsolidationMode.NONE,
        ):
            if reply.ok is None:
                continue
            try:
                answer = codec.decode(reply.ok.payload.to_bytes())
            except (msgspec.DecodeError, msgspec.ValidationError):
                continue
            if isinstance(answer, m.Ok) and isinstance(answer.result, dict):
                stats = answer.result
                out[f"{stats.get('role')}:{stats.get('name')}"] = stats
    return out


def render(status: dict[str, Any], *, wide: bool = False) -> str:
    lines = []
    eng = status.get("engine")
    if eng:
        leader = eng.get("leader") or []
        who = f"   leader {leader[1]} (epoch {leader[0]})" if leader else ""
        lines.append(f"system      {eng['system']} ({', '.join(eng['deployment'])}){who}")
        lines.append(f"selection   {', '.join(eng['selection']) or '-'}")
        cv = ", ".join(f"{k}={v:.3g}" for k, v in sorted(eng["cv"].items()))
        lines.append(f"cv          {cv or '-'}")
        for node, values in sorted(eng.get("overrides", {}).items()):
            set_ = ", ".join(f"{k}={v!r}" for k, v in sorted(values.items()))
            lines.append(f"operator    {node}: {set_}")
        lines += adaptation_lines(eng)
        if eng.get("failed"):
            lines.append("last adaptation FAILED (rolled back); see `rra events`")
    else:
        lines.append("resolution engine: not reachable")
    unreachable = set((eng or {}).get("unreachable", []))
    hosts = ", ".join(
        f"{h} ({'unreachable' if h in unreachable else 'up'})" for h in status.get("hosts", [])
    )
    lines.append(f"hosts       {hosts or '-'}")
    desired = (eng or {}).get("desired", {})
    stats = {
        k.split(":", 1)[1]: v
        for k, v in status.get("stats", {}).items()
        if not k.startswith("host:")
    }
    lines.append("")
    header = (
        f"{'NODE':<24} {'HOST':<8} {'WANT':<7} {'STATE':<12} {'PID':>7} {'RST':>3} "
        f"{'RECV':>7} {'DROP':>5} {'REJ':>4}"
    )
    lines.append(header + ("  IMPLEMENTATION" if wide else ""))
    seen = set()
    for n in sorted(status["nodes"], key=lambda n: (n["host"], n["node"])):
        seen.add(n["node"])
        lines.append(_row(n, desired.get(n["node"]), stats.get(n["node"], {}), wide))
    for name, d in sorted(desired.items()):
        if name not in seen:  # desired, but no host agent reports it
            row = {"node": name, "host": d["host"], "state": "UNKNOWN", "restarts": 0}
            lines.append(_row(row, d, {}, wide))
    return "\n".join(lines)


def adaptation_lines(eng: dict[str, Any]) -> list[str]:
    """The features operators forced (``rra select``) and the run-time conflicts in force,
    as the Run-time Resolution Engine holds them (nothing when there are none)."""
    lines = []
    forced = eng.get("forced") or {}
    if forced:
        lines.append("forced      " + ", ".join(f"{f} {v}" for f, v in sorted(forced.items())))
    for c in eng.get("conflicts") or []:
        rules = c.get("rules") or []
        wants = c.get("wants") or {}
        who = ", ".join(f"{r} wants {wants.get(r, '?')}" for r in rules)
        since = time.strftime("%H:%M:%S", time.localtime(c.get("since") or c.get("stamp", 0)))
        lines.append(f"conflict    {c.get('target')}: {who} (since {since})")
    return lines


def _row(n: dict[str, Any], want: dict[str, Any] | None, st: dict[str, Any], wide: bool) -> str:
    if want is None:
        role = st.get("role", "node")
        wanted = "engine" if role in ("monitor", "adaptation", "resolution") else "-"
    else:
        wanted = "standby" if want.get("standby") else "run"
    pid = str(n.get("pid") or "-")
    recv, drop, rej = (
        str(st.get(k, 0)) if st else "-" for k in ("received", "dropped", "rejected")
    )
    line = (
        f"{n['node'][:24]:<24} {n['host'][:8]:<8} {wanted:<7} {n['state']:<12} {pid:>7} "
        f"{n.get('restarts', 0):>3} {recv:>7} {drop:>5} {rej:>4}"
    )
    return line + (f"  {n.get('implementation', '')}" if wide else "")


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
                print(render(status, wide=args.wide), flush=True)
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


def set_params(
    client: BusClient,
    node: str,
    values: dict[str, Any],
    reset: Sequence[str] = (),
    timeout: float = 5.0,
) -> dict[str, Any]:
    """Set a node's parameters as an operator: through the Run-time Resolution Engine, so
    they are checked, become part of the Run-time Configured System Model and survive
    restarts. Raises `RraError` with the engine's refusal."""
    try:
        wait_for_leader(client, timeout)
    except TimeoutError:
        raise RraError(
            f"no Run-time Resolution Engine leads system {client.keys.system!r}"
        ) from None
    request = m.SetParam(node=node, params=values, reset=list(reset))
    reply = client.request(client.keys.engine_ctl("resolution"), request, timeout)
    if isinstance(reply, m.Err):
        raise RraError(f"{node}: {reply.message}")
    return reply.result  # type: ignore[union-attr]


def engine_params(client: BusClient, node: str, timeout: float = 5.0) -> dict[str, Any]:
    """A node's parameters in the Run-time Configured System Model (the engine's state)."""
    try:
        wait_for_leader(client, timeout)
        reply = client.request(client.keys.engine_ctl("resolution"), m.GetState(), timeout)
    except (TimeoutError, NoReply):
        raise RraError(f"no Run-time Resolution Engine leads {client.keys.system!r}") from None
    if not isinstance(reply, m.Ok):
        raise RraError(f"{node}: {reply.message}")  # type: ignore[union-attr]
    state = msgspec.convert(reply.result, m.EngineState)
    spec = next((s for s in (*state.running, *state.standby) if s.name == node), None)
    if spec is None:
        raise RraError(f"no running node {node!r} in system {client.keys.system!r}")
    return dict(spec.params)


def run_param(args: argparse.Namespace) -> int:
    """Set parameters of a running node (or print them all when none is given)."""
    values = parse_assignments(args.values)
    with BusClient(bus_from_args(args), args.system) as client:
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
                raise RraError(f"no running node {args.node!r} in system {args.system!r}") from None
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
