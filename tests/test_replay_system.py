"""Replay equivalence and what-if on recordings of the shipped scenarios, in real processes.

Each shipped package's scenario is run with ``rra test --out DIR --keep`` (its engines record
into the run folder), then ``rra replay DIR`` must re-run every recorded evaluation of every
Adaptation Engine replica to the same selection and CV values (exit 0). A leader killed in
the run (``engine_faults``) is replayed too: the killed replica's file ends where it was
killed, its restart is a file of its own. The what-if test edits the radio rule's threshold
and checks exactly which decisions change; the damaged-record tests truncate and change a
real recording.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from rra_agent.record.replay import load_edited, open_run, what_if
from rra_agent.scenario import expectations as x
from rra_agent.scenario.plugin import shared_run

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
#: One case of each shipped package (and the engine failover), by scenario file and case.
CASES = [
    ("quadcopter/motor_failure.scenario.yaml", "motor_failure::adaptive"),
    ("quadcopter/engine_faults.scenario.yaml", "engine_faults::adaptation_killed"),
    ("object_storing/radio.scenario.yaml", "radio::adaptive"),
    ("base_station/link_cut.scenario.yaml", "link_cut::short"),
    # Its battery is a ROS 2 topic: samples the monitor decoded from CDR, recorded decoded.
    ("ros2_rover/power.scenario.yaml", "power::adaptive"),
]

pytestmark = pytest.mark.system


def rra(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rra_agent", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT, check=False)  # fmt: skip


class Runs:
    """The run folders of the scenario cases recorded in this module (each recorded once; the
    suite's own run of a shipped case when it had one, `shared_run`)."""

    def __init__(self, base: Path, config: pytest.Config) -> None:
        self.base = base
        self.config = config
        self.done: dict[str, Path] = {}

    def get(self, scenario: str, case: str) -> Path:
        shared = shared_run(self.config, case)
        if shared is not None and (shared.run_dir / "record" / "run.json").exists():
            self.done.setdefault(case, shared.run_dir)
        if case not in self.done:
            out = rra("test", str(SCENARIOS / scenario), "-k", case, "--out", str(self.base),
                      "--keep")  # fmt: skip
            folder = self.base / case.replace("::", "-")
            assert (folder / "record" / "run.json").exists(), out.stdout + out.stderr
            self.done[case] = folder
        return self.done[case]


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory, pytestconfig: pytest.Config) -> Runs:
    return Runs(tmp_path_factory.mktemp("runs"), pytestconfig)


@pytest.mark.parametrize(("scenario", "case"), CASES, ids=[c for _, c in CASES])
def test_a_recorded_run_replays_to_the_same_decisions(runs: Runs, scenario: str, case: str):
    folder = runs.get(scenario, case)
    out = rra("replay", str(folder), timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.splitlines()[-1] == "rra replay: every selection and CV value as recorded"
    first = out.stdout.splitlines()[0]
    assert " evaluations (" in first and not first.startswith("rra replay: 0 "), first


def test_the_killed_leader_and_its_restart_are_both_in_the_record(runs: Runs) -> None:
    folder = runs.get(*CASES[1])
    run = open_run(folder)
    adaptation = [fr.records[0].process for fr in run.files["adaptation"]]
    assert len(adaptation) == 3, adaptation  # a, b, and the killed one restarted
    assert run.sealed  # `rra up` ended cleanly: the killed process's file is as it was left


def test_what_if_an_edited_threshold_changes_exactly_the_expected_decisions(
    runs: Runs, tmp_path: Path
) -> None:
    """radio: the battery drops from 100 % to 40 % at low_battery. With the Radio rule's
    threshold at 30 % instead of 50 %, the low-latency channel B stays: from the recorded
    switch to channel A (after the injection) to the end, and only there, ChannelA and
    ChannelB differ."""
    folder = runs.get(*CASES[2])
    pkg = tmp_path / "edited"
    shutil.copytree(SCENARIOS / "object_storing", pkg,
                    ignore=shutil.ignore_patterns("*.scenario.yaml", "__pycache__"))  # fmt: skip
    rules = pkg / "adaptation.rra"
    rules.write_text(rules.read_text().replace('cdm.BattLev > "50"', 'cdm.BattLev > "30"'))
    run = open_run(folder)
    result = what_if(run, load_edited(run, pkg))
    rec = x.load_recording((folder / "recording.msgpack").read_bytes())
    low = next(a.stamp for a in rec.injections if a.name == "low_battery") - run.info.started
    assert {m.what for m in result.moments} == {"feature ChannelA", "feature ChannelB"}
    # The recorded switch to channel A (after the injection, however late the machine saw it).
    tl = result.recorded
    switch = next(t for t, sel in zip(tl.times, tl.selections, strict=True)
                  if t >= low and "ChannelA" in sel)  # fmt: skip
    for moment in result.moments:
        assert moment.start == pytest.approx(switch), (moment, switch)
        assert moment.end == pytest.approx(result.recorded.times[-1])
        assert moment.rules == ("Radio",)
    a = next(mo for mo in result.moments if mo.what == "feature ChannelA")
    assert (a.recorded, a.edited) == ("selected", "not selected")
    # The command: the same moments, exit 0, and the side-by-side recording.
    out = rra("replay", str(folder), "--package", str(pkg), "--rrd", str(tmp_path / "w.rrd"))
    assert out.returncode == 0, out.stdout + out.stderr
    assert "rra replay: 2 moment(s) where the decisions differ" in out.stdout
    from rra_agent.viz.recording import entity_paths

    paths = entity_paths(tmp_path / "w.rrd")
    assert {"/recorded/features/ChannelA", "/edited/features/ChannelA", "/differences",
            "/context/BattLev"} <= paths, paths  # fmt: skip


def test_a_truncated_or_tampered_recording_is_one_clear_line(runs: Runs, tmp_path: Path):
    folder = runs.get(*CASES[2])
    cut = tmp_path / "cut"
    shutil.copytree(folder, cut)
    record = sorted((cut / "record").glob("adaptation-a-*.rec"))[0]
    record.write_bytes(record.read_bytes()[: record.stat().st_size // 2])
    out = rra("replay", str(cut))
    assert out.returncode == 1 and out.stdout == ""
    [line] = out.stderr.strip().splitlines()
    assert line.startswith(f"rra replay: {record}: truncated: ") and line.endswith(
        "when the run ended"), line
    tampered = tmp_path / "tampered"
    shutil.copytree(folder, tampered)
    rules = next((tampered / "record" / "models").glob("*/adaptation.rra"))
    rules.write_text(rules.read_text().replace('> "50"', '> "60"'))
    out = rra("replay", str(tampered))
    assert out.returncode == 1 and len(out.stderr.strip().splitlines()) == 1, out.stderr
    assert "digest mismatch" in out.stderr and "the recorded models were changed" in out.stderr
    # Nothing of the original recording was touched: it still replays.
    assert rra("replay", str(folder)).returncode == 0


def test_a_package_that_no_longer_matches_the_recording_is_one_line(
    runs: Runs, tmp_path: Path
) -> None:
    folder = runs.get(*CASES[2])
    pkg = tmp_path / "edited"
    shutil.copytree(SCENARIOS / "object_storing", pkg,
                    ignore=shutil.ignore_patterns("*.scenario.yaml", "__pycache__"))  # fmt: skip
    manifest = pkg / "rra.yaml"
    features = pkg / "features.uvl"
    features.write_text(features.read_text().replace("Detection", "Detect"))
    for path in (manifest, pkg / "deployment.yaml", pkg / "runtime.yaml"):
        path.write_text(path.read_text().replace("Detection", "Detect"))
    out = rra("replay", str(folder), "--package", str(pkg), "--no-rrd")
    assert out.returncode == 1 and out.stdout == "", out.stdout
    [line] = out.stderr.strip().splitlines()
    assert "no feature Detection of the recorded deployment-time selection" in line, line
