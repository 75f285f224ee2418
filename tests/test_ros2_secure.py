"""ROS 2 executables in a system with certificates (mutual TLS and the generated access
control): the host agent writes each one a Zenoh session configuration (its host's node
certificate, a Zenoh id of its own) and the access control admits that session with the ROS
domain's keys only.

- in-process: the configuration file (its content, mode 0600, what Zenoh reads of it), the
  executable's environment, and the access control's subject of each ROS 2 executable;
- real processes (``rra up --certs`` of scenarios/ros2_rover on a ``tls/`` endpoint): the
  rover's ROS 2 executables join, and the Power adaptation works end to end; a session with
  the node certificate but another Zenoh id cannot publish on the ROS domain.
"""

from __future__ import annotations

import json
import shutil
import stat
import threading
from pathlib import Path
from typing import Any

import pytest
import zenoh
from conftest import run_rra
from test_ros2_system import ROVER, Rover, economy

from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig, free_port, node_zid, ros2_zid
from rra_agent.bus.session import open_session
from rra_agent.deployment import deploy
from rra_agent.ros2 import launch
from rra_agent.security.acl import access_control
from rra_agent.security.certs import issue

SYSTEM = "ros2_rover"
EXECUTABLES = ("battery", "planner_fast", "planner_eco", "controller", "saboteur")


# ---- in-process: the file, the environment, the access control -------------------------------
def test_the_session_configuration_of_a_ros2_executable(tmp_path: Path) -> None:
    zid = ros2_zid(SYSTEM, "battery")
    assert zid != node_zid(SYSTEM, "battery") and len(zid) <= 32
    config = launch.session_config(
        "tls/127.0.0.1:7450", zid=zid, ca="/c/ca.pem", cert="/c/node.pem", key="/c/node.key",
        lease_ms=2000, keep_alive=8,
    )  # fmt: skip
    path = tmp_path / "logs" / "battery.zenoh.json5"
    path.parent.mkdir()
    path.write_text("{}")
    path.chmod(0o644)  # an earlier file, readable by all: replaced, and 0600
    assert launch.write_session_config(path, config) == path
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert json.loads(path.read_text()) == config
    z = zenoh.Config.from_file(str(path))  # what rmw_zenoh and zenoh-ros2-sdk load
    got = {k: json.loads(z.get_json(k)) for k in (
        "id", "mode", "connect/endpoints", "scouting/multicast/enabled",
        "transport/link/tls/root_ca_certificate", "transport/link/tls/connect_certificate",
        "transport/link/tls/connect_private_key", "transport/link/tls/enable_mtls")}  # fmt: skip
    assert got == {
        "id": zid, "mode": "client", "connect/endpoints": ["tls/127.0.0.1:7450"],
        "scouting/multicast/enabled": False,
        "transport/link/tls/root_ca_certificate": "/c/ca.pem",
        "transport/link/tls/connect_certificate": "/c/node.pem",
        "transport/link/tls/connect_private_key": "/c/node.key",
        "transport/link/tls/enable_mtls": True,
    }  # fmt: skip
    # the environment names it; the override says the same endpoint (it applies last)
    _, env = launch.command(launch.Ros2Run("pkg", "exe"), router="tls/127.0.0.1:7450",
                            session_config=str(path))  # fmt: skip
    assert env[launch.SESSION_CONFIG_ENV] == str(path)
    assert env["ZENOH_CONFIG_OVERRIDE"] == 'connect/endpoints=["tls/127.0.0.1:7450"]'
    assert launch.SESSION_CONFIG_ENV not in launch.command(launch.Ros2Run("p", "e"))[1]


def _ros2_subjects(acl: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {s["id"]: s for s in acl["subjects"] if s["id"].startswith("ros2:")}


def test_each_ros2_executable_is_a_subject_with_the_ros_domain_only() -> None:
    acl = access_control(deploy(ROVER), "local")
    subjects = _ros2_subjects(acl)
    assert set(subjects) == {f"ros2:{c}" for c in EXECUTABLES}
    rules = {r["id"]: r for r in acl["rules"]}
    policies = {p["id"]: p for p in acl["policies"]}
    for c in EXECUTABLES:
        assert subjects[f"ros2:{c}"] == {
            "id": f"ros2:{c}",
            "cert_common_names": ["node.local"],
            "zids": [ros2_zid(SYSTEM, c)],
        }
        (rule,) = [rules[r] for r in policies[f"ros2:{c}"]["rules"]]
        assert rule["key_exprs"] == ["0/**", "@ros2_lv/0/**"]  # nothing of rra/...
        assert set(rule["flows"]) == {"ingress", "egress"}


def test_ros2_executables_are_subjects_of_their_own_hosts_routers_only(tmp_path: Path) -> None:
    pkg = tmp_path / "ros2_rover"
    shutil.copytree(ROVER, pkg, ignore=shutil.ignore_patterns("*.scenario.yaml", "__pycache__"))
    system = pkg / "system.yaml"
    text = system.read_text()
    marker = "  - name: controller\n"
    system.write_text(text.replace(marker, marker + "    host: arm\n"))
    dep = deploy(pkg)
    assert "ros2:controller" not in _ros2_subjects(access_control(dep, "local"))
    arm = _ros2_subjects(access_control(dep, "arm"))
    assert arm["ros2:controller"]["cert_common_names"] == ["node.arm"]
    # components without a host run wherever their node is started: every router admits them
    assert "ros2:battery" in arm


# ---- real processes: the rover with certificates ------------------------------------------------
@pytest.fixture
def secure_rover(procs, tmp_path: Path):
    """``rra up --certs`` of the rover on a ``tls/`` endpoint; (rover, certs folder)."""
    certs = tmp_path / "certs"
    issue(certs, ["local"])
    endpoint = f"tls/127.0.0.1:{free_port()}"
    operator = BusConfig(connect=[endpoint], multicast=False, lease_ms=500)
    operator = operator.with_identity(certs / "operator", "operator")
    rover = Rover(procs, operator, tmp_path / "run", ROVER, hostile=False,
                  extra=("--certs", str(certs / "local")))  # fmt: skip
    yield rover, certs
    if rover.proc.poll() is None:
        assert rover.stop() == 0, procs.log("up")


def endpoint(rover: Rover) -> str:
    return f"tls/127.0.0.1:{rover.port}"


def forged_puts_are_dropped(rover: Rover, certs: Path) -> None:
    """A session with the node certificate and another Zenoh id puts on /battery's key: the
    operator, who may read the ROS domain, sees the battery driver's samples and never it."""
    seen: list[tuple[str, bytes]] = []
    lock = threading.Lock()

    def got(sample: zenoh.Sample) -> None:
        with lock:
            seen.append((str(sample.key_expr), sample.payload.to_bytes()))

    sub = rover.client.session.declare_subscriber("0/battery/**", got)
    forged = b"\x00\x01\x00\x00forged by a node certificate"
    bus = BusConfig(connect=[endpoint(rover)], multicast=False)
    session = open_session(bus.with_identity(certs / "local", "node"), wait_connected=True)
    try:
        key = wait_until(lambda: seen and seen[0][0], 10, "the battery driver's samples")
        for _ in range(20):
            session.put(key, forged)
        with lock:
            mark = len(seen)
        # the driver publishes at 10 Hz: 10 of its samples after the forged ones
        wait_until(lambda: len(seen) >= mark + 10, 10, "10 more samples of the driver")
        with lock:
            assert forged not in {payload for _, payload in seen}
    finally:
        session.close()
        sub.undeclare()


@pytest.mark.system
def test_ros2_executables_join_a_secure_system_and_the_rover_adapts(secure_rover) -> None:
    r, certs = secure_rover
    st = r.wait(lambda s: s.get("ros2") and {"/battery_driver", "/controller", "/planner_eco",
                                              "/planner_fast"} <= {n["name"] for n in
                                                                   s["ros2"]["nodes"]},
                "the rover's ROS 2 nodes in the graph")  # fmt: skip
    st = r.wait(lambda s: {n["node"] for n in s["nodes"] if n["state"] == "RUNNING"}
                >= set(EXECUTABLES), "the rover's nodes RUNNING")  # fmt: skip
    pids = {n["node"]: n["pid"] for n in st["nodes"] if n["node"] in EXECUTABLES}
    wait_until(lambda: r.measurement("BattLev") == pytest.approx(1.0), 10, "BattLev")
    wait_until(lambda: r.measurement("DrivePlanner") == "planner_fast", 10, "planner_fast")
    forged_puts_are_dropped(r, certs)
    r.set("battery", level=20.0)  # a SetParameters of the ROS 2 battery driver, under mTLS
    r.wait(economy, "Economy in effect", 15)
    wait_until(lambda: r.measurement("DrivePlanner") == "planner_eco", 5, "planner_eco drives")
    assert r.measurement("DriveSpeed") == pytest.approx(0.25)
    # what the controller drives is capped: its max_speed took effect on the ROS 2 side (an
    # operator may not call a node's control: `rra param` reads it through the engine)
    who = ["--system", SYSTEM, "--certs", str(certs / "operator"), "--connect", endpoint(r)]
    param = run_rra("param", *who, "controller")
    assert param.returncode == 0 and "max_speed = 0.25" in param.stdout, param.stderr
    st = r.gather()
    assert {n["node"]: n["pid"] for n in st["nodes"] if n["node"] in EXECUTABLES} == pids
    # the session configuration each executable was given
    logs = r.run_dir / "logs"
    for c in EXECUTABLES:
        path = logs / f"{c}.zenoh.json5"
        assert stat.S_IMODE(path.stat().st_mode) == 0o600
        config = json.loads(path.read_text())
        assert config["id"] == ros2_zid(SYSTEM, c)
        assert config["connect"]["endpoints"] == [endpoint(r)]
        assert config["transport"]["link"]["tls"]["connect_certificate"] == str(
            (certs / "local" / "node.pem").resolve())
