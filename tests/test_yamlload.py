"""YAML model files -> Structs, every error at its file:line:col (rra_agent.package.yamlload).

Expected positions are computed from the text by finding the planted token, never hard-coded.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from rra_agent.errors import ErrorGroup, Location, ModelError
from rra_agent.models.manifest import Manifest
from rra_agent.models.measurements import MeasurementsModel
from rra_agent.models.resolution import RuntimeResolutionModel
from rra_agent.models.system import SystemModel
from rra_agent.package.yamlload import YamlDoc, load_yaml, load_yaml_text, unknown_name

F = "f.yaml"


def at(text: str, token: str, nth: int = 1) -> Location:
    """The 1-based location of the ``nth`` occurrence of ``token`` in ``text``."""
    idx = -1
    for _ in range(nth):
        idx = text.index(token, idx + 1)
    line = text.count("\n", 0, idx) + 1
    return Location(F, line, idx - (text.rfind("\n", 0, idx) + 1) + 1)


def fail(text: str, type_: type = SystemModel) -> ModelError:
    with pytest.raises(ModelError) as info:
        load_yaml_text(text, F, type_)
    return info.value


COMP = "system: s\ncomponents:\n  - name: a\n    implementation: pkg.A\n"


# ---- values and types ----------------------------------------------------------------------
def test_a_valid_file_loads_and_keeps_its_tree() -> None:
    text = "# yaml-language-server: $schema=../schemas/system.schema.json\n" + COMP
    model, doc = load_yaml_text(text, F, SystemModel)
    assert model.components[0].implementation == "pkg.A"
    assert doc.file == F
    assert doc.loc("components", 0, "implementation") == at(text, "pkg.A")
    assert doc.key_loc("components", 0, "implementation") == at(text, "implementation")


@pytest.mark.parametrize("written, value", [("1e-3", 0.001), ("2.5E3", 2500.0), ("-4e+1", -40.0)])
def test_an_exponent_without_a_dot_or_sign_is_a_float(written: str, value: float) -> None:
    """YAML 1.2 and JSON read ``1e-3`` as a float; PyYAML (YAML 1.1) read it as the string
    '1e-3', and a float parameter written so was refused ("is not of type float")."""
    text = COMP + f"    parameters:\n      gain: {{type: float, value: {written}}}\n"
    model, _ = load_yaml_text(text, F, SystemModel)
    assert model.components[0].parameters["gain"].value == value


def test_the_command_line_reads_its_scalars_as_the_models_do() -> None:
    from rra_agent.cli.param import parse_assignments

    got = parse_assignments(["kp=1e-3", "n=10", "name=1e", "on=true"])
    assert got == {"kp": 0.001, "n": 10, "name": "1e", "on": True}
    assert isinstance(got["kp"], float)


def test_wrong_type_points_at_the_value() -> None:
    text = (
        COMP
        + "    ports:\n      - {name: p, direction: publish, type: T}\n"
        + ("      - {name: q, direction: subscribe, type: 7}\n")
    )
    err = fail(text)
    assert err.message == "Expected `str`, got `int`"
    assert err.location == at(text, "7")
    assert err.source_line == "      - {name: q, direction: subscribe, type: 7}"
    assert str(err).splitlines()[-1].index("^") == len("    ") + at(text, "7").col - 1


def test_unknown_field_points_at_the_key_and_suggests() -> None:
    text = COMP + "    prots: []\n"
    err = fail(text)
    assert err.location == at(text, "prots")
    assert err.message.startswith("unknown field 'prots' (did you mean 'ports'? known: binding,")


def test_missing_field_points_at_the_mapping() -> None:
    text = "system: s\ncomponents:\n  - name: a\n    host: h\n"
    err = fail(text)
    assert (err.message, err.location) == (
        "missing required field 'implementation'",
        at(text, "name"),
    )


def test_invalid_enum_value() -> None:
    text = "replacement:\n  default: swap\n"
    err = fail(text, RuntimeResolutionModel)
    assert (err.message, err.location) == ("Invalid enum value 'swap'", at(text, "swap"))


def test_renamed_field_in_the_path() -> None:
    text = "system: s\nconnections:\n  - {from: 12, to: a.b}\n"
    assert fail(text).location == at(text, "12")


def test_union_member_error() -> None:
    text = "system: s\ncomponents:\n  - name: a\n    implementation: {command: run-it}\n"
    err = fail(text)
    assert (err.message, err.location) == ("Expected `array`, got `str`", at(text, "run-it"))


def test_dict_value_error_finds_the_entry() -> None:
    # msgspec says only `$.components[0].parameters[...]`: the loader finds which entry.
    text = COMP + (
        "    parameters:\n"
        "      gain: {type: float, value: 1}\n"
        "      mode: {type: int, value: 'fast'}\n"
        "      tail: {type: str, value: 'x'}\n"
    )
    err = fail(text)
    assert err.message == "value 'fast' is not of type int"
    assert err.location == at(text, "'fast'")


def test_dict_value_error_inside_a_list_in_the_entry() -> None:
    text = (
        "features:\n"
        "  A:\n    - include_component: x\n"
        "  B:\n    - include_component: y\n    - set_parameter: {component: a, parameter: p}\n"
    )
    err = fail(text, RuntimeResolutionModel)
    assert "exactly one of 'value' and 'from_attribute'" in err.message
    assert err.location == at(text, "{component: a")


def test_dict_value_error_in_a_nested_field() -> None:
    text = "data_types:\n  - name: D\n    fields: {a: float, b: [int]}\n"
    err = fail(text, MeasurementsModel)
    assert (err.message, err.location) == ("Expected `str`, got `array`", at(text, "[int]"))


def test_a_bad_dict_key_points_at_the_key() -> None:
    text = (
        COMP + "    parameters:\n      ok: {type: int, value: 1}\n      17: {type: int, value: 1}\n"
    )
    err = fail(text)
    assert (err.message, err.location) == ("Expected `str`, got `int`", at(text, "17"))


def test_struct_check_error_points_at_the_named_value() -> None:
    text = "system: s\nconnections:\n  - from: a.b\n    to: ab\n"
    err = fail(text)
    assert err.message == "expected 'component.port', got 'ab'"
    assert err.location == at(text, "ab\n")


@pytest.mark.parametrize(
    "sched, message",
    [
        ("{policy: fifo}", "a fifo policy needs a priority 1..99, got 0"),
        ("{policy: rr, priority: 100}", "a rr policy needs a priority 1..99, got 100"),
        ("{nice: 5, priority: 3}", "priority is for the fifo and rr policies, not 'other'"),
        ("{nice: -21}", "nice must be -20..19, got -21"),
        ("{cpus: [0, 0]}", "cpus must be distinct CPU numbers, got [0, 0]"),
    ],
)
def test_a_scheduling_the_kernel_cannot_take_is_a_located_error(sched: str, message: str):
    text = COMP + f"    scheduling: {sched}\n"
    err = fail(text)
    assert err.message == message
    assert err.location is not None and err.location.line == 5


@pytest.mark.parametrize(
    "extra, message",
    [
        ("  - name: b\n    implementation: pkg.B\n    container: a\n",
         "container 'a' has a component's name"),
        ("  - name: b\n    implementation: pkg.B\n    container: k\n    host: h1\n"
         "  - name: c\n    implementation: pkg.C\n    container: k\n    host: h2\n",
         "the components of container 'k' are on two hosts"),
        ("  - name: b\n    implementation: {command: [tool]}\n    container: k\n",
         "a component in a container needs Python implementations"),
    ],
)  # fmt: skip
def test_an_impossible_container_is_a_located_error(extra: str, message: str) -> None:
    err = fail(COMP + extra)
    assert err.message == message and err.location is not None


def test_duplicate_names_point_at_the_second() -> None:
    text = COMP + "  - name: b\n    implementation: x\n  - name: a\n    implementation: y\n"
    err = fail(text)
    assert err.message == "duplicate component name(s) a"
    assert err.location == at(text, "a\n", 2)


def test_duplicate_ports_point_at_the_second() -> None:
    text = COMP + (
        "    ports:\n"
        "      - {name: p, direction: publish, type: T}\n"
        "      - {name: p, direction: subscribe, type: T}\n"
    )
    assert fail(text).location == at(text, "p,", 2)


def test_root_of_the_wrong_kind() -> None:
    err = fail("- 1\n", MeasurementsModel)
    assert (err.message, err.location) == ("Expected `object`, got `array`", Location(F, 1, 1))


def test_empty_file() -> None:
    assert load_yaml_text("", F, MeasurementsModel)[0] == MeasurementsModel()
    err = fail("# nothing\n")
    assert (err.message, err.location) == ("missing required field 'system'", Location(F, 1, 1))


# ---- YAML itself -------------------------------------------------------------------------
def test_duplicate_keys_are_errors() -> None:
    text = "system: s\ndescription: x\nsystem: t\ncomponents: []\ndescription: y\n"
    with pytest.raises(ErrorGroup) as info:
        load_yaml_text(text, F, SystemModel)
    errs = info.value.errors
    assert [(e.message, e.location) for e in errs if isinstance(e, ModelError)] == [
        ("duplicate key 'system' (first at line 1)", at(text, "system", 2)),
        ("duplicate key 'description' (first at line 2)", at(text, "description", 2)),
    ]


def test_a_duplicate_key_in_a_flow_mapping_inside_a_list() -> None:
    text = COMP + "    ports:\n      - {name: p, direction: publish, name: q, type: T}\n"
    err = fail(text)
    assert (err.message, err.location) == (
        "duplicate key 'name' (first at line 6)",
        at(text, "name", 3),
    )


@pytest.mark.parametrize(
    ("text", "token", "fragment"),
    [
        ("system: s\ndescription: a: b\n", ": b", "mapping values are not allowed here"),
        ("system: s\ncomponents:\n  - name: a\n\t- name: b\n", "\t", "cannot start any token"),
        ("system: s\nhosts: [{name: a}\ncomponents: []\n", "components", "expected ',' or ']'"),
        ("system: s\n---\nsystem: t\n", "---", "expected a single document"),
        ("system: *anchor\n", "*anchor", "found undefined alias 'anchor'"),
        ("system: s\n  hosts: []\n", ": []", "mapping values are not allowed here"),
    ],
)
def test_yaml_syntax_errors_are_located(text: str, token: str, fragment: str) -> None:
    err = fail(text)
    assert err.message.startswith("YAML syntax: ")
    assert fragment in err.message
    assert err.location == at(text, token)


def test_unsupported_tags_are_errors() -> None:
    text = "system: !!python/name:os.system s\n"
    assert fail(text).location == at(text, "!!python")
    text = "system: s\ncomponents: !!set {a: null}\n"
    err = fail(text)
    assert (err.message, err.location) == (
        "unsupported YAML tag 'tag:yaml.org,2002:set'",
        at(text, "!!set"),
    )


def test_anchors_and_merge_keys_work_and_own_keys_win() -> None:
    text = COMP + "    parameters:\n      g: &g {type: int, value: 1}\n      h:\n        <<: *g\n"
    text += "        value: 2\n"
    model, doc = load_yaml_text(text, F, SystemModel)
    params = model.components[0].parameters
    assert (params["g"].value, params["h"].value, params["h"].type) == (1, 2, "int")
    assert doc.loc("components", 0, "parameters", "h", "type") == at(text, "int")


# ---- the document and the file -----------------------------------------------------------
def test_yamldoc_locations_fall_back_to_the_nearest_ancestor() -> None:
    text = COMP + "    ports:\n      - {name: p, direction: publish, type: T}\n"
    _, doc = load_yaml_text(text, F, SystemModel)
    assert doc.loc("components", 0, "ports", 0, "type") == at(text, "T}")
    assert doc.loc("components", 0, "ports", 3, "type") == at(text, "- {name: p")
    assert doc.loc("components", 0, "nope") == at(text, "name: a")
    assert doc.key_loc("components", 0, "ports") == at(text, "ports")
    assert doc.key_loc("components", 0) == at(text, "name: a")
    assert doc.node("components", 0, "nope") is None
    assert doc.loc() == Location(F, 1, 1)
    assert YamlDoc("x.yaml", None).loc("a", 1) == Location("x.yaml", 1, 1)


def test_load_yaml_reads_a_file(tmp_path: Path) -> None:
    path = tmp_path / "rra.yaml"
    text = "name: demo\ndefault_selection: [A, 3]\n"
    path.write_text(text)
    with pytest.raises(ModelError) as info:
        load_yaml(path, Manifest)
    assert info.value.location == Location(str(path), at(text, "3").line, at(text, "3").col)
    path.write_text("name: demo\n")
    manifest, doc = load_yaml(path, Manifest)
    assert manifest.name == "demo" and doc.file == str(path)
    with pytest.raises(ModelError, match="no such file"):
        load_yaml(tmp_path / "missing.yaml", Manifest)


def test_unknown_name_message() -> None:
    assert unknown_name("component", "radio_drver_a", ["radio_driver_b", "radio_driver_a"]) == (
        "unknown component 'radio_drver_a' (did you mean 'radio_driver_a'? known:"
        " radio_driver_a, radio_driver_b)"
    )
    assert unknown_name("host", "x", []) == "unknown host 'x' (known: none)"
    many = unknown_name("port", "zz", [f"p{i:02}" for i in range(20)], " of 'c'")
    assert many.startswith("unknown port 'zz' of 'c' (known: p00,") and many.endswith(", ...)")


def test_a_recursive_alias_is_an_error_not_a_crash() -> None:
    text = "system: s\ndescription: &d [1, *d]\n"
    err = fail(text)
    assert (err.message, err.location) == ("a YAML alias refers to itself", at(text, "&d"))


def test_aliases_are_not_expanded_exponentially() -> None:
    lines = ["system: s", "x0: &a0 [1, 2]"]
    lines += [f"x{i}: &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}]" for i in range(1, 40)]
    err = fail("\n".join(lines) + "\n")  # 4**39 leaves if expanded: must answer at once
    assert err.message.startswith("unknown field 'x0'")
