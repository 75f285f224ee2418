"""What a host agent derives from its own model for a request (rra_agent.host.catalog)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import msgspec
import pytest

from rra_agent.bus import messages as m
from rra_agent.deployment import _prepared, deploy, prepare
from rra_agent.host.catalog import Catalog, Refused
from rra_agent.models.system import Command, Supervision

PACKAGE = Path(__file__).parent / "data" / "hosttest"


@pytest.fixture(scope="module")
def catalog() -> Catalog:
    dep = deploy(PACKAGE)
    c = Catalog(dep.configured, "h1", package_root=PACKAGE)
    engine = Command(command=["python3", "-m", "x"])
    c.add_builtins(
        [m.NodeSpec(system="hosttest", name="resolution-a", host="h1", implementation=engine)]
    )
    return c


def request(name: str = "relay", **kw) -> m.NodeSpec:
    kw.setdefault("implementation", "rra_agent.nodes.generic.Relay")
    return m.NodeSpec(system="hosttest", name=name, host="h1", **kw)


def test_everything_but_the_choice_comes_from_the_model(catalog):
    asked = request(
        params={"offset": 2.0},
        path=["/tmp/evil"],  # an import path would let a request load any module
        decl={"offset": m.ParamDecl(type="float", min=-1e9, max=1e9)},
        supervision=Supervision(restart="never", heartbeat_timeout=0.0),
    )
    spec = catalog.admit(asked)
    assert spec.path == [str(PACKAGE.resolve())]
    assert spec.decl["offset"] == m.ParamDecl(type="float", min=-10.0, max=10.0)
    assert spec.supervision == Supervision(heartbeat_timeout=1.0, probe_timeout=0.5)
    assert spec.params == {"offset": 2.0}
    assert m.spec_digest(spec) == m.spec_digest(msgspec.structs.replace(spec, path=["/else"]))


@pytest.mark.parametrize(
    ("spec", "why"),
    [
        (request("resolution-a"), "started by this host agent only"),
        (request("tool"), "not one the model declares"),
        (request("relay", implementation=Command(command=["id"])), "not one the model declares"),
        (request("elsewhere"), "no component 'elsewhere' is placed on host h1"),
        (request(".hidden"), "may not start with '.'"),
        (request("a/b"), "cannot be used in a key expression"),
        (request(params={"offset": 11.0}), "offset"),
        (request(params={"offset": "x"}), "offset"),
    ],
)
def test_refusals_say_which_rule(catalog, spec, why):
    with pytest.raises(Refused, match=why):
        catalog.admit(spec)


def test_the_builtins_run_by_this_interpreter_are_forked(catalog):
    """The fork server forks the host agent's own ``python -m`` processes of this
    interpreter (``rra up``'s engines); another interpreter's command is exec'd."""
    assert catalog.forked == []  # ``python3 -m x`` is not this interpreter
    mine = [sys.executable, "-m", "rra_agent.engines.monitor", "--package", str(PACKAGE)]
    c = Catalog(deploy(PACKAGE).configured, "h1", package_root=PACKAGE)
    c.add_builtins(
        m.NodeSpec(system="hosttest", name=n, host="h1", implementation=Command(command=mine))
        for n in ("monitor-a", "monitor-b")
    )
    assert c.forked == [mine]


def test_a_prepared_deployment_is_shared_until_a_file_of_the_package_changes(tmp_path):
    """`prepare` keeps what it deployed: `deploy` of the same package and selection returns
    that very object (what the engines forked by the fork server share) until a file of
    the package changes."""
    pkg = tmp_path / "pkg"
    shutil.copytree(PACKAGE, pkg)
    prepared = prepare(pkg)
    try:
        assert deploy(pkg) is prepared
        assert deploy(pkg / "rra.yaml") is prepared  # the same package, by its manifest
        assert deploy(pkg, ["Base"]) is not prepared  # another selection: not that one
        system = pkg / "system.yaml"
        system.write_text(system.read_text() + "\n# changed\n")
        fresh = deploy(pkg)
        assert fresh is not prepared and fresh.configured == prepared.configured
    finally:
        _prepared.clear()
