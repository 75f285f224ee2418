"""Operators' overrides (``rra select``) and run-time conflicts end to end: `rra up` of
tests/data/relay_system with real engine and node processes (issue 11, deliverable 3).

Level above 5 makes PathRule select Filtered (swap ``direct`` -> ``filtered``), else Direct.
"""

from __future__ import annotations

import signal
import threading

import pytest
from conftest import RELAY_KEYS as K
from conftest import package_copy, run_rra

from rra_agent.bus import messages as m
from rra_agent.bus.client import NoReply, wait_until
from rra_agent.bus.config import free_port

SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)


def select(sys_, *choices: str):
    return run_rra("select", "--system", "relay_system", "--connect", sys_.connect, *choices)


def adaptation_status(sys_, name: str = "adaptation") -> dict | None:
    try:
        reply = sys_.client.request(K.engine_ctl(name), m.Status(), 1.0)
    except NoReply:
        return None
    return reply.result if isinstance(reply, m.Ok) and reply.result else None


def test_an_operator_forces_a_feature_the_rules_would_not_select_until_released(system, bus):
    sys_ = system()
    sys_.connect = bus.connect[0]
    assert "direct" in sys_.status["engine"]["running"]  # Level 0: the rules want Direct

    out = select(sys_, "Filtered=on")
    assert out.returncode == 0, out.stderr
    assert "Filtered = on" in out.stdout
    st = sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the forced swap to Filtered")
    assert st["engine"]["forced"] == {"Filtered": "on"}
    override = wait_until(
        lambda: [e for e in sys_.events() if getattr(e, "kind", "") == "override"],
        10,
        "the override event in events.jsonl",
    )
    assert "forced Filtered on" in override[0].message and "@" in override[0].message
    listed = select(sys_)
    assert listed.returncode == 0 and listed.stdout.strip() == "Filtered = on"
    status = run_rra("status", "--system", "relay_system", "--connect", sys_.connect)
    assert "forced      Filtered on" in status.stdout, status.stdout

    # The context changes so that the rule wants Direct: Filtered stays.
    sys_.set_level(2.0)
    sys_.wait(lambda s: s["engine"]["cv"].get("Gain") == 2.0, "Level 2 seen by the rules")
    st = sys_.gather()
    assert "Filtered" in st["engine"]["selection"] and "filtered" in st["engine"]["running"]

    # Both Adaptation Engine replicas die: the restarted ones resume with the override.
    for name in ("adaptation-a", "adaptation-b"):
        sys_.client.host("local", m.SignalNode(node=name, signal=signal.SIGKILL))
    wait_until(
        lambda: (adaptation_status(sys_) or {}).get("forced") == {"Filtered": "on"},
        30,
        "a restarted adaptation leader with the override",
    )
    sys_.set_level(1.0)
    sys_.wait(lambda s: s["engine"]["cv"].get("Gain") == 1.0, "Level 1 seen by the new leader")
    assert "Filtered" in sys_.gather()["engine"]["selection"]

    # Released: the rules take over again.
    out = select(sys_, "Filtered=auto")
    assert out.returncode == 0, out.stderr
    assert "no run-time feature is forced" in out.stdout
    st = sys_.wait(lambda s: "direct" in s["engine"]["running"], "the rules' Direct again")
    assert not st["engine"]["forced"]


def test_refused_overrides_are_one_line_errors(system, bus):
    sys_ = system()
    sys_.connect = bus.connect[0]
    for choice, text in (
        ("Relay=off", "Relay: not a run-time feature"),
        ("Nope=on", "Nope: no such feature"),
        ("Path=off", "cannot"),
    ):
        out = select(sys_, choice)
        assert out.returncode == 1 and text in out.stderr, (choice, out.stderr)
        assert len(out.stderr.strip().splitlines()) == 1 and "Traceback" not in out.stderr
    assert not sys_.gather()["engine"]["forced"]
    out = run_rra(
        "select", "--system", "no_such_system", "--connect", sys_.connect, "--timeout", "1", "A=on"
    )
    assert out.returncode == 1 and "no rra system 'no_such_system' answers" in out.stderr
    assert len(out.stderr.strip().splitlines()) == 1
    # The one system at the endpoint is found without --system.
    out = run_rra("select", "--connect", sys_.connect)
    assert out.returncode == 0 and "no run-time feature is forced" in out.stdout, out.stderr


@pytest.mark.system
def test_no_bus_at_the_endpoint_is_one_line() -> None:
    out = run_rra("select", "--system", "relay_system", "--connect", f"tcp/127.0.0.1:{free_port()}")
    assert out.returncode == 1 and "Traceback" not in out.stderr
    (line,) = out.stderr.strip().splitlines()
    assert line.startswith("rra select: ") and "tcp/127.0.0.1:" in line


def test_a_run_time_conflict_is_reported_once_when_it_starts_and_once_when_it_ends(
    system, bus, tmp_path
):
    pkg = package_copy(tmp_path)
    rules = pkg / "adaptation.rra"
    rules.write_text(
        rules.read_text()
        + "\nrule Calm period 0 ms:\n    if (cdm.Level > 8)\n        activate_feature(Direct)\n"
    )
    sys_ = system(pkg)
    sys_.connect = bus.connect[0]
    reports: list[m.ConflictReport] = []
    lock = threading.Lock()

    def on_selection(sample) -> None:
        msg = SEL.decode(sample.payload.to_bytes())
        if isinstance(msg, m.ConflictReport):
            with lock:
                reports.append(msg)

    sub = sys_.client.session.declare_subscriber(K.selection, on_selection)
    try:
        sys_.set_level(9.0)  # PathRule wants Filtered, Calm (written later) Direct
        st = sys_.wait(lambda s: s["engine"]["conflicts"], "the conflict in rra status")
        (c,) = st["engine"]["conflicts"]
        assert c["rules"] == ["Calm", "PathRule"] and c["target"] == "the alternatives of Path"
        assert c["wants"] == {"Calm": "Direct", "PathRule": "Filtered"}
        assert c["context"] == {"Level": 9.0}
        status = run_rra("status", "--system", "relay_system", "--connect", sys_.connect)
        assert "conflict    the alternatives of Path: Calm wants Direct, PathRule wants " in (
            status.stdout
        )
        # Unchanged, it is not sent again (the selection heartbeat is 1 s, the tick 50 ms).
        sys_.set_level(9.5)
        sys_.wait(lambda s: s["engine"]["cv"].get("Gain") == 9.5, "Level 9.5 seen")
        wait_until(lambda: _count(reports, lock) >= 1, 5, "the report")
        sys_.set_level(3.0)  # both want Direct: the conflict ends
        sys_.wait(lambda s: not s["engine"]["conflicts"], "the conflict's end in rra status")
        wait_until(lambda: _count(reports, lock) >= 2, 5, "the end report")
    finally:
        sub.undeclare()
    with lock:
        states = [(r.state, r.id) for r in reports]
    assert states == [
        ("started", "alternative:the alternatives of Path:Calm|PathRule"),
        ("ended", "alternative:the alternatives of Path:Calm|PathRule"),
    ]
    assert reports[1].duration is not None and reports[1].duration > 0
    events = wait_until(lambda: _conflict_events(sys_, 2), 10, "both events in events.jsonl")
    start, end = events
    assert start.message.startswith("conflict started: rules Calm and PathRule")
    assert start.context == {"Level": 9.0} and [r.rule for r in start.cause] == ["Calm", "PathRule"]
    assert end.message.startswith("conflict ended after") and not end.durations
    log = (sys_.run_dir / "logs").glob("adaptation*.log")
    assert any("conflict started: rules Calm and PathRule" in p.read_text() for p in log)


def _conflict_events(sys_, n: int) -> list[m.AdaptationEvent] | None:
    found = [e for e in sys_.events() if isinstance(e, m.AdaptationEvent) and e.kind == "conflict"]
    return found if len(found) >= n else None


def _count(reports: list, lock: threading.Lock) -> int:
    with lock:
        return len(reports)
