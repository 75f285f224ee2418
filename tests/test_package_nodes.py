"""A new robot's package: node classes kept in the package folder import like measurement
functions do, and ``rra validate`` resolves every implementation without starting anything.

The package is ``tests/data/rover`` (a field rover nobody here wrote): its GNSS receiver is a
node class of the package folder (``rover_nodes.py``), its speed a measurement function of the
package folder (``rover_functions.py``).
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, plant, position, run_rra

from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.bus.messages import NodeSpec, PortSpec
from rra_agent.bus.session import open_session
from rra_agent.errors import Location, ModelError
from rra_agent.host.processes import LocalHost
from rra_agent.node import NodeError
from rra_agent.node.loading import load_node_class
from rra_agent.package.loader import load_package
from rra_agent.package.validate import validate_package

ROVER = Path(__file__).parent / "data" / "rover"


def copy_rover(tmp_path: Path) -> Path:
    root = tmp_path / "rover"
    shutil.copytree(ROVER, root, ignore=shutil.ignore_patterns("__pycache__", "*.scenario.yaml"))
    return root


def errors_of(root: Path) -> list[ModelError]:
    return validate_package(load_package(root, validate=False))


def planted(tmp_path: Path, old: str, new: str) -> tuple[Path, str, list[ModelError]]:
    root = copy_rover(tmp_path)
    text = plant(root, "system.yaml", old, new)
    return root, text, errors_of(root)


@pytest.mark.system
def test_the_rover_package_validates() -> None:
    assert errors_of(ROVER) == []
    out = run_rra("validate", str(ROVER))
    assert out.returncode == 0, out.stdout + out.stderr


# ---- rra validate resolves implementations ---------------------------------------------------
@pytest.mark.system
def test_a_typo_in_a_generic_node_class_is_a_located_error(tmp_path: Path) -> None:
    old = "implementation: rra_agent.nodes.generic.Relay\n    parameters:"
    new = "implementation: rra_agent.nodes.generic.Tickr\n    parameters:"
    root, text, errors = planted(tmp_path, old, new)
    (err,) = errors
    assert err.location == Location(
        str(root / "system.yaml"), *position(text, "rra_agent.nodes.generic.Tickr")
    )
    assert "unknown node class 'Tickr' in 'rra_agent.nodes.generic'" in err.message
    assert "did you mean 'Ticker'" in err.message
    out = run_rra("validate", str(root))
    line, col = position(text, "rra_agent.nodes.generic.Tickr")
    assert out.returncode == 1
    assert out.stdout.startswith(f"{root / 'system.yaml'}:{line}:{col}: unknown node class")


@pytest.mark.parametrize(
    ("new", "fragment"),
    [
        ("rover_nodes.GnssReciever", "unknown node class 'GnssReciever' in 'rover_nodes'"),
        ("rover_node.GnssReceiver", "no module named 'rover_node'"),
        (
            "rover_functions.speed",
            "'rover_functions.speed' is not a subclass of rra_agent.node.Node",
        ),
        ("rover_nodes", "is not a dotted Python path"),
    ],
)
def test_package_folder_implementations_are_resolved(
    tmp_path: Path, new: str, fragment: str
) -> None:
    root, text, errors = planted(tmp_path, "rover_nodes.GnssReceiver", new)
    (err,) = errors
    assert fragment in err.message
    assert err.location == Location(str(root / "system.yaml"), *position(text, new))


def test_an_import_error_inside_a_node_module_is_located_with_its_message(tmp_path: Path) -> None:
    root = copy_rover(tmp_path)
    (root / "rover_nodes.py").write_text("import rover_driver_sdk_xyz  # not installed\n")
    text = (root / "system.yaml").read_text()
    (err,) = errors_of(root)
    assert err.location == Location(str(root / "system.yaml"), *position(text, "rover_nodes.Gnss"))
    assert err.message == ("importing 'rover_nodes' failed: No module named 'rover_driver_sdk_xyz'")


def test_a_package_module_hidden_by_the_standard_library_is_reported(tmp_path: Path) -> None:
    """A package's ``platform.py`` would be the standard library's ``platform`` in the node
    process: said at validate time, not found out as a FATAL node."""
    root = copy_rover(tmp_path)
    (root / "rover_nodes.py").rename(root / "platform.py")
    text = plant(root, "system.yaml", "rover_nodes.GnssReceiver", "platform.GnssReceiver")
    (err,) = errors_of(root)
    assert err.location == Location(str(root / "system.yaml"), *position(text, "platform.Gnss"))
    assert err.message.startswith("module 'platform' of the package folder (platform.py) is hidden")
    assert "rename the package's module" in err.message


def test_external_commands_must_exist(tmp_path: Path) -> None:
    root = copy_rover(tmp_path)
    tool = root / "bin" / "visual_odometry"
    tool.parent.mkdir()
    tool.write_text("#!/bin/sh\nexit 0\n")
    plain = root / "bin" / "not_executable"
    plain.write_text("data\n")
    text = (root / "system.yaml").read_text()
    impls = {
        "gnss_localizer": "{command: [rover-gnss-localizer-xyz, --fast]}",
        "visual_localizer": f"{{command: [{tool}]}}",  # not executable yet
        "drive": f"{{command: [./bin/not_executable], cwd: {root}}}",
    }
    for name, impl in impls.items():
        head = f"  - name: {name}\n    implementation: rra_agent.nodes.generic.Relay"
        text = text.replace(head, f"  - name: {name}\n    implementation: {impl}")
    (root / "system.yaml").write_text(text)
    errors = errors_of(root)
    assert [e.message for e in errors] == [
        "program 'rover-gnss-localizer-xyz' of the external command is not on PATH",
        f"program '{tool}' of the external command is not an executable file",
        "program './bin/not_executable' of the external command is not an executable file",
    ]
    assert errors[0].location == Location(
        str(root / "system.yaml"), *position(text, "rover-gnss-localizer-xyz")
    )
    tool.chmod(0o755)
    plain.unlink()
    remaining = errors_of(root)
    assert [e.message for e in remaining[1:]] == [
        "program './bin/not_executable' of the external command does not exist"
        f" ({root}/bin/not_executable)"
    ]
    assert len(remaining) == 2  # python3 on PATH and the executable file pass


def test_running_a_package_does_not_import_its_node_classes(tmp_path: Path) -> None:
    """``rra up``/``rra agent`` load the package without importing every node class (another
    host's may need libraries this one has not): only ``rra validate`` resolves them."""
    root = copy_rover(tmp_path)
    plant(root, "system.yaml", "rover_nodes.GnssReceiver", "rover_nodes.Missing")
    load_package(root)  # validates everything else
    assert "rover_nodes" not in sys.modules
    assert any("Missing" in e.message for e in errors_of(root))


# ---- the import path of a node process -------------------------------------------------------
def test_the_package_folder_comes_after_the_standard_library(tmp_path: Path, monkeypatch) -> None:
    root = copy_rover(tmp_path)
    (root / "json.py").write_text("raise RuntimeError('the package json must not be imported')\n")
    (root / "platform.py").write_text((ROVER / "rover_nodes.py").read_text())
    monkeypatch.setattr(sys, "path", list(sys.path))
    cls = load_node_class("rover_nodes.GnssReceiver", [str(root)])
    assert cls.__module__ == "rover_nodes" and sys.path[-1] == str(root.resolve())
    import json  # the standard library's, still

    assert json.dumps([1]) == "[1]"
    with pytest.raises(NodeError, match=r"module 'platform' of the package folder .* is hidden"):
        load_node_class("platform.GnssReceiver", [str(root)])
    sys.modules.pop("rover_nodes", None)


@pytest.mark.system
def test_the_fork_server_preloads_and_warms_up_package_node_classes(tmp_path: Path) -> None:
    """The zygote has the package folder on its import path: a package's node class is
    imported and warmed up once there, and the forked node inherits it."""
    root = tmp_path / "pkg"
    root.mkdir()
    (root / "warm_nodes.py").write_text(
        "import os\n"
        "from rra_agent.node import Node\n\n"
        "class Warm(Node):\n"
        "    warmed_in = None\n\n"
        "    @classmethod\n"
        "    def warm_up(cls):\n"
        "        cls.warmed_in = os.getpid()\n\n"
        "    def on_start(self):\n"
        "        print(f'warmed in {self.warmed_in}, running in {os.getpid()}', flush=True)\n"
    )
    bus = BusConfig(connect=[f"tcp/127.0.0.1:{free_port()}"])
    hub = open_session(bus.host_router(hub=True))
    host = LocalHost("h", bus, tmp_path / "logs", preload=[str(root), "warm_nodes.Warm"])
    spec = NodeSpec(
        system="warm", name="w", host="h", implementation="warm_nodes.Warm",
        ports={"out": PortSpec(direction="publish", type="X", keys=["rra/warm/data/w"])},
        path=[str(root)],
    )  # fmt: skip
    try:
        pid = host.spawn(spec)
        log = tmp_path / "logs" / "w.log"
        wait_until(lambda: log.exists() and "warmed in" in log.read_text(), 20, "the node's start")
        line = next(x for x in log.read_text().splitlines() if "warmed in" in x)
        assert host.zygote is not None
        assert line == f"warmed in {host.zygote.pid}, running in {pid}"
    finally:
        host.kill_all()
        hub.close()


# ---- rra up of the package --------------------------------------------------------------------
@pytest.mark.system
def test_rra_up_runs_the_package_s_own_node_class(tmp_path: Path) -> None:
    """The GNSS receiver of the package folder reaches RUNNING and its fixes flow through the
    localizer to the drive; the package's measurement function computes Speed."""
    out = subprocess.run(
        [sys.executable, "-m", "rra_agent", "test", str(ROVER / "drive.scenario.yaml"),
         "--out", str(tmp_path / "runs")],
        capture_output=True, text=True, timeout=240, check=False,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    assert out.returncode == 0, out.stdout + out.stderr
    assert "1 passed, 0 failed" in out.stderr
    assert "drive     node gnss_receiver RUNNING within 1 s" in out.stdout


# ---- the generic nodes' documented ports ------------------------------------------------------
def test_the_generic_nodes_ports_are_documented_as_they_are_used() -> None:
    """Each row of docs/models.md's table of generic nodes names a Node class and exactly the
    ports it publishes on and reads (checked by running it in a NodeHarness)."""
    import re

    from rra_agent.node import NodeHarness

    text = (ROOT / "docs" / "models.md").read_text()
    section = text.split("### Generic nodes", 1)[1].split("\n## ", 1)[0]
    rows = re.findall(r"^\| `(rra_agent\.nodes\.generic\.\w+)` \| ([^|]+) \|", section, re.M)
    assert {r[0].rsplit(".", 1)[1] for r in rows} == {"Ticker", "Relay", "Echo"}
    for impl, ports in rows:
        documented = dict(re.findall(r"`(\w+)` \((publish|subscribe)\)", ports))
        ports = {p: (d, "Sample") for p, d in documented.items()}
        h = NodeHarness(load_node_class(impl), ports=ports, params={"rate_hz": 100.0})
        if "in" in documented:
            h.send("in", {"value": 1.0, "seq": 1})
        else:
            h.step(0.01)
        published = {port for port, _ in h.iter_published()}
        assert published == {p for p, d in documented.items() if d == "publish"}, impl
