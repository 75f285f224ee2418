"""Attacks from the bus on a running system (``rra up`` on loopback, no TLS): the host agent
runs only what the model declares, whatever the request says, and discloses no command line.
(With certificates, the access control of tests/test_security.py refuses these callers before
they reach the host agent; these checks hold even without it.)"""

from __future__ import annotations

import msgspec
from conftest import RELAY

from rra_agent.bus import messages as m
from rra_agent.cli.up import engine_specs
from rra_agent.deployment import deploy
from rra_agent.models.system import Command


def test_an_engine_command_line_with_injected_variables_runs_nothing(system, tmp_path):
    sys_ = system()
    listed = sys_.client.host("local", m.ListNodes())
    assert isinstance(listed, m.Ok)
    text = msgspec.json.encode(listed.result).decode()
    assert "rra_agent.engines" not in text and "--package" not in text  # nothing to copy
    # The attacker knows the engine's command line anyway (it is open source).
    engine = engine_specs(deploy(RELAY), [], tmp_path, "local", True)[0]
    marker = tmp_path / "pwned"
    payload = f"import os;os.system('id > {marker}')"
    evil = msgspec.structs.replace(
        engine.implementation,  # type: ignore[arg-type]
        env={"PYTHONWARNINGS": f"ignore::0:{payload}:0", "BROWSER": f"sh -c 'id > {marker}'"},
    )
    attacks = [
        m.StartNode(spec=msgspec.structs.replace(engine, implementation=evil)),
        m.StartNode(spec=msgspec.structs.replace(engine, name="resolution-z")),
        m.StartNode(spec=msgspec.structs.replace(engine, name="sink", implementation=evil)),
        m.StartNode(spec=msgspec.structs.replace(
            engine, name="sink", implementation=Command(command=["sh", "-c", f"id > {marker}"]))),
        m.UpdateSpec(specs=[msgspec.structs.replace(engine, implementation=evil)]),
    ]  # fmt: skip
    for attack in attacks:
        reply = sys_.client.host("local", attack)
        assert isinstance(reply, m.Err) and reply.code == "denied", reply
    stats = sys_.client.host("local", m.Stats())
    assert isinstance(stats, m.Ok) and stats.result["rejected"] >= len(attacks)
    assert not marker.exists()
    st = sys_.gather()
    assert {n["node"] for n in st["nodes"]} >= {"sink", "source"}
    assert "resolution-z" not in {n["node"] for n in st["nodes"]}
    assert "refused (denied)" in sys_.procs.log("up")
