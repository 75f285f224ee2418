"""Reflexes in real processes (`rra up` of tests/data/reflex_system): the plant publishes its
level and is commanded by ``main``; a level below 0 selects ``Backup``, a hot standby, so the
switch is one rewire of the plant's command input, which the plant makes itself as a reflex.

- a reflex fires and the engines confirm it (an event with both times), the plant commanded
  by ``backup``;
- no reflex where a higher-priority rule could overturn the decision; the engines switch;
- a reflex is withdrawn when an operator forces a feature, and armed again when released;
- a reflex the engines do not confirm (the Adaptation Engine frozen) is rolled back;
- a node whose measurement function raises keeps running and the engines make the switch;
- a reflex survives a Resolution Engine failover and switches once.

Deadlines, not sleeps (the one sleep is the length of a fault: an engine frozen).
"""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path
from typing import Any

import msgspec
import pytest
import zenoh
from conftest import System, edit_yaml

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, set_params, wait_until
from rra_agent.bus.keys import Keys
from rra_agent.cli.status import render

pytestmark = pytest.mark.system

PKG = Path(__file__).parent / "data" / "reflex_system"
K = Keys("reflex_system")
MAIN = K.data("main/out")
BACKUP = K.data("backup/out")
_EVT = m.Codec[m.EventMessage](m.EventMessage)


class Events:
    """The adaptation events this test's session sees."""

    def __init__(self, client: BusClient) -> None:
        self.lock = threading.Lock()
        self.items: list[m.AdaptationEvent] = []
        self.sub = client.session.declare_subscriber(K.events, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        try:
            msg = _EVT.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            return  # junk (--hostile) is no event
        if isinstance(msg, m.AdaptationEvent):
            with self.lock:
                self.items.append(msg)

    def of(self, kind: str, outcome: str | None = None) -> list[m.AdaptationEvent]:
        with self.lock:
            return [e for e in self.items
                    if e.kind == kind and (outcome is None or e.outcome == outcome)]  # fmt: skip

    def applied(self, feature: str) -> list[m.AdaptationEvent]:
        return [e for e in self.of("adaptation", "ok") if f"'{feature}'" in e.message]


class Seen:
    """The Level measurements and selections this test's session sees."""

    def __init__(self, client: BusClient) -> None:
        self.level: list[m.Measurement] = []
        self.selections: list[m.Selection] = []
        ctx, sel = m.Codec[m.CtxMessage](m.CtxMessage), m.Codec[m.SelectionMessage](
            m.SelectionMessage
        )
        self.subs = [
            client.session.declare_subscriber(K.ctx("Level"), lambda s: self._add(ctx, s)),
            client.session.declare_subscriber(K.selection, lambda s: self._add(sel, s)),
        ]

    def _add(self, codec: Any, sample: zenoh.Sample) -> None:
        try:
            msg = codec.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        # Only the engines' own: --hostile forges selections (fenced by no live leader).
        if isinstance(msg, m.Measurement) and "plant.out" in msg.sources:
            self.level.append(msg)
        elif isinstance(msg, m.Selection) and msg.fence and msg.fence.leader.startswith("adapt"):
            self.selections.append(msg)

    def decided_after_negative_level(self) -> m.Selection | None:
        first = next((x.stamp for x in list(self.level) if float(x.value) < 0), None)
        if first is None:
            return None
        return next((s for s in list(self.selections) if s.stamp > first), None)

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()


def start(system, package: Path = PKG, *extra: str) -> System:
    return system(package, *extra, name="reflex_system", ready="plant")


def copy(tmp_path: Path) -> Path:
    import shutil

    pkg = tmp_path / "pkg"
    shutil.copytree(PKG, pkg, ignore=shutil.ignore_patterns("__pycache__"))
    return pkg


def reflexes(st: dict) -> dict[str, Any]:
    return (st.get("engine") or {}).get("reflexes") or {}


def installed(sys_: System) -> dict:
    """Wait until the engines report a reflex installed; its record."""
    st = sys_.wait(lambda s: reflexes(s).get("installed"), "a reflex installed")
    [record] = reflexes(st)["installed"]
    return record


def plant(sys_: System) -> dict:
    reply = sys_.ctl("plant", m.Describe())
    assert isinstance(reply, m.Ok), reply
    return {"reflexes": {}, **reply.result}  # an empty map is left out on the wire


def cmd_keys(sys_: System) -> list[str]:
    return next(p["keys"] for p in plant(sys_)["ports"] if p["name"] == "cmd")


def counters(sys_: System, node: str) -> dict[str, int]:
    reply = sys_.ctl(node, m.Stats())
    assert isinstance(reply, m.Ok), reply
    return reply.result["counters"]


def commanded_by(sys_: System) -> dict[str, int]:
    reply = sys_.ctl("plant", m.ExportState())
    assert isinstance(reply, m.Ok), reply
    return reply.result["by"]


def set_level(sys_: System, value: float) -> None:
    set_params(sys_.client, "plant", {"value": value})


def test_a_reflex_fires_and_the_engines_confirm_it(system) -> None:
    sys_ = start(system)
    events = Events(sys_.client)
    record = installed(sys_)
    assert (record["rule"], record["nodes"]) == ("Fallback", ["plant"])
    assert record["actions"]["plant"] == [{"kind": "rewire", "port": "cmd", "keys": [BACKUP]}]
    assert plant(sys_)["reflexes"] == {record["id"]: 0.0}
    assert cmd_keys(sys_) == [MAIN]
    shown = render(sys_.gather()).splitlines()
    assert "reflex      Fallback in plant: +Backup, -Main (armed)" in shown
    set_level(sys_, -1.0)
    [event] = wait_until(lambda: events.of("reflex"), 30, "the reflex reported")
    assert (event.outcome, event.node, event.context) == ("ok", "plant", {"Level": -1.0}), event
    assert "reflex Fallback fired in plant at" in event.message
    assert "the engines decided +Backup, -Main and confirmed it at" in event.message
    assert 0 < event.durations["confirm"] < 5.0
    wait_until(lambda: events.applied("Backup"), 30, "the engines' plan for Backup")
    assert cmd_keys(sys_) == [BACKUP]
    wait_until(lambda: commanded_by(sys_).get("backup"), 10, "backup's commands reach the plant")
    assert counters(sys_, "plant")["reflexes_fired"] == 1
    # The engines' plan found the switch made; the spent reflex is withdrawn (the rule
    # changes nothing in the new configuration: no reflex for it).
    sys_.wait(lambda s: not reflexes(s).get("installed"), "the reflex withdrawn")
    wait_until(lambda: plant(sys_)["reflexes"] == {}, 10, "the plant's reflex withdrawn")
    assert events.of("reflex", "rolled_back") == []


def test_no_reflex_where_a_higher_priority_rule_could_overturn_it(system, tmp_path) -> None:
    pkg = copy(tmp_path)
    (pkg / "adaptation.rra").write_text(
        "import reflex.contextDepMeasModel as cdm\n"
        "ruleSet Mode:\n"
        "    rule Fallback priority 2: if (cdm.Level < 0) activate_feature(Backup)\n"
        "    rule Hold priority 1: if (cdm.Level < -50) activate_feature(Main)\n"
    )
    sys_ = start(system, pkg)
    events = Events(sys_.client)
    st = sys_.wait(lambda s: "Fallback" in reflexes(s).get("not_installed", {}), "the reasons")
    assert reflexes(st)["installed"] == []
    assert reflexes(st)["not_installed"]["Fallback"] == (
        "rule Mode.Hold may overturn it (activate_feature(Main))"
    )
    assert plant(sys_)["reflexes"] == {}
    set_level(sys_, -1.0)
    wait_until(lambda: events.applied("Backup"), 30, "the engines switch to Backup")
    assert cmd_keys(sys_) == [BACKUP]
    assert events.of("reflex") == []
    assert counters(sys_, "plant").get("reflexes_fired", 0) == 0


def test_a_reflex_is_withdrawn_when_an_operator_forces_a_feature(system) -> None:
    sys_ = start(system)
    events = Events(sys_.client)
    record = installed(sys_)
    force = sys_.client.request(
        K.engine_ctl("adaptation"), m.ForceFeatures(features={"Main": "on"}, operator="t")
    )
    assert isinstance(force, m.Ok), force
    wait_until(lambda: plant(sys_)["reflexes"] == {}, 30, "the reflex withdrawn from the plant")
    st = sys_.wait(lambda s: not reflexes(s).get("installed"), "no reflex installed")
    assert "Fallback" in reflexes(st)["not_installed"]
    seen = Seen(sys_.client)
    set_level(sys_, -1.0)
    try:  # a selection decided after the Adaptation Engine had Level -1: still Main
        later = wait_until(seen.decided_after_negative_level, 30, "a selection after Level -1")
    finally:
        seen.close()
    assert "Main" in later.features
    assert cmd_keys(sys_) == [MAIN] and events.of("reflex") == []
    # Released: armed again; the level does not change, so it does not fire (the rule runs on
    # the monitor's next publication of Level), and the engines switch.
    release = sys_.client.request(
        K.engine_ctl("adaptation"), m.ForceFeatures(features={"Main": "auto"}, operator="t")
    )
    assert isinstance(release, m.Ok), release
    wait_until(lambda: events.applied("Backup"), 30, "the engines switch to Backup")
    assert events.of("reflex") == [] and record["rule"] == "Fallback"


def test_an_unconfirmed_reflex_is_rolled_back(system) -> None:
    sys_ = start(system)
    events = Events(sys_.client)
    installed(sys_)
    st = sys_.gather()
    frozen = [sys_.node(st, f"adaptation-{r}")["pid"] for r in "ab"]
    for pid in frozen:  # the Adaptation Engine decides nothing meanwhile: no confirmation
        os.kill(pid, signal.SIGSTOP)
    try:
        set_level(sys_, -1.0)
        [event] = wait_until(lambda: events.of("reflex"), 30, "the reflex reported")
        assert event.outcome == "rolled_back"
        assert "not confirmed (not confirmed within 1000 ms): rolled back" in event.message
        assert cmd_keys(sys_) == [MAIN]  # back to what the engines gave it
    finally:
        for pid in frozen:
            os.kill(pid, signal.SIGCONT)
    # The engines decide Backup once the Adaptation Engine is back; the reflex, rolled back
    # in this configuration, is not armed again: it fired once.
    wait_until(lambda: events.applied("Backup"), 30, "the engines switch to Backup")
    assert cmd_keys(sys_) == [BACKUP]
    assert counters(sys_, "plant")["reflexes_fired"] == 1
    assert len(events.of("reflex")) == 1


def test_a_node_that_cannot_evaluate_its_reflex_goes_on_and_the_engines_switch(
    system, tmp_path
) -> None:
    pkg = copy(tmp_path)
    edit_yaml(pkg / "measurements.yaml", lambda d: d["measurements"][0].update(
        function="reflex_functions.level_but_not_in_the_plant"))  # fmt: skip
    sys_ = start(system, pkg)
    events = Events(sys_.client)
    installed(sys_)  # it installs: the function imports; it raises on every sample
    pid = plant(sys_)["pid"]
    set_level(sys_, -1.0)
    wait_until(lambda: events.applied("Backup"), 30, "the engines switch to Backup")
    assert cmd_keys(sys_) == [BACKUP]
    assert events.of("reflex") == []
    stats = counters(sys_, "plant")
    assert stats["reflex_errors"] > 0 and stats.get("reflexes_fired", 0) == 0
    node = sys_.node(sys_.gather(), "plant")
    assert (node["pid"], node.get("restarts", 0), node["state"]) == (pid, 0, "RUNNING")


def test_a_reflex_survives_a_resolution_engine_failover(system) -> None:
    sys_ = start(system)
    events = Events(sys_.client)
    record = installed(sys_)
    st = sys_.gather()
    old = sys_.leader(st)
    os.kill(sys_.node(st, old)["pid"], signal.SIGKILL)
    st = sys_.wait(lambda s: sys_.leader(s) not in ("", old), "a new Resolution Engine leader")
    new = sys_.leader(st)
    # The new leader knows the reflex its predecessor installed: the same one, not again.
    assert [r["id"] for r in reflexes(st)["installed"]] == [record["id"]]
    assert plant(sys_)["reflexes"] == {record["id"]: 0.0}
    set_level(sys_, -1.0)
    [event] = wait_until(lambda: events.of("reflex"), 30, "the reflex reported")
    assert (event.outcome, event.source) == ("ok", new)
    wait_until(lambda: events.applied("Backup"), 30, "the new leader's plan for Backup")
    assert cmd_keys(sys_) == [BACKUP]
    assert counters(sys_, "plant")["reflexes_fired"] == 1
    assert len(events.of("reflex")) == 1 and len(events.applied("Backup")) == 1
