"""Explanations as text: what changed a selection and what was overruled (`messages.Why`).

Shared by ``rra events``, ``rra why`` and the Rerun event log, so each says the same. The
changes one cause made go on one line: ``+HumanZone -NormalZone by SafetyZone:
activate_feature(HumanZone) reading Zone="near" (12:00:01.234)``, each overruled rule on a
line of its own under it: ``overruled Zone: activate_feature(NormalZone) (wants
NormalZone): rule SafetyZone, written later, wins (a run-time conflict)``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence

from rra_agent.bus import messages as m


def clock(stamp: float) -> str:
    """``12:00:01.234`` (local time)."""
    return time.strftime("%H:%M:%S", time.localtime(stamp)) + f".{int(stamp % 1 * 1000):03d}"


def value_text(value: object) -> str:
    """A measurement value as written in a rule: strings quoted, numbers short."""
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def reads_text(f: m.FiredRule) -> str:
    """``Zone="near" (12:00:01.234), BattLev=10 (override 12:00:00.998)``: what a rule
    read (an operator's override as such)."""
    return ", ".join(
        f"{n}={value_text(f.values[n]) if n in f.values else '?'} "
        f"({'override ' if n in f.overrides else ''}{clock(stamp)})"
        for n, stamp in f.reads.items()
    )


def target_text(w: m.Why) -> str:
    """``+HumanZone``, ``-NormalZone``, ``MaxSpeed=0.5``."""
    if w.kind == "cv":
        return f"{w.target}={w.value}"
    return ("+" if w.value == "on" else "-") + w.target


def cause_text(w: m.Why) -> str:
    """What made the change: the rules (with what they read), or what else."""
    rules = "; ".join(
        f"{f.rule}: {f.action}" + (f" reading {reads_text(f)}" if f.reads else "") for f in w.by
    )
    match w.reason:
        case "rule":
            return f"by {rules}" if rules else "by a rule"
        case "nfr":
            return "by an NFR" + (f", after {rules}" if rules else "")
        case "operator":
            return "by an operator"
        case "unavailable":
            return "as a feature is unavailable"
        case "default":
            return "the default since the start"
        case "resumed":
            return "as the system had it when the engine resumed"
    return "by the feature model"


def overruled_text(o: m.Overruled) -> str:
    wants = f" (wants {o.wants})" if o.wants else ""
    return f"overruled {o.rule}: {o.action}{wants}: {o.detail or o.why}"


def change_lines(why: Sequence[m.Why]) -> list[str]:
    """One line per cause (the changes it made, what it read, why it is so), then one line
    per rule it overruled, indented by two spaces."""
    groups: dict[tuple[object, ...], list[m.Why]] = {}
    for w in why:
        key = (w.reason, tuple((f.rule, f.action) for f in w.by), w.detail if not w.by else "")
        groups.setdefault(key, []).append(w)
    lines = []
    for members in groups.values():
        first = members[0]
        details = list(dict.fromkeys(w.detail for w in members if w.detail))
        line = " ".join(target_text(w) for w in members) + " " + cause_text(first)
        lines.append(line + "".join(f"; {d}" for d in details))
        seen: dict[tuple[str, str, str], m.Overruled] = {}
        for w in members:
            for o in w.overruled:
                seen.setdefault((o.rule, o.action, o.why), o)
        lines += [f"  {overruled_text(o)}" for o in seen.values()]
    return lines
