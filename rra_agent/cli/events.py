"""``rra events``: follow the adaptation events of a running system, or print a saved log."""

from __future__ import annotations

import argparse
import ast
import re
import textwrap
import time
from collections.abc import Iterable
from typing import Any

import msgspec
import zenoh

from rra_agent.bus import failure
from rra_agent.bus import messages as m
from rra_agent.bus.client import connect_system, engine_status
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.bus.why import change_lines
from rra_agent.cli.common import WIDTH, UntilStopped, add_system_argument
from rra_agent.errors import RraError

_EVT = m.Codec[m.EventMessage](m.EventMessage)


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
            if ev.why:  # what changed, by which rule, reading what; what it overruled
                lines += [(f"    {text}", " " * 8) for text in change_lines(ev.why)]
            elif cause:
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
    stops = UntilStopped()
    with connect_system(bus_from_args(args), args.system) as client:
        engine = engine_status(client, 2.0)
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
        entities: list[Any] = [client.session.declare_subscriber(client.keys.events, on_event)]
        return stops.follow(client.session, client.keys, entities, args.json)
