"""One system, one set of engines (issue 22, item 6): a second ``rra up`` of a system that
runs on the bus, or a second agent of a host, is refused in one line and starts nothing;
two processes with one replica name (the sides of a partition that joins again) end with
one leader, whose term every receiver tells from the other's.

Real processes on loopback, deadlines instead of sleeps.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from conftest import RELAY, System, pid_alive
from conftest import RELAY_KEYS as K

from rra_agent.bus import messages as m
from rra_agent.bus.client import NoReply, wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.bus.loop import MainLoop
from rra_agent.bus.session import open_session
from rra_agent.engines.election import Election

#: Every test here starts processes or opens Zenoh sessions (pytest -m 'not system').
pytestmark = pytest.mark.system


def pids(st: dict) -> dict[str, int]:
    return {n["node"]: n["pid"] for n in st["nodes"] if n["state"] == "RUNNING"}


def terms(sys_: System) -> dict[str, list]:
    """The term each engine role's leader answers with."""
    out = {}
    for role in ("monitor", "adaptation", "resolution"):
        try:
            reply = sys_.client.request(K.engine_ctl(role), m.Status(), 2.0)
        except NoReply:
            out[role] = []
            continue
        out[role] = reply.result["leader"] if isinstance(reply, m.Ok) else []
    return out


def settled(sys_: System) -> tuple[dict[str, int], dict[str, list]]:
    """The nine processes running and every role led: (pids, leader terms)."""
    found: list = []

    def check(st: dict) -> bool:
        if len(pids(st)) != 9:
            return False
        now = terms(sys_)
        found[:] = [pids(st), now]
        return all(now.values())

    sys_.wait(check, "nine processes running, every engine role led")
    return found[0], found[1]


def finished(proc: subprocess.Popen[bytes], timeout: float = 60.0) -> int:
    """The exit status of a command that must end by itself (refused), else a failure."""
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"still running after {timeout:g} s: it was not refused") from None


def started_by(marker: str) -> list[int]:
    """Processes whose command line names ``marker`` (a run folder of this test)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if marker in (entry / "cmdline").read_bytes().decode(errors="replace"):
                out.append(int(entry.name))
        except OSError:
            continue
    return [p for p in out if pid_alive(p)]


def test_a_second_rra_up_linked_to_a_running_system_is_refused(system, procs, bus, tmp_path):
    sys_ = system()
    before, leaders = settled(sys_)
    second_dir = tmp_path / "second-run"
    # The tester's set-up: a second `rra up` of the same package, its own hub, its router
    # linked to the first one's.
    second = procs.python(
        "rra_agent", "up", str(RELAY), "--run-dir", str(second_dir),
        "--connect", f"tcp/127.0.0.1:{free_port()}", "--connect", bus.connect[0],
        "--no-multicast", name="second-up",
    )  # fmt: skip
    assert finished(second) != 0
    out = procs.log("second-up").strip().splitlines()
    assert len(out) == 1, out  # one line, no traceback
    line = out[0]
    assert line.startswith("rra up: system 'relay_system' already runs on this bus"), line
    assert "host local" in line and f"agent pid {sys_.proc.pid}" in line
    assert bus.connect[0] in line
    # Nothing started: no run folder, no process of the second run.
    assert not second_dir.exists()
    assert not started_by(str(second_dir))
    # The first system undisturbed: the same processes, the same leaders.
    after, now = settled(sys_)
    assert after == before
    assert now == leaders
    st = sys_.gather()
    assert not [n for n in st["nodes"] if n.get("restarts")]


def test_a_second_agent_of_a_host_is_refused(system, procs, bus, tmp_path):
    sys_ = system()
    before, leaders = settled(sys_)
    agent = procs.python(
        "rra_agent", "agent", "--package", str(RELAY), "--host", "local",
        "--log-dir", str(tmp_path / "second-logs"), "--connect", bus.connect[0],
        "--listen", f"tcp/127.0.0.1:{free_port()}", "--no-multicast", name="second-agent",
    )  # fmt: skip
    assert finished(agent) != 0
    out = procs.log("second-agent").strip().splitlines()
    assert len(out) == 1, out
    want = (
        "rra agent: host local of system 'relay_system' already has its agent on this bus, "
        f"host local (agent pid {sys_.proc.pid}"
    )
    assert out[0].startswith(want), out
    after, now = settled(sys_)
    assert after == before and now == leaders


def test_two_leaders_of_one_replica_name_joined_after_a_partition_become_one(tmp_path):
    """Each side of a partition runs a replica ``resolution-a`` that leads at epoch 1 (two
    systems started apart, or one started on the far side of a cut). When the sides join,
    the two claims are two terms (their instances differ): one replica steps down, and a
    receiver that has accepted the winner's fence refuses the other's."""
    first, second = free_port(), free_port()
    routers = [
        open_session(BusConfig(mode="router", listen=[f"tcp/127.0.0.1:{p}"], connect=[],
                               multicast=False))
        for p in (first, second)
    ]  # fmt: skip
    sessions, elections, loops = [], [], []
    try:
        for port in (first, second):
            session = open_session(
                BusConfig(connect=[f"tcp/127.0.0.1:{port}"], multicast=False), wait_connected=True
            )
            loop = MainLoop()
            election = Election(session, K, "resolution", "resolution-a", loop, lambda: None)
            sessions.append(session)
            loops.append(loop)
            elections.append(election)
            election.start()
        assert all(e.leading for e in elections)
        assert elections[0].term[:2] == elections[1].term[:2] == (1, "resolution-a")  # type: ignore[index]
        assert elections[0].term != elections[1].term
        # The partition ends: a third router links both sides.
        bridge = BusConfig(
            mode="router",
            listen=[f"tcp/127.0.0.1:{free_port()}"],
            connect=[f"tcp/127.0.0.1:{first}", f"tcp/127.0.0.1:{second}"],
            multicast=False,
        )
        routers.append(open_session(bridge))

        def one_leader() -> bool:
            for loop in loops:
                loop.cycle(0.01)
            return sum(e.leading for e in elections) == 1 and all(
                e.leader == elections[0].leader for e in elections
            )

        wait_until(one_leader, 10, "one leader of the joined sides", interval=0.01)
        winner = next(e for e in elections if e.leading)
        loser = next(e for e in elections if not e.leading)
        assert winner.instance < loser.instance
        # Both sides' terms at one receiver: the winner's and the loser's are never both
        # accepted once the winner's is (the receivers' rule, `newer`).
        from rra_agent.core.election import newer

        assert winner.term is not None
        stale = (winner.term[0], "resolution-a", loser.instance)
        assert not newer(stale, winner.term)
    finally:
        for e in elections:
            e.close()
        for s in [*sessions, *routers]:
            s.close()
