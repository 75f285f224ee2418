"""Operators' overrides of run-time features (``rra select``): pure logic, no I/O.

An operator may *force* a run-time feature on or off; ``auto`` releases it. While a feature
is forced, the adaptation rules may not change it: their requests on it are refused (with
the reason), and whatever else they change is applied only as far as the forced features
keep their state. The feature model still holds: forcing a feature that is not a run-time
feature, that the deployment makes unavailable, or that the model forbids with the current
selection (including the other forced features) is refused with a one-line reason.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping, Sequence
from typing import Literal

from rra_agent.core.features import Request, apply_requests
from rra_agent.errors import RraError
from rra_agent.models.features import FeatureModel

#: What an operator asks for one feature.
Choice = Literal["on", "off", "auto"]
CHOICES: tuple[str, ...] = ("on", "off", "auto")


class OverrideError(RraError):
    """An override the feature model does not allow (the message is one line)."""


def requests_for(forced: Mapping[str, bool]) -> list[Request]:
    """The (de)activation requests that put every forced feature in its forced state."""
    return [("activate" if on else "deactivate", f) for f, on in sorted(forced.items())]


def holds(selection: Collection[str], forced: Mapping[str, bool]) -> bool:
    """Whether every forced feature has its forced state in ``selection``."""
    return all((f in selection) == on for f, on in forced.items())


def violated(selection: Collection[str], forced: Mapping[str, bool]) -> list[str]:
    """The forced features ``selection`` does not honour, as ``F (forced on|off)``."""
    return [
        f"{f} (forced {'on' if on else 'off'})"
        for f, on in sorted(forced.items())
        if (f in selection) != on
    ]


def change(
    fm: FeatureModel,
    deployment: Collection[str],
    selectable: Collection[str],
    selection: frozenset[str],
    forced: Mapping[str, bool],
    choices: Mapping[str, str],
) -> tuple[frozenset[str], dict[str, bool]]:
    """Apply an operator's ``choices`` (feature -> on | off | auto) to ``forced``.

    Returns the new run-time selection (the current one with the forced features in their
    forced state) and the new forced set; raises `OverrideError` (nothing changed) when a
    choice is unknown, names a feature that is not a selectable run-time feature, or cannot
    hold together with the feature model, the deployment and the other forced features.
    """
    new = dict(forced)
    for name, choice in choices.items():
        if choice not in CHOICES:
            raise OverrideError(f"{name}={choice}: expected on, off or auto")
        if name not in fm.features:
            raise OverrideError(f"{name}: no such feature in the feature model")
        if fm.binding.get(name) != "runtime":
            raise OverrideError(
                f"{name}: not a run-time feature (bound at deployment time); "
                "only run-time features can be forced"
            )
        if choice == "auto":
            new.pop(name, None)
            continue
        if choice == "on" and name not in selectable:
            raise OverrideError(
                f"{name}: cannot be forced on: it is not selectable with the deployment-time "
                f"selection"
            )
        new[name] = choice == "on"
    requests = requests_for(new)
    result, refused = apply_requests(fm, deployment, selection, requests)
    if refused:
        _, reason = refused[0]
        raise OverrideError(_one_line(reason))
    if not holds(result, new):
        raise OverrideError(
            "the forced features cannot hold together: "
            + ", ".join(violated(result, new))
            + " would be overturned by the others"
        )
    return result, new


def split(
    requests: Sequence[tuple[str, str]], forced: Mapping[str, bool]
) -> tuple[list[int], list[tuple[int, str]]]:
    """The indices of the rules' ``requests`` that may be applied, and the refused ones
    (index, reason): a request on a forced feature that would change it."""
    kept: list[int] = []
    refused: list[tuple[int, str]] = []
    for i, (kind, f) in enumerate(requests):
        on = forced.get(f)
        if on is not None and on != (kind == "activate"):
            state = "on" if on else "off"
            refused.append((i, f"{f} is forced {state} by an operator (rra select)"))
        else:
            kept.append(i)
    return kept, refused


def enforce(
    fm: FeatureModel,
    deployment: Collection[str],
    selection: frozenset[str],
    forced: Mapping[str, bool],
) -> frozenset[str] | None:
    """``selection`` with the forced features put back in their state (a rule's request on
    another feature may have changed them, e.g. by choosing an alternative), or None when
    that is impossible."""
    if holds(selection, forced):
        return selection
    result, refused = apply_requests(fm, deployment, selection, requests_for(forced))
    return None if refused or not holds(result, forced) else result


def _one_line(text: str) -> str:
    return " ".join(text.split())
