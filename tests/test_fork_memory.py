"""What a process forked by the fork server inherits instead of making again (each thing it
makes writes to, and so copies, pages of the fork server's memory: docs/performance.md,
*tools/bench_memory.py*): the allocator's pools filled before the fork; an engine's parsed
command line, initial CV values and compiled rules. In process: nothing is forked here."""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest

from rra_agent.core import adaptation
from rra_agent.deployment import _prepared, deploy, prepare
from rra_agent.engines import launch
from rra_agent.engines import resolution as resolution_engine
from rra_agent.host import forkserver

OBJECT_STORING = Path(__file__).parents[1] / "scenarios" / "object_storing"


def test_arguments_parsed_ahead_are_handed_over_as_a_copy(monkeypatch):
    argv = ["--package", "pkg", "--retry-after", "2.5", "--name", "resolution-a"]
    built: list[str] = []

    def arguments() -> argparse.ArgumentParser:
        built.append("parser")
        return resolution_engine.arguments()

    monkeypatch.setattr(launch, "_parsed", {})
    launch._parse_ahead(arguments, argv)
    assert built == ["parser"]
    first = launch.parse_engine_args(arguments, argv)
    second = launch.parse_engine_args(arguments, argv)
    assert built == ["parser"]  # no parser built for either: parsed ahead
    assert first == second == resolution_engine.arguments().parse_args(argv)
    assert first is not second  # each engine gets its own copy
    first.retry_after = 9.0
    assert launch.parse_engine_args(arguments, argv).retry_after == 2.5
    # Other arguments are parsed as they come.
    assert launch.parse_engine_args(arguments, [*argv, "--start-timeout", "3"]).start_timeout == 3
    assert built == ["parser", "parser"]


def test_arguments_that_do_not_parse_are_left_to_the_engine(monkeypatch, capsys):
    monkeypatch.setattr(launch, "_parsed", {})
    launch._parse_ahead(resolution_engine.arguments, ["--no-such-option"])
    assert launch._parsed == {}
    assert capsys.readouterr().err == ""  # the engine prints the error, in its own log


def test_the_initial_cv_values_are_computed_once_per_prepared_deployment(monkeypatch):
    built: list[int] = []
    real = adaptation.AdaptationEngine.__init__

    def counting(self, *args, **kwargs):
        built.append(1)
        real(self, *args, **kwargs)

    monkeypatch.setattr(adaptation.AdaptationEngine, "__init__", counting)
    try:
        dep = prepare(OBJECT_STORING)
        assert built == [1]  # by prepare, in the fork server
        cv = deploy(OBJECT_STORING).initial_cv()
        assert built == [1] and cv and cv == dep.initial_cv()
        cv.clear()  # a caller's copy
        assert dep.initial_cv()
    finally:
        _prepared.clear()


def test_the_rules_are_compiled_once_per_source():
    dep = deploy(OBJECT_STORING)
    pkg = dep.package
    assert pkg.adaptation is not None
    adaptation._compiled.cache_clear()
    for _ in range(3):
        adaptation.AdaptationEngine(pkg.features, dep.selection, pkg.adaptation)
    info = adaptation._compiled.cache_info()
    assert (info.misses, info.hits) == (1, 2)


def test_the_allocators_free_blocks_are_read_and_filled():
    """`fill_pools` reads CPython's allocator statistics (32 block sizes of 16 to 512 bytes)
    and fills the free blocks of its partly used pools (of 48 bytes and more: a bytes
    object's smallest block), so a forked child's first objects do not land in them."""
    before = forkserver._pool_vacancies()
    assert sorted(before) == list(range(16, 513, 16))
    forkserver.fill_pools()
    after = forkserver._pool_vacancies()
    # What is left free is the fillers' own newest pools (and their list), not the old ones.
    assert sum(after[s] for s in after if s >= 48) < sum(before[s] for s in before if s >= 48)


@pytest.mark.system  # a new interpreter (a second, no session)
def test_numpy_and_rosbags_are_imported_only_for_ros2():
    """`rra up` (its CLI and host agent) and the engines import numpy and rosbags (the ROS 2
    message types, ~8 MiB of private memory per interpreter) only once a package with ROS 2
    builds its type registry. A new interpreter: this one has imported them already."""
    modules = ["rra_agent.cli.up", "rra_agent.engines.monitor", "rra_agent.engines.adaptation",
               "rra_agent.engines.resolution", "rra_agent.node.process"]  # fmt: skip
    code = (
        f"import sys\nfor m in {modules!r}: __import__(m)\n"
        "print(sorted({'numpy', 'rosbags'} & set(sys.modules)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.system  # a new interpreter (a second, no session)
def test_rra_up_does_not_import_the_node_sdk():
    """`rra up`'s process (the CLI, the host agent, the catalog) names a node's spec variable
    and the container implementation without importing the Node SDK (rra_agent.node and the
    reflexes' core it imports: 15 modules, ~0.5 MiB private in the longest-lived process)."""
    code = (
        "import sys, rra_agent.cli.up\n"
        "print(sorted(m for m in sys.modules if m.startswith(('rra_agent.node', "
        "'rra_agent.core.reflex', 'rra_agent.core.monitor'))))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"




WARM_MODULE = """
seen = []


def warm_up(args):
    seen.append(("warm_up", args))


def main(args):
    seen.append(("main", args))
    return 0
"""


def test_an_engine_started_without_the_branch_warms_up_after_the_failover(
    tmp_path, monkeypatch
):
    """The engines' branch retires when idle (`forkserver.BRANCH_IDLE`, on by default); an
    engine started after that (a killed one replaced, whose standby has taken over) runs
    in a spare, which has not imported it: `run_main` waits `REWARM_DELAY` (the standby's
    first plan), then imports it and runs its ``warm_up`` (~0.35 s of CPU) and ``main``.
    A module already imported (warmed up by the branch) starts at once."""
    (tmp_path / "warmmod.py").write_text(WARM_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(forkserver.atexit, "_clear", lambda: None)  # pytest's hooks stay
    monkeypatch.setattr(forkserver.atexit, "_run_exitfuncs", lambda: None)
    monkeypatch.setattr(sys, "argv", list(sys.argv))
    monkeypatch.delitem(sys.modules, "warmmod", raising=False)
    waits: list[float] = []
    monkeypatch.setattr(forkserver.time, "sleep", lambda s: waits.append(s))
    try:
        assert forkserver.run_main("warmmod", ["x"]) == 0
        assert waits == [forkserver.REWARM_DELAY]
        assert forkserver.run_main("warmmod", ["y"]) == 0
        seen = sys.modules["warmmod"].seen
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        sys.modules.pop("warmmod", None)
    assert seen == [("warm_up", ["x"]), ("main", ["x"]), ("main", ["y"])]
    assert waits == [forkserver.REWARM_DELAY]  # once: the second found it imported
    assert forkserver.REWARM_DELAY >= 1 and forkserver.BRANCH_IDLE > 0  # retired by default


APART = """
import sys
import msgspec
from rra_agent.deployment import deploy_apart
from rra_agent.errors import RraError

for path in sys.argv[1:]:
    dep = deploy_apart(path)
    print(msgspec.json.encode([dep.configured, dep.package.system, dep.package.manifest,
                               dep.models, sorted(dep.selection), dep.initial_cv()]).decode())
print("lark" in sys.modules)
try:
    deploy_apart(sys.argv[1] + "-missing")
except RraError as e:
    print(e)
"""


@pytest.mark.system  # a new interpreter, which forks (no session)
def test_rra_up_loads_its_package_in_a_fork_and_keeps_only_the_deployment(tmp_path):
    """`rra up` runs for the whole run: it loads the package in a forked child and takes the
    deployment it made (`deployment.deploy_apart`), so it never imports the model parsers
    (lark) nor keeps what loading left in its heap (~3.5 MiB private, docs/performance.md).
    The deployment is the one `deploy` makes, down to its encoding (msgspec omits a default
    by identity: a plain pickle's defaults are new objects, and node specs would encode and
    hash otherwise than the engines'); a model error is `deploy`'s own message."""
    script = tmp_path / "apart.py"
    script.write_text(APART)
    packages = [OBJECT_STORING, *(OBJECT_STORING.parent / n for n in ("quadcopter", "ros2_rover"))]
    argv = [sys.executable, str(script), *map(str, packages)]
    out = subprocess.run(argv, capture_output=True, text=True, check=True).stdout.splitlines()
    for line, package in zip(out, packages, strict=False):
        dep = deploy(package)
        parts = [dep.configured, dep.package.system, dep.package.manifest, dep.models]
        assert line == msgspec.json.encode(
            [*parts, sorted(dep.selection), dep.initial_cv()]
        ).decode()
    assert out[len(packages)] == "False"  # lark: never imported
    assert "no such system package" in out[-1]
