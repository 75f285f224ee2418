"""The Rerun views of a recording: a blueprint made from the system package.

``rra up --rerun ...`` (`rra_agent.viz.recording.attach_blueprint`), before any process logs,
derives a `Layout` from the package (what is measured, which run-time features can change,
which Continuous Variability attributes and NFR limits exist, which simulated world runs),
passes the limits and choices to the processes (`describe`) and has a child process `send`
the blueprint built from it with the recording's application id, so the viewer opens every
recording of the system with the same designed views instead of guessing a grid:

- a system that runs the quadcopter simulator: the 3D vehicle (``/world``: body, rotors,
  thrust arrows, trajectory) and the adaptation events on the left; on the right the altitude
  against its target, the motor currents and measured speeds, the context measurements (the
  working motors) next to the selected run-time features (the controller), and the phase
  timings of each adaptation;
- a system that runs the object-storing robot: the 2D floor map (``/map``: rooms, corridor,
  doors, racks, the robot and its path) and the events on the left; on the right one plot per
  numeric measurement (battery, obstacle distance), the string measurements (semantic
  location, material) and the selected run-time features (radio channel, environment...) as
  state lanes, each CV attribute against the NFR limits that constrain it (MaxVel against
  VelocityLimit), and the phase timings;
- any other system: the same right-hand column and the events.

The time panel opens on ``sim_time`` (simulation time since the run started; see
`rra_agent.viz.rerun_log`), not wall time.

`Layout` is plain data (no rerun import); `build` imports rerun.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rra_agent.viz.rerun_log import SIM, RerunConfig

if TYPE_CHECKING:
    from rra_agent.models.features import Feature
    from rra_agent.package.contents import SystemPackage

VEHICLE_SIMULATOR = "rra_agent.sim.nodes.VehicleSimulator"
ROBOT_DRIVER = "rra_agent.nodes.object_storing.RobotDriver"
BLUEPRINT_FILE = "blueprint.rrd"


@dataclass(frozen=True)
class Layout:
    """What a system's recording holds, as far as the views are concerned."""

    system: str
    #: Numeric measurements (``/context/<name>`` time series), with their units.
    measurements: tuple[tuple[str, str], ...] = ()
    #: String measurements (``/context/<name>`` state lanes).
    text_measurements: tuple[str, ...] = ()
    #: Run-time choices: (parent feature, the leaves of its group that may be selected);
    #: the logger draws ``/choice/<parent>`` as a state lane naming the selected one.
    choices: tuple[tuple[str, tuple[str, ...]], ...] = ()
    #: Continuous Variability attributes (``/cv/<name>``) with their units.
    cv: tuple[tuple[str, str], ...] = ()
    #: NFR limits: (name, feature whose selection activates it, value, attribute it constrains).
    limits: tuple[tuple[str, str, float, str], ...] = ()
    vehicle: bool = False
    floor_map: bool = False


def _walk(feature: Feature) -> Iterator[Feature]:
    yield feature
    for group in feature.groups:
        for child in group.children:
            yield from _walk(child)


def layout_of(package: SystemPackage) -> Layout:
    """The `Layout` of a loaded package."""
    fm = package.features
    runtime = set(fm.runtime_features())
    features = list(_walk(fm.root))
    # A choice: the leaves of a non-mandatory group that may be selected at run time
    # (e.g. the radio channels).
    choices = []
    for f in features:
        for g in f.groups:
            leaves = tuple(c.name for c in g.children if c.name in runtime and not c.groups)
            if g.kind != "mandatory" and leaves:
                choices.append((f.name, leaves))
    cv: list[tuple[str, str]] = []
    limits: list[tuple[str, str, float, str]] = []
    for f in features:
        for a in f.attributes:
            v = a.value
            if not isinstance(v, dict):
                continue
            if v.get("kind") == "cv":
                cv.append((a.name, str(v.get("unit", ""))))
            elif v.get("kind") == "nfr" and isinstance(v.get("value"), int | float):
                limits.append((a.name, f.name, float(v["value"]), str(v.get("constrains", ""))))
    numeric = tuple(
        (m.name, m.unit or "") for m in package.measurements.measurements if m.type != "str"
    )
    text = tuple(m.name for m in package.measurements.measurements if m.type == "str")
    impls = [i for c in package.system.components for i in c.implementations_all]
    names = {i if isinstance(i, str) else " ".join(i.command) for i in impls}  # a Command
    return Layout(
        system=package.system.system,
        measurements=numeric,
        text_measurements=text,
        choices=tuple(choices),
        cv=tuple(cv),
        limits=tuple(limits),
        vehicle=VEHICLE_SIMULATOR in names,
        floor_map=ROBOT_DRIVER in names,
    )


def _unit(name: str, unit: str) -> str:
    return f"{name} ({unit})" if unit else name


def build(layout: Layout) -> Any:
    """The ``rerun.blueprint.Blueprint`` of ``layout``: the vehicle or floor map above the
    adaptation events on the left, the plots and state lanes on the right."""
    import rerun.blueprint as rrb

    views = _Views(layout)
    right = views.right()
    # Room for the state lanes (one per text measurement and choice, ~35 px each).
    shares = [3.0 if isinstance(v, rrb.StateTimelineView) else 2.0 for v in right]
    if layout.vehicle:
        shares[0] = 3.0  # the altitude
    # The phases' legend has six entries (decide, deliver, plan, switch, execute, total): at
    # a share of 2 of a 1000 px window it was cut after the fifth, hiding "total".
    shares[-1] = 3.0
    return rrb.Blueprint(
        rrb.Horizontal(views.left(), rrb.Vertical(*right, row_shares=shares), column_shares=[2, 3]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=SIM),
        auto_layout=False,
        auto_views=False,
    )


class _Views:
    """The views of `build`, one method each (rerun imported here, not with this module)."""

    def __init__(self, layout: Layout) -> None:
        import rerun as rr
        import rerun.blueprint as rrb

        self.layout, self.rr, self.rrb = layout, rr, rrb
        self.whole = rrb.TimeAxis(  # the whole run, not a window around the time cursor
            view_range=rr.TimeRange(
                start=rrb.TimeRangeBoundary.infinite(), end=rrb.TimeRangeBoundary.infinite()
            )
        )

    def part(self, name: str) -> str:
        return str(self.rr.escape_entity_path_part(name))

    def plot(self, **kw: Any) -> Any:
        return self.rrb.TimeSeriesView(axis_x=self.whole, **kw)

    def ctx(self, name: str) -> str:
        return f"/context/{self.part(name)}"

    def right(self) -> list[Any]:
        """The right column, top to bottom: the vehicle's plots, the measurements and state
        lanes, the CV values against their limits, the adaptation phases."""
        layout, rrb = self.layout, self.rrb
        right = self.vehicle() if layout.vehicle else []
        plots = [
            self.plot(name=_unit(n, u), origin=self.ctx(n), contents=[self.ctx(n)])
            for n, u in layout.measurements
        ]
        lanes = self.lanes()
        if layout.vehicle:  # few measurements: the working motors beside the controller
            right.append(rrb.Horizontal(*plots, *lanes))
        else:
            if plots:
                right.append(rrb.Horizontal(*plots))
            right.extend(lanes)
        right.extend(self.cv())
        right.append(self.plot(name="Adaptation phases (ms)", origin="/timing"))
        return right

    def vehicle(self) -> list[Any]:
        """The altitude against its target, the motors' currents and speeds."""
        altitude = ["/vehicle/altitude", "/vehicle/altitude_target", "/vehicle/injections"]
        return [
            self.plot(name="Altitude against its target (m)", origin="/vehicle", contents=altitude),
            self.rrb.Horizontal(
                self.plot(name="Motor currents (A)", origin="/vehicle/motors/current"),
                self.plot(name="Motor speeds (rad/s)", origin="/vehicle/motors/measured_speed"),
            ),
        ]

    def lanes(self) -> list[Any]:
        """One state timeline of the text measurements, the choices and the faults injected
        (none if there is nothing of the kind)."""
        layout, rrb = self.layout, self.rrb
        if not (layout.text_measurements or layout.choices or layout.vehicle):
            return []
        groups = [group for group, _ in layout.choices]
        title = "Selected " + ", ".join(groups)
        if layout.text_measurements:
            title = ", ".join(layout.text_measurements) + " and s" + title[1:]
        if layout.vehicle:  # the faults the simulator was given (`Logger.injection`)
            title = f"{title} and faults injected" if groups else "Faults injected"
        contents = [
            *(self.ctx(n) for n in layout.text_measurements),
            *(f"/choice/{self.part(group)}" for group in groups),
            *(["/injections"] if layout.vehicle else []),
        ]
        every = rrb.VisibleTimeRanges(  # every state of the run
            timeline=SIM,
            start=rrb.TimeRangeBoundary.infinite(),
            end=rrb.TimeRangeBoundary.infinite(),
        )
        return [rrb.StateTimelineView(name=title, origin="/", time_ranges=every, contents=contents)]

    def cv(self) -> list[Any]:
        """A plot per context variable, against the limits set on it."""
        out = []
        for name, unit in self.layout.cv:
            against = [lim for lim in self.layout.limits if lim[3] == name]
            title = name + "".join(f" against {lim[0]}" for lim in against)
            contents = [f"/cv/{self.part(name)}", *(f"/cv/{self.part(lim[0])}" for lim in against)]
            out.append(self.plot(name=_unit(title, unit), origin="/cv", contents=contents))
        return out

    def left(self) -> Any:
        """The adaptation events, under the vehicle or the floor map where there is one."""
        rrb = self.rrb
        events = rrb.TextLogView(
            name="Adaptation events",
            origin="/",
            contents=["/events", "/rules"],
            columns=rrb.TextLogColumns(
                timeline_columns=[SIM], text_log_columns=["loglevel", "body"]
            ),
            # DEBUG lines are adaptations that only changed CV values (plotted beside)
            rows=rrb.TextLogRows(filter_by_log_level=["INFO", "WARN", "ERROR", "CRITICAL"]),
        )
        if self.layout.vehicle:
            scene = rrb.Spatial3DView(name="Vehicle", origin="/world")
        elif self.layout.floor_map:
            scene = rrb.Spatial2DView(name="Floor map (m)", origin="/map")
        else:
            return events
        return rrb.Vertical(scene, events, row_shares=[3, 2])


def describe(config: RerunConfig, layout: Layout) -> None:
    """Put what the processes need to draw the views in ``config``: the NFR limits and the
    run-time choices of the package (no rerun import)."""
    config.limits = [(n, f, v) for n, f, v, _ in layout.limits]
    config.choices = [(group, list(leaves)) for group, leaves in layout.choices]


def send(config: RerunConfig, layout: Layout) -> None:
    """Give the recording of ``config`` its blueprint (``save``: a ``blueprint.rrd`` in the
    processes' folder, merged with their files; ``connect``: sent to the viewer). Imports
    rerun: ``rra up`` runs it in a child process (``python -m rra_agent.viz.blueprint``), so
    that neither it nor the processes it forks load rerun."""
    import rerun as rr

    bp = build(layout)
    rec = rr.RecordingStream(config.application_id, recording_id=config.recording_id or None)
    rec.set_log_time_enabled(False)
    if config.mode == "save":
        folder = Path(config.dir)
        folder.mkdir(parents=True, exist_ok=True)
        rec.save(folder / BLUEPRINT_FILE, default_blueprint=bp)
    elif config.mode == "connect":
        rec.connect_grpc(config.url, default_blueprint=bp)
    else:
        return
    rec.flush(timeout_sec=5.0)
    rec.disconnect()


@dataclass(frozen=True)
class SavedView:
    """A view as stored in a recording's blueprint."""

    kind: str  # Rerun's view class: "3D", "2D", "TimeSeries", "StateTimeline", "TextLog"...
    name: str
    origin: str
    contents: tuple[str, ...]

    def shows(self, paths: Iterable[str]) -> set[str]:
        """Which of the entity ``paths`` this view's contents query includes (``$origin``
        substituted; ``/a/**`` is ``/a`` and everything under it; ``- rule`` excludes)."""
        out: set[str] = set()
        for rule in self.contents:
            exclude = rule.startswith("- ")
            rule = rule.removeprefix("- ").removeprefix("+ ").replace("$origin", self.origin)
            rule = "/" + rule.strip("/") if rule.strip("/") != "**" else "/**"
            if rule.endswith("/**"):
                base = rule[:-3] or "/"
                hits = {p for p in paths if p == base or p.startswith(base.rstrip("/") + "/")}
            else:
                hits = {p for p in paths if p == rule}
            out = out - hits if exclude else out | hits
        return out


@dataclass(frozen=True)
class SavedBlueprint:
    views: tuple[SavedView, ...]
    timeline: str | None  # the time panel's timeline


def read_blueprint(path: Path) -> SavedBlueprint | None:
    """The blueprint stored in the recording ``path`` (None if it has none). Imports rerun."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    stores = reader.blueprints()
    if not stores:
        return None
    rows: dict[str, dict[str, Any]] = {}
    for chunk in reader.stream(store=stores[0]).to_chunks():
        batch = chunk.to_record_batch()
        row = rows.setdefault(chunk.entity_path, {})
        for name in batch.schema.names:
            if ":" in name:
                values = [v for v in batch.column(name).to_pylist() if v is not None]
                if values:
                    row[name.partition(":")[2]] = values[-1]
    views = []
    for entity, row in sorted(rows.items()):
        if entity.startswith("/view/") and "class_identifier" in row:
            contents = rows.get(f"{entity}/ViewContents", {}).get("query", [])
            views.append(
                SavedView(
                    kind=row["class_identifier"][0],
                    name=(row.get("display_name") or [""])[0],
                    origin=(row.get("space_origin") or ["/"])[0],
                    contents=tuple(contents),
                )
            )
    timeline = rows.get("/time_panel", {}).get("timeline")
    return SavedBlueprint(tuple(views), timeline[0] if timeline else None)


def main(argv: list[str] | None = None) -> int:
    """``python -m rra_agent.viz.blueprint PKG``: `send` the blueprint of the package PKG for
    the recording that ``RRA_RERUN`` describes."""
    from rra_agent.package.loader import load_package

    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m rra_agent.viz.blueprint PKG", file=sys.stderr)
        return 2
    send(RerunConfig.from_env(), layout_of(load_package(args[0])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
