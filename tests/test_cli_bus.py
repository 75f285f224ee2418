"""A failure of the bus at the command line is one actionable line: what, where, what to try.

Exit status 1, no traceback, no empty run folder left behind: `rra up` on a port another
program holds; `rra status`, `rra events` and `rra param` with nothing listening at the
endpoint (at once, not after Zenoh's 10 s connect timeout), with a Zenoh router that runs no
system, with certificate files that are not what they should be (the file is named), and
with certificates of another system's CA (the TLS handshake is refused).
"""

from __future__ import annotations

import shutil
import socket
import time
from pathlib import Path

import pytest
from conftest import RELAY, run_rra

from rra_agent.bus.client import ANSWER_TIMEOUT
from rra_agent.bus.config import BusConfig, Tls, free_port
from rra_agent.bus.session import open_session
from rra_agent.cli import main

#: Every test here starts processes or opens Zenoh sessions (pytest -m 'not system').
pytestmark = pytest.mark.system

TOOLS = [["status"], ["events"], ["param", "source"]]


def one_line(err: str) -> str:
    """The only line of ``err`` (a traceback or several lines fail the test)."""
    assert "Traceback" not in err, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    return lines[0]


def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


# ---- rra up -------------------------------------------------------------------------------
def test_up_on_a_taken_port_says_which_and_leaves_no_run_folder(tmp_path: Path) -> None:
    port = free_port()
    runs = tmp_path / "runs"
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", port))
        holder.listen()
        r = run_rra("up", str(RELAY), "--connect", f"tcp/127.0.0.1:{port}", "-q",
                    "--run-dir", str(runs / "r1"))  # fmt: skip
    assert r.returncode == 1, r.stderr
    line = one_line(r.stderr)
    assert line.startswith(f"rra up: cannot listen on tcp/127.0.0.1:{port}: port {port} is "
                           "already in use"), line  # fmt: skip
    assert f"--connect tcp/127.0.0.1:{port + 1}" in line  # what to try
    assert not runs.exists(), list(runs.rglob("*"))


def test_up_on_an_address_of_another_machine(tmp_path: Path) -> None:
    runs = tmp_path / "runs"
    r = run_rra("up", str(RELAY), "--connect", "tcp/192.0.2.1:7447", "--insecure", "-q",
                "--run-dir", str(runs / "r"))  # fmt: skip
    assert r.returncode == 1
    assert one_line(r.stderr) == (
        "rra up: cannot listen on tcp/192.0.2.1:7447: no network interface of this machine "
        "has the address 192.0.2.1 (`ip -brief address` lists them); listen on one of them, "
        "or on 0.0.0.0 for all"
    )
    assert not runs.exists()


def test_up_refusing_an_option_leaves_no_run_folder(tmp_path: Path, capsys) -> None:
    runs = tmp_path / "runs"
    assert main(["up", str(RELAY), "--run-dir", str(runs / "r"), "--rerun", "bogus"]) == 2
    assert "--rerun" in one_line(capsys.readouterr().err)
    assert not runs.exists()


# ---- the tools with no system ---------------------------------------------------------------
@pytest.mark.parametrize("cmd", TOOLS, ids=lambda c: c[0])
def test_a_tool_with_nothing_at_the_endpoint_says_so_at_once(
    cmd: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    ep = endpoint()
    t0 = time.monotonic()
    rc = main([*cmd, "--connect", ep])
    elapsed = time.monotonic() - t0
    line = one_line(capsys.readouterr().err)
    assert rc == 1
    assert line == (
        f"rra {cmd[0]}: no rra system answers at {ep}; start one with `rra up PKG` or give "
        "--connect ENDPOINT"
    )
    assert elapsed < 1.0, f"{elapsed:.2f} s"  # a refused connection is a definite answer


@pytest.mark.parametrize("cmd", TOOLS, ids=lambda c: c[0])
def test_a_tool_at_a_router_without_a_system(
    cmd: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    ep = endpoint()
    router = open_session(BusConfig(mode="router", listen=[ep], connect=[]))
    try:
        t0 = time.monotonic()
        rc = main([*cmd, "--connect", ep])
        elapsed = time.monotonic() - t0
    finally:
        router.close()
    line = one_line(capsys.readouterr().err)
    assert rc == 1
    assert f"no rra system answers at {ep}" in line
    # The router answers at once that no host agent is there: no wait for a timeout.
    assert elapsed < ANSWER_TIMEOUT, f"{elapsed:.2f} s"


def short_timeout(tmp_path: Path) -> Path:
    """A --bus-config file with a 1.5 s connect timeout (Zenoh's default is 10 s)."""
    path = tmp_path / "bus.yaml"
    path.write_text("connect_timeout_ms: 1500\n")
    return path


def test_a_tool_at_something_else_than_a_router(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    port = free_port()
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", port))
        holder.listen()
        rc = main(["status", "--connect", f"tcp/127.0.0.1:{port}",
                   "--bus-config", str(short_timeout(tmp_path))])  # fmt: skip
    line = one_line(capsys.readouterr().err)
    assert rc == 1
    assert line == (
        f"rra status: something listens at tcp/127.0.0.1:{port} but no Zenoh session opens: "
        "it is not an rra hub (or it needs TLS: --certs DIR)"
    )


# ---- TLS ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("certs") / "certs"
    assert main(["certs", str(RELAY), "--out", str(out)]) == 0
    return out


@pytest.mark.parametrize("file", ["operator.pem", "ca.pem", "operator.key"])
def test_a_bad_certificate_file_is_named(
    certs: Path, tmp_path: Path, file: str, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "operator"
    shutil.copytree(certs / "operator", folder)
    (folder / file).write_text("garbage\n")
    rc = main(["status", "--certs", str(folder), "--connect", f"tls/127.0.0.1:{free_port()}"])
    line = one_line(capsys.readouterr().err)
    assert rc == 1
    assert f"bad TLS identity: {folder / file}: not a PEM" in line, line
    assert "rra certs" in line


def test_a_missing_certificate_file_is_named(
    certs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    folder = tmp_path / "operator"
    shutil.copytree(certs / "operator", folder)
    (folder / "operator.key").unlink()
    assert main(["events", "--certs", str(folder)]) == 1
    line = one_line(capsys.readouterr().err)
    assert "operator.key missing" in line and str(folder) in line


def test_a_certificate_of_another_ca_is_named(
    certs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other = tmp_path / "other"
    assert main(["certs", str(RELAY), "--out", str(other)]) == 0
    folder = tmp_path / "operator"
    shutil.copytree(certs / "operator", folder)
    shutil.copy(other / "operator" / "operator.pem", folder / "operator.pem")
    shutil.copy(other / "operator" / "operator.key", folder / "operator.key")
    rc = main(["param", "source", "--certs", str(folder)])
    line = one_line(capsys.readouterr().err)
    assert rc == 1
    assert f"{folder / 'operator.pem'}: not signed by the CA of {folder / 'ca.pem'}" in line


def test_a_refused_tls_handshake(
    certs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A hub of this system's CA; an operator identity of another system's: refused."""
    port = free_port()
    local = certs / "local"
    hub = BusConfig(
        mode="router",
        listen=[f"tls/127.0.0.1:{port}"],
        connect=[],
        tls=Tls(ca=str(local / "ca.pem"), cert=str(local / "agent.pem"),
                key=str(local / "agent.key")),
    )  # fmt: skip
    other = tmp_path / "other"
    assert main(["certs", str(RELAY), "--out", str(other)]) == 0
    router = open_session(hub)
    try:
        t0 = time.monotonic()
        rc = main(["status", "--certs", str(other / "operator"),
                   "--connect", f"tls/127.0.0.1:{port}"])  # fmt: skip
        elapsed = time.monotonic() - t0
    finally:
        router.close()
    line = one_line(capsys.readouterr().err)
    assert rc == 1
    assert f"something listens at tls/127.0.0.1:{port} but no Zenoh session opens: the TLS " \
           "handshake was refused: the hub's certificate is not signed by the CA of --certs " \
           f"({other / 'operator' / 'ca.pem'})" in line, line  # fmt: skip
    # Zenoh would try for its whole connect timeout (10 s); the answer is definite at once.
    assert elapsed < 2.0, f"{elapsed:.2f} s"  # a generous bound (the probe: ~0.2 s)


def test_an_operator_at_a_hub_without_tls_is_told_at_once(
    certs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`rra status --certs` at the hub of a system run without certificates (same port, the
    default tls/ endpoint's): 10.3 s, then "the TLS handshake was refused"; now at once, with
    the endpoint that works."""
    port = free_port()
    router = open_session(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{port}"], connect=[]))
    try:
        t0 = time.monotonic()
        rc = main(["status", "--certs", str(certs / "operator"), "--system", "relay_system",
                   "--connect", f"tls/127.0.0.1:{port}"])  # fmt: skip
        elapsed = time.monotonic() - t0
    finally:
        router.close()
    assert rc == 1
    assert one_line(capsys.readouterr().err) == (
        f"rra status: tls/127.0.0.1:{port} is a hub without TLS: connect with --connect "
        f"tcp/127.0.0.1:{port}"
    )
    assert elapsed < 2.0, f"{elapsed:.2f} s"  # generous: the probes take ~0.3 s


def test_a_tool_without_certificates_at_a_tls_hub_is_told_at_once(
    certs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    port = free_port()
    local = certs / "local"
    hub = BusConfig(mode="router", listen=[f"tls/127.0.0.1:{port}"], connect=[],
                    tls=Tls(ca=str(local / "ca.pem"), cert=str(local / "agent.pem"),
                            key=str(local / "agent.key")))  # fmt: skip
    router = open_session(hub)
    try:
        t0 = time.monotonic()
        rc = main(["events", "--connect", f"tcp/127.0.0.1:{port}"])
        elapsed = time.monotonic() - t0
    finally:
        router.close()
    assert rc == 1
    assert one_line(capsys.readouterr().err) == (
        f"rra events: tcp/127.0.0.1:{port} is a TLS hub (certificates): give --certs "
        f"DIR/operator (from `rra certs`) and --connect tls/127.0.0.1:{port}"
    )
    assert elapsed < 2.0, f"{elapsed:.2f} s"


def test_up_with_a_bad_certificate_names_it(certs: Path, tmp_path: Path) -> None:
    folder = tmp_path / "local"
    shutil.copytree(certs / "local", folder)
    (folder / "agent.pem").write_text("garbage\n")
    runs = tmp_path / "runs"
    r = run_rra("up", str(RELAY), "--certs", str(folder), "-q", "--run-dir", str(runs / "r"),
                "--connect", f"tls/127.0.0.1:{free_port()}")  # fmt: skip
    assert r.returncode == 1
    line = one_line(r.stderr)
    assert f"bad TLS identity: {folder / 'agent.pem'}: not a PEM certificate" in line, line
    assert not runs.exists()
