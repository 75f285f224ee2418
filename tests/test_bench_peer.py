"""tools/bench_peer.py compares like with like: both sides send the same 93 bytes, and the
rra-agent packages and dora dataflows it writes are the graphs its report names (the
packages load and validate). In process: nothing is started here."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path

import msgspec
import pytest
import yaml

from rra_agent.deployment import deploy

TOOLS = Path(__file__).resolve().parents[1] / "tools"
sys.path.insert(0, str(TOOLS))
try:
    import bench_peer
    import peer_dora
    import peer_nodes
finally:
    sys.path.remove(str(TOOLS))


@pytest.mark.parametrize("seq", [0, 1, 99, 100, 127, 12345])
def test_both_sides_send_the_same_93_bytes(seq: int) -> None:
    rra = msgspec.msgpack.encode(peer_nodes.payload(seq))
    assert rra == peer_dora.payload(seq)
    assert len(rra) == 93


@pytest.mark.parametrize(("figure", "nodes"), [("roundtrip", 2), ("restart", 2), ("chain", 10)])
def test_the_packages_and_dataflows_are_the_same_graphs(tmp_path, figure: str, nodes: int):
    out = tmp_path / "out.txt"
    pkg = bench_peer.rra_package(tmp_path, figure, out, 100, 10)
    dep = deploy(pkg)
    components = dep.package.system.components
    assert len(components) == nodes
    flow = yaml.safe_load(bench_peer.dora_dataflow(tmp_path, figure, out, 100, 10).read_text())
    assert len(flow["nodes"]) == nodes
    if figure == "restart":  # dora restarts at once, as rra-agent does after a first crash
        source = flow["nodes"][0]
        assert source["restart_policy"] == "always" and source["restart_delay"] == 0
    if figure == "chain":  # a chain: each node reads the one before it
        pairs = itertools.pairwise(flow["nodes"])
        assert all(b["inputs"]["in"] == f"{a['id']}/out" for a, b in pairs)
