"""The Rerun recording of a what-if replay (``rra replay RUN --package EDITED``).

Both sides of the comparison on one timeline, ``run_time`` (seconds since the run began):

    /recorded/features/<feature>   StateChange ``selected`` / ``not selected``, on change
    /edited/features/<feature>     the same, as the edited models decided
    /recorded/cv/<attribute>       Scalars, the CV values the run decided
    /edited/cv/<attribute>         Scalars, the edited models' values
    /context/<measurement>         Scalars (numbers, booleans as 0/1) or StateChange (text):
                                   the measurements the evaluations read
    /differences                   TextLog: each moment where the two sides differ

The blueprint puts the recorded side on the left and the edited side on the right (features
as state lanes above the CV values), the context and the differences below. Plain data in,
a file out: `save` imports rerun only when called.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

TIMELINE = "run_time"
SIDES = ("recorded", "edited")


@dataclass
class Side:
    """One side's decisions at each evaluation (times shared by both sides)."""

    selections: Sequence[frozenset[str]] = ()
    cv: Sequence[Mapping[str, float]] = ()


@dataclass
class WhatIfData:
    title: str
    times: Sequence[float]
    features: Sequence[str]
    recorded: Side
    edited: Side
    context: Mapping[str, Sequence[tuple[float, Any]]] = field(default_factory=dict)
    #: (time, line) of each difference.
    differences: Sequence[tuple[float, str]] = ()


def save(path: Path, data: WhatIfData) -> Path:
    """Write the recording (and its blueprint) to ``path``."""
    import numpy as np
    import rerun as rr

    rec = rr.RecordingStream("rra-whatif", recording_id=data.title)
    rec.set_log_time_enabled(False)
    rec.save(path, default_blueprint=blueprint(data))
    part = rr.escape_entity_path_part
    times = np.asarray(data.times, dtype=np.float64)
    for side_name, side in zip(SIDES, (data.recorded, data.edited), strict=True):
        _features(rec, rr, f"/{side_name}/features", data, side, part)
        keys = sorted({k for cv in side.cv for k in cv})
        for key in keys:
            values = np.asarray([cv.get(key, np.nan) for cv in side.cv], dtype=np.float64)
            rec.send_columns(f"/{side_name}/cv/{part(key)}",
                             indexes=[rr.TimeColumn(TIMELINE, duration=times)],
                             columns=rr.Scalars.columns(scalars=values))  # fmt: skip
    _context(rec, rr, np, data, part)
    for t, line in data.differences:
        rec.set_time(TIMELINE, duration=t)
        rec.log("/differences", rr.TextLog(line, level=rr.TextLogLevel.WARN))
    rec.flush()
    rec.disconnect()
    return path


def _features(rec: Any, rr: Any, base: str, data: WhatIfData, side: Side, part: Any) -> None:
    for feature in data.features:
        last: bool | None = None
        for t, selection in zip(data.times, side.selections, strict=True):
            on = feature in selection
            if on != last:
                last = on
                rec.set_time(TIMELINE, duration=t)
                rec.log(f"{base}/{part(feature)}",
                        rr.StateChange(state="selected" if on else "not selected"))  # fmt: skip


def _context(rec: Any, rr: Any, np: Any, data: WhatIfData, part: Any) -> None:
    for name, series in data.context.items():
        path = f"/context/{part(name)}"
        if series and isinstance(series[0][1], str):
            for t, value in series:
                rec.set_time(TIMELINE, duration=t)
                rec.log(path, rr.StateChange(state=value))
            continue
        ts = np.asarray([t for t, _ in series], dtype=np.float64)
        vs = np.asarray([float(v) for _, v in series], dtype=np.float64)
        rec.send_columns(path, indexes=[rr.TimeColumn(TIMELINE, duration=ts)],
                         columns=rr.Scalars.columns(scalars=vs))  # fmt: skip


def blueprint(data: WhatIfData) -> Any:
    import rerun as rr
    import rerun.blueprint as rrb

    whole = rrb.TimeAxis(view_range=rr.TimeRange(
        start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite()))  # fmt: skip
    everything = rrb.VisibleTimeRanges(timeline=TIMELINE, start=rrb.TimeRangeBoundary.infinite(),
                                       end=rrb.TimeRangeBoundary.infinite())  # fmt: skip

    has_cv = any(cv for side in (data.recorded, data.edited) for cv in side.cv)

    def column(side: str, title: str) -> Any:
        features = rrb.StateTimelineView(name=f"{title}: features", origin=f"/{side}/features",
                                         time_ranges=everything)  # fmt: skip
        if not has_cv:
            return features
        return rrb.Vertical(
            features,
            rrb.TimeSeriesView(name=f"{title}: CV values", origin=f"/{side}/cv", axis_x=whole),
            row_shares=[3, 2],
        )

    numeric = [n for n, s in data.context.items() if not (s and isinstance(s[0][1], str))]
    bottom = [
        rrb.TimeSeriesView(name="Context", origin="/context", axis_x=whole,
                           contents=[f"/context/{rr.escape_entity_path_part(n)}"
                                     for n in numeric] or ["/context/**"]),
        rrb.TextLogView(name="Where the decisions differ", origin="/differences"),
    ]  # fmt: skip
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(column("recorded", "Recorded"), column("edited", "Edited")),
            rrb.Horizontal(*bottom),
            row_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE),
        auto_layout=False,
        auto_views=False,
    )
