"""The distributed runtime end to end: `rra up` with real engine and node processes.

Uses tests/data/relay_system: a Ticker ``source`` whose value is the measurement Level; Level
above 5 selects Filtered (swap ``direct`` -> ``filtered``, rewire ``sink``), and the CV Gain
follows Level into ``sink.offset``. Loopback only, a free hub port per test, multicast off,
deadlines instead of sleeps; no process may outlive a test.
"""

from __future__ import annotations

import math
import signal

import pytest
from conftest import RELAY as DATA
from conftest import RELAY_KEYS as K
from conftest import edit_yaml, package_copy, pid_alive, tcp_peers

from rra_agent.bus import messages as m
from rra_agent.bus.client import wait_until
from rra_agent.bus.config import free_port


def test_measurement_change_swaps_rewires_and_sets_cv_parameter(system):
    sys_ = system()
    st = sys_.status
    assert set(st["engine"]["running"]) == {"source", "direct", "sink"}
    sink_pid = sys_.node(st, "sink")["pid"]

    sys_.set_level(7.0)
    st = sys_.wait(lambda s: "Filtered" in s["engine"]["selection"]
                   and "filtered" in s["engine"]["running"], "the swap to Filtered")  # fmt: skip
    assert "direct" not in st["engine"]["running"]
    assert sys_.node(st, "direct")["state"] == "STOPPED"
    assert st["engine"]["cv"]["Gain"] == pytest.approx(7.0)
    # The sink was rewired in place: same process, now listening to filtered's output ...
    assert sys_.node(st, "sink")["pid"] == sink_pid
    info = sys_.ctl("sink", m.Describe())
    assert isinstance(info, m.Ok)
    ports = {p["name"]: p["keys"] for p in info.result["ports"]}
    assert ports["in"] == [K.data("filtered/out")]
    # ... and the CV value reached its parameter.
    assert info.result["params"]["offset"] == pytest.approx(7.0)
    # What it now receives comes through `filtered` (offset 100 added there).
    out: list[dict] = []
    from rra_agent.bus.data import decode_data

    sub = sys_.client.session.declare_subscriber(
        K.data("sink/out"), lambda s: out.append(decode_data(s.payload.to_bytes()))
    )
    wait_until(lambda: any(o.get("relay") == "sink" and o.get("value", 0) >= 114 for o in out), 10,
               "samples through filtered")  # fmt: skip
    sub.undeclare()

    adaptations = [e for e in sys_.events() if isinstance(e, m.AdaptationEvent)
                   and e.kind == "adaptation" and e.outcome == "ok"]  # fmt: skip
    swap = next(e for e in adaptations if any("start filtered" in p for p in e.plan))
    assert any(c.rule == "PathRule" for c in swap.cause)
    assert {"plan", "execute"} <= set(swap.durations)


def test_a_stop_then_start_swap_kills_the_old_node_at_its_stop_deadline(system, tmp_path):
    """runtime.yaml ``stop_deadline: {direct: 0}``: the cold swap to ``filtered`` exports
    direct's state (with the sink's rewire, one batch), kills direct at once (no grace
    period: a stop, not a failure), then starts filtered; the sink's output goes through it."""
    pkg = package_copy(tmp_path)
    edit_yaml(pkg / "runtime.yaml",
              lambda d: d["replacement"].update(stop_deadline={"direct": 0}))  # fmt: skip
    sys_ = system(pkg)
    direct_pid = sys_.node(sys_.status, "direct")["pid"]
    st = swap_to_filtered(sys_)
    assert sys_.node(st, "direct")["state"] == "STOPPED" and not pid_alive(direct_pid)
    states = [e for e in sys_.events() if isinstance(e, m.NodeState) and e.node == "direct"]
    stopping = next(e for e in states if e.state == "STOPPING")
    stopped = next(e for e in states if e.state == "STOPPED")
    assert "deadline 0 ms" in stopping.reason and "status -9" in stopped.reason, states
    assert not any(e.state in ("BACKOFF", "FATAL") for e in states)
    swap = next(e for e in sys_.events() if isinstance(e, m.AdaptationEvent)
                and any("start filtered" in p for p in e.plan))  # fmt: skip
    plan = swap.plan
    assert plan.index(next(p for p in plan if p.startswith("export_state direct"))) < plan.index(
        next(p for p in plan if p.startswith("stop direct"))
    ), plan


def swap_to_filtered(sys_) -> dict:
    """Level 7 swaps ``filtered`` in; the status once the sink's output goes through it."""
    from rra_agent.bus.data import decode_data

    out: list[dict] = []
    sub = sys_.client.session.declare_subscriber(
        K.data("sink/out"), lambda s: out.append(decode_data(s.payload.to_bytes()))
    )
    try:
        sys_.set_level(7.0)
        st = sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the swap to filtered")
        wait_until(lambda: any(o["value"] >= 100 for o in ticks(out)), 10,
                   "samples through filtered")  # fmt: skip
    finally:
        sub.undeclare()
    return st


def test_crashed_node_restarts_with_its_current_wiring(system):
    sys_ = system()
    sys_.set_level(7.0)
    st = sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the swap")
    sink = sys_.node(st, "sink")
    assert sys_.client.host("local", m.SignalNode(node="sink", signal=signal.SIGKILL))
    st = sys_.wait(lambda s: sys_.node(s, "sink")["pid"] not in (None, sink["pid"])
                   and sys_.node(s, "sink")["state"] == "RUNNING", "sink restarted")  # fmt: skip
    assert sys_.node(st, "sink")["restarts"] == 1
    info = sys_.ctl("sink", m.Describe())
    ports = {p["name"]: p["keys"] for p in info.result["ports"]}
    assert ports["in"] == [K.data("filtered/out")]  # not the deployment-time wiring
    assert info.result["params"]["offset"] == pytest.approx(7.0)


def test_replacement_that_fails_to_start_is_rolled_back_alone(system, tmp_path):
    """Filtered's node cannot start: its swap is undone (Direct runs again), the Gain
    parameter of the same plan is applied, the event says partly applied and why, and the
    implementation becomes unavailable, so the Adaptation Engine decides Direct again."""
    pkg = package_copy(tmp_path)

    def break_filtered(data):
        comp = next(c for c in data["components"] if c["name"] == "filtered")
        comp["implementation"] = "rra_agent.nodes.generic.NoSuchNode"

    edit_yaml(pkg / "system.yaml", break_filtered)
    sys_ = system(pkg)
    direct_pid = sys_.node(sys_.status, "direct")["pid"]
    sys_.set_level(7.0)

    def event(outcome: str = "", kind: str = "") -> m.AdaptationEvent | None:
        return next((e for e in sys_.events() if isinstance(e, m.AdaptationEvent)
                     and (not outcome or e.outcome == outcome)
                     and (not kind or e.kind == kind)), None)  # fmt: skip

    sys_.wait(lambda s: event("partial") is not None, "the partly applied event")
    partial = event("partial")
    assert partial is not None and "filtered" in partial.message
    assert "Direct" in partial.message  # what is in effect
    sys_.wait(lambda s: event(kind="unavailable") is not None, "the unavailable event")
    unavailable = event(kind="unavailable")
    assert unavailable is not None and "filtered" in unavailable.message
    assert "Filtered" in unavailable.message
    st = sys_.wait(
        lambda s: sys_.node(s, "direct")["state"] == "RUNNING"
        and s["engine"]["selection"] == ["Direct", "Path", "Tuning"],
        "Direct decided again",
    )
    assert st["engine"]["effective"] == ["Direct", "Path", "Tuning"]
    assert "filtered" not in st["engine"]["running"]
    assert [u["component"] for u in st["engine"]["unavailable"]] == ["filtered"]
    assert sys_.node(st, "direct")["pid"] != direct_pid  # stop-then-start: it was restarted
    assert sys_.ctl("sink", m.Describe()).result["params"]["offset"] == 7.0  # Gain applied


def test_standby_replacement_is_prestarted_and_switched_by_activation(system, tmp_path):
    pkg = package_copy(tmp_path)
    edit_yaml(pkg / "runtime.yaml",
              lambda d: d["replacement"].update(components={"filtered": "standby"}))  # fmt: skip
    sys_ = system(pkg)
    st = sys_.status
    assert st["engine"]["standby"] == ["filtered"]
    filtered_pid = sys_.node(st, "filtered")["pid"]
    assert sys_.ctl("filtered", m.Describe()).result["active"] is False
    sys_.set_level(7.0)
    st = sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the standby switch")
    assert sys_.node(st, "filtered")["pid"] == filtered_pid  # no process was started
    assert sys_.ctl("filtered", m.Describe()).result["active"] is True
    swap = next(e for e in sys_.events() if isinstance(e, m.AdaptationEvent)
                and any("activate filtered" in p for p in e.plan))  # fmt: skip
    assert not any(p.startswith("start ") for p in swap.plan)


def ticks(out: list[dict]) -> list[dict]:
    """The sink's outputs of the source's ticks: a well-typed ``Sample`` with a finite value
    (a hostile client's forged samples, relayed as they are by the generic Relay nodes, are
    ill-typed or not finite: a typed consumer drops them)."""
    return [o for o in out if is_tick(o)]


def is_tick(o: dict) -> bool:
    seq, value = o.get("seq"), o.get("value")
    number = isinstance(value, int | float) and not isinstance(value, bool)
    return isinstance(seq, int) and not isinstance(seq, bool) and number and math.isfinite(value)


def tick_every_5_s(tmp_path, strategy: str):
    """The relay package with ``filtered`` swapped in by ``strategy`` and a source ticking
    every 5 s (Level never stale meanwhile): a sample is one tick, never the next one."""
    pkg = package_copy(tmp_path)
    edit_yaml(pkg / "runtime.yaml",
              lambda d: d["replacement"].update(components={"filtered": strategy}))  # fmt: skip
    edit_yaml(pkg / "system.yaml", lambda d: d["components"][0]["parameters"]["rate_hz"]
              .update(value=0.2))  # fmt: skip
    edit_yaml(pkg / "measurements.yaml",
              lambda d: d["measurements"][0].update(max_age_ms=60000))  # fmt: skip
    return pkg


def test_a_standby_replacement_s_first_output_reaches_its_rewired_consumer(system, tmp_path):
    """The sink is rewired before the standby is activated: the sample ``filtered``
    publishes the moment it is activated (its latest, as a standby controller publishes its
    latest command) reaches the sink. Rewired in the same batch as the activation, the sink
    was not yet subscribed and lost it: its first sample through ``filtered`` came with the
    next tick. A tick every 5 s makes the two cases unmistakable (the tick that carries
    Level 7 also triggers the switch)."""
    sys_ = system(tick_every_5_s(tmp_path, "standby"))
    first_output_through_filtered_is_the_trigger_tick_s(sys_)


def first_output_through_filtered_is_the_trigger_tick_s(sys_) -> None:
    """Level 7 is set; the sink's first output through ``filtered`` must carry the tick
    that carried Level 7 (and triggered the switch), not the next one, 5 s later."""
    from rra_agent.bus.data import decode_data

    out: list[dict] = []
    sub = sys_.client.session.declare_subscriber(
        K.data("sink/out"), lambda s: out.append(decode_data(s.payload.to_bytes()))
    )
    # What filtered itself published (a hostile client's forgeries on its key included), for
    # the failure's message: under --hostile the sample it held may have been a forgery.
    made: list[bytes] = []
    own = sys_.client.session.declare_subscriber(
        K.data("filtered/out"), lambda s: made.append(s.payload.to_bytes())
    )
    try:
        sys_.set_level(7.0)
        wait_until(lambda: any(o["value"] >= 100 for o in ticks(out)), 30,
                   "a sample through filtered")  # fmt: skip
        first = next(o for o in ticks(out) if o["value"] >= 100)
        trigger = [o for o in ticks(out) if 7 <= o["value"] < 100]
        seen = {"sink": out, "filtered": made}
        assert trigger, seen
        assert first["seq"] == trigger[-1]["seq"], seen  # that tick's, not the next one
    finally:
        own.undeclare()
        sub.undeclare()


def test_a_hot_standby_switch_is_one_rewire_that_delivers_its_held_output(system, tmp_path):
    """``filtered`` as a hot standby runs active from deployment, publishing on its own key,
    which the sink listens to without delivering. The switch starts no process and
    activates nothing: the sink's rewire delivers the output ``filtered`` made of the tick
    that carried Level 7 (held by the sink), not the next tick's (5 s later)."""
    sys_ = system(tick_every_5_s(tmp_path, "hot-standby"))
    st = sys_.status
    assert st["engine"]["standby"] == ["filtered"]
    filtered_pid = sys_.node(st, "filtered")["pid"]
    assert sys_.ctl("filtered", m.Describe()).result["active"] is True
    sink_in = next(p for p in sys_.ctl("sink", m.Describe()).result["ports"] if p["name"] == "in")
    assert sink_in["keys"] == [K.data("direct/out")]
    assert sink_in["standby"] == [K.data("filtered/out")]
    first_output_through_filtered_is_the_trigger_tick_s(sys_)
    st = sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the switch")
    assert sys_.node(st, "filtered")["pid"] == filtered_pid
    swap = next(e for e in sys_.events() if isinstance(e, m.AdaptationEvent)
                and any("rewire in of sink" in p for p in e.plan))  # fmt: skip
    assert not any(p.startswith(("start ", "activate ")) for p in swap.plan), swap.plan
    assert any(p.startswith("select filtered") for p in swap.plan), swap.plan
    for role in ("monitor", "adaptation"):  # Level 7 went through them without a hand-off
        stats = sys_.client.node(sys_.leader(st, role), m.Stats())
        assert isinstance(stats, m.Ok) and stats.result["counters"]["inline"] > 0, (role, stats)


def test_a_swap_inside_a_component_container(system, tmp_path):
    """direct, filtered (standby) and sink in one container: the Run-time Resolution Engine
    swaps and rewires them as it does processes; the switch is an activation inside the
    same process, and the sink's output goes through filtered."""
    pkg = package_copy(tmp_path)
    edit_yaml(pkg / "runtime.yaml",
              lambda d: d["replacement"].update(components={"filtered": "standby"}))  # fmt: skip

    def contain(d: dict) -> None:
        for c in d["components"]:
            if c["name"] in ("direct", "filtered", "sink"):
                c["container"] = "box"

    edit_yaml(pkg / "system.yaml", contain)
    sys_ = system(pkg)
    st = sys_.status
    box = {sys_.node(st, n)["pid"] for n in ("direct", "filtered", "sink")}
    assert len(box) == 1 and sys_.node(st, "source")["pid"] not in box
    st = swap_to_filtered(sys_)
    assert {sys_.node(st, n)["pid"] for n in ("filtered", "sink")} == box
    assert sys_.ctl("filtered", m.Describe()).result["active"] is True
    # the requests of the switch to components of the box went as batches to the container
    stats = sys_.ctl("box", m.Stats())
    assert isinstance(stats, m.Ok) and stats.result["counters"].get("batched", 0) >= 2, stats


def test_random_bytes_on_every_key_crash_nothing(system):
    sys_ = system()
    session = sys_.client.session
    junk = [b"", b"\x00", b"\xc1\xff", b"\x81\xa1t\xa3zzz", bytes(range(256)) * 4]
    keys = [K.data("source/out"), K.data("direct/out"), K.ctx("Level"), K.selection,
            K.events, K.inject("motor/2")]  # fmt: skip
    for key in keys:
        for payload in junk:
            session.put(key, payload)
    for key in [K.node_ctl("sink"), K.host_ctl("local"), K.engine_ctl("resolution")]:
        for payload in junk:
            list(session.get(key, payload=payload, timeout=2))
    # Everything is still alive and still adapts.
    sys_.set_level(8.0)
    sys_.wait(lambda s: "filtered" in s["engine"]["running"], "adaptation after junk")
    # Every process up (replicas still starting when the junk came included), none restarted.
    st = sys_.wait(lambda s: {n["state"] for n in s["nodes"]} <= {"RUNNING", "STOPPED"},
                   "every process running")  # fmt: skip
    assert all(n.get("restarts", 0) == 0 for n in st["nodes"])
    assert sys_.ctl("sink", m.Describe()).result["dropped"] >= 1
    assert sys_.proc.poll() is None


def test_ctrl_c_leaves_no_process_behind(system, procs):
    sys_ = system()
    st = sys_.gather()
    pids = [n["pid"] for n in st["nodes"] if n.get("pid")]
    assert len(pids) == 9  # three engines in two replicas each, three nodes
    assert sys_.stop() == 0
    from conftest import pid_alive

    assert not [p for p in pids if pid_alive(p)]


def test_rra_param_prints_and_sets_a_running_nodes_parameters(system, bus):
    import subprocess
    import sys

    sys_ = system()

    def rra_param(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "rra_agent", "param", "--system", "relay_system",
             "--connect", bus.connect[0], *args],
            capture_output=True, text=True, timeout=30,
        )  # fmt: skip

    shown = rra_param("source")
    assert shown.returncode == 0, shown.stderr
    assert "value = 1.0" in shown.stdout
    assert rra_param("source", "value=9").returncode == 0
    sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the swap after rra param")
    bad = rra_param("nosuch", "x=1")
    assert bad.returncode == 1 and "no node 'nosuch'" in bad.stderr
    assert "Traceback" not in bad.stderr
    bounded = rra_param("source", "rate_hz=x")
    assert bounded.returncode == 1 and "expected float" in bounded.stderr


def test_standby_resolution_engine_takes_over_from_a_killed_leader(system):
    sys_ = system()
    sys_.set_level(7.0)
    st = sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the swap to Filtered")
    leader = sys_.leader(st)
    before = {n["node"]: n.get("pid") for n in st["nodes"] if n["state"] == "RUNNING"}
    assert sys_.client.host("local", m.SignalNode(node=leader, signal=signal.SIGKILL))

    def takeover(s) -> bool:
        return s["engine"] is not None and sys_.leader(s) not in (leader, "")

    st = sys_.wait(takeover, "the standby leading")
    # It continued from the same model: same selection, same processes, nothing restarted.
    assert "Filtered" in st["engine"]["selection"]
    assert set(st["engine"]["running"]) == {"source", "filtered", "sink"}
    nodes = {n["node"]: n.get("pid") for n in st["nodes"]}
    assert all(nodes[n] == before[n] for n in ("source", "filtered", "sink"))
    # ... and it still adapts, while the killed replica comes back as a standby.
    sys_.set_level(2.0)
    st = sys_.wait(lambda s: "direct" in s["engine"]["running"], "the swap back to Direct")
    assert sys_.node(st, "sink")["pid"] == before["sink"]
    st = sys_.wait(lambda s: sys_.node(s, leader)["state"] == "RUNNING", "the old leader back")
    assert sys_.leader(st) != leader  # no flapping back
    # The log holds the killed leader's crash once: it came while nobody led, and the new
    # leader logged it as it took over (with its restart, which came after).
    crashes = [e for e in sys_.events() if isinstance(e, m.NodeState) and e.node == leader
               and e.state == "BACKOFF"]  # fmt: skip
    assert len(crashes) == 1 and "status -9" in crashes[0].reason, crashes
    restarts = [e for e in sys_.events() if isinstance(e, m.NodeState) and e.node == leader
                and e.previous == "BACKOFF" and e.state == "STARTING"]  # fmt: skip
    assert len(restarts) == 1, restarts


def test_a_lone_restarted_resolution_engine_resumes_and_adopts(system):
    sys_ = system(DATA, "--replicas", "1")
    sys_.set_level(7.0)
    st = sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the swap to Filtered")
    before = {n["node"]: n.get("pid") for n in st["nodes"] if n["state"] == "RUNNING"}
    engine_pid = before.pop("resolution-a")
    assert sys_.client.host("local", m.SignalNode(node="resolution-a", signal=signal.SIGKILL))

    def adopted() -> list:
        return [e for e in sys_.events() if isinstance(e, m.AdaptationEvent)
                and e.kind == "adopt" and e.outcome == "ok"]  # fmt: skip

    st = sys_.wait(
        lambda s: (
            sys_.node(s, "resolution-a").get("pid") not in (None, engine_pid)
            and s["engine"] is not None
            and s["engine"]["deployed"]
            and adopted()
        ),
        "the resolution engine restarted and adopted the nodes",
    )
    # It came back with the selection it had applied (its state file) and took the nodes
    # over: same processes, no restart, nothing started; the operator's value is kept.
    assert "Filtered" in st["engine"]["selection"]
    assert set(st["engine"]["running"]) == {"source", "filtered", "sink"}
    assert st["engine"]["overrides"] == {"source": {"value": 7.0}}
    after = {n["node"]: n.get("pid") for n in st["nodes"] if n["state"] == "RUNNING"}
    assert all(after[n] == before[n] for n in ("source", "filtered", "sink"))
    adopt = adopted()[-1]
    assert not any(p.startswith(("start", "stop")) for p in adopt.plan), adopt.plan
    sys_.set_level(2.0)
    st = sys_.wait(lambda s: "direct" in s["engine"]["running"], "the swap back to Direct")
    assert sys_.node(st, "sink")["pid"] == before["sink"]


def test_nodes_are_placed_on_the_host_the_model_names(system, procs, bus, tmp_path):
    pkg = package_copy(tmp_path)

    def place(data):
        data["hosts"] = [{"name": "local"}, {"name": "h2"}]
        for c in data["components"]:
            c["host"] = "h2" if c["name"] in ("sink", "filtered") else "local"

    edit_yaml(pkg / "system.yaml", place)
    h2_router = free_port()
    procs.python(
        "rra_agent", "agent", "--system", "relay_system", "--host", "h2",
        "--package", str(pkg), "--log-dir", str(tmp_path / "h2-logs"),
        "--connect", bus.connect[0], "--listen", f"tcp/127.0.0.1:{h2_router}",
        "--no-multicast", "--lease-ms", "500", name="agent-h2",
    )  # fmt: skip
    sys_ = system(pkg)
    # The engine reports the deployment once it is applied; each host agent lists its own
    # nodes in the status, and h2's answer may come in a later gather (CI, under load).
    st = sys_.wait(lambda s: {"sink", "source", "direct"} <= {n["node"] for n in s["nodes"]},
                   "every node listed by its host")  # fmt: skip
    hosts = {n["node"]: n["host"] for n in st["nodes"]}
    assert hosts["sink"] == "h2" and hosts["source"] == "local" and hosts["direct"] == "local"
    assert (tmp_path / "h2-logs" / "sink.log").exists()
    # Each host has its router: h2's node is a client of h2's router, not of the hub.
    assert tcp_peers(sys_.node(st, "sink")["pid"]) == {h2_router}
    assert tcp_peers(sys_.node(st, "source")["pid"]) == {int(bus.connect[0].rsplit(":", 1)[1])}
    sys_.set_level(7.0)
    st = sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the swap across hosts")
    assert {n["node"]: n["host"] for n in st["nodes"]}["filtered"] == "h2"


def test_a_host_router_refuses_plain_text_beyond_loopback_unless_insecure():
    from rra_agent.bus.config import BusConfig
    from rra_agent.errors import RraError

    with pytest.raises(RraError, match=r"without TLS.*--insecure"):
        BusConfig(listen=["tcp/0.0.0.0:7447"]).host_router(hub=True)
    with pytest.raises(RraError, match=r"tcp/10\.0\.0\.1:7447"):
        BusConfig(connect=["tcp/10.0.0.1:7447"]).host_router(hub=False)
    cfg = BusConfig(listen=["tcp/0.0.0.0:7447"], insecure=True).host_router(hub=True)
    assert cfg.listen == ["tcp/0.0.0.0:7447"]  # the loopback hub endpoint is covered by it
    assert cfg.local_client().connect == ["tcp/127.0.0.1:7447"]
    ok = BusConfig(listen=["tls/0.0.0.0:7448"]).host_router(hub=False)
    assert ok.local_client().connect == ["tls/127.0.0.1:7448"]


def test_rra_up_beyond_loopback_needs_tls_or_an_explicit_insecure(procs, tmp_path):
    import subprocess
    import sys

    from conftest import listening

    port = free_port()
    run_dir = tmp_path / "run"
    args = [sys.executable, "-m", "rra_agent", "up", str(DATA), "--run-dir", str(run_dir)]
    args += ["--connect", f"tcp/127.0.0.1:{free_port()}", "--listen", f"tcp/0.0.0.0:{port}"]
    refused = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert refused.returncode == 1 and refused.stdout == ""
    assert refused.stderr.count("\n") == 1 and "--insecure" in refused.stderr
    assert "Traceback" not in refused.stderr and not run_dir.exists()
    proc = procs.spawn([*args, "--insecure", "-q"], name="insecure")
    wait_until(lambda: listening(port), 60, "rra up --insecure listening")
    assert "WARNING: --insecure" in procs.log("insecure")
    proc.send_signal(signal.SIGINT)
    assert proc.wait(30) == 0
