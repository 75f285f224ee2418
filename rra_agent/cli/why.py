"""``rra why [FEATURE|CV ...]``: why the running system's run-time features and CV values are
what they are, and what the rules can reach from here.

Asks the Adaptation Engine leader (`Explain`). For each feature or CV attribute named (none:
all, one line each): its state, when it got it, what put it there (the rule and action, the
measurement values it read and when they were computed; or an NFR, an operator, an
unavailable implementation, the default), and the rules that fire now wanting otherwise,
with why they do not prevail. Without names (or with ``--reachable``) it adds the run-time
configurations the rules can reach from the current one (a static search: the conditions'
measurements taken as free) and the features they can never select from here.
"""

from __future__ import annotations

import argparse
import textwrap
from typing import Any

import msgspec

from rra_agent.bus import messages as m
from rra_agent.bus.client import connect_system, engine_request
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.bus.why import cause_text, clock, overruled_text
from rra_agent.cli.common import WIDTH, add_system_argument, cut


def configure(p: argparse.ArgumentParser) -> None:
    add_system_argument(p)
    p.add_argument("names", nargs="*", metavar="FEATURE|CV", help="none: all, one line each")
    p.add_argument(
        "--reachable",
        action="store_true",
        help="also the configurations the rules can reach (always shown without names)",
    )
    p.add_argument("--json", action="store_true", help="the engine's answer as JSON")
    p.add_argument("--wide", action="store_true", help=f"lines not cut at {WIDTH} columns")
    add_bus_arguments(p)


def wrap(text: str, indent: str, wide: bool) -> list[str]:
    """``text`` on lines of at most `WIDTH` columns, continued under ``indent`` + 2."""
    if wide or len(text) <= WIDTH:
        return [text]
    return textwrap.wrap(text, WIDTH, subsequent_indent=indent + "  ", break_on_hyphens=False)


def summary_lines(why: list[m.Why], wide: bool = False) -> list[str]:
    """One line per feature or CV: name, state, since, what put it there; then each rule
    overruled now, indented."""
    width = max([len(w.target) for w in why] + [6])
    lines = [f"{'TARGET':<{width}} {'NOW':<6} {'SINCE':<12} WHY"]
    for w in why:
        since = clock(w.since) if w.since else "-"
        text = cause_text(w) + (f"; {w.detail}" if w.detail else "")
        lines.append(cut(f"{w.target:<{width}} {w.value:<6} {since:<12} {text}", WIDTH, wide))
        lines += [cut(f"  {overruled_text(o)}", WIDTH, wide) for o in w.overruled]
    return lines


def detail_lines(w: m.Why, wide: bool = False) -> list[str]:
    """Everything about one feature or CV, wrapped at `WIDTH` columns."""
    since = f" since {clock(w.since)}" if w.since else ""
    out = [f"{w.target} is {w.value}{since}"]
    if w.reason == "rule" and not w.by:
        out.append("  by a rule")
    for f in w.by:
        where = f" ({f.where})" if f.where else ""
        prefix = "after rule" if w.reason == "nfr" else "by rule"
        out += wrap(f"  {prefix} {f.rule}: {f.action}{where}", "  ", wide)
        for name, stamp in f.reads.items():
            value = repr(f.values[name]) if name in f.values else "?"
            origin = f"override by {f.overrides[name]}" if name in f.overrides else "computed"
            out.append(f"    reading {name} = {value} ({origin} {clock(stamp)})")
    if not w.by:
        out += wrap(f"  {cause_text(w)}", "  ", wide)
    if w.detail:
        out += wrap(f"  {w.detail}", "  ", wide)
    for o in w.overruled:
        where = f" ({o.where})" if o.where else ""
        wants = f", wants {o.wants}" if o.wants else ""
        out += wrap(f"  overruled {o.rule}: {o.action}{where}{wants}: {o.detail or o.why}",
                    "  ", wide)  # fmt: skip
    if not w.overruled:
        out.append("  no rule wants otherwise now")
    return out


def _state_text(state: list[str], common: set[str]) -> str:
    return ", ".join(f for f in state if f not in common) or "(none)"


def reachable_lines(r: dict[str, Any], wide: bool = False) -> list[str]:
    """What the rules can reach from the current configuration: a line per family of
    features that can change (its states, the current one starred), and what never is."""
    count = r.get("count", 1)
    more = "" if r.get("complete", True) else " at least (the search was cut short)"
    head = f"reachable   {count} run-time configuration{'s' if count != 1 else ''}{more} "
    lines = wrap(head + "from the current one (the rules' conditions taken as free)", "", wide)
    current = set(r.get("current", []))
    for fam in r.get("families", []):
        states = fam.get("states", [])
        common = set.intersection(*(set(s) for s in states)) if states else set()
        now = set(fam["features"]) & current
        shown = [("*" if set(s) == now else "") + _state_text(s, common) for s in states]
        lines += wrap(f"  {fam['features'][0]}: {' | '.join(shown)}", "  ", wide)
    if len(lines) == 1:
        lines.append("  nothing else: the rules keep the current configuration")
    never = r.get("never", [])
    if never:
        text = f"never       {', '.join(never)}: no rule can select them from here"
        lines += wrap(text, "           ", wide)
    return lines


def run(args: argparse.Namespace) -> int:
    reachable = args.reachable or not args.names
    request = m.Explain(targets=list(args.names), reachable=reachable)
    with connect_system(bus_from_args(args), args.system) as client:
        result = engine_request(client, "adaptation", request)
    if args.json:
        print(msgspec.json.encode(result).decode())
        return 0
    why = msgspec.convert(result.get("why", []), list[m.Why])
    if args.names:
        lines = [line for w in why for line in detail_lines(w, args.wide)]
    else:
        lines = summary_lines(why, args.wide)
    if reachable and "reachable" in result:
        lines += ["", *reachable_lines(result["reachable"], args.wide)]
    print("\n".join(lines))
    return 0
