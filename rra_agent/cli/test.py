"""``rra test PKG_OR_SCENARIO...``: run scenarios headless and print the verdict.

Each argument is a scenario file or a folder (a system package, or any folder: every
``*.scenario.yaml`` below it). Every case runs its own system in turn; the table printed at
the end has one row per expectation: scenario, expectation, outcome, observed value and time,
in 100 columns (the expectation and what was observed wrapped in their columns; ``--wide``:
one line per row).
A failed case keeps its run folder (events log, the ``.rrd`` recording when there is one, the
bus recording, every process's log) and its paths are printed; a passed one is removed unless
``--keep``. A node that crashed (an exception of its code, a failing external command) is
named after the table with what it raised, where, and its log, which is kept
(``crashed/<node>.log`` of the run folder, with ``results.txt``) even when its case passed.
Exit status 1 when a scenario does not load or any expectation fails.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

from rra_agent.cli.common import add_wide_argument
from rra_agent.errors import RraError

PATTERN = "*.scenario.yaml"


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "paths", nargs="+", metavar="PKG_OR_SCENARIO", help="scenario files or folders of them"
    )
    p.add_argument(
        "--case",
        "-k",
        action="append",
        default=[],
        metavar="TEXT",
        help="only the cases whose id (scenario or scenario::case) contains TEXT (repeatable)",
    )
    p.add_argument("--skip-slow", action="store_true", help="skip the scenarios marked slow")
    p.add_argument("--out", metavar="DIR", help="put the run folders here (default: a temp dir)")
    p.add_argument("--keep", action="store_true", help="keep the run folders of passed cases")
    add_wide_argument(p, "the verdict table")


def find_scenarios(paths: list[str]) -> list[Path]:
    """Scenario files named by ``paths`` (folders searched recursively), in order."""
    out: list[Path] = []
    for raw in paths:
        p = Path(raw)
        if p.is_dir():
            found = sorted(p.rglob(PATTERN))
            if not found:
                raise RraError(f"{raw}: no {PATTERN} file in this folder")
            out += found
        elif p.is_file():
            out.append(p)
        else:
            raise RraError(f"{raw}: no such file or folder")
    return list(dict.fromkeys(out))


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", text).strip("-") or "case"


def run(args: argparse.Namespace) -> int:
    from rra_agent.package.loader import error_line, flatten_errors
    from rra_agent.scenario.model import ScenarioCase, load_scenario
    from rra_agent.scenario.runner import (
        describe_failure,
        prune,
        render_crashes,
        render_rows,
        run_case,
    )

    status = 0
    cases: list[ScenarioCase] = []
    for path in find_scenarios(args.paths):
        try:
            cases += load_scenario(path).cases
        except RraError as e:
            for err in flatten_errors(e):
                print(error_line(err), file=sys.stderr, flush=True)
            status = 1
    cases = [c for c in cases if not args.case or any(k in c.id for k in args.case)]
    if args.skip_slow:
        cases = [c for c in cases if not c.slow]
    if not cases:
        print("rra test: no scenario to run", file=sys.stderr, flush=True)
        return status or 1
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="rra-test-"))
    started = time.monotonic()
    runs = []
    for case in cases:
        print(
            f"rra test: {case.id}: running ({case.duration:g} s) ...", file=sys.stderr, flush=True
        )
        result = run_case(case, base / slug(case.id))
        verdict = "passed" if result.passed else "FAILED"
        print(
            f"rra test: {case.id}: {verdict} in {result.seconds:.1f} s", file=sys.stderr, flush=True
        )
        runs.append(result)
        if result.passed and not args.keep:
            prune(result)  # all but its crashed nodes' logs and its verdict
    print(render_rows(runs, wide=args.wide), flush=True)
    failed = [r for r in runs if not r.passed]
    crashed = render_crashes([r for r in runs if r.passed], wide=args.wide)
    if crashed:
        print(f"\n{crashed}", flush=True)
    for r in failed:
        print()
        print(describe_failure(r, wide=args.wide))
    if not args.out and not failed and not crashed and not args.keep:
        shutil.rmtree(base, ignore_errors=True)
    print(
        f"\n{len(runs) - len(failed)} passed, {len(failed)} failed "
        f"in {time.monotonic() - started:.1f} s",
        file=sys.stderr,
    )
    return 1 if failed or status else 0
