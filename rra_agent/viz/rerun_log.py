"""Rerun logging for a whole RRA system: one recording, one recording id, many processes.

``rra up --rerun save|connect`` puts a `RerunConfig` as JSON in the environment variable
``RRA_RERUN``; every process it starts inherits it. A process that logs calls
`open_logger` once and gets a `Logger` (or None when logging is off, so callers write
``if log: log.measurement(...)``). Processes that never call `open_logger` never import
rerun, and neither does this module at import time: ``import rerun`` costs ~0.4 s and
happens in `Logger.__init__` only.

Sinks. ``save``: each process writes ``<dir>/<process>.rrd`` (``<process>-<pid>.rrd`` if a
process of that name already wrote one, e.g. after a restart) and ``rra up`` merges them with
``rerun rrd merge`` once every child has exited (`rra_agent.viz.recording`). ``connect``: every
process streams to a viewer's gRPC proxy (``rerun+http://HOST:9876/proxy``); the viewer must
be up first (`open_logger` checks it with a TCP connect and logs nothing otherwise, because an
unreachable gRPC sink makes the process' exit take ~11 s; a viewer that goes away during the
run still costs that at exit, beyond the supervisor's SIGINT grace of 2 s).

Timelines: ``sim_time`` (duration: seconds of simulation time since the run started; the
viewer's default, see `rra_agent.viz.blueprint`) and ``wall_time`` (timestamp, seconds since
the epoch) on everything. The simulated worlds run in real time (the vehicle simulator's
``realtime_factor`` is 1 by default, the object-storing robot has no clock of its own), so a
process that has no simulation clock (the engines, the robot's nodes) stamps ``sim_time`` with
the wall-clock seconds since ``RerunConfig.t0`` (the start of ``rra up``), and a process that
passes its own ``sim_time`` (the vehicle simulator: physics seconds since it armed) has it
placed on that axis at the run time of its first sample (so the vehicle, the measurements and
the adaptation events line up; at another realtime factor the physics axis stretches against
the engines'). Rerun's automatic ``log_time`` is turned off: ``wall_time`` is the time of the
*event* (a measurement's computation, a selection's decision), not of the logging call.

Entity tree (names are escaped path parts)::

    /context/<measurement>        Scalars (bool as 0/1); string measurements: TextLog,  monitor
                                  and StateChange when the value changes
    /selection/<feature>          Scalars 1 selected / 0 not (run-time features)        adaptation
    /choice/<group>               StateChange: the selected feature of a run-time       adaptation
                                  choice (`RerunConfig.choices`), on change
    /rules                        TextLog: the rules that changed the selection (DEBUG  adaptation
                                  when only CV values changed)
    /cv/<attribute>               Scalars, the Continuous Variability values            adaptation
    /events                       TextLog with level: adaptation events (plan steps,    resolution
                                  phase durations; DEBUG for a CV-only adaptation)
    /timing/<phase>               Scalars drawn as points: an adaptation's phases (ms)  resolution
    /nodes/<node>/state           TextLog with level: STARTING, RUNNING pid 12, ...     resolution
    /nodes/<node>/running         Scalars 1 running / 0.5 standby (inactive) / 0 not    resolution
    /world/vehicle                Transform3D: the body pose in the world frame         simulator
    /world/vehicle/frame          Boxes3D (static): the body                            simulator
    /world/vehicle/rotors         Points3D (static, body frame): the rotor discs        simulator
    /world/vehicle/arms           LineStrips3D (static): centre to each rotor           simulator
    /world/vehicle/thrust         Arrows3D (body frame): one per rotor, length ~ thrust simulator
    /world/trajectory             LineStrips3D: the path flown so far (world frame)     simulator
    /vehicle/altitude             Scalars (and /vehicle/altitude_target)                simulator
    /vehicle/injections           Scalars drawn as markers: the altitude at each fault  simulator
                                  injected (`injection`)
    /injections                   StateChange: the last fault injected (a lane)         simulator
    /vehicle/motors/<quantity>    Scalars, one series per motor (m1, m2, ...)           simulator
    /map/...                      2D floor map (static) and /map/robot, /map/path       robot driver
                                  (`robot_pose_2d`)

The 3D scene lives under ``/world``, the 2D map under ``/map`` and the plots elsewhere; the
views a user sees are laid out by the blueprint of `rra_agent.viz.blueprint`, which ``rra up``
adds to every recording.

Failures never reach the caller: every public method catches, counts (``errors``) and
prints the first failure once to stderr.

A simulator node (``t``: simulated seconds; MuJoCo's quaternions are w, x, y, z, Rerun's
x, y, z, w)::

    log = open_logger(ctx.name)                  # None unless `rra up --rerun ...`
    draw = Every(0.02)                           # 3D at 50 Hz of simulated time
    if log:
        log.vehicle_geometry(rotor_positions)    # once, body frame
    ...                                          # every step:
    if log:
        log.altitude(z, sim_time=t, target=z_ref)
        log.motors("thrust", thrusts, sim_time=t)
        if draw(t):
            log.vehicle_pose(pos, (qx, qy, qz, qw), sim_time=t)
            log.thrust(thrusts, sim_time=t, failed=broken)
    ...                                          # on stop:
    if log:
        log.close()

Costs measured on the development machine (rerun-sdk 0.41, file sink, 2 cores shared with
other work, so +-30 %): ``import rerun`` 0.35-0.5 s once per logging process, `Logger`
creation ~15 ms, `close` (flush, finalise the file) ~15 ms. Per call: `scalar` and
`measurement` 40-60 us (one ``rr.log``: the SDK's Python-side cost dominates), `text`
50-80 us, `node_state` 100-130 us, `event` 120-180 us, `selection` ~45 us per feature and CV
value, `vehicle_pose` 80-120 us, `thrust` (4 arrows) 115-165 us. The buffered calls
(`scalar_row`, `altitude`, `motors`) cost 2-3 us per row including their share of the
batched ``send_columns``, 20x less than one ``rr.log`` per row. So a 500 Hz simulator logs
altitude and motors every step (buffered) and the pose and thrust arrows decimated to 50 Hz
(`Every`): ~15 us per step on average, ~1.5 % of a core.
"""

from __future__ import annotations

import atexit
import functools
import math
import os
import socket
import sys
import textwrap
import threading
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, ParamSpec, TypeVar
from urllib.parse import urlsplit

import msgspec

from rra_agent.bus.why import change_lines

if TYPE_CHECKING:
    from rra_agent.bus.messages import AdaptationEvent, NodeState, Why

#: Characters of a ``/rules`` row: what the events view's body column shows of a row at
#: 1600 px in the designed views (rendered with tools/render_rrd.py); longer lines go on.
RULES_WIDTH = 72

ENV_VAR = "RRA_RERUN"
DEFAULT_URL = "rerun+http://127.0.0.1:9876/proxy"
WALL = "wall_time"
SIM = "sim_time"

Mode = Literal["off", "save", "connect"]
Vec3 = Sequence[float]


class RerunConfig(msgspec.Struct, kw_only=True, omit_defaults=True, forbid_unknown_fields=True):
    """How the processes of one run log; passed to every child as JSON in ``RRA_RERUN``."""

    mode: Mode = "off"
    #: Shared by every process, so their data lands in one recording.
    recording_id: str = ""
    application_id: str = "rra"
    #: ``save``: the folder each process writes ``<process>.rrd`` into.
    dir: str = ""
    #: ``connect``: the viewer's gRPC proxy URL.
    url: str = ""
    #: The run's start (wall clock, seconds since the epoch): zero of the ``sim_time``
    #: timeline for every process (0: each process' own start).
    t0: float = 0.0
    #: NFR limits (name, feature, value): while the feature is selected, the value is logged
    #: as ``/cv/<name>`` beside the CV values (a gap while it is not).
    limits: list[tuple[str, str, float]] = []
    #: Run-time choices (group, its features): ``/choice/<group>`` is a state lane naming
    #: the selected feature of the group ("-" when none is).
    choices: list[tuple[str, list[str]]] = []

    @classmethod
    def new(cls, mode: Mode, system: str, *, dir: str = "", url: str = "") -> RerunConfig:
        """A configuration with a fresh recording id and an application id named after
        ``system`` (letters, digits, ``-`` and ``_`` only, as Rerun wants)."""
        app = "".join(c if c.isalnum() or c in "-_" else "-" for c in system)
        return cls(
            mode=mode,
            recording_id=uuid.uuid4().hex,
            application_id=f"rra-{app}",
            dir=dir,
            url=url,
            t0=time.time(),
        )

    def to_env(self) -> str:
        return msgspec.json.encode(self).decode()

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> RerunConfig:
        """The configuration in ``RRA_RERUN`` (mode ``off`` when unset).

        Raises ValueError when the variable is set but malformed.
        """
        raw = (os.environ if environ is None else environ).get(ENV_VAR, "").strip()
        if not raw:
            return cls()
        try:
            return msgspec.json.decode(raw, type=cls)
        except (msgspec.DecodeError, msgspec.ValidationError) as e:
            raise ValueError(f"bad {ENV_VAR}: {e}") from None


def viewer_address(url: str) -> tuple[str, int]:
    """(host, port) of a viewer URL (``rerun+http://host:port/proxy``, default port 9876)."""
    parts = urlsplit(url or DEFAULT_URL)
    if not parts.hostname:
        raise ValueError(f"not a Rerun viewer URL: {url!r}")
    default = 443 if parts.scheme in ("rerun", "rerun+https") else 9876
    return parts.hostname, parts.port or default


def viewer_reachable(url: str, timeout: float = 0.5) -> bool:
    """Whether something accepts TCP connections at the viewer URL's address."""
    try:
        with socket.create_connection(viewer_address(url), timeout=timeout):
            return True
    except (OSError, ValueError):
        return False


def open_logger(process: str, environ: Mapping[str, str] | None = None) -> Logger | None:
    """This process' logger, or None if ``RRA_RERUN`` says not to log (or logging cannot start;
    the reason is printed once). ``process`` names the file (``save``) and the log lines."""
    try:
        config = RerunConfig.from_env(environ)
    except ValueError as e:
        print(f"rra viz ({process}): {e}; not logging", file=sys.stderr, flush=True)
        return None
    if config.mode == "off":
        return None
    if config.mode == "connect" and not viewer_reachable(config.url):
        print(
            f"rra viz ({process}): no Rerun viewer at {config.url or DEFAULT_URL}; not logging",
            file=sys.stderr,
            flush=True,
        )
        return None
    try:
        logger = Logger(config, process)
    except Exception as e:  # a broken rerun install must not stop an engine
        print(f"rra viz ({process}): cannot start logging: {e!r}", file=sys.stderr, flush=True)
        return None
    atexit.register(logger.close)
    return logger


class Every:
    """Decimation: ``every(t)`` is true at most once per ``period`` of the clock ``t`` (and
    again at once if ``t`` goes back, e.g. a simulation restarted)::

        draw = Every(0.02)  # 50 Hz of simulated time
        if log and draw(t):
            log.vehicle_pose(p, q, sim_time=t)
    """

    def __init__(self, period: float) -> None:
        self.period = period
        self.next = -math.inf

    def __call__(self, t: float) -> bool:
        if self.next - self.period <= t < self.next:
            return False
        self.next = t + self.period
        return True


P = ParamSpec("P")
R = TypeVar("R")


def _safe(fn: Callable[P, R]) -> Callable[P, R | None]:
    """Run a `Logger` method under its lock; count and report failures instead of raising."""

    @functools.wraps(fn)
    def wrapper(*args: P.args, **kwargs: P.kwargs) -> R | None:
        self: Logger = args[0]  # type: ignore[assignment]
        with self._lock:
            if self.closed:
                return None
            try:
                return fn(*args, **kwargs)
            except Exception as e:
                self._failure(fn.__name__, e)
                return None

    return wrapper


_LEVELS = {"debug": "DEBUG", "info": "INFO", "warning": "WARN", "error": "ERROR"}
_STATE_LEVELS = {"FATAL": "ERROR", "BACKOFF": "WARN", "EXITED": "WARN"}


class _Rows:
    """Buffered rows of one scalar entity, sent with ``send_columns``."""

    __slots__ = ("sim", "values", "wall")

    def __init__(self) -> None:
        self.sim: list[float] = []
        self.wall: list[float] = []
        self.values: list[Any] = []



def rule_rows(why: Sequence[Why], width: int = RULES_WIDTH) -> list[str]:
    """The rows of ``/rules`` for one change of the selection: each line of
    `rra_agent.bus.why.change_lines` cut at words into rows of at most ``width`` characters
    (a row goes on, indented, in the next), so that the events view cuts none of the cause."""
    rows: list[str] = []
    for line in change_lines(why):
        text = line if line.startswith(" ") else f"selection {line}"
        indent = " " * (len(text) - len(text.lstrip()) + 4)
        rows += textwrap.wrap(text, width, subsequent_indent=indent, break_on_hyphens=False)
    return rows

class Logger:
    """One process' handle on the shared recording. Thread-safe; every method is a no-op after
    `close` and never raises."""

    #: Buffered rows are sent when this many have accumulated on one entity ...
    batch_rows = 256
    #: ... or when this much wall-clock time has passed since the last send.
    batch_seconds = 0.1
    #: The trajectory keeps points at least this far apart (m), at most this many ...
    trajectory_step = 0.01
    trajectory_points = 5000
    #: ... and is re-logged at most once per this much simulated time (s).
    trajectory_period = 0.1

    def __init__(self, config: RerunConfig, process: str) -> None:
        import numpy as np
        import rerun as rr

        self.rr = rr
        self._np = np
        self.config = config
        self.process = process
        self.errors = 0
        self.closed = False
        self.path: Path | None = None
        self._lock = threading.RLock()
        self._parts: dict[str, str] = {}
        self._features: set[str] = set()
        self._rows: dict[str, _Rows] = {}
        self._named: set[str] = set()
        self._last_send = time.monotonic()
        self._rotors: Any = None
        self._thrust_scale = 0.05
        self._trajectory: deque[tuple[float, float, float]] = deque(maxlen=self.trajectory_points)
        self._trajectory_due = Every(self.trajectory_period)
        self._t0 = config.t0 or time.time()
        self._sim_offset: float | None = None  # run time of a simulation clock's zero
        self._last_sim = -math.inf
        self._states: dict[str, str] = {}  # last StateChange per entity
        self._last_selection: set[str] | None = None
        self._last_applied = ""
        self._path2d: deque[tuple[float, float]] = deque(maxlen=self.trajectory_points)
        self._path_due = Every(1.0)
        rec = rr.RecordingStream(config.application_id, recording_id=config.recording_id or None)
        rec.set_log_time_enabled(False)
        if config.mode == "save":
            folder = Path(config.dir or ".")
            folder.mkdir(parents=True, exist_ok=True)
            stem = "".join(c if c.isalnum() or c in "-_." else "_" for c in process) or "process"
            path = folder / f"{stem}.rrd"
            if path.exists():
                path = folder / f"{stem}-{os.getpid()}.rrd"
            rec.save(path)
            self.path = path
        elif config.mode == "connect":
            rec.connect_grpc(config.url or DEFAULT_URL)
        else:
            raise ValueError(f"unknown rerun mode {config.mode!r}")
        self.rec = rec

    # ---- plumbing -----------------------------------------------------------------------
    def _failure(self, what: str, e: BaseException) -> None:
        self.errors += 1
        if self.errors == 1:
            print(
                f"rra viz ({self.process}): {what} failed: {type(e).__name__}: {e} "
                "(further failures are only counted)",
                file=sys.stderr,
                flush=True,
            )

    def _part(self, name: str) -> str:
        part = self._parts.get(name)
        if part is None:
            part = self._parts[name] = self.rr.escape_entity_path_part(name)
        return part

    def _run_time(self, sim_time: float | None, wall: float) -> float:
        """The ``sim_time`` of a sample: the run's clock (see the module's docstring)."""
        if sim_time is None:
            return wall - self._t0
        if self._sim_offset is None or sim_time < self._last_sim - 1.0:  # first, or restarted
            self._sim_offset = (wall - self._t0) - sim_time
        self._last_sim = sim_time
        return sim_time + self._sim_offset

    def _at(self, sim_time: float | None, wall_time: float | None) -> None:
        rec = self.rec
        wall = time.time() if wall_time is None else wall_time
        rec.reset_time()  # time is per thread: drop a time an earlier call left here
        rec.set_time(WALL, timestamp=wall)
        rec.set_time(SIM, duration=self._run_time(sim_time, wall))

    def _state(self, path: str, state: str) -> None:
        """A StateChange at ``path`` if ``state`` differs from the last one (time set)."""
        if self._states.get(path) != state:
            self._states[path] = state
            self.rec.log(path, self.rr.StateChange(state=state))

    def _log(self, path: str, item: Any, sim_time: float | None, wall_time: float | None) -> None:
        self._at(sim_time, wall_time)
        self.rec.log(path, item)

    def _push(self, path: str, value: Any, sim_time: float | None, wall_time: float | None) -> None:
        rows = self._rows.get(path)
        if rows is None:
            rows = self._rows[path] = _Rows()
        wall = time.time() if wall_time is None else wall_time
        rows.sim.append(self._run_time(sim_time, wall))
        rows.wall.append(wall)
        rows.values.append(value)
        now = time.monotonic()
        if len(rows.values) >= self.batch_rows or now - self._last_send >= self.batch_seconds:
            self._send_rows()

    def _send_rows(self) -> None:
        rr, np = self.rr, self._np
        self._last_send = time.monotonic()
        for path, rows in list(self._rows.items()):
            if not rows.values:
                continue
            indexes = [
                rr.TimeColumn(WALL, timestamp=np.asarray(rows.wall, dtype=np.float64)),
                rr.TimeColumn(SIM, duration=np.asarray(rows.sim, dtype=np.float64)),
            ]
            values = np.asarray(rows.values, dtype=np.float64)
            self._rows[path] = _Rows()
            self.rec.send_columns(path, indexes=indexes, columns=rr.Scalars.columns(scalars=values))

    # ---- the engines --------------------------------------------------------------------
    @_safe
    def measurement(
        self,
        name: str,
        value: float | int | bool | str,
        stamp: float,
        sim_time: float | None = None,
    ) -> None:
        """A Context Dependent Measurement at ``/context/<name>`` (``stamp``: its wall time)."""
        path = f"/context/{self._part(name)}"
        if isinstance(value, str):
            self._log(path, self.rr.TextLog(value), sim_time, stamp)
            self._state(path, value)
        else:
            self._log(path, self.rr.Scalars(float(value)), sim_time, stamp)

    @_safe
    def selection(
        self,
        features: Iterable[str],
        cv: Mapping[str, float],
        stamp: float,
        *,
        universe: Iterable[str] = (),
        fired: Sequence[str] = (),
        changed: bool = False,
        why: Sequence[Why] = (),
    ) -> None:
        """The run-time selection: ``/selection/<f>`` is 1 for each selected feature and 0 for
        every other feature of ``universe`` (or seen selected before); ``/choice/<group>`` the
        selected feature of each choice of ``RerunConfig.choices``; ``/cv/<a>`` the CV values
        and the active NFR limits of ``RerunConfig.limits``; when ``changed``, rows of
        ``/rules``: what changed (``+Added -Removed``) and by which rules, with what they read,
        then each rule they overruled, a row per line so that a view cuts none (``why``;
        else one row naming the ``fired`` rules)."""
        selected = set(features)
        self._features.update(universe)
        self._features.update(selected)
        rr = self.rr
        self._at(None, stamp)
        for f in sorted(self._features):
            self.rec.log(f"/selection/{self._part(f)}", rr.Scalars(1.0 if f in selected else 0.0))
        for attr, value in sorted(cv.items()):
            self.rec.log(f"/cv/{self._part(attr)}", rr.Scalars(float(value)))
        for group, options in self.config.choices:
            chosen = [f for f in options if f in selected]
            self._state(f"/choice/{self._part(group)}", ", ".join(chosen) or "-")
        for name, feature, limit in self.config.limits:
            active = feature in selected
            self.rec.log(f"/cv/{self._part(name)}", rr.Scalars(limit if active else math.nan))
        if changed:  # DEBUG when only CV values changed (the features did not)
            last = self._last_selection
            level = "INFO" if selected != last else "DEBUG"
            if last is None or selected == last:
                text = f"selection {sorted(selected)}"
            else:  # what changed: +added -removed
                diff = [f"+{f}" for f in sorted(selected - last)]
                text = "selection " + " ".join(diff + [f"-{f}" for f in sorted(last - selected)])
            if why:  # a row per line: a view shows one line of each row, so none is hidden
                for row in rule_rows(why):
                    self.rec.log("/rules", rr.TextLog(row, level=level))
            else:
                text += f" by {'; '.join(fired)}" if fired else ""
                self.rec.log("/rules", rr.TextLog(text, level=level))
        self._last_selection = selected

    @_safe
    def event(self, ev: AdaptationEvent) -> None:
        """An adaptation event: a line of ``/events`` (with its plan steps and phase
        durations) and, for an adaptation that changed features, its phase durations at
        ``/timing/<phase>`` (ms)."""
        rr = self.rr
        head = f"{ev.kind}: {ev.message}" + (f" [{ev.outcome}]" if ev.outcome else "")
        phases = ", ".join(f"{p} {s * 1000.0:.1f} ms" for p, s in ev.durations.items())
        lines = [head + (f" ({phases})" if phases else "")]
        lines += [f"  {line}" for line in change_lines(ev.why)]  # the whole cause, untruncated
        if ev.cause and not ev.why:
            lines += [f"  cause {c.rule}: {c.action}" for c in ev.cause]
        lines += [f"  {step}" for step in ev.plan]
        level = _LEVELS.get(ev.level, "INFO")
        if ev.kind == "adaptation" and ev.message.startswith("applied selection"):
            applied = ev.message.partition("]")[0]
            if applied == self._last_applied and level == "INFO":
                level = "DEBUG"  # the same features again: only CV values changed
            self._last_applied = applied
        self._at(None, ev.stamp)
        self.rec.log("/events", rr.TextLog("\n".join(lines), level=level))
        # The phases of the adaptations that changed features only: a deployment's seconds
        # would flatten them, and CV-only adaptations (every tick) bury them; the durations
        # of every event are in its line of /events.
        structural = ev.kind == "adaptation" and level != "DEBUG"
        timed = ev.durations.items() if structural else ()
        for phase, seconds in sorted(timed):
            path = f"/timing/{self._part(phase)}"
            if path not in self._named:  # a few samples per run: points, not lines
                self._named.add(path)
                self.rec.log(path, rr.SeriesPoints(names=phase, marker_sizes=4.0), static=True)
            self.rec.log(path, rr.Scalars(seconds * 1000.0))

    @_safe
    def node_state(self, st: NodeState) -> None:
        """A node's state transition at ``/nodes/<node>/state`` and ``.../running``; one
        that came with a failure (what the node raised, where, its log) also as an error
        line of ``/events``."""
        from rra_agent.bus.failure import details, without_summary

        rr = self.rr
        text = st.state + (f" pid {st.pid}" if st.pid else "") + ("" if st.active else " standby")
        reason = without_summary(st.reason, st.failure)
        if reason:
            text += f" ({reason})"
        if st.failure is not None:
            text += "".join(f"\n  {line}" for line in details(st.failure))
        running = 0.0 if st.state != "RUNNING" else 1.0 if st.active else 0.5
        base = f"/nodes/{self._part(st.node)}"
        self._at(None, st.stamp)
        self.rec.log(f"{base}/state", rr.TextLog(text, level=_STATE_LEVELS.get(st.state, "INFO")))
        self.rec.log(f"{base}/running", rr.Scalars(running))
        if st.failure is not None:
            self.rec.log("/events", rr.TextLog(f"node {st.node}: {text}", level="ERROR"))

    # ---- generic ------------------------------------------------------------------------
    @_safe
    def scalar(
        self,
        path: str,
        value: float | Sequence[float],
        *,
        sim_time: float | None = None,
        wall_time: float | None = None,
    ) -> None:
        """One sample of a time series (several values: several series in one plot)."""
        self._log(path, self.rr.Scalars(value), sim_time, wall_time)

    @_safe
    def scalar_row(
        self,
        path: str,
        value: float | Sequence[float],
        *,
        sim_time: float | None = None,
        wall_time: float | None = None,
    ) -> None:
        """Like `scalar`, buffered: rows are sent together with ``send_columns`` every
        ``batch_seconds`` or ``batch_rows``. For high-rate series (keep one width per path,
        and give ``sim_time`` always or never)."""
        self._push(path, value, sim_time, wall_time)

    @_safe
    def scalar_columns(
        self,
        path: str,
        values: Any,
        *,
        sim_times: Any = None,
        wall_times: Any = None,
    ) -> None:
        """A whole batch at once: ``values`` of shape (N,) or (N, k), times of shape (N,)
        (``wall_times`` default to now for every row)."""
        rr, np = self.rr, self._np
        vals = np.asarray(values, dtype=np.float64)
        walls = np.full(len(vals), time.time()) if wall_times is None else wall_times
        walls = np.asarray(walls, dtype=np.float64)
        if sim_times is None:
            sims = walls - self._t0
        else:
            sims = np.asarray(sim_times, dtype=np.float64)
            sims = sims + (self._run_time(float(sims[0]), float(walls[0])) - sims[0])
        indexes = [rr.TimeColumn(WALL, timestamp=walls), rr.TimeColumn(SIM, duration=sims)]
        self.rec.send_columns(path, indexes=indexes, columns=rr.Scalars.columns(scalars=vals))

    @_safe
    def text(
        self,
        path: str,
        text: str,
        *,
        level: str = "INFO",
        sim_time: float | None = None,
        wall_time: float | None = None,
    ) -> None:
        """A line of a text log (level: DEBUG, INFO, WARN, ERROR, CRITICAL)."""
        self._log(path, self.rr.TextLog(text, level=level), sim_time, wall_time)

    @_safe
    def transform(
        self,
        path: str,
        translation: Vec3,
        quaternion_xyzw: Sequence[float] | None = None,
        *,
        sim_time: float | None = None,
        wall_time: float | None = None,
    ) -> None:
        """A rigid transform of ``path`` relative to its parent entity."""
        rr = self.rr
        quat = rr.Quaternion(xyzw=quaternion_xyzw) if quaternion_xyzw is not None else None
        self._log(
            path, rr.Transform3D(translation=translation, quaternion=quat), sim_time, wall_time
        )

    @_safe
    def log(
        self,
        path: str,
        *items: Any,
        sim_time: float | None = None,
        wall_time: float | None = None,
        static: bool = False,
    ) -> None:
        """Any rerun archetypes (``logger.rr`` is the rerun module), at these times or static."""
        if not static:
            self._at(sim_time, wall_time)
        self.rec.log(path, *items, static=static)

    # ---- the simulated vehicle ----------------------------------------------------------
    @_safe
    def vehicle_geometry(
        self,
        rotor_positions: Sequence[Vec3],
        *,
        body_half_size: Vec3 = (0.1, 0.1, 0.03),
        rotor_radius: float = 0.05,
        thrust_scale: float = 0.05,
    ) -> None:
        """The vehicle's shape, once (static): body box, rotors and arms in the body frame.
        ``thrust_scale`` (m per N) sets the length of the `thrust` arrows."""
        rr, np = self.rr, self._np
        rotors = np.asarray(rotor_positions, dtype=np.float32).reshape(-1, 3)
        self._rotors = rotors
        self._thrust_scale = thrust_scale
        labels = [f"m{i + 1}" for i in range(len(rotors))]
        self.rec.log(
            "/world/vehicle/frame",
            rr.Boxes3D(half_sizes=[body_half_size], colors=[(90, 90, 110)]),
            static=True,
        )
        self.rec.log(
            "/world/vehicle/rotors",
            rr.Points3D(rotors, radii=rotor_radius, labels=labels, colors=[(60, 60, 60)]),
            static=True,
        )
        arms = [[(0.0, 0.0, 0.0), tuple(r)] for r in rotors.tolist()]
        self.rec.log("/world/vehicle/arms", rr.LineStrips3D(arms, radii=0.01), static=True)

    @_safe
    def vehicle_pose(
        self,
        position: Vec3,
        quaternion_xyzw: Sequence[float],
        *,
        sim_time: float,
        wall_time: float | None = None,
    ) -> None:
        """The body pose (``/world/vehicle``); also extends ``/world/trajectory``."""
        rr = self.rr
        x, y, z = position
        pos = (float(x), float(y), float(z))
        self._log(
            "/world/vehicle",
            rr.Transform3D(translation=pos, quaternion=rr.Quaternion(xyzw=quaternion_xyzw)),
            sim_time,
            wall_time,
        )
        traj = self._trajectory
        if not traj or math.dist(traj[-1], pos) >= self.trajectory_step:
            traj.append(pos)
        if len(traj) > 1 and self._trajectory_due(sim_time):
            self.rec.log(
                "/world/trajectory",
                rr.LineStrips3D([list(traj)], radii=0.005, colors=[(40, 140, 230)]),
            )

    @_safe
    def thrust(
        self,
        thrusts: Sequence[float],
        *,
        sim_time: float,
        failed: Sequence[bool] = (),
        wall_time: float | None = None,
    ) -> None:
        """Thrust arrows at the rotors (body frame, along +z, ``thrust_scale`` m per N; failed
        motors red). Needs `vehicle_geometry` first."""
        if self._rotors is None:
            raise RuntimeError("thrust() before vehicle_geometry()")
        rr, np = self.rr, self._np
        t = np.asarray(thrusts, dtype=np.float32)
        vectors = np.zeros((len(t), 3), dtype=np.float32)
        vectors[:, 2] = t * self._thrust_scale
        broken = [bool(failed[i]) if i < len(failed) else False for i in range(len(t))]
        colors = [(220, 40, 40) if b else (250, 160, 30) for b in broken]
        arrows = rr.Arrows3D(origins=self._rotors[: len(t)], vectors=vectors, colors=colors)
        self._log("/world/vehicle/thrust", arrows, sim_time, wall_time)

    @_safe
    def altitude(
        self,
        z: float,
        *,
        sim_time: float,
        target: float | None = None,
        wall_time: float | None = None,
    ) -> None:
        """Altitude (and its set point) as ``/vehicle/altitude[_target]`` (buffered)."""
        if "/vehicle/altitude" not in self._named:
            self._named.add("/vehicle/altitude")
            rr = self.rr
            self.rec.log(
                "/vehicle/altitude",
                rr.SeriesLines(names="altitude", colors=(40, 140, 230), widths=2.0),
                static=True,
            )
            self.rec.log(
                "/vehicle/altitude_target",
                rr.SeriesLines(names="target", colors=(230, 120, 30), widths=1.5),
                static=True,
            )
        self._push("/vehicle/altitude", float(z), sim_time, wall_time)
        if target is not None:
            self._push("/vehicle/altitude_target", float(target), sim_time, wall_time)

    @_safe
    def injection(
        self,
        detail: str,
        *,
        sim_time: float | None = None,
        wall_time: float | None = None,
        altitude: float | None = None,
    ) -> None:
        """A fault injected (``detail``: ``break_motor motor=2``): a WARN line of ``/events``,
        the ``/injections`` lane changing to it and, given the ``altitude`` then, a marker on
        the altitude plot (``/vehicle/injections``)."""
        rr = self.rr
        self._at(sim_time, wall_time)
        self.rec.log("/events", rr.TextLog(f"injection: {detail}", level="WARN"))
        self.rec.log("/injections", rr.StateChange(state=detail))
        if altitude is None:
            return
        if "/vehicle/injections" not in self._named:
            self._named.add("/vehicle/injections")
            marker = rr.SeriesPoints(
                names="fault", colors=(220, 30, 30), markers="cross", marker_sizes=8.0
            )
            self.rec.log("/vehicle/injections", marker, static=True)
        self.rec.log("/vehicle/injections", rr.Scalars(float(altitude)))

    @_safe
    def motors(
        self,
        quantity: str,
        values: Sequence[float],
        *,
        sim_time: float,
        wall_time: float | None = None,
    ) -> None:
        """Motor telemetry: ``/vehicle/motors/<quantity>``, one series per motor named m1,
        m2, ... (buffered; e.g. quantity ``thrust``, ``speed``, ``command``)."""
        path = f"/vehicle/motors/{self._part(quantity)}"
        if path not in self._named:
            names = [f"m{i + 1}" for i in range(len(values))]
            self.rec.log(path, self.rr.SeriesLines(names=names), static=True)
            self._named.add(path)
        self._push(path, [float(v) for v in values], sim_time, wall_time)

    # ---- a mobile robot on a floor map ------------------------------------------------------
    @_safe
    def robot_pose_2d(
        self,
        x: float,
        y: float,
        theta: float,
        *,
        sim_time: float | None = None,
        wall_time: float | None = None,
    ) -> None:
        """The robot on the 2D map: ``/map/robot`` (a dot and a heading arrow, m and rad in
        the map frame) and ``/map/path`` (where it has been, points 5 cm apart). The 2D
        view's y axis points down, so y is drawn negated (the map's y points up)."""
        rr = self.rr
        self._at(sim_time, wall_time)
        y = -y
        heading = (0.5 * math.cos(theta), -0.5 * math.sin(theta))
        self.rec.log(
            "/map/robot",
            rr.Points2D([(x, y)], radii=0.2, colors=[(30, 120, 220)], labels=["robot"]),
            rr.Arrows2D(origins=[(x, y)], vectors=[heading], colors=[(30, 120, 220)]),
        )
        path = self._path2d
        if not path or math.dist(path[-1], (x, y)) >= 0.05:
            path.append((x, y))
        now = self._run_time(sim_time, time.time() if wall_time is None else wall_time)
        if len(path) > 1 and self._path_due(now):  # the whole path, once a second at most
            self.rec.log(
                "/map/path", rr.LineStrips2D([list(path)], radii=0.03, colors=[(30, 120, 220)])
            )

    # ---- lifecycle ----------------------------------------------------------------------
    @_safe
    def flush(self, timeout: float = 2.0) -> None:
        """Send buffered rows and wait (up to ``timeout``) until the sink has everything."""
        self._send_rows()
        self.rec.flush(timeout_sec=timeout)

    def close(self, timeout: float = 2.0) -> None:
        """Flush and close the sink (finalises the ``.rrd`` file). Idempotent, never raises."""
        with self._lock:
            if self.closed:
                return
            try:
                self._send_rows()
                self.rec.flush(timeout_sec=timeout)
                self.rec.disconnect()
            except Exception as e:
                self._failure("close", e)
            self.closed = True
        if self.errors > 1:
            print(f"rra viz ({self.process}): {self.errors} logging failures", file=sys.stderr)

    def __enter__(self) -> Logger:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()
