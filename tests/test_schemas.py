"""The JSON Schemas in schemas/ are generated from the model Structs and kept in sync."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def gen() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gen_schemas", ROOT / "tools" / "gen_schemas.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_schema_files_are_up_to_date(gen: ModuleType) -> None:
    stale = gen.outdated(ROOT / "schemas")
    assert stale == [], f"out of date: {stale}; run `python tools/gen_schemas.py`"


def test_every_yaml_model_has_a_schema(gen: ModuleType) -> None:
    names = sorted(p.name for p in (ROOT / "schemas").glob("*.schema.json"))
    assert names == sorted(gen.generate())
    assert set(gen.generate()) == {
        f"{n}.schema.json"
        for n in ("system", "deployment", "runtime", "measurements", "manifest", "scenario")
    }


def test_schema_content(gen: ModuleType) -> None:
    texts = gen.generate()
    assert texts == gen.generate()  # deterministic
    for name, text in texts.items():
        schema = json.loads(text)
        assert list(schema)[:2] == ["$schema", "title"], name
        assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        top = schema["$defs"][schema["$ref"].rsplit("/", 1)[1]]
        assert top["additionalProperties"] is False  # typos are errors in editors too
    system = json.loads(texts["system.schema.json"])["$defs"]
    assert set(system["Connection"]["properties"]) == {"from", "to", "optional", "binding"}
    assert system["Port"]["properties"]["direction"]["enum"] == ["publish", "subscribe"]
    runtime = json.loads(texts["runtime.schema.json"])["$defs"]
    assert (
        runtime["Transformation"]["minProperties"],
        runtime["Transformation"]["maxProperties"],
    ) == (1, 1)


def test_check_mode(gen: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert gen.main(["--check", "--out", str(tmp_path)]) == 1
    assert "system.schema.json: out of date" in capsys.readouterr().out
    assert gen.main(["--out", str(tmp_path)]) == 0
    assert gen.main(["--check", "--out", str(tmp_path)]) == 0
    (tmp_path / "runtime.schema.json").write_text("{}\n")
    assert gen.main(["--check", "--out", str(tmp_path)]) == 1
    assert (
        capsys.readouterr()
        .out.strip()
        .endswith("runtime.schema.json: out of date (run python tools/gen_schemas.py)")
    )
