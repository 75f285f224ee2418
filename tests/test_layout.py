"""The house's layout: floors from the bottom up, no import circles, no upward imports.

Every module of ``rra_agent`` belongs to a floor (`FLOORS`, bottom first). A module may
import modules of its own floor or of a lower one, at the top of the file or inside a
function (a lazy import is still a dependency); modules never import each other in a
circle. docs/architecture.md draws the same floors.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "rra_agent"

#: Bottom first. A module's floor is that of the longest prefix listed.
FLOORS: list[tuple[str, ...]] = [
    ("rra_agent.errors", "rra_agent.trace", "rra_agent._compat", "rra_agent.text",
     "rra_agent.files"),
    # the rmw_zenoh wire layer: a library of its own (it imports nothing of rra-agent but its
    # errors and its file writing), so that the models, their validation, the nodes and the
    # engines may all use it
    ("rra_agent.ros2",),
    ("rra_agent.models", "rra_agent.library"),
    ("rra_agent.dsl",),
    ("rra_agent.package",),
    ("rra_agent.core",),
    ("rra_agent.deployment", "rra_agent.model_changes"),
    ("rra_agent.bus",),
    ("rra_agent.node",),
    ("rra_agent.viz",),
    ("rra_agent.record",),
    ("rra_agent.security", "rra_agent.engines"),
    ("rra_agent.host",),
    ("rra_agent.nodes", "rra_agent.sim"),
    ("rra_agent.scenario",),
    ("rra_agent.demo", "rra_agent.cli", "rra_agent.__main__", "rra_agent"),
]


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


MODULES = {module_name(p): p for p in sorted(ROOT.rglob("*.py"))}


def floor(module: str) -> int:
    best, level = "", -1
    for i, names in enumerate(FLOORS):
        for name in names:
            if (module == name or module.startswith(name + ".")) and len(name) > len(best):
                best, level = name, i
    assert level >= 0, f"{module} belongs to no floor: add it to FLOORS"
    return level


def imports(module: str) -> Iterator[tuple[str, int]]:
    """The rra_agent modules ``module`` imports (a ``from X import y`` of a submodule
    ``X.y`` counts as ``X.y``), with the line."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("rra_agent"):
                    yield alias.name, node.lineno
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1])
                base = f"{base}.{node.module}" if node.module else base
            if not base.startswith("rra_agent"):
                continue
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                yield (sub if sub in MODULES else base), node.lineno


def graph() -> dict[str, set[str]]:
    return {m: {t for t, _ in imports(m) if t in MODULES and t != m} for m in MODULES}


def test_every_module_has_a_floor() -> None:
    for m in MODULES:
        floor(m)


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_upward_import(module: str) -> None:
    mine = floor(module)
    upward = [
        f"line {line}: {target} (floor {floor(target)})"
        for target, line in imports(module)
        if target in MODULES and floor(target) > mine
    ]
    assert not upward, f"{module} (floor {mine}) imports upward: {upward}"


def test_no_import_circle() -> None:
    g = graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    circles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(g[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                on.discard(w)
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                circles.append(sorted(part))

    for v in sorted(g):
        if v not in index:
            visit(v)
    assert not circles, f"import circles: {circles}"


def test_the_pure_core_touches_no_bus_clock_or_file() -> None:
    """rra_agent.core imports no zenoh, no clock (time), no files or processes."""
    banned = {"zenoh", "time", "os", "pathlib", "socket", "subprocess"}
    for m, path in MODULES.items():
        if not m.startswith("rra_agent.core"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name.split(".")[0] for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names = [node.module.split(".")[0]]
            assert not set(names) & banned, f"{m}: imports {set(names) & banned}"
