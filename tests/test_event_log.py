"""The adaptation event log (`rra_agent.engines.events.EventSink`): what a new leader adds."""

from __future__ import annotations

from pathlib import Path

import pytest

from rra_agent.bus import messages as m
from rra_agent.engines import events
from rra_agent.engines.events import EventSink, read_events


def state(node: str, new: str, stamp: float) -> m.NodeState:
    return m.NodeState(stamp=stamp, node=node, host="local", state=new, previous="RUNNING")


def test_a_new_leader_logs_only_what_the_log_lacks(tmp_path: Path) -> None:
    log = tmp_path / "events.jsonl"
    old_leader = EventSink(None, "k", log)
    logged = [state("source", "STOPPING", 1.0), state("sink", "STOPPING", 2.0)]
    for ev in logged:
        old_leader.record(ev)
    old_leader.close()
    new_leader = EventSink(None, "k", log)
    crash = state("resolution-a", "BACKOFF", 3.0)
    written = new_leader.record_missing([*logged, crash, crash])
    new_leader.close()
    assert written == [crash]
    assert read_events(log) == [*logged, crash]


def test_only_the_tail_of_the_log_is_read_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    log = tmp_path / "events.jsonl"
    sink = EventSink(None, "k", log)
    first, last = state("a", "STOPPING", 1.0), state("b", "STOPPING", 2.0)
    sink.record(first)
    sink.record(last)
    # a tail that starts inside the first line: that torn line is not taken as logged
    monkeypatch.setattr(events, "TAIL", log.stat().st_size - 5)
    assert sink.record_missing([first, last]) == [first]
    sink.close()
