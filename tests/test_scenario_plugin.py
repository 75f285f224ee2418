"""The pytest plugin (rra_agent.scenario.plugin), driven through pytest's own `pytester`.

Collection (one item per scenario or per case, the ini pattern, the slow marker, schema and
name errors shown at collection as file:line:col) is checked without running anything. Two
runs use tests/data/relay_system (four nodes, so they take seconds): a scenario that passes,
and a copy of it with one planted failing expectation, whose report must name the scenario
line and the observed value and keep the events log.
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

ROOT = Path(__file__).resolve().parents[1]
RELAY = ROOT / "tests" / "data" / "relay_system"
#: Load the plugin by module whether or not the ``rra`` entry point is installed (blocking
#: the entry point's name first, so it is never registered twice).
PLUGIN = ("-p", "no:rra", "-p", "rra_agent.scenario.plugin")

RELAY_SCENARIO = """\
name: relay
description: Level above 5 swaps direct for filtered; Gain follows the level
package: pkg
duration: 4
timeline:
  - {at: 1.5, name: high, set_params: {node: source, params: {value: 7.0}}}
expect:
  - feature Direct selected during [0, high]
  - measurement Level == 7 within 0.5 s after high
  - feature Filtered selected within 0.5 s after high
  - swap(direct -> filtered) within 1.5 s after high
  - cv Gain == 7 within 0.5 s after high
  - param sink.offset == 7 from high + 1.5
  - sink.out.value > 100 within 2 s after high
  - no node FATAL
  - no orphan process
"""


def project(pytester: pytest.Pytester, **files: str) -> None:
    shutil.copytree(RELAY, pytester.path / "pkg")
    for name, text in files.items():
        path = pytester.path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def run(pytester: pytest.Pytester, *args: str) -> pytest.RunResult:
    # a subprocess: an in-process run shares (and restores) sys.modules with this one, so
    # message classes could be imported twice and isinstance checks fail
    return pytester.runpytest_subprocess(*PLUGIN, "-p", "no:cacheprovider", *args)


# ---- collection ---------------------------------------------------------------------------------
def test_one_item_per_scenario_or_case(pytester: pytest.Pytester) -> None:
    cases = RELAY_SCENARIO.replace("name: relay", "name: relay2") + (
        "cases:\n  - {name: adaptive}\n  - {name: control, adaptation: false, slow: true}\n"
    )
    project(
        pytester,
        **{
            "relay.scenario.yaml": RELAY_SCENARIO,
            "more/two.scenario.yaml": cases.replace("package: pkg", "package: ../pkg"),
            "more/ignored.yaml": "name: x\n",
        },
    )
    result = run(pytester, "--collect-only", "-q")
    assert result.ret == 0, result.stdout.str()
    ids = [line for line in result.stdout.lines if "::" in line]
    assert ids == [
        "more/two.scenario.yaml::adaptive",
        "more/two.scenario.yaml::control",
        "relay.scenario.yaml::relay",
    ]
    # the slow case is deselected by the marker
    result = run(pytester, "--collect-only", "-q", "-m", "not slow")
    ids = [line for line in result.stdout.lines if "::" in line]
    assert "more/two.scenario.yaml::control" not in ids and len(ids) == 2
    assert "1 deselected" in result.stdout.str()
    # reportinfo points at the scenario file and the case's line
    items, _ = pytester.inline_genitems(*PLUGIN, str(pytester.path / "more"))
    assert [(i.location[0], i.location[1]) for i in items] == [
        ("more/two.scenario.yaml", cases.splitlines().index("  - {name: adaptive}")),
        ("more/two.scenario.yaml", cases.splitlines().index(cases.splitlines()[-1])),
    ]
    assert items[0].location[2] == "scenario relay2::adaptive"
    assert {m.name for m in items[1].iter_markers()} == {"slow", "scenario"}


def test_the_ini_pattern_chooses_the_files(pytester: pytest.Pytester) -> None:
    project(
        pytester,
        **{
            "scenarios/a/relay.scenario.yaml": RELAY_SCENARIO.replace("pkg", "../../pkg"),
            "other/relay.scenario.yaml": RELAY_SCENARIO.replace("pkg", "../pkg"),
        },
    )
    pytester.makeini("[pytest]\nrra_scenario_files = scenarios/**/*.scenario.yaml\n")
    result = run(pytester, "--collect-only", "-q")
    ids = [line for line in result.stdout.lines if "::" in line]
    assert ids == ["scenarios/a/relay.scenario.yaml::relay"]


def test_schema_and_name_errors_show_at_collection(pytester: pytest.Pytester) -> None:
    bad = RELAY_SCENARIO.replace("duration: 4", "durashun: 4").replace("Filtered", "Filterd")
    names = RELAY_SCENARIO.replace("feature Filtered", "feature Filterd")
    project(pytester, **{"bad.scenario.yaml": bad, "names.scenario.yaml": names})
    result = run(pytester, "--collect-only", "-q")
    assert result.ret == pytest.ExitCode.INTERRUPTED
    out = result.stdout.str()
    line = bad.splitlines().index("durashun: 4") + 1
    assert f"bad.scenario.yaml:{line}:1: unknown field 'durashun'" in out
    line = names.splitlines().index("  - feature Filterd selected within 0.5 s after high") + 1
    assert f"names.scenario.yaml:{line}:13: unknown feature 'Filterd'" in out
    assert "did you mean 'Filtered'?" in out
    assert "2 errors" in out


# ---- running ------------------------------------------------------------------------------------
def test_a_passing_scenario_and_a_planted_failure(pytester: pytest.Pytester) -> None:
    planted = RELAY_SCENARIO.replace("name: relay", "name: planted").replace(
        "cv Gain == 7 within", "cv Gain == 9 within"
    )
    project(pytester, **{"relay.scenario.yaml": RELAY_SCENARIO, "planted.scenario.yaml": planted})
    pytester.makeini(f"[pytest]\nrra_scenario_runs = {pytester.path / 'runs'}\n")
    result = run(pytester, "-rA")
    out = result.stdout.str()
    result.assert_outcomes(passed=1, failed=1)
    line = planted.splitlines().index("  - cv Gain == 9 within 0.5 s after high") + 1
    assert f"planted.scenario.yaml:{line}: expectation failed: cv Gain == 9 within 0.5 s" in out
    observed = re.search(r"observed: never in \[(\S+), (\S+)\] s: (.*)", out)
    assert observed is not None, out
    assert observed[3].endswith("7") or "(last 7)" in observed[3]  # what Gain was
    kept = re.search(r"kept: (\S+events\.jsonl)", out)
    assert kept is not None and Path(kept[1]).exists()
    assert Path(kept[1]).parent.parent == pytester.path / "runs"
    # the passed run's folder is gone, the failed one's kept; the table is in the report
    assert len(list((pytester.path / "runs").iterdir())) == 1
    # (the table fits 100 columns: the expectation may be wrapped in its column)
    assert re.search(r"relay\s+swap\(direct -> filtered\) within 1\.5 s[^\n]*\s+pass", out)


def test_planted_failures_in_a_copy_of_an_object_storing_scenario(
    pytester: pytest.Pytester,
) -> None:
    """Edit four expectations of radio.scenario.yaml (a value, a state, a swap, a feature):
    each fails naming its line and what the run showed; the others still pass."""
    text = (ROOT / "scenarios" / "object_storing" / "radio.scenario.yaml").read_text()
    text = text.replace(
        "name: radio\n", f"name: radio\npackage: {ROOT / 'scenarios' / 'object_storing'}\n"
    )
    planted = {
        "measurement BattLev < 50 within 1 s after low_battery": (
            "measurement BattLev < 30 within 1 s after low_battery",
            r"never in \[3\.00, 4\.00\] s: 40",
        ),
        "node radio_driver_b STOPPED from low_battery + 1.5": (
            "node radio_driver_b RUNNING from low_battery + 1.5",
            r"STOPPED at 4\.50 s",
        ),
        "swap(radio_driver_b -> radio_driver_a) within 1.5 s after low_battery": (
            "swap(radio_driver_a -> radio_driver_b) within 1.5 s after low_battery",
            r"not in \[3\.00, 4\.50\] s; happened at 0\.\d\d s",
        ),
        "feature ChannelB selected within 1 s": (
            "feature ChannelB selected from low_battery + 1",
            r"not selected at 4\.00 s",
        ),
    }
    for old, (new, _) in planted.items():
        assert old in text
        text = text.replace(old, new)
    (pytester.path / "radio.scenario.yaml").write_text(text)
    pytester.makeini(f"[pytest]\nrra_scenario_runs = {pytester.path / 'runs'}\n")
    result = run(pytester, "-k", "adaptive")
    result.assert_outcomes(failed=1, deselected=2)
    out = result.stdout.str()
    lines = text.splitlines()
    planted_lines = set()
    for new, observed in planted.values():
        line = next(i for i, t in enumerate(lines, 1) if t.strip() == f"- {new}")
        planted_lines.add(str(line))
        head = re.escape(f"radio.scenario.yaml:{line}: expectation failed: {new}")
        assert re.search(head + r"\n\s+observed: " + observed, out), (new, out)
    # exactly the planted ones failed (pytest may print each twice: with CI set, its short
    # summary repeats the whole message, so count distinct lines)
    failed = set(re.findall(r"radio\.scenario\.yaml:(\d+): expectation failed", out))
    assert failed == planted_lines


@pytest.mark.system
def test_the_adversity_options_are_the_suite_s_for_every_path_it_runs() -> None:
    """``pytest --cpu-hog --hostile scenarios/...`` given alone was refused ("unrecognized
    arguments": the options were tests/conftest.py's, read only for paths under tests/).
    They are the rootdir's conftest.py's: the scenarios are collected, the header says what
    is in effect (the hog spins for the session; no hostile client on a scenario's run)."""
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "pytest", "--cpu-hog", "--hostile", "--collect-only",
         "scenarios/quadcopter/motor_failure.scenario.yaml"],
        cwd=ROOT, capture_output=True, text=True, timeout=120, check=False,
    )  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    assert "rra adversity: --cpu-hog --hostile" in out.stdout
    assert "not scenario runs" in out.stdout
    assert "<ScenarioItem control>" in out.stdout
