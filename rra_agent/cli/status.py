"""``rra status`` and ``rra events``: look at a running system from another terminal.

``rra status`` asks the resolution engine for the current run-time selection and CV values,
and every host agent for its nodes (host, state, pid, implementation, active flag, restarts);
``--watch S`` redraws it every S seconds; the samples the Context Monitor refused are listed
per source and reason at the end. ``rra events`` follows the adaptation events and
node-state transitions live (or prints a saved ``events.jsonl`` with ``--log``).
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import re
import textwrap
import threading
import time
from collections.abc import Iterable, Sequence
from typing import Any

import msgspec
import zenoh

from rra_agent import failure
from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply, connect_system, wait_until
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.errors import RraError

_EVT = m.Codec[m.EventMessage](m.EventMessage)


#: ``rra status`` fits this many columns unless ``--wide`` is given.
WIDTH = 100
#: Engine roles (a node with one of these roles is an engine replica).
ENGINE_ROLES = ("monitor", "adaptation", "resolution")


def add_system_argument(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--system",
        help="system name (the package's); needed only when several systems run at the endpoint",
    )


def configure_status(p: argparse.ArgumentParser) -> None:
    add_system_argument(p)
    p.add_argument("--watch", type=float, metavar="S", help="refresh every S seconds")
    p.add_argument("--json", action="store_true", help="machine-readable output (everything)")
    p.add_argument(
        "--wide",
        action="store_true",
        help=f"the full table (each node's implementation), not cut to {WIDTH} columns",
    )
    add_bus_arguments(p)


def _leader_token(client: BusClient, role: str) -> str:
    return f"{client.keys.lead(role)}/**"


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
    hosts = sorted({*eng.get("hosts", {}), *present})
    return {
        "engine": engine,
        "nodes": nodes,
        # The model's hosts as the engine sees them (an unreachable one too), and any other.
        "hosts": hosts,
        "host_agents": _host_agents(client, hosts, present, unreachable, nodes, timeout),
        "stats": process_stats(client, timeout, families=families),
    }


def _host_agents(
    client: BusClient,
    hosts: list[str],
    present: set[str],
    unreachable: set[str],
    nodes: list[dict[str, Any]],
    timeout: float,
) -> list[dict[str, Any]]:
    """Each host agent: whether it is up, its router's endpoints (its answer to a ``Ping``;
    an operator with a certificate may not ask) and how many nodes run on it."""
    out = []
    for host in hosts:
        info: dict[str, Any] = {}
        if host in present and not client.restricted:
            with contextlib.suppress(NoReply):
                reply = client.host(host, m.Ping(), timeout)
                if isinstance(reply, m.Ok) and isinstance(reply.result, dict):
                    info = reply.result
        live = [n for n in nodes if n.get("host") == host and n.get("state") in LIVE_STATES]
        state = "up" if host in present else "unreachable" if host in unreachable else "absent"
        out.append(
            {
                "host": host,
                "state": state,
                "pid": info.get("pid"),
                "listen": info.get("listen", []),
                "connect": info.get("connect", []),
                "nodes": len(live),
            }
        )
    return out


#: Node states in which a process exists (``rra status`` counts them per host).
LIVE_STATES = frozenset({"STARTING", "RUNNING", "UNRESPONSIVE", "STOPPING"})


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


# ---- rendering: one function per section ---------------------------------------------------
def render(status: dict[str, Any], *, wide: bool = False) -> str:
    """``rra status`` as text: the system, its hosts, its nodes; at most `WIDTH` columns
    unless ``wide``."""
    sections = [
        _system_section(status.get("engine"), wide),
        _hosts_section(status, wide),
        _nodes_section(status, wide),
        _failures_section(status, wide),
        refused_section(status, wide),
    ]
    return "\n\n".join("\n".join(lines) for lines in sections if lines)


def _field(label: str, text: str, wide: bool) -> list[str]:
    """``label`` and ``text`` in two columns, ``text`` wrapped at `WIDTH` (unless ``wide``)."""
    head = f"{label:<11} "
    if wide or len(head) + len(text) <= WIDTH:
        return [head + text]
    return textwrap.wrap(
        text,
        WIDTH,
        initial_indent=head,
        subsequent_indent=" " * len(head),
        break_on_hyphens=False,
    )


def _system_section(eng: dict[str, Any] | None, wide: bool) -> list[str]:
    """The system, its leader, the run-time selection, the CV values and operator settings."""
    if not eng:
        return ["resolution engine: not reachable"]
    leader = eng.get("leader") or []
    who = f"; leader {leader[1]} (epoch {leader[0]})" if leader else ""
    lines = _field("system", f"{eng['system']} ({', '.join(eng['deployment'])}){who}", wide)
    lines += effect_lines(eng, wide)
    for node, values in sorted(eng.get("overrides", {}).items()):
        set_ = ", ".join(f"{k}={v!r}" for k, v in sorted(values.items()))
        lines += _field("operator", f"{node}: {set_}", wide)
    lines += adaptation_lines(eng, wide)
    return lines


def _cv_text(cv: dict[str, float]) -> str:
    return ", ".join(f"{k}={v:.3g}" for k, v in sorted(cv.items())) or "-"


def effect_lines(eng: dict[str, Any], wide: bool = False) -> list[str]:
    """The selection and CV values, decided and in effect (one line each where they agree),
    the parameters that differ, the unavailable implementations and why the system is
    degraded."""
    decided, cv = eng["selection"], eng["cv"]
    effective = eng.get("effective", decided)
    effective_cv = eng.get("effective_cv", cv)
    if effective == decided:
        lines = _field("selection", ", ".join(decided) or "-", wide)
    else:
        lines = _field("decided", ", ".join(decided) or "-", wide)
        lines += _field("in effect", ", ".join(effective) or "-", wide)
    if effective_cv == cv:
        lines += _field("cv", _cv_text(cv), wide)
    else:
        lines += _field("cv decided", _cv_text(cv), wide)
        lines += _field("cv effect", _cv_text(effective_cv), wide)
    for node, apart in sorted((eng.get("params") or {}).items()):
        text = ", ".join(
            f"{k}={apart['effective'].get(k)!r} (decided {v!r})"
            for k, v in apart["decided"].items()
        )
        lines += _field("params", f"{node}: {text}", wide)
    for u in eng.get("unavailable") or []:
        what = u["component"] + (f" ({u['implementation']})" if u.get("implementation") else "")
        probe = max(0.0, u.get("probe_at", 0.0) - time.time())
        lines += _field("unavailable", f"{what}: {u['reason']} (probe in {probe:.0f} s)", wide)
    for why in eng.get("degraded") or []:
        lines += _field("degraded", why, wide)
    if eng.get("degraded"):
        lines.append("what was decided is not all in effect; see `rra events`, `rra retry`")
    return lines


def _hosts_section(status: dict[str, Any], wide: bool) -> list[str]:
    """One line per host agent: up or not, its router's endpoints, its live nodes."""
    agents = status.get("host_agents", [])
    if not agents:
        return ["hosts       -"]
    lines = [f"{'HOST':<16} {'AGENT':<11} {'NODES':>5}  ROUTER"]
    for a in agents:
        endpoints = [f"listens {ep}" for ep in a["listen"]] + [f"links {ep}" for ep in a["connect"]]
        router = ", ".join(endpoints) or "-"
        line = f"{_cut(a['host'], 16, wide):<16} {a['state']:<11} {a['nodes']:>5}  {router}"
        lines.append(_cut(line, WIDTH, wide))
    return lines


def _nodes_section(status: dict[str, Any], wide: bool) -> list[str]:
    """One row per node: desired and observed state, host, pid, restarts, counters."""
    eng = status.get("engine") or {}
    desired = eng.get("desired", {})
    stats = {
        k.split(":", 1)[1]: v
        for k, v in status.get("stats", {}).items()
        if not k.startswith("host:")
    }
    header = (
        f"{'NODE':<24} {'HOST':<8} {'WANT':<7} {'STATE':<12} {'PID':>7} {'RST':>3} "
        f"{'RECV':>7} {'DROP':>5} {'REJ':>4}"
    )
    lines = [header + ("  IMPLEMENTATION" if wide else "")]
    seen = set()
    for n in sorted(status["nodes"], key=lambda n: (n["host"] or "", n["node"])):
        seen.add(n["node"])
        lines.append(_row(n, desired.get(n["node"]), stats.get(n["node"], {}), wide))
    for name, d in sorted(desired.items()):
        if name not in seen:  # desired, but no host agent reports it
            row = {"node": name, "host": d["host"], "state": "UNKNOWN", "restarts": 0}
            lines.append(_row(row, d, {}, wide))
    return lines


def _failures_section(status: dict[str, Any], wide: bool) -> list[str]:
    """One line per node that failed: its last failure (an exit, a freeze, a component that
    did not load, with what it raised), or the newest exception in a callback it went on
    after, whichever came last."""
    stats = {k.split(":", 1)[1]: v for k, v in status.get("stats", {}).items()
             if k.startswith("node:")}  # fmt: skip
    lines = []
    for n in sorted(status["nodes"], key=lambda n: (n.get("host") or "", n["node"])):
        last = _last_failure(n, stats.get(n["node"], {}))
        if last is not None:
            at, text = last
            when = time.strftime("%H:%M:%S", time.localtime(at)) if at else "-"
            lines.append(_cut(f"{_cut(n['node'], 24, wide):<24} {when:<8} {text}", WIDTH, wide))
    return [f"{'NODE':<24} {'WHEN':<8} LAST FAILURE", *lines] if lines else []


def _last_failure(n: dict[str, Any], st: dict[str, Any]) -> tuple[float, str] | None:
    """(when, what) of a node's last failure: its host agent's record (``ListNodes``) or its
    own newest callback exception (``Stats``); None if it never failed."""
    found = []
    if n.get("reason") or n.get("failure"):
        f = _failure(n.get("failure"))
        text = failure.summary(f) if f else n["reason"]
        found.append((f.stamp if f else 0.0, text))
    f = _failure(st.get("failure"))
    if f is not None:
        errors = (st.get("counters") or {}).get("errors", 1)
        found.append((f.stamp, f"runs on after {errors} errors: {failure.summary(f)}"))
    return max(found, key=lambda x: x[0]) if found else None


def _failure(raw: Any) -> m.Failure | None:
    try:
        return msgspec.convert(raw, m.Failure) if raw else None
    except msgspec.ValidationError:
        return None
def refused_section(status: dict[str, Any], wide: bool = False) -> list[str]:
    """One row per source and reason of the samples the Context Monitor refused (its
    leader's counts; nothing when it refused none)."""
    monitors = [v for v in status.get("stats", {}).values() if v.get("role") == "monitor"]
    monitors.sort(key=lambda v: not (v.get("counters") or {}).get("leading"))
    rows = monitors[0].get("refused") or [] if monitors else []
    if not rows:
        return []
    lines = [f"{'REFUSED SAMPLES OF':<26} {'REASON':<13} {'COUNT':>7}  LAST"]
    for r in rows:
        line = (
            f"{_cut(r['source'], 26, wide):<26} {r['reason']:<13} {r['count']:>7}  "
            f"{' '.join(str(r.get('last', '')).split())}"
        )
        lines.append(_cut(line, WIDTH, wide))
    return lines


def _cut(text: str, width: int, wide: bool) -> str:
    """``text`` at most ``width`` characters (its end replaced by ``~``) unless ``wide``."""
    return text if wide or len(text) <= width else text[: width - 1] + "~"


def adaptation_lines(eng: dict[str, Any], wide: bool = False) -> list[str]:
    """The features operators forced (``rra select``) and the run-time conflicts in force,
    as the Run-time Resolution Engine holds them (nothing when there are none)."""
    lines = []
    forced = eng.get("forced") or {}
    if forced:
        lines += _field("forced", ", ".join(f"{f} {v}" for f, v in sorted(forced.items())), wide)
    for c in eng.get("conflicts") or []:
        rules = c.get("rules") or []
        wants = c.get("wants") or {}
        who = ", ".join(f"{r} wants {wants.get(r, '?')}" for r in rules)
        since = time.strftime("%H:%M:%S", time.localtime(c.get("since") or c.get("stamp", 0)))
        lines += _field("conflict", f"{c.get('target')}: {who} (since {since})", wide)
    return lines


def _row(n: dict[str, Any], want: dict[str, Any] | None, st: dict[str, Any], wide: bool) -> str:
    if want is None:
        role = st.get("role", "node")
        wanted = "engine" if role in ENGINE_ROLES else "-"
    else:
        wanted = "standby" if want.get("standby") else "run"
    pid = str(n.get("pid") or "-")
    recv, drop, rej = (
        str(st.get(k, 0)) if st else "-" for k in ("received", "dropped", "rejected")
    )
    line = (
        f"{_cut(n['node'], 24, wide):<24} {_cut(n['host'] or '-', 8, wide):<8} {wanted:<7} "
        f"{n['state']:<12} {pid:>7} {n.get('restarts', 0):>3} {recv:>7} {drop:>5} {rej:>4}"
    )
    return line + (f"  {n.get('implementation', '')}" if wide else "")


def run_status(args: argparse.Namespace) -> int:
    with connect_system(bus_from_args(args), args.system) as client:
        while True:
            status = gather(client)
            if not status["hosts"] and status["engine"] is None:
                raise RraError(
                    f"system {client.keys.system!r} stopped: no host agent or engine answers"
                )
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
    add_system_argument(p)
    p.add_argument("--log", metavar="FILE", help="print a saved events.jsonl (in time order)")
    p.add_argument("--json", action="store_true", help="one JSON object per line")
    p.add_argument(
        "--all",
        action="store_true",
        help="also the CV updates (parameters following a context value, e.g. every second)",
    )
    p.add_argument("--wide", action="store_true", help=f"long lines not wrapped at {WIDTH}")
    add_bus_arguments(p)


#: ``applied selection [...]``: the features of an applied adaptation (the Run-time
#: Resolution Engine's message), up to the step count.
_APPLIED = re.compile(r"^applied selection (\[.*?\])")
#: Plan steps that only hand new values to running nodes.
_PARAM_STEP = "set_params "


class EventFilter:
    """Which events ``rra events`` shows by default: all but the CV updates.

    A CV update is an applied adaptation that keeps the run-time selection and only sets
    parameters (a CV value following the context, e.g. MaxVel following the battery every
    second). Everything else is shown, event kinds this filter does not know included:
    swaps, starts and stops, operators' parameters, new selections, failures, warnings.
    ``selection``: the run-time selection when following starts (unknown: the first applied
    adaptation is shown)."""

    def __init__(self, selection: Iterable[str] | None = None) -> None:
        self.selection = frozenset(selection) if selection is not None else None

    def shows(self, ev: m.AdaptationEvent | m.NodeState) -> bool:
        return not self.is_cv_update(ev)

    def is_cv_update(self, ev: m.AdaptationEvent | m.NodeState) -> bool:
        if not isinstance(ev, m.AdaptationEvent) or ev.kind != "adaptation":
            return False
        match = _APPLIED.match(ev.message)
        if match is None or ev.outcome != "ok" or ev.level != "info":
            return False
        try:
            applied = frozenset(ast.literal_eval(match.group(1)))
        except (ValueError, SyntaxError, TypeError):
            return False
        previous, self.selection = self.selection, applied
        steps = [p for p in ev.plan if not p.startswith("note:")]
        return previous == applied and all(p.startswith(_PARAM_STEP) for p in steps)


def in_time_order(events: list[m.AdaptationEvent | m.NodeState]) -> list[Any]:
    """A saved log in time order. The file is appended to by several processes and in the
    order events reach its writer, not the order they happened: the Run-time Resolution
    Engine leader records the host agents' node states as they arrive over the bus (after
    its own adaptation event when a swap's node events queue behind it), a standby writes
    its own events too, and after a failover the new leader appends to the same file."""
    return sorted(events, key=lambda ev: ev.stamp)


def format_event(ev: m.AdaptationEvent | m.NodeState, *, wide: bool = True) -> str:
    """An event as text; lines wrapped at `WIDTH` columns unless ``wide``."""
    t = time.strftime("%H:%M:%S", time.localtime(ev.stamp)) + f".{int(ev.stamp % 1 * 1000):03d}"
    match ev:
        case m.NodeState():
            reason = failure.without_summary(ev.reason, ev.failure)
            why = f" ({reason})" if reason else ""
            head = f"{t} node  {ev.host}/{ev.node}: {ev.previous} -> {ev.state}{why}"
            lines = [(head, " " * 19)]
            if ev.failure is not None:  # what the node raised, where, and its log
                lines += [(f"    {x}", " " * 6) for x in failure.details(ev.failure)]
        case m.AdaptationEvent():
            cause = "; ".join(f"{c.rule}: {c.action}" for c in ev.cause)
            dur = " ".join(f"{k}={v * 1e3:.1f}ms" for k, v in ev.durations.items())
            lines = [(f"{t} {ev.level.upper():<7} {ev.kind}: {ev.message}", " " * 21)]
            if cause:
                lines.append((f"    cause: {cause}", " " * 11))
            lines += [(f"    - {step}", " " * 6) for step in ev.plan]
            if dur:
                lines.append((f"    durations: {dur}", " " * 15))
        case _:
            return repr(ev)
    if wide:
        return "\n".join(text for text, _ in lines)
    return "\n".join(
        "\n".join(textwrap.wrap(text, WIDTH, subsequent_indent=indent, break_on_hyphens=False))
        for text, indent in lines
    )


def run_events(args: argparse.Namespace) -> int:
    enc = msgspec.json.Encoder()
    shown = EventFilter()

    def show(ev: m.AdaptationEvent | m.NodeState) -> None:
        if args.all or shown.shows(ev):
            text = enc.encode(ev).decode() if args.json else format_event(ev, wide=args.wide)
            print(text, flush=True)

    if args.log:
        from rra_agent.engines.events import read_events

        try:
            events = read_events(args.log)
        except OSError as e:
            raise RraError(f"{args.log}: {e.strerror or e}") from None
        for ev in in_time_order(events):
            show(ev)
        return 0
    done = threading.Event()
    with connect_system(bus_from_args(args), args.system) as client:
        engine = _engine_status(client, 2.0)
        if engine is not None:
            shown.selection = frozenset(engine.get("selection", []))

        def on_event(sample: zenoh.Sample) -> None:
            try:
                ev = _EVT.decode(sample.payload.to_bytes())
            except (msgspec.DecodeError, msgspec.ValidationError):
                return
            show(ev)

        if not args.json:
            hidden = "" if args.all else " (CV updates hidden: --all shows them)"
            print(f"following system {client.keys.system!r}{hidden}; Ctrl-C to stop", flush=True)
        hosts: set[str] = set()
        lock = threading.Lock()

        def on_host(sample: zenoh.Sample) -> None:
            """The last host agent of the system gone: it stopped, and so does following."""
            host = str(sample.key_expr).rsplit("/", 1)[-1]
            with lock:
                if sample.kind == zenoh.SampleKind.PUT:
                    hosts.add(host)
                elif host in hosts:
                    hosts.discard(host)
                    if not hosts:
                        done.set()

        entities = [
            client.session.declare_subscriber(client.keys.events, on_event),
            client.session.liveliness().declare_subscriber(
                client.keys.host_alive_all, on_host, history=True
            ),
        ]
        try:
            done.wait()
        except KeyboardInterrupt:
            return 0
        finally:
            for entity in entities:
                entity.undeclare()
        if not args.json:
            print(f"system {client.keys.system!r} stopped: no host agent is left", flush=True)
    return 0


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
