"""Every example in docs/ and README.md is parsed or run, so a doc example is never invalid.

Each fenced block says what it is (its language tag); the test by tag:

- ``yaml``: parses, then converts (strictly: unknown fields refused) into the model Struct
  whose fields its top-level keys are (a system model, a component, measurements, a
  resolution model, a manifest, a scenario...);
- ``uvl``: a feature model `rra_agent.dsl.uvl.parse_uvl` accepts;
- ``rra``: rules `rra_agent.dsl.rules.parse_rules` accepts against the object-storing
  feature model (the paper's case study, which the docs' rule examples are about);
- ``python``: run, in order, in a scratch folder on the import path; a block whose first line
  is a docstring naming ``NAME.py`` is that module, written there for the next blocks;
- ``sh``: every ``rra ...`` command line parses with the ``rra`` command's own parser;
- ``json``: parses; ``text`` (diagrams, grammars, output): nothing to check.
"""

from __future__ import annotations

import json
import re
import runpy
import shlex
from pathlib import Path

import msgspec
import pytest
import yaml

from rra_agent.cli.commands import build_parser
from rra_agent.dsl.rules import parse_rules
from rra_agent.dsl.uvl import load_uvl, parse_uvl
from rra_agent.models.manifest import Manifest
from rra_agent.models.measurements import Measurement, MeasurementsModel
from rra_agent.models.resolution import Replacement, RuntimeResolutionModel
from rra_agent.models.system import Component, Scheduling, Supervision, SystemModel
from rra_agent.scenario.model import Scenario

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
TAGS = {"yaml", "uvl", "rra", "python", "sh", "json", "text"}
_FENCE = re.compile(r"^```(?P<tag>[\w-]*)\n(?P<body>.*?)^```", re.S | re.M)


def blocks() -> list[tuple[Path, int, str, str]]:
    out = []
    for path in DOCS:
        text = path.read_text()
        for mt in _FENCE.finditer(text):
            line = text.count("\n", 0, mt.start()) + 1
            out.append((path, line, mt["tag"], mt["body"]))
    return out


BLOCKS = blocks()


def where(path: Path, line: int) -> str:
    return f"{path.relative_to(ROOT)}:{line}"


def test_every_block_says_what_it_is() -> None:
    untagged = [where(p, n) for p, n, tag, _ in BLOCKS if tag not in TAGS]
    assert not untagged, f"blocks without a known tag ({', '.join(sorted(TAGS))}): {untagged}"


#: Model Structs a YAML example may be (tried in order: the first whose fields hold every
#: top-level key).
MODELS: list[type] = [
    SystemModel, MeasurementsModel, Manifest, RuntimeResolutionModel, Scenario, Component,
]  # fmt: skip
FRAGMENTS: dict[str, type] = {
    "supervision": Supervision,
    "scheduling": Scheduling,
    "replacement": Replacement,
}


def _fields(cls: type) -> set[str]:
    return {f.encode_name for f in msgspec.structs.fields(cls)}


def check_yaml(body: str) -> None:
    data = yaml.safe_load(body)
    if isinstance(data, list):
        kind = Component if data and "implementation" in data[0] else Measurement
        msgspec.convert(data, list[kind])
        return
    assert isinstance(data, dict), f"a model example is a map or a list, got {type(data)}"
    if set(data) <= set(FRAGMENTS):  # a part of a component or of runtime.yaml
        for key, value in data.items():
            msgspec.convert(value, FRAGMENTS[key])
        return
    for cls in MODELS:
        if set(data) <= _fields(cls):
            msgspec.convert(data, cls)
            return
    raise AssertionError(f"no model has the fields {sorted(data)}")


def run_python(path: Path, tmp: Path) -> None:
    """The file's python blocks, in order, in ``tmp`` (on the import path)."""
    for p, line, tag, body in BLOCKS:
        if p != path or tag != "python":
            continue
        named = re.match(r'"""(\w+)\.py', body)
        if named:
            (tmp / f"{named.group(1)}.py").write_text(body)
        else:
            script = tmp / f"block_{line}.py"
            script.write_text(body)
            runpy.run_path(str(script), run_name="__main__")


@pytest.mark.parametrize(
    ("path", "line", "tag", "body"),
    [b for b in BLOCKS if b[2] in ("yaml", "uvl", "rra", "json", "sh")],
    ids=[where(p, n) for p, n, t, _ in BLOCKS if t in ("yaml", "uvl", "rra", "json", "sh")],
)
def test_example(path: Path, line: int, tag: str, body: str) -> None:
    match tag:
        case "yaml":
            check_yaml(body)
        case "uvl":
            parse_uvl(body, where(path, line))
        case "rra":
            fm = load_uvl(ROOT / "scenarios" / "object_storing" / "features.uvl")
            parse_rules(body, where(path, line), fm, None)
        case "json":
            json.loads(body)
        case "sh":
            parser = build_parser()
            for cmd in body.splitlines():
                words = shlex.split(cmd, comments=True)
                if words[:1] == ["rra"]:
                    try:
                        parser.parse_args(words[1:])
                    except SystemExit as e:
                        raise AssertionError(f"{where(path, line)}: {cmd!r} does not parse") from e


@pytest.mark.parametrize(
    "path", sorted({p for p, _, t, _ in BLOCKS if t == "python"}), ids=lambda p: p.name
)
def test_python_examples_run(path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.chdir(tmp_path)
    run_python(path, tmp_path)
