"""``rra replay RUN [--package EDITED]``: re-run a recorded run's decisions offline.

Without ``--package``: every Adaptation Engine replica's recorded evaluations are re-run
through the pure core with the run's own models, in the recorded order and at the recorded
times; exit 0 when every selection and CV value comes out as recorded, 1 naming the first
difference (time, replica, feature or CV, recorded and replayed).

With ``--package EDITED`` (what-if): the edited models decide on the recorded context at every
evaluation of the run's leaders; each moment where they decide differently is printed
(feature or CV, recorded and edited, the rules behind it), a Rerun recording shows both side
by side (``--rrd``, default ``<RUN>/whatif-<models>.rrd``; ``--no-rrd``), exit 0.

A damaged record (a truncated or changed file, models that no longer match their digest), or
an edited package that does not fit the recording, is one line and exit 1.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from rra_agent.errors import RraError

WIDTH = 100


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("run", metavar="RUN", help="a run folder (rra up's --run-dir, rra test's)")
    p.add_argument("--package", metavar="EDITED", help="what-if: decide with these models")
    p.add_argument("--rrd", metavar="FILE", help="what-if: the Rerun recording to write")
    p.add_argument("--no-rrd", action="store_true", help="what-if: write no Rerun recording")
    p.add_argument("--limit", type=int, default=40, metavar="N",
                   help="what-if: print at most N moments (default 40)")  # fmt: skip
    p.add_argument("--wide", action="store_true", help="lines wider than 100 columns")


def run(args: argparse.Namespace) -> int:
    from rra_agent.record.replay import open_run

    if args.package is None:
        return _replay(args, open_run(args.run))
    return _what_if(args, open_run(args.run))


def _fit(line: str, wide: bool) -> str:
    return line if wide or len(line) <= WIDTH else line[: WIDTH - 3] + "..."


def _replay(args: argparse.Namespace, run: object) -> int:
    from rra_agent.record.replay import RecordedRun, replay

    assert isinstance(run, RecordedRun)
    for note in run.notes:
        print(_fit(f"rra replay: note: {note}", args.wide), file=sys.stderr)
    result = replay(run)
    head = (f"rra replay: {result.evaluations} evaluations ({len(result.replicas)} replicas), "
            f"{result.published} selections published, {result.duration:.1f} s of run "
            f"replayed in {result.seconds:.2f} s")  # fmt: skip
    if result.difference is not None:
        print(_fit(head, args.wide))
        print(_fit(f"rra replay: DIFFERENT at {result.difference.line()}", args.wide))
        return 1
    print(_fit(head, args.wide))
    print(_fit("rra replay: every selection and CV value as recorded", args.wide))
    return 0


def _what_if(args: argparse.Namespace, run: object) -> int:
    from rra_agent.record.replay import RecordedRun, load_edited, what_if

    assert isinstance(run, RecordedRun)
    for note in run.notes:
        print(_fit(f"rra replay: note: {note}", args.wide), file=sys.stderr)
    edited = load_edited(run, args.package)
    result = what_if(run, edited)
    again = f"; recomputed: {', '.join(result.recomputed)}" if result.recomputed else ""
    print(_fit(f"rra replay: what-if {result.models or '(models)'}: {result.evaluations} "
               f"evaluations, {result.duration:.1f} s of run in {result.seconds:.2f} s{again}",
               args.wide))  # fmt: skip
    for moment in result.moments[: args.limit]:
        print(_fit(f"  {moment.line()}", args.wide))
    more = len(result.moments) - args.limit
    if more > 0:
        print(f"  ... {more} more (--limit)")
    print(f"rra replay: {len(result.moments)} moment(s) where the decisions differ")
    if not args.no_rrd:
        out = Path(args.rrd) if args.rrd else Path(args.run) / f"whatif-{result.models}.rrd"
        _save(out, run, result)
        print(f"rra replay: Rerun recording: {_shown(out)}")
    return 0


def _shown(path: Path) -> str:
    """``path`` relative to the working folder when inside it (shorter lines)."""
    rel = os.path.relpath(path)
    return str(path) if rel.startswith("..") else rel


def _save(out: Path, run: object, result: object) -> None:
    from rra_agent.record.replay import RecordedRun, WhatIfResult
    from rra_agent.viz import whatif

    assert isinstance(run, RecordedRun) and isinstance(result, WhatIfResult)
    data = whatif.WhatIfData(
        title=f"whatif-{run.info.system}-{result.models}",
        times=result.recorded.times,
        features=result.features,
        recorded=whatif.Side(result.recorded.selections, result.recorded.cv),
        edited=whatif.Side(result.edited.selections, result.edited.cv),
        context=result.context,
        differences=[(mo.start, mo.line()) for mo in result.moments],
    )
    try:
        whatif.save(out, data)
    except OSError as e:
        raise RraError(f"{out}: cannot write the Rerun recording: {e}") from None
