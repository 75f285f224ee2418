"""The Context Monitor's new leader publishes what it computed while no replica led.

The cause of the flaky ``max_velocity`` scenario ("BattLev == 80 within 1 s": the first value
came at 1.19 s, from the next 1 Hz battery sample): at start-up a source publishes before the
monitors' election ends; the replica computes the measurement but, not leading yet, does not
publish it, and the value reached the rules only with the source's next sample.
"""

from __future__ import annotations

import sys
from pathlib import Path
from types import SimpleNamespace

import msgspec
import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.deployment import deploy
from rra_agent.engines.monitor import ContextMonitorProcess

ROVER = Path(__file__).parent / "data" / "rover"


class Publisher:
    def __init__(self, sent: list[m.Measurement]) -> None:
        self.sent = sent

    def put(self, payload: bytes) -> None:
        self.sent.append(msgspec.msgpack.decode(payload, type=m.CtxMessage))


def test_a_measurement_computed_before_leading_is_published_on_taking_the_lead(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(sys, "path", list(sys.path))  # the monitor adds the package folder
    monkeypatch.setitem(sys.modules, "rover_functions", None)  # and imports its functions
    monkeypatch.delitem(sys.modules, "rover_functions")
    proc = ContextMonitorProcess(deploy(ROVER), BusConfig(), name="monitor-a")
    sent: list[m.Measurement] = []
    proc.publishers = {s.m.name: Publisher(sent) for s in proc.core.specs}  # type: ignore[misc]
    fix = {"seq": 1, "satellites": 7, "indoor": False, "speed": 0.5}
    # What the Zenoh callback keeps: the sample decoded (and checked) as a Fix.
    raw = msgspec.msgpack.encode(fix)
    proc._pending["gnss_receiver.fix"] = (proc.core.decode("gnss_receiver.fix", raw), 1.0, raw)
    proc._process()  # the receiver's first fix, while the election runs: computed, not sent
    assert sent == [] and set(proc.latest) == {"Satellites", "Indoor", "Speed"}
    proc.election = SimpleNamespace(leading=True)  # type: ignore[assignment]
    proc.on_leadership(True)
    assert {(s.name, s.value) for s in sent} == {
        ("Satellites", 7),
        ("Indoor", False),
        ("Speed", 0.5),
    }
    assert [s.stamp for s in sent] == [proc.latest[s.name].stamp for s in sent]  # as computed


def test_an_unchanged_measurement_is_sent_again_only_to_stay_fresh(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Changes go out at once; an unchanged value goes out again only after a quarter of
    its ``max_age_ms`` (or every second without one), so the rules never see it stale."""
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setitem(sys.modules, "rover_functions", None)
    monkeypatch.delitem(sys.modules, "rover_functions")
    proc = ContextMonitorProcess(deploy(ROVER), BusConfig(), name="monitor-a")
    proc.election = SimpleNamespace(leading=True)  # type: ignore[assignment]
    sent: list[m.Measurement] = []
    proc.publishers = {s.m.name: Publisher(sent) for s in proc.core.specs}  # type: ignore[misc]
    now = [1000.0]
    monkeypatch.setattr("rra_agent.engines.monitor.time.time", lambda: now[0])

    def fix(seq: int, satellites: int) -> list[tuple[str, object]]:
        sent.clear()
        sample = {"seq": seq, "satellites": satellites, "indoor": False, "speed": 0.5}
        raw = msgspec.msgpack.encode(sample)
        data = proc.core.decode("gnss_receiver.fix", raw)
        proc._pending["gnss_receiver.fix"] = (data, now[0], raw)
        proc._process()
        return [(s.name, s.value) for s in sent]

    assert len(fix(1, 7)) == 3  # first values
    now[0] += 0.01
    assert fix(2, 7) == []  # nothing changed, all fresh
    now[0] += 0.01
    assert fix(3, 8) == [("Satellites", 8)]  # a change, at once
    now[0] += max(proc.refresh.values())
    assert len(fix(4, 8)) == 3  # unchanged, but due again to stay fresh


def test_a_standby_resolution_engine_keeps_a_selection_without_waking_its_loop() -> None:
    """A standby replica only keeps the newest selection (it acts on it when it takes over);
    waking its main loop for each one competed with the leader's plan for the CPU."""
    from conftest import RELAY

    from rra_agent.engines.resolution import ResolutionEngineProcess

    proc = ResolutionEngineProcess(deploy(RELAY), BusConfig(), name="resolution-b")
    proc.election = SimpleNamespace(leading=False)  # type: ignore[assignment]
    sel = m.Selection(seq=1, stamp=1.0, deployment=[], features=["A"], cv={}, changed=True)
    sample = SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: msgspec.msgpack.encode(sel)))
    proc._on_selection(sample)  # type: ignore[arg-type]
    assert proc.latest == sel and proc.loop.inbox.empty()
    proc.election = SimpleNamespace(leading=True)  # type: ignore[assignment]
    proc._on_selection(sample)  # type: ignore[arg-type]
    assert proc.loop.inbox.qsize() == 1  # the leader acts on it


def test_the_leading_adaptation_engine_drops_other_selections_without_waking_its_loop() -> None:
    """The leader follows nobody: a selection fenced by another replica (a forged one, a
    deposed leader's) is dropped on the Zenoh thread. Posted, each one (a hostile client's
    forgeries, many a second) kept the next measurement from being evaluated inline. A
    standby still follows its leader's selections on its main loop."""
    from conftest import RELAY

    from rra_agent.engines.adaptation import AdaptationEngineProcess

    proc = AdaptationEngineProcess(deploy(RELAY), BusConfig(), name="adaptation-a")
    fence = m.Fence(epoch=9, leader="mallory")
    sel = m.Selection(seq=1, stamp=1.0, deployment=[], features=["A"], cv={}, fence=fence)
    sample = SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: msgspec.msgpack.encode(sel)))
    proc.election = SimpleNamespace(leading=True, instance="1f")  # type: ignore[assignment]
    proc._on_selection(sample)  # type: ignore[arg-type]
    assert proc.loop.inbox.empty()
    proc.election = SimpleNamespace(leading=False, instance="1f")  # type: ignore[assignment]
    proc._on_selection(sample)  # type: ignore[arg-type]
    assert proc.loop.inbox.qsize() == 1  # a standby checks it against its leader
