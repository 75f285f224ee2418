"""`rra check`: static conflict analysis from the command line."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

#: Every test here starts processes or opens Zenoh sessions (pytest -m 'not system').
pytestmark = pytest.mark.system

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "scenarios" / "object_storing"


def rra(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "rra_agent", *args], capture_output=True, text=True, timeout=60
    )


def test_fig5_has_no_conflict():
    out = rra("check", str(PKG))
    assert out.returncode == 0, out.stderr
    assert out.stdout == ""
    assert "0 conflict(s)" in out.stderr


def test_planted_conflict_is_reported_at_both_rules(tmp_path):
    pkg = tmp_path / "pkg"
    shutil.copytree(PKG, pkg)
    rules = pkg / "adaptation.rra"
    text = (
        rules.read_text()
        + "\nrule Override:\n    if (cdm.BattLev < 80)\n        activate_feature(Dynamic)\n"
    )
    rules.write_text(text)
    lines = text.splitlines()
    static = next(i for i, line in enumerate(lines) if "activate_feature(Static)" in line)
    planted = max(i for i, line in enumerate(lines) if "activate_feature(Dynamic)" in line)
    out = rra("check", str(pkg))
    assert out.returncode == 1
    col_s = lines[static].index("activate_feature") + 1
    col_p = lines[planted].index("activate_feature") + 1
    assert f"{rules}:{static + 1}:{col_s}: conflict: rules Location and Override" in out.stdout
    assert f"{rules}:{planted + 1}:{col_p}: activate_feature(Dynamic)" in out.stdout
    assert "Traceback" not in out.stderr


def test_the_else_branch_of_an_int_condition_of_a_new_robot(tmp_path):
    """The issue's crash (``OverflowError: cannot convert float infinity to integer``): the
    rover's rule Localize has an else branch on the int measurement Satellites (< 4, bounded
    on one side only); a second rule fights it over the choice of localization."""
    pkg = tmp_path / "rover"
    shutil.copytree(ROOT / "tests" / "data" / "rover", pkg)
    rules = pkg / "adaptation.rra"
    text = (
        rules.read_text() + "\nrule Recover:\n    if (cdm.Satellites > 10) activate_feature(Gnss)\n"
    )
    rules.write_text(text)
    out = rra("check", str(pkg))
    assert "Traceback" not in out.stderr and out.returncode == 1, out.stderr
    line = text.splitlines().index("    else activate_feature(VisualOdometry)") + 1
    assert out.stdout.startswith(
        f"{rules}:{line}:10: conflict: rules Localize and Recover can fire in the same tick with"
        " opposite effects on the alternatives of Localization"
    )
    assert "1 conflict(s), 0 possible conflict(s)" in out.stderr
