"""Re-run a recorded run's decisions offline (``rra replay``), also on edited models.

`open_run` reads and checks a run folder's ``record/`` (`rra_agent.record.run`): the models of
each version against their digests, a sealed record against its seal, every frame against
its CRC. Then:

- `replay` re-runs every Adaptation Engine replica's record through the pure core
  (`AdaptationEngine`, `carry_over` at a reload) in the recorded order, at the recorded
  times, on the recorded measurements, and compares each evaluation's selection and CV values
  with the recorded ones: the first difference is reported (time, replica, feature or CV,
  recorded and replayed);
- `what_if` runs edited models on the recorded context, as the run's leaders saw it (each
  evaluation of the replica that led then, its measurements, the operators' overrides, the
  unavailable implementations), and lists the moments where its decisions differ from the
  recorded ones, with the rules behind them. A measurement the edited models define
  differently is computed again with the Context Monitor's logic (`ContextMonitor`) from the
  source samples the run's monitor leader recorded.

Times are printed in seconds since the run began (``rra up`` started).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from rra_agent.bus import messages as m
from rra_agent.core.adaptation import AdaptationEngine, TickResult
from rra_agent.core.availability import requirements, unavailable_features
from rra_agent.core.conflicts import ranked_variants
from rra_agent.core.monitor import Computed, ContextMonitor
from rra_agent.core.overrides import OverrideError
from rra_agent.core.reload import carry_over, engine_for
from rra_agent.deployment import Deployment, deploy_package
from rra_agent.errors import RraError, SelectionError
from rra_agent.model_changes import plain
from rra_agent.models.adaptation import (
    Activate,
    AdaptationModel,
    Deactivate,
    SelectVariant,
    SetAttribute,
)
from rra_agent.models.features import FeatureModel
from rra_agent.models.measurements import is_ros2_source
from rra_agent.package.bundle import bundle_of
from rra_agent.package.functions import measurement_functions
from rra_agent.package.loader import load_package
from rra_agent.record import format as f
from rra_agent.record.run import (
    RunInfo,
    check_seal,
    models_folder,
    read_info,
    read_models,
    record_dir,
    record_files,
)

Values = dict[str, tuple[Any, float]]


# ---- the recorded run ---------------------------------------------------------------------------
@dataclass
class RecordedRun:
    run_dir: Path
    info: RunInfo
    sealed: bool
    #: Record files by role (``adaptation``, ``monitor``, ``resolution``).
    files: dict[str, list[f.FileRecords]]
    #: What the reader should know (a run that was killed, a torn last record).
    notes: list[str] = field(default_factory=list)
    _models: dict[str, Deployment] = field(default_factory=dict)

    def models(self, digest: str) -> Deployment:
        """The recorded models of one version, loaded (each version once)."""
        dep = self._models.get(digest)
        if dep is None:
            bundle = read_models(self.run_dir, digest)
            pkg = load_package(models_folder(self.run_dir, digest))
            dep = deploy_package(pkg, self.info.deployment, bundle)
            self._models[digest] = dep
        return dep

    @property
    def duration(self) -> float:
        """From the run's start to its last recorded evaluation (seconds)."""
        last = max((r.now for fr in self.files.get("adaptation", []) for r in fr.records
                    if isinstance(r, f.Tick)), default=self.info.started)  # fmt: skip
        return max(0.0, last - self.info.started)

    def t(self, stamp: float) -> float:
        return stamp - self.info.started


def open_run(run_dir: str | Path, roles: tuple[str, ...] = ("adaptation",)) -> RecordedRun:
    """Read and check the record of a run folder (RraError, one line, if it is not one or
    is damaged); only the record files of ``roles`` are read."""
    folder = Path(run_dir)
    if not folder.is_dir():
        raise RraError(f"{run_dir}: no such run folder")
    if not record_dir(folder).is_dir():
        raise RraError(f"{run_dir}: not a recorded run (no record/ folder: was it run with "
                       "--no-record, or by an older rra?)")  # fmt: skip
    info = read_info(folder)
    if info.format != f.FORMAT:
        raise RraError(f"{record_dir(folder)}: record format {info.format}, this rra reads "
                       f"{f.FORMAT}")  # fmt: skip
    sealed = check_seal(folder) is not None
    run = RecordedRun(folder, info, sealed, {})
    if not sealed:
        run.notes.append("the run did not end cleanly (no seal): replayed as far as it was "
                         "recorded")  # fmt: skip
    for path in record_files(folder):
        role = _role(path)
        if role not in roles:
            continue
        fr = f.read_file(path)
        if fr.torn:  # sealed: it was so at the end of the run (the seal has its size)
            run.notes.append(f"{path.name} ends in a torn record (its process was killed)")
        if fr.records:
            run.files.setdefault(role, []).append(fr)
    for files in run.files.values():
        files.sort(key=lambda fr: fr.records[0].stamp)
    run.models(info.models)
    if not run.files.get("adaptation") and "adaptation" in roles:
        raise RraError(f"{record_dir(folder)}: no Adaptation Engine record (run without "
                       "adaptation?)")  # fmt: skip
    return run


def _role(path: Path) -> str:
    """``adaptation-a-1234.rec`` -> ``adaptation``."""
    return path.stem.split("-", 1)[0]


# ---- replay: the recorded models, every replica, compared evaluation by evaluation -----------
@dataclass(frozen=True)
class Difference:
    at: float
    replica: str
    what: str
    recorded: str
    got: str
    rules: tuple[str, ...] = ()

    def line(self) -> str:
        rules = f" (rule {', '.join(self.rules)})" if self.rules else ""
        return (f"t={self.at:.3f} s {self.replica}: {self.what}: recorded {self.recorded}, "
                f"replayed {self.got}{rules}")  # fmt: skip


@dataclass
class ReplayResult:
    evaluations: int = 0
    published: int = 0
    replicas: list[str] = field(default_factory=list)
    difference: Difference | None = None
    seconds: float = 0.0
    duration: float = 0.0

    @property
    def speed(self) -> float:
        return self.duration / self.seconds if self.seconds > 0 else math.inf


def replay(run: RecordedRun) -> ReplayResult:
    """Re-run every Adaptation Engine record; stop at the first difference."""
    t0 = time.perf_counter()
    out = ReplayResult(duration=run.duration)
    for fr in run.files.get("adaptation", []):
        start = fr.records[0]
        out.replicas.append(start.process)
        diff = _replay_file(run, fr, out)
        if diff is not None and (out.difference is None or diff.at < out.difference.at):
            out.difference = diff
    out.seconds = time.perf_counter() - t0
    return out


class _Core:
    """The pure core as the Adaptation Engine process drives it (its calls, replayed)."""

    def __init__(self, dep: Deployment) -> None:
        assert dep.package.adaptation is not None
        self.dep = dep
        self.engine = AdaptationEngine(dep.package.features, dep.selection, dep.package.adaptation)
        self.needs = requirements(dep.package.features, dep.package.runtime)
        self.gone: dict[tuple[str, str], str] = {}

    def apply(self, rec: Any, run: RecordedRun) -> str:
        """Apply a non-tick record; "" or why the core refused (as the process saw it)."""
        match rec:
            case f.Adopt(selection=sel, cv=cv):
                try:
                    self.engine.adopt(sel, cv)
                except SelectionError as e:
                    return str(e)
            case f.Forced(forced=forced):
                self.engine.forced = dict(forced)
            case f.Force(features=features):
                try:
                    self.engine.force(features)
                except OverrideError as e:
                    return str(e)
            case f.Avail(unavailable=unavailable):
                self.avail(unavailable)
            case f.Reload(models=digest):
                self.switch(run.models(digest))
        return ""

    def avail(self, unavailable: list[m.Unavailable]) -> None:
        self.gone = {(u.component, u.implementation): u.reason for u in unavailable}
        self.engine.set_unavailable(unavailable_features(self.needs, self.gone))

    def switch(self, dep: Deployment) -> None:
        assert dep.package.adaptation is not None
        self.needs = requirements(dep.package.features, dep.package.runtime)
        new = engine_for(dep.package.features, dep.selection, dep.package.adaptation)
        self.engine = carry_over(self.engine, new, unavailable_features(self.needs, self.gone))
        self.dep = dep


def _replay_file(run: RecordedRun, fr: f.FileRecords, out: ReplayResult) -> Difference | None:
    start: f.Start = fr.records[0]
    core = _Core(run.models(start.models))
    for rec, values in _fold(fr):
        if not isinstance(rec, f.Tick):
            error = core.apply(rec, run)
            recorded = getattr(rec, "error", "")
            if bool(error) != bool(recorded):
                what = type(rec).__name__.lower()
                return Difference(run.t(rec.stamp), start.process, what,
                                  recorded or "accepted", error or "accepted")  # fmt: skip
            continue
        result = core.engine.tick(rec.now, values, changed=rec.changed)
        out.evaluations += 1
        out.published += rec.seq > 0
        diff = _compare(rec.selection, rec.cv, result)
        if diff is not None:
            what, recorded, got = diff
            return Difference(run.t(rec.now), start.process, what, recorded, got,
                              tuple(dict.fromkeys([*rec.fired, *_fired(result)])))  # fmt: skip
    return None


def _fold(fr: f.FileRecords) -> Iterator[tuple[Any, Values]]:
    """Each record after the start, with the measurements an evaluation sees (a tick's new
    ones put in)."""
    values: Values = {}
    for rec in fr.records[1:]:
        if isinstance(rec, f.End):
            return
        if isinstance(rec, f.Tick):
            for c in rec.ctx:
                values[c.name] = (c.value, c.stamp)
        yield rec, values


def _compare(
    selection: list[str], cv: Mapping[str, float], result: TickResult
) -> tuple[str, str, str] | None:
    """(what, recorded, got) of the first difference, or None."""
    got = result.selection
    for feature in sorted(set(selection) ^ got):
        on = feature in got
        return (f"feature {feature}", _on(not on), _on(on))
    for key in sorted(set(cv) | set(result.cv)):
        a, b = cv.get(key), result.cv.get(key)
        if a != b:
            return (f"cv {key}", _num(a), _num(b))
    return None


def _on(selected: bool) -> str:
    return "selected" if selected else "not selected"


def _num(v: float | None) -> str:
    return "unset" if v is None else repr(v)


def _fired(result: TickResult) -> list[str]:
    return [r.rule if r.ruleset is None else f"{r.ruleset}.{r.rule}" for r in result.fired]


# ---- what-if: edited models on the recorded context --------------------------------------------
@dataclass(frozen=True)
class Moment:
    """An interval where the edited models decide differently on one feature or CV."""

    start: float
    end: float
    what: str
    recorded: str
    edited: str
    rules: tuple[str, ...] = ()

    def line(self) -> str:
        rules = f"  (rule {', '.join(self.rules)})" if self.rules else ""
        span = f"t={self.start:.2f}..{self.end:.2f} s"
        return f"{span:<20} {self.what}: recorded {self.recorded}, edited {self.edited}{rules}"


@dataclass
class Timeline:
    """The decisions of one side at each leader evaluation (for the Rerun recording)."""

    times: list[float] = field(default_factory=list)
    selections: list[frozenset[str]] = field(default_factory=list)
    cv: list[dict[str, float]] = field(default_factory=list)


@dataclass
class WhatIfResult:
    models: str
    evaluations: int = 0
    moments: list[Moment] = field(default_factory=list)
    recorded: Timeline = field(default_factory=Timeline)
    edited: Timeline = field(default_factory=Timeline)
    #: Measurement name -> (time, value) as the edited models saw them.
    context: dict[str, list[tuple[float, Any]]] = field(default_factory=dict)
    #: Measurements computed again with the edited definitions.
    recomputed: list[str] = field(default_factory=list)
    features: list[str] = field(default_factory=list)
    seconds: float = 0.0
    duration: float = 0.0

    @property
    def speed(self) -> float:
        return self.duration / self.seconds if self.seconds > 0 else math.inf


def load_edited(run: RecordedRun, path: str | Path) -> Deployment:
    """The edited package, deployed as the run was; RraError (one line) if it no longer fits
    the recording: another system, a feature of the recorded deployment missing, no rules."""
    pkg = load_package(path)
    info = run.info
    if pkg.system.system != info.system:
        raise RraError(f"{path}: system {pkg.system.system}, the run was of {info.system}")
    missing = [n for n in info.deployment if n not in pkg.features.features]
    if missing:
        raise RraError(f"{pkg.file('features')}: no feature {', '.join(missing)} of the "
                       "recorded deployment-time selection: the package no longer matches "
                       "the recording")  # fmt: skip
    if pkg.adaptation is None:
        raise RraError(f"{path}: no adaptation model to replay")
    try:
        bundle = bundle_of(pkg)
    except RraError:
        bundle = None
    try:
        return deploy_package(pkg, info.deployment, bundle)
    except RraError as e:
        raise RraError(f"{path}: cannot deploy as the run did: {e}") from None


def what_if(run: RecordedRun, edited: Deployment) -> WhatIfResult:
    """The edited models' decisions at every evaluation of the run's leaders, beside the
    recorded ones (RraError if a measurement their rules read is not in the recording)."""
    t0 = time.perf_counter()
    model = edited.package.adaptation
    assert model is not None
    recorded_names = _recorded_measurements(run)
    recompute = _to_recompute(run, edited, recorded_names)
    fresh = _recomputed(run, edited, recompute) if recompute else {}
    out = WhatIfResult(models=edited.models, duration=run.duration, recomputed=sorted(recompute))
    out.features = sorted(edited.package.features.runtime_features())
    core = _Core(edited)
    targets = _targets(model, edited.package.features)
    old_targets = _targets_of_run(run)
    tracker = _Moments(run, targets, old_targets)
    cursor = {name: 0 for name in fresh}
    previous_now = -math.inf
    for rec, values in _leader_stream(run):
        if isinstance(rec, f.Force):
            if not rec.error:
                core.apply(rec, run)
            continue
        if isinstance(rec, f.Avail):
            core.avail(rec.unavailable)
            continue
        seen = {k: v for k, v in values.items() if k not in fresh}
        changed = [n for n in rec.changed if n not in fresh]
        for name, series in fresh.items():
            i = cursor[name]
            while i < len(series) and series[i][0] <= rec.now:
                i += 1
            cursor[name] = i
            if i:
                at, value = series[i - 1]
                seen[name] = (value, at)
                if at > previous_now:
                    changed.append(name)
        previous_now = rec.now
        result = core.engine.tick(rec.now, seen, changed=changed)
        out.evaluations += 1
        t = run.t(rec.now)
        _timeline(out.recorded, t, frozenset(rec.selection), rec.cv)
        _timeline(out.edited, t, result.selection, result.cv)
        for name, (value, stamp) in seen.items():
            series_out = out.context.setdefault(name, [])
            if not series_out or series_out[-1][0] != run.t(stamp):
                series_out.append((run.t(stamp), value))
        tracker.add(t, rec, result)
    out.moments = tracker.close()
    out.seconds = time.perf_counter() - t0
    return out


def _timeline(side: Timeline, t: float, selection: frozenset[str], cv: Mapping[str, float]) -> None:
    side.times.append(t)
    side.selections.append(selection)
    side.cv.append(dict(cv))


def _leader_stream(run: RecordedRun) -> Iterator[tuple[Any, Values]]:
    """The evaluations of whichever replica led, in time order, each with the measurements it
    saw; the operators' overrides and each change of availability, in between."""
    events: list[tuple[float, int, Any, Values]] = []
    n = 0
    for fr in run.files.get("adaptation", []):
        last_avail: list[m.Unavailable] | None = None
        for rec, values in _fold(fr):
            n += 1
            if isinstance(rec, f.Tick) and rec.lead:
                events.append((rec.now, n, rec, dict(values)))
            elif isinstance(rec, f.Force):
                events.append((rec.stamp, n, rec, {}))
            elif isinstance(rec, f.Avail) and rec.unavailable != last_avail:
                last_avail = rec.unavailable
                events.append((rec.stamp, n, rec, {}))
    events.sort(key=lambda e: (e[0], e[1]))
    for _, _, rec, values in events:
        yield rec, values


def _recorded_measurements(run: RecordedRun) -> set[str]:
    return {c.name for fr in run.files.get("adaptation", []) for r in fr.records
            if isinstance(r, f.Tick) for c in r.ctx}  # fmt: skip


def _to_recompute(run: RecordedRun, edited: Deployment, recorded: set[str]) -> set[str]:
    """The measurements the edited rules read that the edited models define otherwise than
    the run's (or that it never had): computed again from the recorded source samples."""
    model = edited.package.adaptation
    assert model is not None
    reads = _rule_reads(model)
    old = {meas.name: plain(meas) for meas in run.models(run.info.models).package
           .measurements.measurements}  # fmt: skip
    new = {meas.name: meas for meas in edited.package.measurements.measurements}
    out = set()
    for name, where in sorted(reads.items()):
        meas = new.get(name)
        if meas is None:
            continue  # the rules' parser has refused it already
        if name in old and old[name] == plain(meas) and name in recorded:
            continue
        if meas.reachable is not None or meas.available is not None:
            raise RraError(f"{where}: measurement {name} is not in the recording and cannot "
                           "be computed offline (a host's reachability or a component's "
                           "availability)")  # fmt: skip
        if name in old and old[name] == plain(meas):
            raise RraError(f"{where}: measurement {name} was never received in the run: the "
                           "package no longer matches the recording")  # fmt: skip
        out.add(name)
    return out


def _rule_reads(model: AdaptationModel) -> dict[str, str]:
    """Measurement name -> where a rule first reads it (``file:line:col``)."""
    from rra_agent.models.adaptation import Measure, walk

    out: dict[str, str] = {}
    for rule in model.rules():
        for branch in rule.branches:
            exprs = [branch.condition, *(a.value for a in branch.actions
                                         if isinstance(a, SetAttribute))]  # fmt: skip
            for expr in exprs:
                for node in walk(expr) if expr is not None else ():
                    if isinstance(node, Measure) and node.name not in out:
                        span = node.span
                        out[node.name] = (f"{span.file}:{span.line}:{span.col}" if span
                                          else f"rule {rule.name}")  # fmt: skip
    return out


def _recomputed(
    run: RecordedRun, edited: Deployment, names: set[str]
) -> dict[str, list[tuple[float, Any]]]:
    """Each measurement of ``names`` as the edited Context Monitor would have published it
    (its value when it changes, else every quarter of its max age) from the monitor
    leader's recorded samples: name -> [(time computed, value)]."""
    samples = _monitor_samples(run)
    measurements = [meas for meas in edited.package.measurements.measurements
                    if meas.name in names]  # fmt: skip
    model = msgspec.structs.replace(edited.package.measurements, measurements=measurements)
    recorded_sources = {s.source for s in samples}
    for meas in measurements:
        unknown = [src for src in meas.inputs if src not in recorded_sources]
        if unknown:
            raise RraError(f"measurement {meas.name} reads {', '.join(unknown)}, whose samples "
                           "the run did not record: the package no longer matches the "
                           "recording")  # fmt: skip
    functions = measurement_functions(edited.package)
    monitor = ContextMonitor(model, {n: fn for n, fn in functions.items() if n in names},
                             _port_types(edited, measurements))  # fmt: skip
    refresh = {meas.name: 1.0 if meas.max_age_ms is None else meas.max_age_ms / 4000.0
               for meas in measurements}  # fmt: skip
    out: dict[str, list[tuple[float, Any]]] = {n: [] for n in names}
    last: dict[str, tuple[float, Any]] = {}
    for s in samples:
        for c in _monitor_computes(monitor, s):
            prev = last.get(c.name)
            if prev is None or prev[1] != c.value or s.at - prev[0] >= refresh[c.name]:
                last[c.name] = (s.at, c.value)
                out[c.name].append((s.at, c.value))
    return out


def _monitor_computes(monitor: ContextMonitor, s: f.Sample) -> list[Computed]:
    """What the recorded sample yields: a port's raw bytes are decoded as the monitor did;
    a ROS 2 topic's sample was recorded decoded, as msgpack."""
    if is_ros2_source(s.source):
        return monitor.on_sample(s.source, msgspec.msgpack.decode(s.data), s.stamp)
    return monitor.on_raw(s.source, s.data, s.stamp)


def _monitor_samples(run: RecordedRun) -> list[f.Sample]:
    files = run.files.get("monitor")
    if files is None:
        more = open_run(run.run_dir, roles=("monitor",))
        files = run.files["monitor"] = more.files.get("monitor", [])
    samples = [r for fr in files for r in fr.records if isinstance(r, f.Sample)]
    samples.sort(key=lambda s: s.at)
    return samples


def _port_types(dep: Deployment, measurements: list[Any]) -> dict[str, str]:
    from rra_agent.models.system import parse_endpoint

    out = {}
    for meas in measurements:
        for src in meas.inputs:
            ep = parse_endpoint(src)
            comp = dep.package.system.component(ep.component)
            port = comp.port(ep.port) if comp is not None else None
            if port is not None:
                out[src] = port.type
    return out


# ---- which rules decide a feature or a CV -------------------------------------------------
def _targets(model: AdaptationModel, fm: FeatureModel) -> dict[str, set[str]]:
    """Rule (``ruleset.rule``) -> the features and CV attributes its actions decide."""
    out: dict[str, set[str]] = {}
    for ruleset, rules in model.units():
        for rule in rules:
            name = rule.name if ruleset is None else f"{ruleset.name}.{rule.name}"
            mine = out.setdefault(name, set())
            for branch in rule.branches:
                for action in branch.actions:
                    mine |= _decides(action, fm)
    return out


def _decides(action: Any, fm: FeatureModel) -> set[str]:
    match action:
        case Activate(features=fs) | Deactivate(features=fs):
            return {name for x in fs for name in _with_alternatives(fm, x.name)}
        case SelectVariant():
            return set(ranked_variants(fm, action)) | {
                c.name for c in fm.features[action.point.name].children}
        case SetAttribute(target=t):
            return {t.name, f"{t.feature}.{t.name}"}
    return set()


def _with_alternatives(fm: FeatureModel, name: str) -> set[str]:
    """A feature and the others of its group when the group is exclusive (activating one
    deselects them)."""
    group = fm.group_of.get(name)
    exclusive = group is not None and (
        group.kind == "alternative" or (group.kind == "cardinality" and group.upper == 1)
    )
    return {name, *(c.name for c in group.children)} if exclusive and group else {name}


def _targets_of_run(run: RecordedRun) -> dict[str, set[str]]:
    dep = run.models(run.info.models)
    model = dep.package.adaptation
    return _targets(model, dep.package.features) if model is not None else {}


class _Moments:
    """Collects the intervals where the two sides differ, per feature or CV."""

    def __init__(
        self, run: RecordedRun, targets: dict[str, set[str]], old: dict[str, set[str]]
    ) -> None:
        self.run = run
        self.targets, self.old = targets, old
        self.open: dict[str, Moment] = {}
        self.done: list[Moment] = []
        self.last_t = 0.0

    def add(self, t: float, rec: f.Tick, result: TickResult) -> None:
        self.last_t = t
        now: dict[str, tuple[str, str]] = {}
        recorded = set(rec.selection)
        for feature in sorted(recorded ^ result.selection):
            now[f"feature {feature}"] = (_on(feature in recorded), _on(feature in result.selection))
        for key in sorted(set(rec.cv) | set(result.cv)):
            old, new = rec.cv.get(key), result.cv.get(key)
            if old != new:
                now[f"cv {key}"] = (_fmt(old), _fmt(new))
        for what in list(self.open):
            if what not in now or (what.startswith("feature") and now[what] != (
                    self.open[what].recorded, self.open[what].edited)):  # fmt: skip
                self._close(what, t)
        for what, (a, b) in now.items():
            if what not in self.open:
                rules = self._rules(what.split(" ", 1)[1], rec.fired, _fired(result))
                self.open[what] = Moment(t, t, what, a, b, rules)

    def _rules(self, target: str, fired_old: list[str], fired_new: list[str]) -> tuple[str, ...]:
        new = [r for r in fired_new if target in self.targets.get(r, ())]
        old = [r for r in fired_old if target in self.old.get(r, ())]
        found = list(dict.fromkeys([*new, *old]))
        if not found:  # none fired now: the rules that can decide it (edited, then recorded)
            found = [r for r, t in {**self.old, **self.targets}.items() if target in t]
        return tuple(found)

    def _close(self, what: str, t: float) -> None:
        self.done.append(dataclasses.replace(self.open.pop(what), end=t))

    def close(self) -> list[Moment]:
        for what in list(self.open):
            self._close(what, self.last_t)
        return sorted(self.done, key=lambda mo: (mo.start, mo.what))


def _fmt(v: float | None) -> str:
    return "unset" if v is None else f"{v:.6g}"
