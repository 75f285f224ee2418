"""Generate the JSON Schemas of the YAML models (``schemas/*.schema.json``) from the Structs.

Editors (e.g. the YAML language server, via a ``# yaml-language-server: $schema=...`` comment)
then validate model files as they are typed. ``--check`` exits 1 when a file is out of date
(the test suite runs the same comparison).

    python tools/gen_schemas.py            # (re)write schemas/
    python tools/gen_schemas.py --check    # verify only
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import msgspec

from rra_agent.models.manifest import Manifest
from rra_agent.models.measurements import MeasurementsModel
from rra_agent.models.resolution import DeploymentResolutionModel, RuntimeResolutionModel
from rra_agent.models.system import SystemModel
from rra_agent.scenario.model import Scenario

ROOT = Path(__file__).resolve().parent.parent
SCHEMA_DIR = ROOT / "schemas"
DRAFT = "https://json-schema.org/draft/2020-12/schema"

#: Schema name -> (Struct, title).
MODELS: dict[str, tuple[type, str]] = {
    "system": (SystemModel, "RRA Template System Model (system.yaml)"),
    "deployment": (
        DeploymentResolutionModel,
        "RRA Deployment-time Resolution Model (deployment.yaml)",
    ),
    "runtime": (RuntimeResolutionModel, "RRA Run-time Resolution Model (runtime.yaml)"),
    "measurements": (MeasurementsModel, "RRA Data Types and Measurements (measurements.yaml)"),
    "manifest": (Manifest, "RRA system package manifest (rra.yaml)"),
    "scenario": (Scenario, "RRA scenario (*.scenario.yaml)"),
}


def schema_for(type_: type, title: str) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of one model Struct, with ``$schema`` and a title."""
    body = msgspec.json.schema(type_)
    _one_key_transformations(body)
    return {"$schema": DRAFT, "title": title, **body}


def _one_key_transformations(schema: dict[str, Any]) -> None:
    """A transformation is a one-key mapping (its Struct checks that in ``__post_init__``)."""
    t = schema.get("$defs", {}).get("Transformation")
    if t is not None:
        t["minProperties"] = 1
        t["maxProperties"] = 1


def render(schema: dict[str, Any]) -> str:
    return json.dumps(schema, indent=2, ensure_ascii=False) + "\n"


def generate() -> dict[str, str]:
    """File name (``system.schema.json``, ...) -> its text."""
    return {f"{name}.schema.json": render(schema_for(*m)) for name, m in MODELS.items()}


def outdated(directory: Path = SCHEMA_DIR) -> list[str]:
    """The schema files under ``directory`` that are missing or differ from `generate`."""
    out = []
    for name, text in generate().items():
        path = directory / name
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            out.append(name)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="exit 1 when files are out of date")
    parser.add_argument("--out", type=Path, default=SCHEMA_DIR, help="schema folder")
    args = parser.parse_args(argv)
    if args.check:
        stale = outdated(args.out)
        for name in stale:
            print(f"{args.out / name}: out of date (run python tools/gen_schemas.py)")
        return 1 if stale else 0
    args.out.mkdir(parents=True, exist_ok=True)
    for name, text in generate().items():
        (args.out / name).write_text(text, encoding="utf-8")
        print(f"wrote {args.out / name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
