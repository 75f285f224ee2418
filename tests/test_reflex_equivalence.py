"""The same decisions with reflexes and without (issue 25 item 2): the shipped scenario cases
where a reflex acts (with ``-m slow``: every other case of every shipped scenario) run twice
as real systems, once as shipped (reflexes on where eligible) and
once from a copy of its package with ``reflexes: {enabled: false}``; the selections the
Adaptation Engine made (in order, repeats dropped), their CV values, what was in effect at the
end and the nodes running at the end are identical. Only timing may differ: the comparison
starts from the selection in force a second after deployment (what a run records before
depends on when its recorder attached), and CV values computed from drifting measurements
are equal within 2 %.

Where a case fired a reflex, the run with reflexes shows it (an event of kind ``reflex``,
confirmed): the comparison is not between two runs without any.
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml

from rra_agent.bus import messages as m
from rra_agent.scenario.model import load_scenario
from rra_agent.scenario.plugin import shared_run
from rra_agent.scenario.runner import run_case

pytestmark = pytest.mark.system

ROOT = Path(__file__).resolve().parents[1]
FILES = sorted((ROOT / "scenarios").glob("*/*.scenario.yaml"))


def label_of(path: Path, case: str | None) -> str:
    return f"{path.parent.name}/{path.name.split('.')[0]}/{case or 'default'}"


#: Cases where a reflex fires: the run with reflexes must show it confirmed, or the comparison
#: would be between two runs without any. The quadcopter's motor failure, and the same with
#: the Resolution Engine leader killed 0.2 s before it (the reflex confirmed by its standby).
FIRES = {"quadcopter/motor_failure/adaptive", "quadcopter/engine_faults/resolution_killed"}
#: Every other case of every shipped scenario is marked ``slow`` (``pytest -m slow
#: tests/test_reflex_equivalence.py``, about 8 minutes here): in those both runs take the
#: engines' path, and the comparison can only repeat the scenario's own run-to-run timing.
CASES = [
    pytest.param(
        f,
        i,
        id=label_of(f, c.case),
        marks=() if label_of(f, c.case) in FIRES else (pytest.mark.slow,),
    )
    for f in FILES
    for i, c in enumerate(load_scenario(f).cases)
]


def without_reflexes(package: Path, into: Path) -> Path:
    """A copy of ``package`` whose manifest turns reflexes off."""
    shutil.copytree(package, into, ignore=shutil.ignore_patterns("__pycache__"))
    manifest = yaml.safe_load((into / "rra.yaml").read_text())
    manifest["reflexes"] = {**(manifest.get("reflexes") or {}), "enabled": False}
    (into / "rra.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return into


#: Seconds after deployment in which what a run records depends on when its recorder and the
#: monitor's first values came: the comparison starts from the selection in force then.
SETTLE = 1.0
#: CV values computed from measurements that drift (a battery drained by motion) differ by
#: when they were computed: equal within this relative tolerance.
CV_TOLERANCE = 0.02


def decisions(rec: Any) -> list[tuple[tuple[str, ...], dict[str, float]]]:
    """The run-time selections in order (one entry per change of the feature selection, with
    the CV values it came with), from the one in force `SETTLE` s after deployment."""
    sels = [s for s in rec.selections if isinstance(s, m.Selection)]
    first = max((i for i, s in enumerate(sels) if s.stamp - rec.t0 <= SETTLE), default=0)
    out: list[tuple[tuple[str, ...], dict[str, float]]] = []
    for s in sels[first:]:
        features = tuple(sorted(s.features))
        if not out or out[-1][0] != features:
            out.append((features, dict(s.cv)))
    if sels:  # the final CV values, whatever changed them last
        out[-1] = (out[-1][0], dict(sels[-1].cv))
    return out


def same_cv(a: dict[str, float], b: dict[str, float]) -> bool:
    return a.keys() == b.keys() and all(
        math.isclose(a[k], b[k], rel_tol=CV_TOLERANCE, abs_tol=1e-9) for k in a
    )


def configuration(rec: Any) -> dict[str, Any]:
    """What was in effect at the end and which nodes ran (active or not)."""
    last = rec.effects[-1] if rec.effects else None
    return {
        "in effect": sorted(last.features) if last else None,
        "running": sorted((n.node, n.active) for n in rec.nodes if n.state == "RUNNING"),
    }


def reflex_events(rec: Any) -> list[m.AdaptationEvent]:
    return [e for e in rec.events if isinstance(e, m.AdaptationEvent) and e.kind == "reflex"]


@pytest.mark.parametrize(("path", "index"), CASES)
def test_the_same_decisions_with_and_without_reflexes(
    path: Path, index: int, tmp_path: Path, pytestconfig: pytest.Config
) -> None:
    case = load_scenario(path).cases[index]
    off_pkg = without_reflexes(case.package, tmp_path / "pkg-off")
    # As shipped (reflexes on): the suite's own run of the case if it had one.
    on = shared_run(pytestconfig, case.id) or run_case(case, tmp_path / "on")
    runs = {
        "on": on,
        "off": run_case(dataclasses.replace(case, package=off_pkg), tmp_path / "off"),
    }
    for name, run in runs.items():
        assert run.error is None and run.recording is not None, f"{name}: {run.error}"
    on, off = (runs[k].recording for k in ("on", "off"))
    assert reflex_events(off) == []
    assert all(e.outcome == "ok" for e in reflex_events(on)), reflex_events(on)
    assert bool(reflex_events(on)) or label_of(path, case.case) not in FIRES, "no reflex fired"
    if not reflex_events(on):
        # No reflex acted: both runs took the engines' path, and what differs between them
        # is the scenario's own run-to-run timing (faults injected into a running plan).
        return
    a, b = decisions(on), decisions(off)
    assert [f for f, _ in a] == [f for f, _ in b], (a, b)
    assert all(same_cv(x, y) for (_, x), (_, y) in zip(a, b, strict=True)), (a, b)
    assert configuration(on) == configuration(off)
