"""``rra agent`` says what it is and what it does: its host, its router's endpoints (the hub
it listens on or links to) and one line per node it starts or stops, as ``rra up`` does."""

from __future__ import annotations

import re
import signal
import socket
from pathlib import Path

import pytest
from conftest import run_rra, wait_until
from test_host_agent import PACKAGE, SYSTEM, relay_spec

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.bus.keys import Keys
from rra_agent.bus.session import open_session
from rra_agent.host.links import DEADLINE
from rra_agent.text import WIDTH

#: Every test here starts processes or opens Zenoh sessions (pytest -m 'not system').
pytestmark = pytest.mark.system


def test_agent_prints_its_host_router_and_nodes(procs, bus, tmp_path: Path) -> None:
    hub = bus.connect[0]
    other = f"tcp/127.0.0.1:{free_port()}"  # a first host that is not there (yet)
    proc = procs.python(
        "rra_agent", "agent", "--package", str(PACKAGE), "--host", "h1", "--hub",
        "--log-dir", str(tmp_path / "nodes"), "--connect", hub, "--connect", other,
        "--no-multicast", name="agent",
    )  # fmt: skip
    wait_until(lambda: "Ctrl-C to stop" in procs.log("agent"), 60, "the agent's banner")
    banner = procs.log("agent").splitlines()[:4]
    assert banner == [
        f"rra agent: host h1 of system {SYSTEM!r}; Ctrl-C to stop",
        f"  router  listens on {hub}",
        f"  links   to {other}: not linked yet",  # nothing listens there: not "linked"
        f"  logs    {tmp_path / 'nodes'}",
    ]
    with BusClient(bus, SYSTEM) as client:
        wait_until(lambda: list(client.session.liveliness().get(Keys(SYSTEM).host_alive("h1"),
                   timeout=0.5)), 15, "the host agent's token")  # fmt: skip
        assert isinstance(client.host("h1", m.StartNode(spec=relay_spec())), m.Ok)
        wait_until(lambda: re.search(r"relay +RUNNING pid \d+", procs.log("agent")), 30,
                   "relay RUNNING printed")  # fmt: skip
        reply = client.host("h1", m.Ping())
        assert isinstance(reply, m.Ok)
        assert reply.result["host"] == "h1" and reply.result["listen"] == [hub]
        assert reply.result["connect"] == [other]
        assert isinstance(client.host("h1", m.StopNode(node="relay")), m.Ok)
        wait_until(lambda: re.search(r"relay +STOPPED pid \d+", procs.log("agent")), 30,
                   "relay STOPPED printed")  # fmt: skip
    proc.send_signal(signal.SIGINT)
    assert proc.wait(30) == 0
    lines = procs.log("agent").splitlines()
    states = [re.sub(r"^\[[\d:]+\] ", "", line).split()[:2] for line in lines
              if re.match(r"^\[[\d:]+\] ", line)]  # fmt: skip
    assert states == [["relay", s] for s in ("STARTING", "RUNNING", "STOPPING", "STOPPED")]
    assert lines[-1] == "rra agent: host h1: all processes stopped"
    assert max(map(len, lines)) <= WIDTH, [line for line in lines if len(line) > WIDTH]


def test_agent_says_when_its_link_comes_and_goes(procs, tmp_path: Path) -> None:
    """"Linked" only once the link exists: a warning (one line, what a TCP connection says)
    when it does not come within the deadline, a line when it comes, one when it is lost."""
    other = f"tcp/127.0.0.1:{free_port()}"
    procs.python(
        "rra_agent", "agent", "--package", str(PACKAGE), "--host", "h1",
        "--log-dir", str(tmp_path / "nodes"), "--listen", f"tcp/127.0.0.1:{free_port()}",
        "--connect", other, "--no-multicast", name="agent",
    )  # fmt: skip
    wait_until(lambda: "Ctrl-C to stop" in procs.log("agent"), 60, "the agent's banner")
    assert f"  links   to {other}: not linked yet" in procs.log("agent").splitlines()
    warning = (
        f"rra agent: WARNING: not linked to {other} after {DEADLINE:g} s: nothing listens there"
    )
    wait_until(lambda: warning in procs.log("agent"), DEADLINE + 30, "the warning")
    assert f"linked to {other}" not in procs.log("agent").replace(f"not linked to {other}", "")
    router = open_session(BusConfig(mode="router", listen=[other], connect=[], multicast=False))
    try:
        wait_until(lambda: f"rra agent: linked to {other}" in procs.log("agent"), 30, "linked")
    finally:
        router.close()
    wait_until(lambda: f"rra agent: link to {other} lost" in procs.log("agent"), 30, "lost")
    lines = procs.log("agent").splitlines()
    assert sum(line.startswith("rra agent: WARNING") for line in lines) == 1
    assert max(map(len, lines)) <= WIDTH, lines


def test_agent_on_a_taken_port_says_which_option_moves_it(tmp_path: Path) -> None:
    port = free_port()
    with socket.socket() as holder:
        holder.bind(("127.0.0.1", port))
        holder.listen()
        r = run_rra("agent", "--package", str(PACKAGE), "--host", "h1",
                    "--log-dir", str(tmp_path / "nodes"), "--listen", f"tcp/127.0.0.1:{port}",
                    "--connect", f"tcp/127.0.0.1:{free_port()}")  # fmt: skip
    assert r.returncode == 1
    assert "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [
        f"rra agent: cannot listen on tcp/127.0.0.1:{port}: port {port} is already in use "
        f"(another `rra up`? `ss -ltnp 'sport = :{port}'` shows which program); stop it, or "
        f"use another port: --listen tcp/127.0.0.1:{port + 1}"
    ]
