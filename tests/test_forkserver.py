"""The fork server: nodes forked from a pre-imported interpreter, reaped and reported."""

from __future__ import annotations

import os
import signal

from conftest import free_port, pid_alive

from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig
from rra_agent.bus.messages import NodeSpec, PortSpec
from rra_agent.host.forkserver import ForkServer
from rra_agent.node import SPEC_ENV


def spec(name: str, impl: str = "rra_agent.nodes.generic.Relay") -> NodeSpec:
    return NodeSpec(
        system="fork", name=name, host="h", implementation=impl,
        ports={"in": PortSpec(direction="subscribe", type="X", keys=["rra/fork/data/a"]),
               "out": PortSpec(direction="publish", type="X", keys=["rra/fork/data/b"])},
    )  # fmt: skip


def env() -> dict[str, str]:
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"], connect_timeout_ms=100)
    return {"RRA_BUS_CONFIG": bus.to_env(), SPEC_ENV: ""}


def test_forked_node_runs_is_the_zygotes_child_and_reports_its_exit(tmp_path):
    fs = ForkServer()
    try:
        pid = fs.spawn(spec("n1"), env(), str(tmp_path / "n1.log"))
        assert fs.poll(pid) is None and pid_alive(pid)
        with open(f"/proc/{pid}/stat") as f:
            ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        assert ppid == fs.proc.pid  # forked by the zygote, not started by exec
        os.kill(pid, signal.SIGKILL)
        wait_until(lambda: fs.poll(pid) is not None, 10, "the exit report")
        assert fs.poll(pid) == -signal.SIGKILL  # as subprocess.Popen.returncode would say
        bad = fs.spawn(spec("n2", "no.such.Node"), env(), str(tmp_path / "n2.log"))
        wait_until(lambda: fs.poll(bad) is not None, 10, "the bad node's exit")
        assert fs.poll(bad) == 2  # unusable implementation: the supervisor's FATAL status
        assert "no.such" in (tmp_path / "n2.log").read_text()
    finally:
        fs.close()
    assert fs.proc.returncode == 0


def test_nodes_die_with_the_zygote(tmp_path):
    fs = ForkServer()
    pid = fs.spawn(spec("n3"), env(), str(tmp_path / "n3.log"))
    assert pid_alive(pid)
    fs.proc.kill()
    fs.proc.wait()
    wait_until(lambda: not pid_alive(pid), 10, "the node to die with its zygote")
