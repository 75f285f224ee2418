"""The suite's adversity options, for every path it runs (``tests/`` and ``scenarios/``):

- ``--cpu-hog``: tools/cpuhog.py spins on every core from the start of the session to its end
  (the scenario runs included: they are not fixtures' users, so this is a session hook);
- ``--hostile``: a hostile client (tools/hostile.py) on the bus of every system a test of
  ``tests/`` starts (the ``system`` fixture and the tests that start a system of their own
  read the option). A scenario's run has none: its recorder takes what it receives on the
  bus for the system's own (the header says so when scenarios are collected).

Here, in the rootdir's conftest, because pytest reads the options of the conftest files of
the rootdir and of the paths given before it parses the command line: options defined in
``tests/conftest.py`` were refused ("unrecognized arguments") in ``pytest --cpu-hog
scenarios/``.
"""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent
_HOG = pytest.StashKey[subprocess.Popen[bytes]]()


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("rra adversity", "run the runtime tests under adverse conditions")
    group.addoption(
        "--cpu-hog",
        action="store_true",
        help="a busy loop on every core for the whole run (scenarios included)",
    )
    group.addoption(
        "--hostile",
        action="store_true",
        help="a hostile client (tools/hostile.py) on the bus of every system a test of tests/ "
        "starts (not of a scenario's run)",
    )


def pytest_configure(config: pytest.Config) -> None:
    """The tests stop the processes they start with SIGINT, as Ctrl-C does. A shell that
    runs the suite in the background without job control (``pytest &`` in a script) starts
    it with SIGINT ignored, and an ignored signal is inherited: every process a test starts
    would ignore it too (``rra status --watch`` and ``rra events`` never stopped). The suite
    takes Python's default back."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_sessionstart(session: pytest.Session) -> None:
    if session.config.getoption("--cpu-hog"):
        hog = subprocess.Popen([sys.executable, str(ROOT / "tools" / "cpuhog.py")])
        session.config.stash[_HOG] = hog


def pytest_sessionfinish(session: pytest.Session) -> None:
    hog = session.config.stash.get(_HOG, None)
    if hog is not None:
        hog.kill()  # its busy loops die with it (tools/cpuhog.py: PR_SET_PDEATHSIG)
        hog.wait()


def pytest_report_header(config: pytest.Config) -> list[str]:
    said = [o for o in ("--cpu-hog", "--hostile") if config.getoption(o)]
    lines = [f"rra adversity: {' '.join(said)}"] if said else []
    if config.getoption("--hostile"):
        lines.append("rra adversity: --hostile disturbs the systems of tests/, not scenario runs")
    return lines
