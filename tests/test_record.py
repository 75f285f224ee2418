"""The run record and its offline replay, in process (docs/recording.md).

A record is made here as the Adaptation Engine process makes it (`AdaptationRecorder` around
an `AdaptationEngine`, the relay system's and the object-storing system's rules), then read
back, damaged, replayed and replayed against edited models. The record of real runs, and
`rra replay` on them, are tested in tests/test_replay_system.py.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import msgspec
import pytest

from rra_agent.bus import messages as m
from rra_agent.cli.commands import main as rra
from rra_agent.core.adaptation import AdaptationEngine
from rra_agent.deployment import Deployment, deploy
from rra_agent.errors import RraError
from rra_agent.record import format as f
from rra_agent.record.hooks import AdaptationRecorder, open_writer
from rra_agent.record.replay import load_edited, open_run, replay, what_if
from rra_agent.record.run import RunInfo, begin, record_dir, seal

ROOT = Path(__file__).resolve().parents[1]
RELAY = ROOT / "tests" / "data" / "relay_system"
OBJECT_STORING = ROOT / "scenarios" / "object_storing"
T0 = 1_700_000_000.0


def record_run(
    run_dir: Path, dep: Deployment, steps: Iterable[tuple[float, dict[str, Any]]], *,
    sealed: bool = True, replicas: tuple[str, ...] = ("adaptation-a",),
) -> None:
    """A run's record as the Adaptation Engine processes write it: each replica evaluates
    every step (t: seconds after T0; the measurements received since the step before),
    the first one leads and publishes."""
    assert dep.bundle is not None and dep.package.adaptation is not None
    info = RunInfo(system=dep.system, deployment=sorted(dep.selection), started=T0,
                   models=dep.models)  # fmt: skip
    begin(run_dir, info, dep.bundle)
    steps = list(steps)
    for i, name in enumerate(replicas):
        writer = open_writer(run_dir, name, "adaptation", dep)
        assert writer is not None
        rec = AdaptationRecorder(writer)
        engine = AdaptationEngine(dep.package.features, dep.selection, dep.package.adaptation)
        rec.lead(i == 0, m.Fence(epoch=1, leader=replicas[0]))
        values: dict[str, tuple[Any, float]] = {}
        seq = 0
        for t, new in steps:
            now = T0 + t
            for k, v in new.items():
                msg = m.Measurement(name=k, value=v, stamp=now - 0.001)
                rec.received(msg)
                values[k] = (msg.value, msg.stamp)
            result = engine.tick(now, dict(values), changed=set(new))
            seq += i == 0
            rec.tick(now, dict(values), set(new), force=False, lead=i == 0,
                     selection=result.selection, cv=result.cv, fired=[], seq=seq if i == 0 else 0)
        writer.close(end=T0 + 100)
    if sealed:
        seal(run_dir)


def relay_steps() -> list[tuple[float, dict[str, Any]]]:
    """Level 1 for 2 s, 7 (Filtered) for 2 s, then 3: 0.1 s apart."""
    return [(0.1 * i, {"Level": 1.0 if i < 20 else 7.0 if i < 40 else 3.0}) for i in range(60)]


@pytest.fixture
def relay_run(tmp_path: Path) -> Path:
    run = tmp_path / "run"
    record_run(run, deploy(RELAY), relay_steps(), replicas=("adaptation-a", "adaptation-b"))
    return run


# ---- the file format ------------------------------------------------------------------------
def test_records_are_read_back_as_written(tmp_path: Path) -> None:
    w = f.RecordWriter(tmp_path / "x.rec")
    start = f.Start(process="p", role="adaptation", pid=1, stamp=1.0, system="s", models="m",
                    deployment=[])  # fmt: skip
    tick = f.Tick(now=2.0, ctx=[f.Ctx(name="A", value=float("inf"), stamp=1.5)], lead=True,
                  selection=["X"], cv={"G": 0.1 + 0.2}, seq=3)  # fmt: skip
    w.write(start)
    w.write(tick)
    w.close(end=3.0)
    got = f.read_file(tmp_path / "x.rec")
    assert got.records[:2] == [start, tick] and isinstance(got.records[2], f.End)
    assert got.records[1].cv["G"] == 0.1 + 0.2 and not got.torn  # floats exact, inf kept


def two_records(path: Path) -> None:
    """A record file of a start and a leadership, closed."""
    w = f.RecordWriter(path)
    w.write(f.Start(process="p", role="r", pid=1, stamp=1.0, system="s", models="m",
                    deployment=[]))  # fmt: skip
    w.write(f.Lead(stamp=2.0, leading=True))
    w.close()


def test_a_torn_last_record_is_the_end_of_a_killed_writer(tmp_path: Path) -> None:
    two_records(tmp_path / "x.rec")
    data = (tmp_path / "x.rec").read_bytes()
    (tmp_path / "x.rec").write_bytes(data[:-3])
    got = f.read_file(tmp_path / "x.rec")
    assert got.torn and len(got.records) == 1


def test_a_changed_byte_is_damage_named_by_file_and_offset(tmp_path: Path) -> None:
    two_records(tmp_path / "x.rec")
    data = bytearray((tmp_path / "x.rec").read_bytes())
    data[-2] ^= 0xFF
    (tmp_path / "x.rec").write_bytes(bytes(data))
    with pytest.raises(f.RecordError, match=r"x\.rec: damaged record at byte \d+ \(CRC"):
        f.read_file(tmp_path / "x.rec")


# ---- replay ---------------------------------------------------------------------------------
def test_a_record_replays_exactly(relay_run: Path) -> None:
    run = open_run(relay_run)
    result = replay(run)
    assert result.difference is None, result.difference
    assert result.evaluations == 120 and result.published == 60
    assert result.replicas == ["adaptation-a", "adaptation-b"] and run.sealed


def test_a_recorded_decision_the_models_do_not_make_is_the_first_difference(
    relay_run: Path,
) -> None:
    """The record says Direct at 2.5 s where the rules select Filtered: replay names it."""
    path = next(record_dir(relay_run).glob("adaptation-a-*.rec"))
    got = f.read_file(path)
    out = b""
    for rec in got.records:
        if isinstance(rec, f.Tick) and abs(rec.now - (T0 + 2.5)) < 1e-6:
            rec = msgspec.structs.replace(rec, selection=["Direct", "Path", "Tuning"])
        out += f.frame(rec)
    path.write_bytes(out)
    (record_dir(relay_run) / "SEAL.json").unlink()  # a run that was not sealed: read as is
    result = replay(open_run(relay_run))
    assert result.difference is not None
    assert result.difference.line().startswith(
        "t=2.500 s adaptation-a: feature Direct: recorded selected, replayed not selected")


def test_a_truncated_sealed_record_is_refused(relay_run: Path, capsys) -> None:
    path = next(record_dir(relay_run).glob("adaptation-b-*.rec"))
    path.write_bytes(path.read_bytes()[:-40])
    assert rra(["replay", str(relay_run)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "truncated" in err[0] and path.name in err[0], err


def test_tampered_models_are_refused(relay_run: Path, capsys) -> None:
    rules = next((record_dir(relay_run) / "models").glob("*/adaptation.rra"))
    rules.write_text(rules.read_text().replace("> 5", "> 6"))
    assert rra(["replay", str(relay_run)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "digest mismatch" in err[0] and "models were changed" in err[0]


def test_a_changed_record_file_of_a_sealed_run_is_refused(relay_run: Path, capsys) -> None:
    path = next(record_dir(relay_run).glob("adaptation-a-*.rec"))
    data = bytearray(path.read_bytes())
    data[40] ^= 1
    path.write_bytes(bytes(data))
    assert rra(["replay", str(relay_run)]) == 1
    err = capsys.readouterr().err.strip()
    assert "digest mismatch: changed since the run ended" in err and "\n" not in err


def test_an_unsealed_run_is_replayed_as_far_as_it_goes(tmp_path: Path, capsys) -> None:
    run = tmp_path / "run"
    record_run(run, deploy(RELAY), relay_steps(), sealed=False)
    path = next(record_dir(run).glob("adaptation-a-*.rec"))
    path.write_bytes(path.read_bytes()[:-5])  # killed in the middle of its last write
    assert rra(["replay", str(run)]) == 0
    out = capsys.readouterr()
    assert "every selection and CV value as recorded" in out.out
    assert "did not end cleanly" in out.err and "torn record" in out.err


def test_not_a_run_folder(tmp_path: Path, capsys) -> None:
    assert rra(["replay", str(tmp_path)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.endswith("not a recorded run (no record/ folder: was it run with --no-record, "
                        "or by an older rra?)") and "\n" not in err  # fmt: skip


# ---- what-if --------------------------------------------------------------------------------
def edited(tmp_path: Path, src: Path, old: str, new: str, file: str = "adaptation.rra") -> Path:
    pkg = tmp_path / "edited"
    shutil.copytree(src, pkg, ignore=shutil.ignore_patterns("__pycache__", "*.scenario.yaml"))
    text = (pkg / file).read_text()
    assert text.count(old) == 1
    (pkg / file).write_text(text.replace(old, new))
    return pkg


def test_what_if_an_edited_threshold_changes_exactly_the_expected_decisions(
    relay_run: Path, tmp_path: Path
) -> None:
    """Level > 5 -> Level > 2: Filtered from the start until the level drops to ... still
    3 > 2: Filtered to the end, where the run had Direct; the 7 stretch agrees."""
    run = open_run(relay_run)
    result = what_if(run, load_edited(run, edited(tmp_path, RELAY, "> 5", "> 2")))
    lines = [(mo.what, round(mo.start, 3), round(mo.end, 3), mo.recorded, mo.edited, mo.rules)
             for mo in result.moments]  # fmt: skip
    assert lines == [
        ("feature Direct", 4.0, 5.9, "selected", "not selected", ("PathRule",)),
        ("feature Filtered", 4.0, 5.9, "not selected", "selected", ("PathRule",)),
    ]
    assert result.evaluations == 60  # the leader's only


def test_what_if_of_a_cv_rule(tmp_path: Path) -> None:
    """object_storing: MaxVel follows BattLev; with the battery term halved every
    evaluation after the battery is known differs, and only MaxVel."""
    run_dir = tmp_path / "run"
    dep = deploy(OBJECT_STORING, ["Detection"])
    steps = [(0.1 * i, {"BattLev": 80.0, "ObstDist": 1.0, "SemLoc": "RoomA", "Material": "Wood"})
             for i in range(10)]  # fmt: skip
    record_run(run_dir, dep, steps)
    run = open_run(run_dir)
    pkg = edited(tmp_path, OBJECT_STORING, "* (BattLev / 100)", "* (BattLev / 200)")
    result = what_if(run, load_edited(run, pkg))
    assert [mo.what for mo in result.moments] == ["cv MaxVel"]
    [moment] = result.moments
    assert moment.start == 0.0 and moment.end == pytest.approx(0.9)
    # 0.4 + 0.4 * 0.8 * (1 - e^-1) against 0.4 + 0.4 * 0.4 * (1 - e^-1)
    assert float(moment.recorded) == pytest.approx(0.60228, abs=1e-5)
    assert float(moment.edited) == pytest.approx(0.50114, abs=1e-5)
    assert moment.rules == ("MaxVelocity.maxVelBattObst",)


def test_what_if_with_unchanged_rules_finds_nothing(relay_run: Path) -> None:
    run = open_run(relay_run)
    assert what_if(run, load_edited(run, RELAY)).moments == []


def test_a_package_that_no_longer_matches_the_recording(relay_run: Path, tmp_path: Path) -> None:
    run = open_run(relay_run)
    other = edited(tmp_path, RELAY, "cdm.Level > 5", "cdm.Speed > 5")
    measurements = other / "measurements.yaml"
    measurements.write_text(measurements.read_text().replace(
        "max_age_ms: 2000", "max_age_ms: 2000\n  - {name: Speed, type: float, source: "
        "sink.out, field: value}"))  # fmt: skip
    with pytest.raises(RraError, match=r"measurement Speed reads sink\.out, whose samples the "
                       r"run did not record"):  # fmt: skip
        what_if(run, load_edited(run, other))


def test_a_package_of_another_system_or_deployment_is_refused(
    relay_run: Path, tmp_path: Path
) -> None:
    run = open_run(relay_run)
    with pytest.raises(RraError, match="system object_storing, the run was of relay_system"):
        load_edited(run, OBJECT_STORING)
    renamed = edited(tmp_path, RELAY, "Relay {abstract}", "Relais {abstract}", "features.uvl")
    manifest = renamed / "rra.yaml"
    manifest.write_text(manifest.read_text().replace("[Relay]", "[Relais]"))
    with pytest.raises(RraError, match="no feature Relay of the recorded deployment-time"):
        load_edited(run, renamed)


def test_rra_replay_what_if_prints_the_moments(relay_run: Path, tmp_path: Path, capsys) -> None:
    pkg = edited(tmp_path, RELAY, "> 5", "> 2")
    assert rra(["replay", str(relay_run), "--package", str(pkg), "--no-rrd"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert any("feature Filtered: recorded not selected, edited selected  (rule PathRule)" in line
               for line in out)  # fmt: skip
    assert out[-1] == "rra replay: 2 moment(s) where the decisions differ"
    assert all(len(line) <= 100 for line in out)
