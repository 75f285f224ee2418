"""pytest plugin: scenario files (``*.scenario.yaml``) as tests.

Registered as the ``rra`` entry point of the ``pytest11`` group, so installing rra-agent is
enough: ``pytest scenarios/`` collects every file matching the ``rra_scenario_files`` ini
patterns (default ``*.scenario.yaml``) as a `ScenarioFile`, one `ScenarioItem` per
scenario (or per case of a file with ``cases``). A file that does not load (YAML, schema,
an unknown feature/node/measurement in an expectation) is a collection error showing each
problem as ``file:line:col``. A scenario with ``slow: true`` is marked ``slow``
(``-m "not slow"`` deselects it).

An item runs its system with `rra_agent.scenario.runner.run_case` in a run folder under
``rra_scenario_runs`` (ini; default: the system temp dir); the folder is removed when the
scenario passes (unless ``--rra-keep-runs``) and kept when it fails. With
``rra_scenario_share = true`` (ini) a passed run is kept whole until the session ends, and a
test reuses it with `shared_run` instead of running the case again. A failure shows each
failing expectation as ``scenario-file:line: expectation failed: TEXT`` with what was
observed, and the paths of the events log and recordings. A node that crashed is named in
the report with what it raised, and its log is kept (``crashed/<node>.log``, also when the
scenario passes).

Patterns: one without ``/`` matches the file name; one with ``/`` matches the path relative
to the rootdir, where ``**/`` stands for any number of folders (``scenarios/**/*.scenario.yaml``).
"""

from __future__ import annotations

import fnmatch
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from rra_agent.errors import RraError

DEFAULT_PATTERNS = ["*.scenario.yaml"]


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addini(
        "rra_scenario_files",
        type="args",
        default=DEFAULT_PATTERNS,
        help="glob patterns of RRA scenario files to collect (default: *.scenario.yaml)",
    )
    parser.addini(
        "rra_scenario_runs",
        default="",
        help="folder for the run folders of RRA scenarios (default: the system temp dir)",
    )
    parser.addini(
        "rra_scenario_share",
        type="bool",
        default=False,
        help="keep the runs of passed scenarios until the session ends, for tests to reuse "
        "(`shared_run`)",
    )
    group = parser.getgroup("rra", "RRA scenarios")
    group.addoption(
        "--rra-keep-runs",
        action="store_true",
        default=False,
        help="keep the run folders of passed scenarios too",
    )


#: The passed runs of this session by case id, kept whole until it ends (``rra_scenario_share``).
SHARED = pytest.StashKey[dict[str, Any]]()


def shared_run(config: pytest.Config, case_id: str) -> Any:
    """The passed run (`rra_agent.scenario.runner.CaseRun`, its run folder intact) of the
    shipped scenario case ``case_id`` (``motor_failure::adaptive``) if this session has run it
    already, else None: a test that needs a run of a shipped case does not run it again."""
    return config.stash.get(SHARED, {}).get(case_id)


def pytest_sessionfinish(session: pytest.Session) -> None:
    """The shared runs pruned as any passed run is (`rra_agent.scenario.runner.prune`)."""
    from rra_agent.scenario.runner import prune

    keep = session.config.getoption("rra_keep_runs")
    for run in session.config.stash.get(SHARED, {}).values():
        if not keep:
            prune(run)


def pytest_configure(config: pytest.Config) -> None:
    config.stash[SHARED] = {}
    config.addinivalue_line("markers", "slow: a slow test (deselect with -m 'not slow')")
    config.addinivalue_line("markers", "scenario: an RRA scenario run against a real system")


def matches(rel: str, pattern: str) -> bool:
    """Whether the rootdir-relative POSIX path ``rel`` matches ``pattern``."""
    if "/" not in pattern:
        return fnmatch.fnmatch(rel.rsplit("/", 1)[-1], pattern)
    wild = {"**/": "(?:[^/]*/)*", "*": "[^/]*", "?": "[^/]"}
    parts = re.split(r"(\*\*/|\*|\?)", pattern)
    regex = "".join(wild.get(p, re.escape(p)) for p in parts)
    return re.fullmatch(regex, rel) is not None


def pytest_collect_file(file_path: Path, parent: pytest.Collector) -> ScenarioFile | None:
    patterns = parent.config.getini("rra_scenario_files")
    try:
        rel = file_path.relative_to(parent.config.rootpath).as_posix()
    except ValueError:
        rel = file_path.as_posix()
    if any(matches(rel, p) for p in patterns):
        return ScenarioFile.from_parent(parent, path=file_path)
    return None


def _shown(path: Path, config: pytest.Config) -> str:
    """``path`` relative to the invocation folder when inside it (shorter messages)."""
    rel = os.path.relpath(path, config.invocation_params.dir)
    return str(path) if rel.startswith("..") else rel


class ScenarioFile(pytest.File):
    def collect(self) -> Iterator[ScenarioItem]:
        from rra_agent.scenario.model import load_scenario

        loaded = load_scenario(_shown(self.path, self.config))
        for case in loaded.cases:
            yield ScenarioItem.from_parent(self, name=case.case or case.scenario, case=case)

    def repr_failure(self, excinfo: pytest.ExceptionInfo[BaseException]) -> Any:  # type: ignore[override]
        if isinstance(excinfo.value, RraError):
            from rra_agent.package.loader import flatten_errors

            return "\n".join(str(e) for e in flatten_errors(excinfo.value))
        return super().repr_failure(excinfo)


class ScenarioFailed(Exception):
    """A scenario run whose expectations did not all hold (or that could not run)."""

    def __init__(self, run: Any) -> None:
        super().__init__(run.case.id)
        self.run = run


class ScenarioItem(pytest.Item):
    def __init__(self, *, case: Any, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.case = case
        self.add_marker(pytest.mark.scenario)
        if case.slow:
            self.add_marker(pytest.mark.slow)

    def _run_dir(self) -> Path:
        base = self.config.getini("rra_scenario_runs")
        root = Path(base) if base else Path(tempfile.gettempdir()) / "rra-scenarios"
        if not root.is_absolute():
            root = self.config.rootpath / root
        root.mkdir(parents=True, exist_ok=True)
        name = re.sub(r"[^A-Za-z0-9_.-]+", "-", self.case.id)
        return Path(tempfile.mkdtemp(prefix=f"{name}-", dir=root))

    def runtest(self) -> None:
        from rra_agent.scenario.runner import prune, render_crashes, render_rows, run_case

        run = run_case(self.case, self._run_dir())
        self.user_properties.append(("rra_run_dir", str(run.run_dir)))
        verdict = "\n\n".join(t for t in (render_rows([run]), render_crashes([run])) if t)
        self.add_report_section("call", "rra scenario", verdict)
        if not run.passed:
            raise ScenarioFailed(run)
        if self.config.getini("rra_scenario_share"):
            self.config.stash[SHARED][self.case.id] = run  # pruned when the session ends
        elif not self.config.getoption("rra_keep_runs"):
            prune(run)  # all but its crashed nodes' logs and its verdict

    def repr_failure(self, excinfo: pytest.ExceptionInfo[BaseException]) -> Any:  # type: ignore[override]
        if isinstance(excinfo.value, ScenarioFailed):
            from rra_agent.scenario.runner import describe_failure

            return describe_failure(excinfo.value.run)
        return super().repr_failure(excinfo)

    def reportinfo(self) -> tuple[Path, int, str]:
        return self.path, self.case.location.line - 1, f"scenario {self.case.id}"
