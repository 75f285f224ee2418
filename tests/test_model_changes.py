"""What a reload changes and what it may not change while the system runs, in process
(`rra_agent.model_changes.compare`; the reload itself: tests/test_reload.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from rra_agent.core.adaptation import AdaptationEngine
from rra_agent.core.reload import carry_over, engine_for
from rra_agent.deployment import deploy
from rra_agent.errors import LocatedError, RraError
from rra_agent.model_changes import Running, compare
from rra_agent.package.bundle import ModelBundle, bundle_of, digest_of
from rra_agent.package.loader import load_package
from tests.conftest import edit_text as edit
from tests.conftest import package_copy, position

ROOT = Path(__file__).resolve().parents[1]
RELAY = ROOT / "tests" / "data" / "relay_system"
#: What runs in the relay system at its default selection.
RUNNING = Running(
    implementations={n: "rra_agent.nodes.generic.Relay" for n in ("direct", "sink")}
    | {"source": "rra_agent.nodes.generic.Ticker"},
    hosts={"direct": "local", "sink": "local", "source": "local"},
    params={"sink": {"offset": 1.0}, "source": {"rate_hz": 20.0, "value": 1.0}},
    selection=frozenset({"Path", "Direct", "Tuning"}),
)


def headlines(errors: list[RraError]) -> list[str]:
    return [e.headline if isinstance(e, LocatedError) else str(e) for e in errors]


def test_a_rule_edit_is_allowed_and_named(tmp_path: Path) -> None:
    pkg = package_copy(tmp_path)
    edit(pkg, "adaptation.rra", "cdm.Level > 5", "cdm.Level > 2")
    out = compare(deploy(RELAY), deploy(pkg), RUNNING)
    assert out.allowed and out.changes == ["rule PathRule: changed"]


def test_comments_and_layout_change_nothing(tmp_path: Path) -> None:
    pkg = package_copy(tmp_path)
    edit(pkg, "adaptation.rra", "rule PathRule", "// a comment\n\nrule PathRule")
    edit(pkg, "system.yaml", "components:", "# the components\ncomponents:")
    out = compare(deploy(RELAY), deploy(pkg), RUNNING)
    assert out.allowed and out.changes == []


def test_what_cannot_change_live_is_refused_where_it_is_written(tmp_path: Path) -> None:
    pkg = package_copy(tmp_path)
    edit(pkg, "measurements.yaml", "data_types:\n", "data_types:\n  - {name: Other, fields: "
         "{value: float}}\n")  # fmt: skip
    text = edit(pkg, "system.yaml", "offset: {type: float, value: 0.0}\n    ports:\n      - {name"
                ": in, direction: subscribe, type: Sample}\n      - {name: out, direction: "
                "publish, type: Sample}\nconnections", "offset: {type: float, value: 0.0, max: "
                "0.5}\n    ports:\n      - {name: in, direction: subscribe, type: Sample}\n"
                "      - {name: out, direction: publish, type: Other}\nconnections")
    pkg_sys = str(pkg / "system.yaml")
    out = compare(deploy(RELAY), deploy(pkg), RUNNING)
    line, col = position(text, "Other")
    assert f"{pkg_sys}:{line}:{col}: component sink: port out: its type cannot change while " \
        "the system runs (Sample -> Other): samples of the old type are on the bus" in \
        headlines(out.refusals)  # fmt: skip
    line, col = position(text, "0.5}")
    assert f"{pkg_sys}:{line}:{col}: component sink: parameter offset: the value it runs with " \
        "(1.0) does not fit the new bounds: 1.0 is above its maximum 0.5" in \
        headlines(out.refusals)  # fmt: skip
    assert len(out.refusals) == 2


def test_removing_a_running_component_is_refused(tmp_path: Path) -> None:
    pkg = package_copy(tmp_path)
    text = edit(pkg, "system.yaml", "  - name: direct\n    implementation: rra_agent.nodes."
                "generic.Relay\n    optional: true\n    binding: runtime\n    parameters:\n"
                "      offset: {type: float, value: 0.0}\n    ports:\n      - {name: in, "
                "direction: subscribe, type: Sample}\n      - {name: out, direction: publish, "
                "type: Sample}\n", "")  # fmt: skip
    text = edit(pkg, "system.yaml", "  - {from: source.out, to: direct.in}\n", "")
    text = edit(pkg, "system.yaml", "  - {from: direct.out, to: sink.in, optional: true, "
                "binding: runtime}\n", "")  # fmt: skip
    edit(pkg, "runtime.yaml", "  Direct:\n    - include_component: direct\n    - add_connection:"
         " {from: direct.out, to: sink.in}\n", "  Direct: []\n")  # fmt: skip
    edit(pkg, "runtime.yaml", "  state_transfer:\n    - {from: direct, to: filtered}\n", "")
    out = compare(deploy(RELAY), deploy(pkg), RUNNING)
    line, col = position(text, "components:")
    [refusal] = headlines(out.refusals)
    assert refusal.startswith(f"{pkg / 'system.yaml'}:{line}:{col}: ")
    assert refusal.endswith("component direct runs on host local: it cannot be removed while "
                            "the system runs (select a configuration without it first)")
    # Not running (the Filtered path is not selected): removing it is a change.
    idle = Running(**{**RUNNING.__dict__, "implementations": {
        k: v for k, v in RUNNING.implementations.items() if k != "direct"}})  # fmt: skip
    assert compare(deploy(RELAY), deploy(pkg), idle).allowed


def test_a_changed_deployment_time_selection_is_refused(tmp_path: Path) -> None:
    pkg = package_copy(tmp_path)
    extra = "        mandatory\n            Extra\n"
    text = edit(pkg, "features.uvl", "        mandatory\n", extra)
    out = compare(deploy(RELAY), deploy(pkg), RUNNING)
    line, col = position(text, "Extra")
    assert f"{pkg / 'features.uvl'}:{line}:{col}: the deployment-time selection would change " \
        "(+Extra, -nothing): it cannot change while the system runs (restart it with `rra up`)" \
        in headlines(out.refusals)  # fmt: skip


def test_a_digest_names_the_models_not_their_folder(tmp_path: Path) -> None:
    pkg = package_copy(tmp_path)
    a, b = bundle_of(load_package(RELAY)), bundle_of(load_package(pkg))
    assert a.digest == b.digest == digest_of(a.files) and len(a.digest) == 16
    edit(pkg, "adaptation.rra", "> 5", "> 2")
    assert bundle_of(load_package(pkg)).digest != a.digest
    with pytest.raises(RraError, match="digest mismatch"):
        ModelBundle(files={**a.files, "adaptation.rra": "x"}, digest=a.digest).verified()
    with pytest.raises(RraError, match="not a plain path"):
        ModelBundle.of({"../etc/passwd": ""})


def test_carry_over_keeps_the_selection_and_the_operators_choices(tmp_path: Path) -> None:
    dep = deploy(RELAY)
    assert dep.package.adaptation is not None
    old = AdaptationEngine(dep.package.features, dep.selection, dep.package.adaptation)
    old.tick(1.0, {"Level": (7.0, 1.0)})
    assert "Filtered" in old.selection and old.cv == {"Gain": 7.0}
    old.force({"Filtered": "on"})
    pkg = package_copy(tmp_path)
    edit(pkg, "adaptation.rra", "> 5", "> 8")
    new_dep = deploy(pkg)
    assert new_dep.package.adaptation is not None
    new = carry_over(old, engine_for(new_dep.package.features, new_dep.selection,
                                     new_dep.package.adaptation), {})  # fmt: skip
    assert new.selection == old.selection and new.cv == {"Gain": 7.0}
    assert new.forced == {"Filtered": True} and new.ticks == 0  # every rule runs next tick
