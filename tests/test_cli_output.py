"""What the ``rra`` command prints fits 100 columns (wider only with ``--wide``): the verdict
tables of ``rra test`` and ``rra demo``, the banners and progress lines of ``rra up`` and
``rra agent``; and ``rra up --listen X`` makes X the hub, leaving the default hub's port to
another system."""

from __future__ import annotations

import argparse
import re
import signal
from pathlib import Path

import pytest
from conftest import RELAY, wait_until

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient
from rra_agent.bus.config import DEFAULT_HUB, BusConfig, free_port
from rra_agent.cli import main
from rra_agent.cli.commands import build_parser
from rra_agent.cli.up import hub_bus
from rra_agent.host.agent import state_printer
from rra_agent.host.links import banner
from rra_agent.scenario import expectations as x
from rra_agent.scenario.runner import CaseRun, Crash, Row, render_crashes, render_rows
from rra_agent.text import WIDTH, table

LONG = "node proploss_controller RUNNING from motor_failure + 0.5 within 0.1 s after injection"
OBSERVED = "1.97485 .. 2.00687 (last 1.99071) over [7.00, 20.00] s (0.04 s after motor_failure)"


def run_of(case_id: str, rows: list[Row], crashes: tuple[Crash, ...] = ()) -> CaseRun:
    case = type("Case", (), {"id": case_id, "file": "s.scenario.yaml"})()
    return CaseRun(case, Path("/tmp/none"), rows, crashes=list(crashes))  # type: ignore[arg-type]


def widest(text: str) -> int:
    return max(len(line) for line in text.splitlines())


def test_the_verdict_table_fits_100_columns_and_says_everything() -> None:
    rows = [
        Row(LONG, "s.scenario.yaml:3", x.Outcome(True, OBSERVED)),
        Row("no node FATAL", "s.scenario.yaml:4", x.Outcome(False, "FATAL at 3.00 s: " * 6)),
    ]
    runs = [run_of("motor_failure::adaptive", rows), run_of("engine_faults::resolution", rows)]
    text = render_rows(runs)
    assert widest(text) <= WIDTH, text
    # Nothing is cut: every word of every cell is there, in its column.
    for word in (*LONG.split(), *OBSERVED.split(), "engine_faults::resolution"):
        assert word in text.split(), word
    lines = text.splitlines()
    assert lines[0].split() == ["SCENARIO", "EXPECTATION", "OUTCOME", "OBSERVED"]
    outcome = lines[0].index("OUTCOME")
    starts = [line for line in lines[1:] if line[:1] != " "]  # one per row
    assert [line[outcome:].split()[0] for line in starts] == ["pass", "FAIL", "pass", "FAIL"]
    wide = render_rows(runs, wide=True).splitlines()
    assert len(wide) == 5 and widest("\n".join(wide)) > WIDTH  # --wide: one line per row
    assert LONG in wide[1] and OBSERVED in wide[1]


def test_crashes_wrap_under_their_line() -> None:
    fail = m.Failure(
        type="RuntimeError", message="camera /dev/video0 not found " * 3,
        where="crashy_nodes.py:12", function="open_camera", during="on_start",
    )  # fmt: skip
    crash = Crash("filtered", "local", "FATAL", fail, Path("/tmp/run/crashed/filtered.log"))
    text = render_crashes([run_of("camera", [], (crash,))])
    assert widest(text) <= WIDTH, text
    assert text.splitlines()[0].startswith("camera: node filtered crashed (FATAL): RuntimeError")
    assert text.splitlines()[-1] == "    log: /tmp/run/crashed/filtered.log"


def test_a_table_wraps_only_the_columns_it_may() -> None:
    rows = [("A", "B", "C"), ("x" * 30, "word " * 30, "y" * 50)]
    text = table(rows, wrapping=(1,), width=100)
    assert widest(text) <= 100
    lines = text.splitlines()[1:]
    assert all(line.startswith("x" * 30) or line.startswith(" " * 30) for line in lines)


def test_banner_and_progress_lines_fit(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    router = BusConfig(mode="router", listen=["tls/10.0.0.1:7447", "tls/127.0.0.1:7447"],
                       connect=["tls/10.0.0.2:7447"])  # fmt: skip
    logs = str(tmp_path / ("a-rather-long-folder-name-" * 4) / "run")
    text, linked = banner("rra up: system 'x' (A, B, C) on host robot; Ctrl-C to stop", router,
                          None, [("logs", logs)])  # fmt: skip
    assert widest(text) <= WIDTH and not linked, text
    assert "  links   to tls/10.0.0.2:7447: not linked yet" in text.splitlines()
    assert "".join(line.strip() for line in text.splitlines()[-2:]).endswith(logs.lstrip("/")[-20:])
    show = state_printer()
    reason = (
        "exited with status 1: RuntimeError: camera /dev/video0 not found (agv.py:42 in on_start)"
    )
    show(m.NodeState(stamp=0.0, node="depth_camera_driver", host="h", state="BACKOFF", pid=4242,
                     reason=reason))  # fmt: skip
    out = capsys.readouterr().out
    assert widest(out) <= WIDTH and len(out.splitlines()) == 2, out
    state_printer(wide=True)(m.NodeState(stamp=0.0, node="n", host="h", state="EXITED",
                                         reason=reason))  # fmt: skip
    assert len(capsys.readouterr().out.splitlines()) == 1


@pytest.mark.parametrize("command", ["up", "agent", "test", "demo", "status", "events"])
def test_every_command_with_a_table_or_banner_takes_wide(command: str) -> None:
    argv = {"up": ["up", "PKG"], "agent": ["agent", "--package", "P", "--host", "h"],
            "test": ["test", "S"], "demo": ["demo"], "status": ["status"],
            "events": ["events"]}[command]  # fmt: skip
    assert build_parser(command).parse_args([*argv, "--wide"]).wide is True


# ---- rra up --listen ---------------------------------------------------------------------------
def up_args(*argv: str) -> argparse.Namespace:
    return build_parser("up").parse_args(["up", "PKG", *argv])


def test_listen_without_connect_is_the_hub() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    bus = hub_bus(up_args("--listen", ep))
    assert bus.hub == ep
    assert bus.host_router(hub=True).listen == [ep]  # not also tcp/127.0.0.1:7447
    wild = hub_bus(up_args("--listen", "tcp/0.0.0.0:7600", "--insecure"))
    assert wild.hub == "tcp/127.0.0.1:7600"  # where the tools of this machine find it
    assert wild.host_router(hub=True).listen == ["tcp/0.0.0.0:7600"]
    other = f"tcp/127.0.0.1:{free_port()}"
    both = hub_bus(up_args("--listen", ep, "--connect", other))  # --connect says where
    assert both.hub == other and both.host_router(hub=True).listen == [other, ep]
    assert hub_bus(up_args()).hub == DEFAULT_HUB


@pytest.mark.system
def test_up_listen_is_where_the_tools_find_it(procs, tmp_path: Path) -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    run_dir = tmp_path / ("a-long-run-folder-name-" * 4) / "run"
    proc = procs.python("rra_agent", "up", str(RELAY), "--listen", ep, "--run-dir",
                        str(run_dir), "--no-multicast", name="up")  # fmt: skip
    wait_until(lambda: "Ctrl-C to stop" in procs.log("up"), 60, "the banner")
    bus = BusConfig(connect=[ep], multicast=False, lease_ms=500)
    with BusClient(bus, "relay_system") as client:
        wait_until(lambda: list(client.session.liveliness().get(
            client.keys.host_alive("local"), timeout=0.5)), 30, "the host agent")  # fmt: skip
        reply = client.host("local", m.Ping())
        assert isinstance(reply, m.Ok) and reply.result["listen"] == [ep]
    assert main(["status", "--connect", ep]) == 0
    proc.send_signal(signal.SIGINT)
    assert proc.wait(30) == 0
    lines = procs.log("up").splitlines()
    assert f"  router  listens on {ep}" in lines
    assert f"  tools   find it at {ep}: give them --connect {ep}" in lines
    assert max(map(len, lines)) <= WIDTH, [line for line in lines if len(line) > WIDTH]
    head = next(line for line in lines if "Ctrl-C to stop" in line)
    assert re.fullmatch(r"rra up: system 'relay_system' \(.*\) on host local; Ctrl-C to stop", head)
