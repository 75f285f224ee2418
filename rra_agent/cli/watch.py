"""``rra watch [MEASUREMENT ...]``: the context as the rules see it, live.

Prints the current value of each measurement named (none: all, derived ones included:
``reachable:``, ``available:``), then a line each time one changes: when it was computed,
its value, and the send time of the source sample it came from (an operator's override says
so, who set it and until when). It ends on Ctrl-C or when the system stops (its last host
agent is gone). Values come from the Context Monitor leader (``rra/<system>/ctx/*``); a
sample that is malformed, names no measurement of the model, or claims an override without
the monitor leader's fence is not shown.
"""

from __future__ import annotations

import argparse
import difflib
import threading
from typing import Any

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, connect_system, context
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.bus.counters import Refused, receive
from rra_agent.bus.why import clock, value_text
from rra_agent.cli.common import WIDTH, UntilStopped, add_system_argument, cut
from rra_agent.engines.leaders import LeaderWatch
from rra_agent.errors import RraError

_CTX = m.Codec[m.CtxMessage](m.CtxMessage)


def configure(p: argparse.ArgumentParser) -> None:
    add_system_argument(p)
    p.add_argument("names", nargs="*", metavar="MEASUREMENT", help="none: every measurement")
    p.add_argument("--json", action="store_true", help="one JSON Measurement per line")
    p.add_argument("--wide", action="store_true", help=f"lines not cut at {WIDTH} columns")
    add_bus_arguments(p)


def line(msg: m.Measurement, unit: str = "") -> str:
    """``12:00:01.234 BattLev = 42.5 % (robot_driver.battery sent 12:00:01.230)``."""
    head = f"{clock(msg.stamp)} {msg.name} = {value_text(msg.value)}" + (f" {unit}" if unit else "")
    if msg.override:
        return f"{head} OVERRIDE by {msg.override} until {clock(msg.until)}"
    sent = ", ".join(f"{src} sent {clock(t)}" for src, t in sorted(msg.sources.items()))
    return f"{head} ({sent})" if sent else head


def chosen(declared: list[dict[str, Any]], names: list[str], system: str) -> list[str]:
    """The measurements to watch (all if none named); RraError naming an unknown one."""
    known = [d["name"] for d in declared]
    for name in names:
        if name not in known:
            close = difflib.get_close_matches(name, known, n=1)
            hint = f" (did you mean {close[0]}?)" if close else f"; it has: {', '.join(known)}"
            raise RraError(f"system {system!r} has no measurement {name!r}{hint}")
    return names or known


class Watcher:
    """Prints a line per change of the watched measurements (Zenoh thread)."""

    def __init__(self, client: BusClient, names: list[str], units: dict[str, str], args) -> None:
        self.names, self.units, self.args = set(names), units, args
        self.last: dict[str, tuple[Any, str]] = {}
        self.lock = threading.Lock()
        self.monitor = LeaderWatch(client.session, client.keys, "monitor")
        self.enc = msgspec.json.Encoder()

    def show(self, msg: m.Measurement, *, trusted: bool = False) -> None:
        """Print ``msg`` if it changes its measurement (``trusted``: the monitor leader's
        own answer, which needs no fence)."""
        if msg.name not in self.names:
            return
        if msg.override and not trusted and not self.monitor.holds(msg.fence):
            return  # a forged override: the rules refuse it too
        with self.lock:
            key = (msg.value, msg.override)
            if self.last.get(msg.name) == key:
                return  # re-sent unchanged
            self.last[msg.name] = key
            if self.args.json:
                print(self.enc.encode(msg).decode(), flush=True)
            else:
                text = line(msg, self.units.get(msg.name, ""))
                print(cut(text, WIDTH, self.args.wide), flush=True)

    def on_sample(self, sample: zenoh.Sample) -> None:
        msg = receive(sample.payload, "ctx", _CTX)
        if not isinstance(msg, Refused):
            self.show(msg)


def _now(entry: dict[str, Any]) -> m.Measurement | None:
    """A status entry's newest value as a Measurement (None: no value yet)."""
    if "value" not in entry:
        return None
    return m.Measurement(
        name=entry["name"],
        value=entry["value"],
        stamp=float(entry.get("stamp", 0.0)),
        sources=dict(entry.get("sources") or {}),
        override=str(entry.get("override", "")),
        until=float(entry.get("until", 0.0)),
    )


def run(args: argparse.Namespace) -> int:
    stops = UntilStopped()
    with connect_system(bus_from_args(args), args.system) as client:
        declared = context(client, 5.0)
        if declared is None:
            raise RraError(f"no Context Monitor answers for system {client.keys.system!r}")
        names = chosen(declared, list(args.names), client.keys.system)
        units = {d["name"]: d.get("unit", "") for d in declared}
        watcher = Watcher(client, names, units, args)
        if not args.json:
            print(f"watching {', '.join(names)} of system {client.keys.system!r}; Ctrl-C to "
                  "stop", flush=True)  # fmt: skip
        session = client.session
        entities: list[Any] = [watcher.monitor]
        try:
            entities.append(session.declare_subscriber(client.keys.ctx_all, watcher.on_sample))
            for entry in declared:  # the current values, then each change
                msg = _now(entry)
                if msg is not None:
                    watcher.show(msg, trusted=True)
        except BaseException:
            for entity in entities:
                entity.undeclare()
            raise
        return stops.follow(session, client.keys, entities, args.json)
