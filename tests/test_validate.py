"""Loading a system package and cross-reference validation (rra_agent.package.loader/validate).

Each case plants one broken reference in a copy of ``tests/data/mini`` and expects a located
error at the planted token, with a message saying what was expected. When the UVL loader is
not available the feature model comes from ``tests/data/mini_features.json`` (its equivalent).
"""

from __future__ import annotations

import importlib.util
import sys
import types
from pathlib import Path

import msgspec
import pytest
from conftest import copy_mini, plant, position

from rra_agent.errors import ErrorGroup, Location, ModelError, RraError
from rra_agent.models.features import FeatureModel
from rra_agent.package import loader
from rra_agent.package.loader import load_package, package_root
from rra_agent.package.validate import validate_package

DATA = Path(__file__).parent / "data"
MINI = DATA / "mini"


# ---- helpers -----------------------------------------------------------------------------
@pytest.fixture(autouse=True)
def features_loader(monkeypatch: pytest.MonkeyPatch) -> None:
    """Use the real UVL loader when there is one, else the JSON twin of the fixture's model."""
    if importlib.util.find_spec("rra_agent.dsl.uvl") is not None:
        return
    fm = msgspec.json.decode((DATA / "mini_features.json").read_bytes(), type=FeatureModel)
    monkeypatch.setattr(loader, "_load_features", lambda file: fm)


def errors_of(root: Path) -> list[ModelError]:
    return validate_package(load_package(root, validate=False))


# ---- a clean package ---------------------------------------------------------------------
def test_fixture_package_loads_and_is_valid() -> None:
    pkg = load_package(MINI)
    assert pkg.name == "mini"
    assert pkg.root == MINI
    assert [c.name for c in pkg.system.components][:3] == ["driver", "laser", "navigation"]
    assert set(pkg.deployment.features) == {"Manipulation"}
    assert pkg.runtime.replacement.strategy_for("radio_b") == "start-then-stop"
    assert pkg.measurements.data_type("LaserScan") is not None
    assert pkg.adaptation is None  # the manifest says `adaptation: null`
    assert set(pkg.docs) == {"manifest", "system", "deployment", "runtime", "measurements"}
    assert pkg.file("system") == MINI / "system.yaml"
    assert pkg.doc("system").loc("components", 1, "name") == Location(
        str(MINI / "system.yaml"), *position((MINI / "system.yaml").read_text(), "laser")
    )


def test_validation_forgets_the_package_modules(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    assert errors_of(root) == []
    assert "mini_functions" not in sys.modules
    assert str(root.resolve()) not in sys.path
    # The same module name in a changed copy is imported afresh, not taken from a cache.
    text = plant(root, "mini_functions.py", "def closest_obstacle(", "def closest_obs(")
    assert "closest_obs(" in text
    errors = errors_of(root)
    assert len(errors) == 1
    assert "unknown name 'closest_obstacle' in 'mini_functions'" in errors[0].message


# ---- one planted error per case ----------------------------------------------------------
# (file, old text, new text, token pointed at (its first occurrence in the new text, or
#  (token, nth)), expected message fragment)
CASES = [
    # system.yaml
    (
        "system.yaml",
        "{from: navigation.cmd_vel, to",
        "{from: navigaton.cmd_vel, to",
        "navigaton.cmd_vel",
        "unknown component 'navigaton' (did you mean 'navigation'? known: arm, driver,",
    ),
    (
        "system.yaml",
        "to: navigation.scan}",
        "to: navigation.scna}",
        "navigation.scna",
        "unknown port 'scna' of 'navigation' (did you mean 'scan'? known: cmd_vel, scan)",
    ),
    (
        "system.yaml",
        "{from: laser.scan, to: navigation.scan}",
        "{from: navigation.scan, to: navigation.scan}",
        "navigation.scan",
        "'navigation.scan' is a subscribe port; expected a publish port here",
    ),
    (
        "system.yaml",
        "{from: navigation.cmd_vel, to: driver.cmd_vel}",
        "{from: driver.battery, to: driver.cmd_vel}",
        "driver.cmd_vel}",
        "message type mismatch: 'driver.battery' publishes BatteryState but 'driver.cmd_vel'"
        " expects Twist",
    ),
    (
        "system.yaml",
        "{name: radio_in, direction: subscribe, type: str}",
        "{name: radio_in, direction: subscribe, type: strr}",
        "strr",
        "unknown type 'strr' (did you mean 'str'?",
    ),
    ("system.yaml", "host: robot", "host: robto", "robto", "unknown host 'robto'"),
    (
        "system.yaml",
        "hosts:\n  - name: robot\n",
        "hosts:\n  - name: robot\n  - name: robot\n",
        ("robot", 2),
        "duplicate host name 'robot'",
    ),
    (
        "system.yaml",
        "value: 0.5, unit: m/s",
        "value: 1.5, unit: m/s",
        "1.5",
        "value 1.5 is above the maximum 1.0",
    ),
    (
        "system.yaml",
        "  - {from: laser.scan, to: navigation.scan}\n",
        "  - {from: laser.scan, to: navigation.scan}\n" * 2,
        ("{from: laser.scan", 2),
        "duplicate connection laser.scan -> navigation.scan",
    ),
    # deployment.yaml
    (
        "deployment.yaml",
        "Manipulation:",
        "Manipulaton:",
        "Manipulaton",
        "unknown feature 'Manipulaton' (did you mean 'Manipulation'?",
    ),
    (
        "deployment.yaml",
        "Manipulation:",
        "ChannelA:",
        "ChannelA",
        "feature 'ChannelA' is bound at run time; its transformations belong in runtime.yaml",
    ),
    (
        "deployment.yaml",
        "include_component: arm",
        "include_component: laser",
        "laser",
        "component 'laser' is not optional",
    ),
    (
        "deployment.yaml",
        "include_component: arm",
        "include_component: radio_a",
        "radio_a",
        "component 'radio_a' is bound at run time; include it from runtime.yaml",
    ),
    (
        "deployment.yaml",
        "value: 0.3",
        "value: fast",
        "fast",
        "value 'fast' is not of type float (the type of parameter navigation.max_vel)",
    ),
    (
        "deployment.yaml",
        "value: 0.3",
        "value: -2",
        "-2",
        "value -2 is below the minimum 0.0 (parameter navigation.max_vel)",
    ),
    (
        "deployment.yaml",
        "parameter: max_vel",
        "parameter: max_vle",
        "max_vle",
        "unknown parameter 'max_vle' of 'navigation' (did you mean 'max_vel'?",
    ),
    (
        "deployment.yaml",
        "value: 0.3",
        "from_attribute: MaxVel",
        "MaxVel",
        "from_attribute is only allowed in the run-time resolution model (runtime.yaml)",
    ),
    (
        "deployment.yaml",
        "- include_component: arm",
        "- remove_component: arn",
        "arn",
        "unknown component 'arn' (did you mean 'arm'?",
    ),
    # runtime.yaml
    (
        "runtime.yaml",
        "include_component: radio_a",
        "include_component: arm",
        "arm",
        "component 'arm' is bound at deployment time; include it from deployment.yaml",
    ),
    (
        "runtime.yaml",
        "add_connection: {from: radio_a.rx, to: radio_switch.radio_in}",
        "add_connection: {from: radio_a.rx, to: driver.cmd_vel}",
        "{from: radio_a.rx, to: driver.cmd_vel}",
        "no connection radio_a.rx -> driver.cmd_vel in the template system model (declare it"
        " in system.yaml with optional: true)",
    ),
    (
        "runtime.yaml",
        "add_connection: {from: radio_a.rx, to: radio_switch.radio_in}",
        "add_connection: {from: laser.scan, to: navigation.scan}",
        "{from: laser.scan",
        "connection laser.scan -> navigation.scan is not optional",
    ),
    (
        "runtime.yaml",
        "add_connection: {from: radio_a.rx, to: radio_switch.radio_in}",
        "remove_connection: {from: radio_a.rx, to: radio_switch.radio_inn}",
        "radio_switch.radio_inn",
        "unknown port 'radio_inn' of 'radio_switch' (did you mean 'radio_in'?",
    ),
    (
        "runtime.yaml",
        "implementation: dwa",
        "implementation: dwb",
        "dwb",
        "unknown implementation 'dwb' of 'navigation' (did you mean 'dwa'? known: dwa)",
    ),
    (
        "runtime.yaml",
        "from_attribute: MaxVel",
        "from_attribute: MaxVal",
        "MaxVal",
        "unknown CV attribute 'MaxVal' (did you mean 'MaxVel'? known: MaxVel)",
    ),
    (
        "runtime.yaml",
        "from_attribute: MaxVel",
        "from_attribute: LatencyA",
        "LatencyA",
        "is a cim attribute; expected a cv one (known: MaxVel)",
    ),
    (
        "runtime.yaml",
        "ChannelB:",
        "Detection:",
        "Detection",
        "feature 'Detection' is bound at deployment time; its transformations belong in"
        " deployment.yaml",
    ),
    (
        "runtime.yaml",
        "  MotionBehavior:\n",
        '  "Motion Behavior": []\n  MotionBehavior:\n',
        "MotionBehavior:",
        "feature 'MotionBehavior' already has transformations (as 'Motion Behavior')",
    ),
    (
        "runtime.yaml",
        "radio_b: start-then-stop",
        "radio_c: start-then-stop",
        "radio_c",
        "unknown component 'radio_c' (did you mean",
    ),
    (
        "runtime.yaml",
        "{from: radio_a, to: radio_b}",
        "{from: radio_a, to: radio_x}",
        "radio_x",
        "unknown component 'radio_x'",
    ),
    (
        "runtime.yaml",
        "radio_b: start-then-stop",
        "radio_b: start-then-stop\n  stop_deadline: {radio_y: 0.01}",
        "radio_y",
        "unknown component 'radio_y' (did you mean",
    ),
    # measurements.yaml
    (
        "measurements.yaml",
        "charging: bool",
        "charging: boolean",
        "boolean",
        "unknown type 'boolean' (did you mean 'bool'?",
    ),
    (
        "measurements.yaml",
        '"list[float]"',
        '"list[flaot]"',
        '"list[flaot]"',
        "unknown type 'list[flaot]'",
    ),
    (
        "measurements.yaml",
        "mini_functions.closest_obstacle",
        "mini_functions.closest_obstacl",
        "mini_functions.closest_obstacl",
        "unknown name 'closest_obstacl' in 'mini_functions' (did you mean 'closest_obstacle'?",
    ),
    (
        "measurements.yaml",
        "function: mini_functions.speed",
        "function: mini_fnctions.speed",
        "mini_fnctions.speed",
        "cannot import 'mini_fnctions.speed': no module named 'mini_fnctions'",
    ),
    (
        "measurements.yaml",
        "function: mini_functions.speed",
        "function: speed",
        "speed",
        "unknown function 'speed'",
    ),
    (
        "measurements.yaml",
        "source: driver.battery",
        "source: driver.batery",
        "driver.batery",
        "unknown port 'batery' of 'driver' (did you mean 'battery'?",
    ),
    (
        "measurements.yaml",
        "source: laser.scan",
        "source: navigation.scan",
        "navigation.scan",
        "'navigation.scan' is a subscribe port; expected a publish port here",
    ),
    (
        "measurements.yaml",
        "driver.battery]",
        "driver.battry]",
        "driver.battry",
        "unknown port 'battry' of 'driver'",
    ),
    (
        "measurements.yaml",
        "field: level",
        "field: levl",
        "levl",
        "unknown field 'levl' of BatteryState (did you mean 'level'? known: charging, level)",
    ),
    (
        "measurements.yaml",
        "field: level",
        "field: charging",
        "charging\n",
        "field 'charging' of BatteryState is bool, but measurement 'BattLev' is float",
    ),
    (
        "measurements.yaml",
        "function: closest",
        "function: closets",
        "closets",
        "unknown function 'closets' (did you mean 'closest'?",
    ),
    (
        "measurements.yaml",
        "fields: {level: float, charging: bool}",
        "fields: {level: float, charging: bool}\n    optional: [charge]",
        "charge]",
        "unknown field 'charge' of BatteryState (did you mean 'charging'?",
    ),
    # rra.yaml
    (
        "rra.yaml",
        "[Detection]",
        "[Detecton]",
        "Detecton",
        "unknown feature 'Detecton' (did you mean 'Detection'?",
    ),
    (
        "rra.yaml",
        "[Detection]",
        "[Detection, ChannelA]",
        "ChannelA",
        "feature 'ChannelA' is bound at run time; a deployment selection names deployment-time"
        " features only",
    ),
]


@pytest.mark.parametrize(
    ("file", "old", "new", "token", "fragment"),
    CASES,
    ids=[f"{c[0]}:{c[2][:30]}" for c in CASES],
)
def test_planted_reference_error_is_located(
    tmp_path: Path, file: str, old: str, new: str, token: str | tuple[str, int], fragment: str
) -> None:
    root = copy_mini(tmp_path)
    text = plant(root, file, old, new)
    tok, nth = token if isinstance(token, tuple) else (token, 1)
    expected = Location(str(root / file), *position(text, tok, nth))
    errors = errors_of(root)
    matching = [e for e in errors if fragment in e.message]
    assert matching, f"no error containing {fragment!r} in {[e.headline for e in errors]}"
    assert matching[0].location == expected, matching[0].headline
    assert matching[0].source_line == text.splitlines()[expected.line - 1]


def test_a_cpu_latency_out_of_range_is_located(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    text = plant(root, "rra.yaml", "[Detection]", "[Detection]\nagents: {cpu_latency_us: -5}")
    with pytest.raises(ModelError) as info:
        load_package(root, validate=False)
    assert info.value.location == Location(
        str(root / "rra.yaml"), *position(text, "{cpu_latency_us")
    )
    assert "agents: cpu_latency_us must be 0..2000000000, got -5" in str(info.value)


def test_a_broken_function_module_is_reported_not_raised(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    (root / "broken_functions.py").write_text("import no_such_dependency_xyz\n\ndef f(x): ...\n")
    text = plant(root, "measurements.yaml", "mini_functions.speed", "broken_functions.f")
    (err,) = errors_of(root)
    assert err.location == Location(
        str(root / "measurements.yaml"), *position(text, "broken_functions.f")
    )
    assert "importing 'broken_functions' failed" in err.message
    assert "no_such_dependency_xyz" in err.message


def test_a_non_callable_function_is_reported(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    (root / "mini_functions.py").write_text(
        (MINI / "mini_functions.py").read_text() + "\nSPEED = 3\n"
    )
    plant(root, "measurements.yaml", "mini_functions.speed", "mini_functions.SPEED")
    (err,) = errors_of(root)
    assert err.message == "'mini_functions.SPEED' is not callable"


def test_errors_are_in_file_order(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    plant(root, "measurements.yaml", "source: laser.scan", "source: lazer.scan")
    plant(root, "system.yaml", "host: robot", "host: robto")
    plant(root, "runtime.yaml", "implementation: dwa", "implementation: dwb")
    plant(root, "system.yaml", "to: navigation.scan}", "to: navigation.scna}")
    errors = errors_of(root)
    files = [Path(e.location.file).name for e in errors if e.location]
    assert files == ["system.yaml", "system.yaml", "runtime.yaml", "measurements.yaml"]
    lines = [e.location.line for e in errors[:2] if e.location]
    assert lines == sorted(lines)


def test_load_package_validates_by_default(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    plant(root, "system.yaml", "host: robot", "host: robto")
    plant(root, "runtime.yaml", "implementation: dwa", "implementation: dwb")
    with pytest.raises(ErrorGroup) as info:
        load_package(root)
    assert [type(e) for e in info.value.errors] == [ModelError, ModelError]
    assert load_package(root, validate=False).name == "mini"


# ---- loading -------------------------------------------------------------------------------
def test_without_manifest_the_defaults_apply_and_the_folder_names_the_package(
    tmp_path: Path,
) -> None:
    root = copy_mini(tmp_path)
    (root / "rra.yaml").unlink()
    pkg = load_package(root)
    assert pkg.name == "mini"
    assert pkg.manifest.default_selection == []
    assert "manifest" not in pkg.docs
    assert pkg.adaptation is None  # default adaptation.rra does not exist: no rules


def test_errors_of_every_file_are_collected(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    system = plant(root, "system.yaml", "    host: robot\n", "    hots: robot\n")
    runtime = plant(root, "runtime.yaml", "default: stop-then-start", "default: stop")
    (root / "deployment.yaml").unlink()
    with pytest.raises(ErrorGroup) as info:
        load_package(root)
    heads = [e.headline for e in info.value.errors if isinstance(e, ModelError)]
    sys_at = "{}:{}:{}".format(root / "system.yaml", *position(system, "hots"))
    rt_at = "{}:{}:{}".format(root / "runtime.yaml", *position(runtime, "stop\n"))
    assert heads == [
        f"{sys_at}: unknown field 'hots' (did you mean 'host'? known: binding, container,"
        " description, host, implementation, implementations, name, optional, parameters,"
        " ports, ros2, scheduling, supervision)",
        f"{root / 'deployment.yaml'}: no such file (the deployment model)",
        f"{rt_at}: Invalid enum value 'stop'",
    ]


def test_a_missing_file_named_by_the_manifest_points_at_the_manifest(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    text = plant(root, "rra.yaml", "adaptation: null", "measurements: meas.yaml")
    with pytest.raises(ModelError) as info:
        load_package(root)
    assert info.value.location == Location(str(root / "rra.yaml"), *position(text, "meas.yaml"))
    assert "no such file" in info.value.message and "meas.yaml" in info.value.message


def test_an_explicit_adaptation_file_must_exist(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    text = plant(root, "rra.yaml", "adaptation: null", "adaptation: rules.rra")
    with pytest.raises(ModelError) as info:
        load_package(root)
    assert info.value.location == Location(str(root / "rra.yaml"), *position(text, "rules.rra"))


def test_the_adaptation_model_comes_from_the_rules_parser(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = copy_mini(tmp_path)
    plant(root, "rra.yaml", "adaptation: null", "adaptation: rules.rra")
    (root / "rules.rra").write_text("rule r1 ...\n")
    calls = []

    def parse_rules(text: str, file: str, fm: FeatureModel, measurements: object) -> str:
        calls.append((text, file, fm.root.name, measurements))
        return "the adaptation model"

    fake = types.ModuleType("rra_agent.dsl.rules")
    fake.parse_rules = parse_rules  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "rra_agent.dsl.rules", fake)
    pkg = load_package(root)
    assert pkg.adaptation == "the adaptation model"
    assert calls == [("rule r1 ...\n", str(root / "rules.rra"), "Mini", pkg.measurements)]


def test_rule_errors_are_collected_with_the_others(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    root = copy_mini(tmp_path)
    plant(root, "rra.yaml", "adaptation: null", "adaptation: rules.rra")
    (root / "rules.rra").write_text("rule\n")
    plant(root, "system.yaml", "system: mini", "system: [mini]")

    def parse_rules(text: str, file: str, fm: object, measurements: object) -> None:
        raise ErrorGroup([ModelError("bad rule", Location(file, 1, 1)), RraError("worse")])

    fake = types.ModuleType("rra_agent.dsl.rules")
    fake.parse_rules = parse_rules  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "rra_agent.dsl.rules", fake)
    with pytest.raises(ErrorGroup) as info:
        load_package(root)
    assert [str(e).splitlines()[0] for e in info.value.errors] == [
        f"{root / 'system.yaml'}:2:9: Expected `str`, got `array`",
        f"{root / 'rules.rra'}:1:1: bad rule",
        "worse",
    ]


def test_package_root(tmp_path: Path) -> None:
    assert package_root(MINI / "rra.yaml") == MINI
    with pytest.raises(RraError, match="no such system package"):
        package_root(tmp_path / "nope")
    with pytest.raises(RraError, match="not a system package"):
        package_root(tmp_path)
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(RraError, match="not a system package"):
        package_root(tmp_path / "x.txt")


def test_the_json_twin_matches_the_uvl_file() -> None:
    uvl = pytest.importorskip("rra_agent.dsl.uvl")
    twin = msgspec.json.decode((DATA / "mini_features.json").read_bytes(), type=FeatureModel)
    real = uvl.load_uvl(MINI / "features.uvl")
    assert real.binding == twin.binding
    assert real.aliases == twin.aliases
    assert real.parent == twin.parent
    assert {n: (f, a.value) for n, (f, a) in real.attributes.items()} == {
        n: (f, a.value) for n, (f, a) in twin.attributes.items()
    }


def test_a_reachability_measurement_names_a_host_of_the_model(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    meas = root / "measurements.yaml"
    meas.write_text(meas.read_text() + "  - {name: RobotUp, type: bool, reachable: robot}\n")
    assert errors_of(root) == []
    text = plant(root, "measurements.yaml", "reachable: robot", "reachable: robbot")
    (err,) = errors_of(root)
    assert err.location == Location(str(meas), *position(text, "robbot"))
    assert "unknown host 'robbot'" in err.message and "robot" in err.message


def test_a_reachability_measurement_is_a_bool_without_function(tmp_path: Path) -> None:
    root = copy_mini(tmp_path)
    meas = root / "measurements.yaml"
    meas.write_text(meas.read_text() + "  - {name: RobotUp, type: float, reachable: robot}\n")
    with pytest.raises(
        ModelError, match=r"measurements.yaml:\d+:\d+: a 'reachable' measurement is of type bool"
    ):
        errors_of(root)


# ---- what the Context Monitor may trust (finite, plausible, optional fields) ---------------
@pytest.mark.parametrize(
    ("old", "new", "token", "message"),
    [
        (
            '    field: level\n    unit: "%"',
            '    field: level\n    unit: "%"\n    plausible: {min: 5, max: 1}',
            "{min: 5",
            "'plausible' min 5.0 is above max 1.0",
        ),
        (
            '    field: level\n    unit: "%"',
            '    field: level\n    unit: "%"\n    plausible: {}',
            "{}",
            "'plausible' needs 'min', 'max' or both",
        ),
        (
            "  - name: BattLev\n    type: float",
            "  - name: BattLev\n    type: bool\n    plausible: {min: 0}",
            "plausible",
            "'plausible' bounds need a numeric measurement, not bool",
        ),
        (
            "    unit: m\n    finite: false",
            "    unit: m\n    finite: maybe",
            "maybe",
            "Expected `bool`, got `str`",
        ),
    ],
    ids=["min-above-max", "no-bounds", "not-numeric", "finite-not-bool"],
)
def test_measurement_trust_settings_are_checked_where_they_are_written(
    tmp_path: Path, old: str, new: str, token: str, message: str
) -> None:
    root = copy_mini(tmp_path)
    text = plant(root, "measurements.yaml", old, new)
    with pytest.raises(ModelError) as info:
        load_package(root)
    where = Location(str(root / "measurements.yaml"), *position(text, token))
    assert (info.value.location, info.value.message) == (where, message), info.value.headline


def test_a_measured_port_of_an_undeclared_type_is_a_warning(tmp_path: Path) -> None:
    """Samples of a type measurements.yaml does not declare can only be checked to be maps:
    `rra validate` says so at the measurement's source, and the package stays valid."""
    from rra_agent.package.validate import measurement_warnings

    root = copy_mini(tmp_path)
    plant(root, "system.yaml", "{name: cmd_vel, direction: subscribe, type: Twist}",
          "{name: cmd_vel, direction: subscribe, type: Twist}\n"
          "      - {name: level, direction: publish, type: float}")  # fmt: skip
    text = plant(root, "measurements.yaml", "source: driver.battery", "source: driver.level")
    text = plant(root, "measurements.yaml", "    field: level\n", "")
    text = plant(root, "measurements.yaml", "[navigation.cmd_vel, driver.battery]",
                 "[navigation.cmd_vel, driver.level]")  # fmt: skip
    pkg = load_package(root)
    warnings = [str(w) for w in measurement_warnings(pkg)]
    file = root / "measurements.yaml"
    at = "{}:{}:{}".format(file, *position(text, "driver.level"))
    at2 = "{}:{}:{}".format(file, *position(text, "driver.level", 2))
    tail = (
        "warning: 'driver.level' carries float, not a data type of data_types: the Context "
        "Monitor can only check that its samples are maps (give the port a data type to have "
        "every sample checked field by field)"
    )
    assert warnings == [f"{at}: {tail}", f"{at2}: {tail}"]
    assert measurement_warnings(load_package(MINI)) == []
