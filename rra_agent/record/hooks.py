"""What the engine processes call to record a run (`rra_agent.record.format`).

Each engine process opens one `RecordWriter` (``<run>/record/<replica>-<pid>.rec``) through
`open_writer`, and calls the recorder of its role:

- `AdaptationRecorder`: every call the Adaptation Engine process makes on its pure core, in
  order: each evaluation (`tick`) with the measurements new since the previous one as
  received (value, stamp, sources, arrival), and its result; `adopt`, `forced`, `force`,
  `avail`, `lead`, `reload`. Every replica records (a standby's history is what it decides
  from when it takes over). Measurements that arrive and are coalesced away before an
  evaluation are not recorded: they were never used.
- `MonitorRecorder`: the source samples the Context Monitor leader computed from (after
  coalescing), raw, for re-running its logic on edited measurements.
- `ResolutionRecorder`: the Run-time Resolution Engine leader's `EngineState` versions and
  the operators' commands.

Recording never raises into the engine: a failed write stops it with one line on stderr.
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.deployment import Deployment
from rra_agent.record import format as f
from rra_agent.record.run import keep_models, record_dir


def open_writer(
    run_dir: Path | str | None, process: str, role: str, dep: Deployment, host: str = ""
) -> f.RecordWriter | None:
    """The record file of this process, begun with its `Start` record (None: no run folder,
    or the models cannot be recorded)."""
    if run_dir is None:
        return None
    bundle = dep.bundle
    if bundle is None:
        return None
    try:
        keep_models(Path(run_dir), bundle)
        writer = f.RecordWriter(record_dir(Path(run_dir)) / f"{process}-{os.getpid()}{f.SUFFIX}")
    except OSError as e:
        print(f"rra {process}: cannot record: {e}", file=sys.stderr, flush=True)
        return None
    writer.write(
        f.Start(
            process=process, role=role, pid=os.getpid(), stamp=time.time(), system=dep.system,
            models=bundle.digest, deployment=sorted(dep.selection), host=host,
        )
    )  # fmt: skip
    return writer


class _Recorder:
    """What every engine's record has: its leadership and the models it runs."""

    def __init__(self, writer: f.RecordWriter) -> None:
        self.writer = writer

    def lead(self, leading: bool, fence: m.Fence | None) -> None:
        self.writer.write(f.Lead(stamp=time.time(), leading=leading, fence=fence))

    def reload(self, models: str, previous: str) -> None:
        self.writer.write(f.Reload(stamp=time.time(), models=models, previous=previous))


class AdaptationRecorder(_Recorder):
    """The Adaptation Engine's calls on its core (see the module doc)."""

    def __init__(self, writer: f.RecordWriter) -> None:
        super().__init__(writer)
        #: The measurements of the previous tick (name -> the (value, stamp) tuple).
        self._previous: dict[str, tuple[Any, float]] = {}
        #: The newest measurement received of each name, and when (Zenoh's thread).
        self._received: dict[str, tuple[m.Measurement, float]] = {}

    def received(self, msg: m.Measurement) -> None:
        self._received[msg.name] = (msg, time.time())

    def tick(
        self,
        now: float,
        values: Mapping[str, tuple[Any, float]],
        changed: Iterable[str],
        *,
        force: bool,
        lead: bool,
        selection: Iterable[str],
        cv: Mapping[str, float],
        fired: list[str],
        seq: int,
    ) -> None:
        previous = self._previous
        new = [self._ctx(name, sample) for name, sample in values.items()
               if previous.get(name) is not sample]  # fmt: skip
        self._previous = dict(values)
        self.writer.write(
            f.Tick(
                now=now, changed=sorted(changed), ctx=new, force=force, lead=lead,
                selection=sorted(selection), cv=dict(cv), fired=fired, seq=seq,
            )
        )  # fmt: skip

    def _ctx(self, name: str, sample: tuple[Any, float]) -> f.Ctx:
        value, stamp = sample
        got = self._received.get(name)
        if got is not None and got[0].stamp == stamp and got[0].value == value:
            msg, at = got
            return f.Ctx(name=name, value=value, stamp=stamp, at=at, sources=dict(msg.sources))
        return f.Ctx(name=name, value=value, stamp=stamp)

    def adopt(
        self, selection: Iterable[str], cv: Mapping[str, float], why: str, error: str
    ) -> None:
        self.writer.write(f.Adopt(stamp=time.time(), selection=sorted(selection), cv=dict(cv),
                                  why=why, error=error))  # fmt: skip

    def forced(self, forced: Mapping[str, bool]) -> None:
        self.writer.write(f.Forced(stamp=time.time(), forced=dict(forced)))

    def force(self, features: Mapping[str, str], operator: str, error: str) -> None:
        self.writer.write(f.Force(stamp=time.time(), features=dict(features), operator=operator,
                                  error=error))  # fmt: skip

    def avail(self, unavailable: list[m.Unavailable]) -> None:
        self.writer.write(f.Avail(stamp=time.time(), unavailable=list(unavailable)))



class MonitorRecorder(_Recorder):
    """The Context Monitor leader's source samples (see the module doc)."""

    def sample(self, source: str, data: bytes, stamp: float) -> None:
        self.writer.write(f.Sample(source=source, data=data, stamp=stamp, at=time.time()))



class ResolutionRecorder(_Recorder):
    """The Run-time Resolution Engine leader's states and the operators' commands."""

    def __init__(self, writer: f.RecordWriter) -> None:
        super().__init__(writer)
        self._version: tuple[int, str, str, int] | None = None

    def state(self, state: m.EngineState) -> None:
        """Each version once (the leader republishes an unchanged state every second)."""
        version = (*state.fence.term, state.version)
        if version != self._version:
            self._version = version
            self.writer.write(f.State(state=state))

    def command(self, kind: str, args: Mapping[str, Any], operator: str, outcome: str) -> None:
        self.writer.write(f.Command(stamp=time.time(), kind=kind, args=dict(args),
                                    operator=operator, outcome=outcome))  # fmt: skip
