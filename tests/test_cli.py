"""The ``rra`` command line: ``validate`` and ``resolve``, in process and as a subprocess.

Every YAML model file of ``tests/data/mini`` is corrupted in a copy, once per kind of mistake
(unknown field, wrong type, dangling reference, duplicate key, YAML syntax error); ``rra
validate`` must exit 1 and print a ``file:line:col:`` line at the planted token, whose position
is computed from the corrupted text.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml
from conftest import copy_mini, plant, position, run_rra

from rra_agent.cli import commands as cli
from rra_agent.cli import main
from rra_agent.cli.resolve import split_selection
from rra_agent.errors import RraError

pytest.importorskip("rra_agent.dsl.uvl")

MINI = Path(__file__).parent / "data" / "mini"
REPO = Path(__file__).resolve().parent.parent


# ---- helpers -----------------------------------------------------------------------------
def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    rc = main(argv)
    out, err = capsys.readouterr()
    return rc, out, err


run_subprocess = run_rra


# ---- the corruption matrix ---------------------------------------------------------------
# kind -> file -> (old, new, (token, nth) pointed at, message fragment)
Plant = tuple[str, str, tuple[str, int], str]
MATRIX: dict[str, dict[str, Plant]] = {
    "unknown-field": {
        "rra.yaml": (
            "adaptation: null\n",
            "adaptation: null\nadaption: x\n",
            ("adaption", 1),
            "unknown field 'adaption' (did you mean 'adaptation'?",
        ),
        "system.yaml": (
            "    host: robot\n",
            "    host: robot\n    colour: red\n",
            ("colour", 1),
            "unknown field 'colour'",
        ),
        "deployment.yaml": (
            "- include_component: arm\n",
            "- include_component: arm\n      also: x\n",
            ("also", 1),
            "unknown field 'also' (known: add_connection,",
        ),
        "runtime.yaml": (
            "  default: stop-then-start",
            "  defualt: stop-then-start",
            ("defualt", 1),
            "unknown field 'defualt' (did you mean 'default'?",
        ),
        "measurements.yaml": (
            "    unit: m\n",
            "    unit: m\n    units: m\n",
            ("units", 1),
            "unknown field 'units' (did you mean 'unit'?",
        ),
    },
    "wrong-type": {
        "rra.yaml": ("name: mini", "name: [mini]", ("[mini]", 1), "Expected `str`, got `array`"),
        "system.yaml": (
            "implementation: mini_nodes.Arm\n    optional: true",
            "implementation: mini_nodes.Arm\n    optional: maybe",
            ("maybe", 1),
            "Expected `bool`, got `str`",
        ),
        "deployment.yaml": (
            "value: 0.3}",
            "value: {x: 1}}",
            ("{x: 1}", 1),
            "Expected `bool | int | float | str | array | null`, got `object`",
        ),
        "runtime.yaml": (
            "default: stop-then-start",
            "default: 42",
            ("42", 1),
            "Expected `str`, got `int`",
        ),
        "measurements.yaml": (
            "type: float\n    source: driver.battery",
            "type: double\n    source: driver.battery",
            ("double", 1),
            "Invalid enum value 'double'",
        ),
    },
    "dangling-reference": {
        "rra.yaml": (
            "[Detection]",
            "[Detecton]",
            ("Detecton", 1),
            "unknown feature 'Detecton' (did you mean 'Detection'?",
        ),
        "system.yaml": (
            "to: driver.cmd_vel}",
            "to: drivr.cmd_vel}",
            ("drivr.cmd_vel", 1),
            "unknown component 'drivr' (did you mean 'driver'?",
        ),
        "deployment.yaml": (
            "include_component: arm",
            "include_component: arn",
            ("arn", 1),
            "unknown component 'arn' (did you mean 'arm'?",
        ),
        "runtime.yaml": (
            "implementation: dwa",
            "implementation: dwx",
            ("dwx", 1),
            "unknown implementation 'dwx' of 'navigation' (did you mean 'dwa'? known: dwa)",
        ),
        "measurements.yaml": (
            "source: laser.scan",
            "source: laser.sacn",
            ("laser.sacn", 1),
            "unknown port 'sacn' of 'laser' (did you mean 'scan'? known: scan)",
        ),
    },
    "duplicate-key": {
        "rra.yaml": (
            "name: mini\n",
            "name: mini\nname: other\n",
            ("name", 2),
            "duplicate key 'name' (first at line",
        ),
        "system.yaml": (
            "  - name: laser\n",
            "  - name: laser\n    name: lidar\n",
            ("name: lidar", 1),
            "duplicate key 'name'",
        ),
        "deployment.yaml": (
            "value: 0.3}\n",
            "value: 0.3}\n  Manipulation: []\n",
            ("Manipulation", 2),
            "duplicate key 'Manipulation'",
        ),
        "runtime.yaml": (
            "    radio_b: start-then-stop\n",
            "    radio_b: start-then-stop\n    radio_b: stop-then-start\n",
            ("radio_b: stop", 1),
            "duplicate key 'radio_b'",
        ),
        "measurements.yaml": (
            "    field: level\n",
            "    field: level\n    field: charging\n",
            ("field: charging", 1),
            "duplicate key 'field'",
        ),
    },
    "yaml-syntax": {
        "rra.yaml": (
            "description: A small but",
            "description: A small: but",
            (": but", 1),
            "YAML syntax: mapping values are not allowed here",
        ),
        "system.yaml": (
            "  - name: laser\n",
            "  - name: laser: x\n",
            (": x", 1),
            "YAML syntax: mapping values are not allowed here",
        ),
        "deployment.yaml": (
            "    - set_parameter",
            "\t- set_parameter",
            ("\t", 1),
            "YAML syntax: found character '\\t' that cannot start any token",
        ),
        "runtime.yaml": (
            "  ChannelB:\n",
            "  ChannelB:\n\t\n",
            ("\t", 1),
            "YAML syntax: found character '\\t' that cannot start any token",
        ),
        "measurements.yaml": (
            "    unit: m\n",
            "    unit: m: s\n",
            (": s", 1),
            "YAML syntax: mapping values are not allowed here",
        ),
    },
}
CASES = [(kind, file, *p) for kind, files in MATRIX.items() for file, p in files.items()]


def corrupt(tmp_path: Path, file: str, old: str, new: str, token: tuple[str, int]) -> tuple:
    """A corrupted copy; (root, expected ``file:line:col:`` prefix)."""
    root = copy_mini(tmp_path)
    text = plant(root, file, old, new)
    line, col = position(text, *token)
    return root, f"{root / file}:{line}:{col}: "


@pytest.mark.parametrize(
    ("kind", "file", "old", "new", "token", "fragment"),
    [c for c in CASES if c[0] in ("unknown-field", "yaml-syntax")],
    ids=[f"{c[0]}-{c[1]}" for c in CASES if c[0] in ("unknown-field", "yaml-syntax")],
)
def test_every_command_prints_a_model_error_as_validate_does(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    kind: str,
    file: str,
    old: str,
    new: str,
    token: tuple[str, int],
    fragment: str,
) -> None:
    """One format: ``file:line:col: message``, one line, whichever command met the error."""
    root, prefix = corrupt(tmp_path, file, old, new, token)
    _, validated, _ = run(["validate", str(root)], capsys)
    assert validated.startswith(prefix + fragment), validated
    for command in (["check"], ["resolve"]):
        rc, out, err = run([*command, str(root)], capsys)
        assert rc == 1 and out == ""
        assert err == validated, (command, err)


def test_a_rule_error_is_one_line_in_check_as_in_validate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pkg = tmp_path / "os"
    shutil.copytree(REPO / "scenarios" / "object_storing", pkg)
    rules = pkg / "adaptation.rra"
    rules.write_text(rules.read_text() + "\nrule Bad: set_attribute(Nope) with_value(1)\n")
    _, validated, _ = run(["validate", str(pkg)], capsys)
    rc, _, err = run(["check", str(pkg)], capsys)
    assert rc == 1 and err == validated and len(err.splitlines()) == 1, err
    assert err.startswith(f"{rules}:"), err


@pytest.mark.parametrize(
    ("kind", "file", "old", "new", "token", "fragment"),
    CASES,
    ids=[f"{c[0]}-{c[1]}" for c in CASES],
)
def test_validate_reports_a_planted_error_at_its_place(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    kind: str,
    file: str,
    old: str,
    new: str,
    token: tuple[str, int],
    fragment: str,
) -> None:
    root, prefix = corrupt(tmp_path, file, old, new, token)
    rc, out, err = run(["validate", str(root)], capsys)
    assert rc == 1
    assert prefix + fragment in out, out
    assert len(out.splitlines()) == 1, out  # just the planted problem, one line
    assert err == f"{root}: 1 error(s)\n"
    assert "Traceback" not in out + err


SUBPROCESS_CASES = [
    ("duplicate-key", "rra.yaml"),
    ("dangling-reference", "system.yaml"),
    ("yaml-syntax", "deployment.yaml"),
    ("unknown-field", "runtime.yaml"),
    ("wrong-type", "measurements.yaml"),
]


@pytest.mark.parametrize(("kind", "file"), SUBPROCESS_CASES)
@pytest.mark.system
def test_validate_as_a_subprocess(tmp_path: Path, kind: str, file: str) -> None:
    old, new, token, fragment = MATRIX[kind][file]
    root, prefix = corrupt(tmp_path, file, old, new, token)
    proc = run_subprocess("validate", str(root))
    assert proc.returncode == 1, proc.stderr
    (line,) = proc.stdout.splitlines()
    assert line.startswith(prefix + fragment)
    assert proc.stderr == f"{root}: 1 error(s)\n"


@pytest.mark.system
def test_a_uvl_syntax_error_is_located(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = copy_mini(tmp_path)
    path = root / "features.uvl"
    text = path.read_text() + "\nconstraints\n    Manipulation => => Detection\n"
    path.write_text(text)
    line, col = position(text, "=>", 2)
    rc, out, err = run(["validate", str(root)], capsys)
    assert rc == 1
    assert out.startswith(f"{path}:{line}:{col}: "), out
    assert "Traceback" not in err
    proc = run_subprocess("validate", str(root))
    assert proc.returncode == 1
    assert proc.stdout.startswith(f"{path}:{line}:{col}: ")
    assert "Traceback" not in proc.stderr


def test_validate_lists_errors_of_several_files(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = copy_mini(tmp_path)
    for kind, file in (("wrong-type", "system.yaml"), ("duplicate-key", "runtime.yaml")):
        old, new, _, _ = MATRIX[kind][file]
        plant(root, file, old, new)
    (root / "measurements.yaml").unlink()
    rc, out, err = run(["validate", str(root)], capsys)
    assert rc == 1
    lines = out.splitlines()
    assert len(lines) == 3
    assert lines[0].startswith(f"{root / 'system.yaml'}:")
    assert lines[1].startswith(f"{root / 'runtime.yaml'}:")
    assert lines[2] == f"{root / 'measurements.yaml'}: no such file (the measurements model)"
    assert err == f"{root}: 3 error(s)\n"


@pytest.mark.system
def test_validate_a_clean_package(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = run(["validate", str(MINI)], capsys)
    assert (rc, err) == (0, "")
    assert out == (
        f"{MINI}: ok (8 features (4 run-time), 7 components, 4 connections, 3 data types,"
        " 3 measurements)\n"
    )
    proc = run_subprocess("validate", "tests/data/mini", cwd=REPO)
    assert (proc.returncode, proc.stdout) == (0, out.replace(str(MINI), "tests/data/mini"))


def test_validate_an_unknown_package(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = run(["validate", str(tmp_path / "nope")], capsys)
    assert (rc, out) == (1, "")
    assert err == f"rra validate: {tmp_path / 'nope'}: no such system package (folder not found)\n"
    rc, out, err = run(["validate", str(tmp_path)], capsys)
    assert rc == 1 and "not a system package" in err


# ---- resolve -------------------------------------------------------------------------------
@pytest.fixture
def resolution_engine() -> None:
    pytest.importorskip("rra_agent.core.features")
    pytest.importorskip("rra_agent.core.resolution")


def component_names(model: dict) -> list[str]:
    return [c["name"] for c in model["components"]]


@pytest.mark.usefixtures("resolution_engine")
def test_resolve_prints_the_configured_model_as_yaml(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, err = run(["resolve", str(MINI), "--select", "Manipulation"], capsys)
    assert (rc, err) == (0, "")
    assert out.startswith("# Deployment-time Configured System Model of 'mini'\n")
    assert "# selection: Mini, Task, Manipulation\n" in out
    model = yaml.safe_load(out)
    assert list(model) == ["system", "components", "connections", "hosts"]  # Struct order
    assert "arm" in component_names(model)
    nav = next(c for c in model["components"] if c["name"] == "navigation")
    assert nav["parameters"]["max_vel"]["value"] == 0.3
    assert {"from": "laser.scan", "to": "navigation.scan"} in model["connections"]


@pytest.mark.usefixtures("resolution_engine")
@pytest.mark.parametrize("fmt", ["yaml", "json"])
def test_resolve_prints_bounds_in_the_parameters_type(
    fmt: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """An int parameter's bounds are ints (``min: 0``, not ``0.0``), a float's floats."""
    rc, out, _ = run(["resolve", str(REPO / "scenarios" / "object_storing"), "-f", fmt], capsys)
    assert rc == 0
    model = json.loads(out) if fmt == "json" else yaml.safe_load(out)
    params = [p for c in model["components"] for p in c["parameters"].values()]
    bounded = [p for p in params if "min" in p or "max" in p]
    assert {p["type"] for p in bounded} == {"int", "float"}
    for p in bounded:
        for bound in ("min", "max"):
            if bound in p:
                assert type(p[bound]) is {"int": int, "float": float}[p["type"]], p
    if fmt == "yaml":
        assert "      type: int\n" in out and "      min: 0\n" in out and "min: 0.0\n" in out


@pytest.mark.usefixtures("resolution_engine")
def test_resolve_defaults_to_the_manifest_selection_and_writes_json(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_file = tmp_path / "configured.json"
    rc, out, err = run(["resolve", str(MINI), "--format", "json", "-o", str(out_file)], capsys)
    assert (rc, out, err) == (0, "", f"wrote {out_file}\n")
    model = json.loads(out_file.read_text())
    assert "arm" not in component_names(model)  # default_selection: [Detection]
    rc, out, _ = run(["resolve", str(MINI), "-s", "Detection", "-f", "yaml"], capsys)
    assert yaml.safe_load(out) == model


@pytest.mark.usefixtures("resolution_engine")
def test_resolve_accepts_lists_and_repeats(capsys: pytest.CaptureFixture[str]) -> None:
    rc, out, _ = run(["resolve", str(MINI), "-s", "Task, Manipulation", "-s", "Mini"], capsys)
    assert rc == 0 and "arm" in component_names(yaml.safe_load(out))


@pytest.mark.usefixtures("resolution_engine")
@pytest.mark.parametrize(
    ("select", "fragment"),
    [("Manipulaton", "Manipulaton"), ("ChannelA", "ChannelA"), ("Detection,Manipulation", "")],
)
def test_resolve_an_impossible_selection(
    capsys: pytest.CaptureFixture[str], select: str, fragment: str
) -> None:
    rc, out, err = run(["resolve", str(MINI), "--select", select], capsys)
    assert (rc, out) == (1, "")
    assert err.startswith("rra resolve: ") and fragment in err
    assert "Traceback" not in err


@pytest.mark.usefixtures("resolution_engine")
def test_resolve_refuses_an_invalid_package(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    old, new, token, fragment = MATRIX["dangling-reference"]["system.yaml"]
    root, prefix = corrupt(tmp_path, "system.yaml", old, new, token)
    rc, out, err = run(["resolve", str(root)], capsys)
    assert (rc, out) == (1, "")
    assert err.startswith(prefix + fragment)


@pytest.mark.usefixtures("resolution_engine")
@pytest.mark.system
def test_resolve_as_a_subprocess() -> None:
    proc = run_subprocess("resolve", str(MINI), "--select", "Manipulation", "--format", "json")
    assert proc.returncode == 0, proc.stderr
    assert "arm" in component_names(json.loads(proc.stdout))


# ---- the command shell ---------------------------------------------------------------------
def test_without_a_command_help_is_printed(capsys: pytest.CaptureFixture[str]) -> None:
    rc, _, err = run([], capsys)
    assert rc == 2 and "validate" in err and "resolve" in err


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--version"])
    assert info.value.code == 0
    assert capsys.readouterr().out.startswith("rra ")


def test_ctrl_c_exits_130_quietly(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def interrupted(args: object) -> int:
        raise KeyboardInterrupt

    cmd = cli.COMMANDS["validate"]
    monkeypatch.setitem(cli.COMMANDS, "validate", cli.Command(cmd.help, cmd.configure, interrupted))
    assert run(["validate", "x"], capsys) == (130, "", "")


def test_any_rra_error_is_one_line_without_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def failing(args: object) -> int:
        raise RraError("the engine is on fire")

    cmd = cli.COMMANDS["resolve"]
    monkeypatch.setitem(cli.COMMANDS, "resolve", cli.Command(cmd.help, cmd.configure, failing))
    assert run(["resolve", "x"], capsys) == (1, "", "rra resolve: the engine is on fire\n")


@pytest.mark.system
def test_split_selection() -> None:
    assert split_selection(["A,B", " C ", ",", "D,"]) == ["A", "B", "C", "D"]


# ---- with adaptation rules -------------------------------------------------------------------
RULES = """rule channel:
    if (BattLev < 20) activate_feature(ChannelB)
    else activate_feature(ChannelA)

rule motion:
    set_attribute(MaxVel) with_value(MaxVel.min)
"""


def test_validate_parses_the_adaptation_rules(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("rra_agent.dsl.rules")
    root = copy_mini(tmp_path)
    plant(root, "rra.yaml", "adaptation: null", "adaptation: adaptation.rra")
    (root / "adaptation.rra").write_text(RULES)
    rc, out, _ = run(["validate", str(root)], capsys)
    assert rc == 0 and out.rstrip().endswith(", 3 measurements, 2 rules)"), out
    text = RULES.replace("activate_feature(ChannelB)", "activate_feature(ChanelB)")
    (root / "adaptation.rra").write_text(text)
    line, col = position(text, "ChanelB")
    rc, out, _ = run(["validate", str(root)], capsys)
    assert rc == 1
    assert out.startswith(f"{root / 'adaptation.rra'}:{line}:{col}: "), out
    assert "ChanelB" in out and "ChannelB" in out


@pytest.mark.system
def test_lazy_handlers_import_on_use() -> None:
    handler = cli.lazy("rra_agent.cli.resolve:split_selection")
    assert handler(["A,B"]) == ["A", "B"]  # type: ignore[arg-type]
