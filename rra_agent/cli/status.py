"""``rra status`` and ``rra events``: look at a running system from another terminal.

``rra status`` asks the resolution engine for the current run-time selection and CV values,
and every host agent for its nodes (host, state, pid, implementation, active flag, restarts);
the Context Monitor for every measurement's current value, age and source (an operator's
override says so); ``--reachable`` adds the configurations the rules can reach (``rra
why``); ``--watch S`` redraws it every S seconds; the samples the Context Monitor refused are
listed per source and reason at the end. ``rra events`` follows the adaptation events and
node-state transitions live (or prints a saved ``events.jsonl`` with ``--log``).
"""

from __future__ import annotations

import argparse
import sys
import textwrap
import time
from typing import Any

import msgspec

from rra_agent import _compat
from rra_agent.bus import failure
from rra_agent.bus import messages as m
from rra_agent.bus.client import connect_system, engine_request, gather
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.bus.why import value_text
from rra_agent.cli.common import WIDTH, add_system_argument, cut
from rra_agent.errors import RraError

_EVT = m.Codec[m.EventMessage](m.EventMessage)


#: Engine roles (a node with one of these roles is an engine replica).
ENGINE_ROLES = ("monitor", "adaptation", "resolution")


def configure_status(p: argparse.ArgumentParser) -> None:
    add_system_argument(p)
    p.add_argument("--watch", type=float, metavar="S", help="refresh every S seconds")
    p.add_argument("--json", action="store_true", help="machine-readable output (everything)")
    p.add_argument(
        "--reachable",
        action="store_true",
        help="also the run-time configurations the rules can reach from the current one",
    )
    p.add_argument(
        "--wide",
        action="store_true",
        help=f"the full table (each node's implementation), not cut to {WIDTH} columns",
    )
    add_bus_arguments(p)


# ---- rendering: one function per section ---------------------------------------------------
def render(status: dict[str, Any], *, wide: bool = False) -> str:
    """``rra status`` as text: the system, its hosts, its nodes; at most `WIDTH` columns
    unless ``wide``."""
    sections = [
        _system_section(status.get("engine"), wide),
        context_section(status, wide),
        _hosts_section(status, wide),
        _nodes_section(status, wide),
        _failures_section(status, wide),
        refused_section(status, wide),
        reachable_section(status, wide),
        ros2_section(status, wide),
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
    lines += reflex_lines(eng, wide)
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


def context_section(status: dict[str, Any], wide: bool, now: float | None = None) -> list[str]:
    """One row per measurement of the model: its current value, how old it is (since the
    monitor computed it), and where it comes from (its source interfaces and how long ago
    their sample was sent; what a derived one follows; an operator's override)."""
    rows = status.get("context")
    if rows is None:
        return ["context     no Context Monitor answers"] if status.get("engine") else []
    now = time.time() if now is None else now
    lines = [f"{'MEASUREMENT':<20} {'VALUE':<20} {'AGE':>6}  FROM"]
    for r in rows:
        if "value" in r:
            value = value_text(r["value"]) + (f" {r['unit']}" if r.get("unit") else "")
            age = _age(now - float(r.get("stamp", now)))
        else:
            value, age = "-", "-"
        origin = r.get("from", "")
        if r.get("override"):
            value += " OVERRIDE"
            left = max(0.0, float(r.get("until", now)) - now)
            origin = f"override by {r['override']}, {_age(left)} left"
        elif r.get("sources"):
            sent = max(float(t) for t in r["sources"].values())
            origin += f" (sent {_age(now - sent)} ago)"
        line = f"{cut(r['name'], 20, wide):<20} {cut(value, 20, wide):<20} {age:>6}  {origin}"
        lines.append(cut(line, WIDTH, wide))
    return lines


def _age(seconds: float) -> str:
    """``0.3s``, ``42s``, ``5m``, ``2h``: how long, in at most six columns."""
    seconds = max(0.0, seconds)
    if seconds < 10:
        return f"{seconds:.1f}s"
    if seconds < 600:
        return f"{seconds:.0f}s"
    return f"{seconds / 60:.0f}m" if seconds < 36000 else f"{seconds / 3600:.0f}h"


def reachable_section(status: dict[str, Any], wide: bool) -> list[str]:
    """``--reachable``: what the rules can reach from here (`rra why`'s section)."""
    from rra_agent.cli.why import reachable_lines

    found = status.get("reachable")
    return reachable_lines(found, wide) if isinstance(found, dict) else []


def _hosts_section(status: dict[str, Any], wide: bool) -> list[str]:
    """One line per host agent: up or not, its router's endpoints, its live nodes (and the
    CPU latency its host keeps, where the agent holds one)."""
    agents = status.get("host_agents", [])
    if not agents:
        return ["hosts       -"]
    lines = [f"{'HOST':<16} {'AGENT':<11} {'NODES':>5}  ROUTER"]
    for a in agents:
        endpoints = [f"listens {ep}" for ep in a["listen"]] + [f"links {ep}" for ep in a["connect"]]
        if a.get("cpu_latency_us") is not None:
            endpoints.append(f"CPU latency {a['cpu_latency_us']} us")
        router = ", ".join(endpoints) or "-"
        line = f"{cut(a['host'], 16, wide):<16} {a['state']:<11} {a['nodes']:>5}  {router}"
        lines.append(cut(line, WIDTH, wide))
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
            lines.append(cut(f"{cut(n['node'], 24, wide):<24} {when:<8} {text}", WIDTH, wide))
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
            f"{cut(r['source'], 26, wide):<26} {r['reason']:<13} {r['count']:>7}  "
            f"{' '.join(str(r.get('last', '')).split())}"
        )
        lines.append(cut(line, WIDTH, wide))
    return lines


def ros2_section(status: dict[str, Any], wide: bool = False) -> list[str]:
    """The ROS 2 graph of the system's domain (a package with ``ros2:``): each node and its
    publishers, subscriptions, services and clients, one line each."""
    graph = status.get("ros2")
    if not graph:
        return []
    from rra_agent.ros2.graph import graph_lines

    return graph_lines(graph, 10_000 if wide else WIDTH)


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


def reflex_lines(eng: dict[str, Any], wide: bool = False) -> list[str]:
    """The reflexes the engines installed (docs/architecture.md, Reflexes): the rule, the
    nodes that switch by themselves, the change, and whether it fired and awaits the
    engines' confirmation; nothing when none is installed."""
    lines = []
    for r in (eng.get("reflexes") or {}).get("installed") or []:
        before, after = set(r.get("before") or []), set(r.get("features") or [])
        change = [f"+{f}" for f in sorted(after - before)]
        change += [f"-{f}" for f in sorted(before - after)]
        fired = r.get("fired") or 0.0
        when = time.strftime("%H:%M:%S", time.localtime(fired)) if fired else ""
        state = f"fired {when}, awaiting confirmation" if fired else "armed"
        nodes = ", ".join(r.get("nodes") or [])
        lines += _field("reflex", f"{r['rule']} in {nodes}: {', '.join(change)} ({state})", wide)
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
        f"{cut(n['node'], 24, wide):<24} {cut(n['host'] or '-', 8, wide):<8} {wanted:<7} "
        f"{n['state']:<12} {pid:>7} {n.get('restarts', 0):>3} {recv:>7} {drop:>5} {rej:>4}"
    )
    return line + (f"  {n.get('implementation', '')}" if wide else "")


def redraw(*, first: bool) -> None:
    """Before each ``--watch`` refresh: on a terminal, clear the screen (escape codes); into a
    pipe or a file, none: a blank line and the time between refreshes."""
    if sys.stdout.isatty():
        print("\033[2J\033[H", end="")
    elif not first:
        print(f"\n-- {time.strftime('%H:%M:%S')}", flush=True)


def run_status(args: argparse.Namespace) -> int:
    with connect_system(bus_from_args(args), args.system) as client:
        first = True
        while True:
            status = gather(client)
            if not status["hosts"] and status["engine"] is None:
                raise RraError(
                    f"system {client.keys.system!r} stopped: no host agent or engine answers"
                )
            if args.reachable:
                request = m.Explain(reachable=True)
                status["reachable"] = engine_request(client, "adaptation", request).get(
                    "reachable"
                )
            if args.json:
                print(msgspec.json.encode(status).decode(), flush=True)
            else:
                if args.watch:
                    redraw(first=first)
                print(render(status, wide=args.wide), flush=True)
            if not args.watch:
                return 0
            first = False
            time.sleep(args.watch)




__getattr__ = _compat.renamed(__name__)  # old names, for one release (docs/api.md)
