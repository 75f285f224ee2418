"""Continuous Variability (paper Sec. II): the CV attributes of a feature model with their
bounds and the NFRs that constrain them, and how a value is clamped into both.

A CV value is clamped into its attribute's ``lower``/``upper`` bounds, then into every NFR
of a selected feature that ``constrains`` it (``min`` raises, ``max`` lowers, the ``max``
applied last). The Adaptation Engine clamps what its rules set; the Run-time Resolution
Engine clamps what it receives. Pure."""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass

from rra_agent.models.features import FeatureModel


@dataclass(slots=True)
class CvAttribute:
    """A CV attribute: its key (name, or feature.name when ambiguous), bounds, NFRs."""

    key: str
    feature: str
    attribute: str
    lower: float | None
    upper: float | None
    nfr_min: list[tuple[str, float]]
    nfr_max: list[tuple[str, float]]
    initial: float | None


def cv_table(fm: FeatureModel) -> list[CvAttribute]:
    """Every CV attribute with its bounds and the NFRs that constrain it."""
    found = [(fname, a) for fname, f in fm.features.items() for a in f.attributes if a.kind == "cv"]
    counts: dict[str, int] = {}
    for _, a in found:
        counts[a.name] = counts.get(a.name, 0) + 1
    out = []
    for fname, a in found:
        key = a.name if counts[a.name] == 1 else f"{fname}.{a.name}"
        nfrs = [
            (owner, n.tag, n.rra_value)
            for owner, f in fm.features.items()
            for n in f.attributes
            if n.kind == "nfr" and n.constrains in (a.name, f"{fname}.{a.name}")
            and isinstance(n.rra_value, int | float) and not isinstance(n.rra_value, bool)
        ]  # fmt: skip
        initial = a.rra_value
        if not isinstance(initial, int | float) or isinstance(initial, bool):
            initial = a.lower if a.lower is not None else a.upper
        out.append(
            CvAttribute(
                key=key,
                feature=fname,
                attribute=a.name,
                lower=a.lower,
                upper=a.upper,
                nfr_min=[(o, float(v)) for o, t, v in nfrs if t == "min"],  # type: ignore[arg-type]
                nfr_max=[(o, float(v)) for o, t, v in nfrs if t == "max"],  # type: ignore[arg-type]
                initial=None if initial is None else float(initial),
            )
        )
    return out


def clamp_cv(
    fm: FeatureModel, active: Collection[str], values: Mapping[str, float]
) -> tuple[dict[str, float], list[str]]:
    """CV values clamped into their attributes' bounds and the NFRs of the ``active``
    features (as the engine clamps its own), and the names that are no CV attribute."""
    table = {c.key: c for c in cv_table(fm)}
    active_set = frozenset(active)
    out: dict[str, float] = {}
    unknown = []
    for name, value in values.items():
        cv = table.get(name)
        if cv is None or isinstance(value, bool) or not isinstance(value, int | float):
            unknown.append(name)
            continue
        if value != value:  # NaN
            unknown.append(name)
            continue
        clamped = clamp(cv, float(value), active_set)
        if clamped is not None:
            out[name] = clamped
    return out, unknown


def clamp(cv: CvAttribute, value: float | None, active: frozenset[str]) -> float | None:
    """A CV value clamped into its bounds, then into the NFRs of the selected features."""
    if value is None:
        return None
    if cv.lower is not None and value < cv.lower:
        value = cv.lower
    if cv.upper is not None and value > cv.upper:
        value = cv.upper
    for owner, limit in cv.nfr_min:
        if owner in active and value < limit:
            value = limit
    for owner, limit in cv.nfr_max:
        if owner in active and value > limit:
            value = limit
    return value


def limiting(
    cv: CvAttribute, value: float | None, active: frozenset[str]
) -> tuple[str, str, float] | None:
    """What set the clamped value of ``value`` (as `clamp` clamps it): ``("lower" | "upper",
    "", bound)``, ``("min" | "max", NFR owner, limit)``, or None when nothing moved it."""
    if value is None:
        return None
    last: tuple[str, str, float] | None = None
    if cv.lower is not None and value < cv.lower:
        value, last = cv.lower, ("lower", "", cv.lower)
    if cv.upper is not None and value > cv.upper:
        value, last = cv.upper, ("upper", "", cv.upper)
    for owner, limit in cv.nfr_min:
        if owner in active and value < limit:
            value, last = limit, ("min", owner, limit)
    for owner, limit in cv.nfr_max:
        if owner in active and value > limit:
            value, last = limit, ("max", owner, limit)
    return last
