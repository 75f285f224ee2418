"""``rra reload``: edited models into a running system, in real processes (docs/recording.md).

A rule edited while the quadcopter hovers changes the decision with no process restarted;
an edit that cannot be made live is refused where it is written, with nothing changed; a
reload during a flood of context samples or during a failover of an engine leader never has
the Run-time Resolution Engine apply a selection decided under other models than it runs,
and every replica ends on the new models (its record replays to the same decisions).
"""

from __future__ import annotations

import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import pytest

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, gather, wait_until
from rra_agent.record.replay import open_run, replay
from tests.conftest import RELAY, RELAY_KEYS, listening, position
from tests.conftest import edit_text as edit

ROOT = Path(__file__).resolve().parents[1]
QUADCOPTER = ROOT / "scenarios" / "quadcopter"
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
_STATE = m.Codec[m.StateMessage](m.StateMessage)

pytestmark = pytest.mark.system


def copy(src: Path, tmp_path: Path, name: str = "edited") -> Path:
    pkg = tmp_path / name
    shutil.copytree(src, pkg, ignore=shutil.ignore_patterns("__pycache__", "*.scenario.yaml"))
    return pkg


def reload(bus: Any, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "rra_agent", "reload", *args, "--connect", bus.connect[0],
         "--no-multicast"],
        capture_output=True, text=True, timeout=120, cwd=ROOT, check=False,
    )  # fmt: skip


def pids(st: dict) -> dict[str, tuple[int, int]]:
    """Every live process of the system: name -> (pid, restarts)."""
    return {n["node"]: (n["pid"], n.get("restarts", 0)) for n in st["nodes"]
            if n.get("pid") and n["state"] == "RUNNING"}  # fmt: skip


def engine(client: BusClient, name: str) -> dict:
    reply = client.request(client.keys.engine_ctl(name), m.Status(), 2.0)
    assert isinstance(reply, m.Ok), reply
    return reply.result


#: The Adaptation Engine replicas `rra up` starts.
ADAPTATION = ("adaptation-a", "adaptation-b")


class Watch:
    """Every selection and Resolution Engine state on the bus during a test."""

    def __init__(self, client: BusClient) -> None:
        self.lock = threading.Lock()
        self.selections: list[m.Selection] = []
        self.states: list[m.EngineState] = []
        s, k = client.session, client.keys
        self.subs = [s.declare_subscriber(k.selection, self._sel),
                     s.declare_subscriber(k.state("resolution"), self._state)]  # fmt: skip

    def _sel(self, sample: Any) -> None:
        """The Adaptation Engine replicas' selections (``--hostile`` forges others: junk, no
        fence, the fence of a leader that is none of them)."""
        try:
            msg = _SEL.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        if isinstance(msg, m.Selection) and msg.fence and msg.fence.leader in ADAPTATION:
            with self.lock:
                self.selections.append(msg)

    def _state(self, sample: Any) -> None:
        try:
            state = _STATE.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        with self.lock:
            self.states.append(state)

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()

    def applied_under_other_models(self) -> list[str]:
        """Selections the Resolution Engine applied although they were decided under other
        models than the state that applied them names."""
        with self.lock:
            by_id = {(s.fence.term if s.fence else None, s.seq): s for s in self.selections}
            states = list(self.states)
        bad: list[str] = []
        last, models = None, None
        for st in states:
            key = (st.selection_fence.term if st.selection_fence else None, st.applied)
            if models is None:  # what the first state seen shows was applied before
                last, models = key, st.models
                continue
            # A heartbeat selection is applied without a new state: one the commit's state
            # shows first was applied before the switch, under the models before.
            under = models  # the previous state's: the commit's state is the new one's first
            if key != last and key in by_id and by_id[key].models != under:
                bad.append(f"selection {st.applied} of {key[0]} under {by_id[key].models}, "
                           f"applied under {under}")  # fmt: skip
            last, models = key, st.models
        return bad


# ---- the quadcopter: a rule edited while it hovers ------------------------------------------
def test_a_rule_edited_while_the_quadcopter_hovers_changes_the_decision_without_a_restart(
    procs, bus, tmp_path: Path
) -> None:
    """MotorLoss fires below 5 working motors instead of 4: with all 4 working the rule
    selects Proploss at once. No process restarts: the engines and every node keep their
    pids; only the standard controller, swapped out by the new decision, stops."""
    run_dir = tmp_path / "run"
    up = procs.python("rra_agent", "up", str(QUADCOPTER), "--select", "Hover", "--run-dir",
                      str(run_dir), "-q", "--connect", bus.connect[0], "--no-multicast",
                      name="up")  # fmt: skip
    port = int(bus.connect[0].rsplit(":", 1)[1])
    wait_until(lambda: up.poll() is not None or listening(port), 60, "rra up listening")
    with BusClient(bus, "quadcopter") as client:
        before = wait_until(lambda: _hovering(client), 60, "the quadcopter hovering")
        models = before.pop("_models")
        pkg = copy(QUADCOPTER, tmp_path)
        edit(pkg, "adaptation.rra", "cdm.WorkingMotors < 4", "cdm.WorkingMotors < 5")
        out = reload(bus, str(pkg))
        assert out.returncode == 0, out.stdout + out.stderr
        assert "  rule MotorLoss: changed" in out.stdout.splitlines()
        assert "rra reload: the Adaptation Engine decides under them" in out.stdout
        after = wait_until(lambda: _selected(client, "Proploss"), 15, "Proploss selected")
        st = gather(client)
        now = pids(st)
        for name, (pid, restarts) in now.items():
            assert before.get(name, (pid, restarts)) == (pid, restarts), (name, before, now)
        assert set(before) - set(now) == {"controller"}, (before, now)
        assert set(now) <= set(before)
        assert after["models"] != models
        assert engine(client, "adaptation")["models"] == after["models"]
    up.send_signal(signal.SIGINT)
    assert up.wait(60) == 0
    events = (run_dir / "events.jsonl").read_text()
    assert '"kind":"reload"' in events and "rule MotorLoss: changed" in events


def _hovering(client: BusClient) -> dict | None:
    st = gather(client, timeout=1.0)
    eng = st["engine"] or {}
    running = pids(st)
    wanted = {"controller", "proploss_controller", "vehicle_simulator"}
    wanted |= {f"{r}-{x}" for r in ("monitor", "adaptation", "resolution") for x in "ab"}
    if not eng.get("deployed") or not wanted <= set(running) or "Standard" not in eng.get(
            "selection", []):  # fmt: skip
        return None
    return {**running, "_models": eng["models"]}  # type: ignore[dict-item]


def _selected(client: BusClient, feature: str) -> dict | None:
    st = gather(client, timeout=1.0)
    eng = st["engine"] or {}
    return eng if feature in eng.get("effective", []) else None


# ---- the relay system: refusals, a flood, a failover ---------------------------------------------
def relay_rules(tmp_path: Path, threshold: str = "0.5") -> Path:
    """Level > 5 -> Level > 0.5: at the source's level 1, Filtered."""
    pkg = copy(RELAY, tmp_path)
    edit(pkg, "adaptation.rra", "cdm.Level > 5", f"cdm.Level > {threshold}")
    return pkg


def test_an_edit_that_cannot_be_made_live_is_refused_and_nothing_changes(system, bus, tmp_path):
    sys_ = system()
    before = sys_.gather()
    pkg = copy(RELAY, tmp_path)
    edit(pkg, "measurements.yaml", "data_types:\n", "data_types:\n  - {name: Other, fields: "
         "{value: float}}\n")  # fmt: skip
    text = edit(pkg, "system.yaml", "      - {name: out, direction: publish, type: Sample}\n"
                "connections", "      - {name: out, direction: publish, type: Other}\n"
                "connections")  # fmt: skip
    edit(pkg, "adaptation.rra", "cdm.Level > 5", "cdm.Level > 0.5")  # would change a decision
    out = reload(bus, str(pkg))
    assert out.returncode == 1, out.stdout + out.stderr
    line, col = position(text, "Other")
    lines = out.stderr.strip().splitlines()
    assert lines == [
        f"{pkg / 'system.yaml'}:{line}:{col}: component sink: port out: its type cannot change "
        "while the system runs (Sample -> Other): samples of the old type are on the bus",
        "rra reload: refused (1 change(s) cannot be made while the system runs): nothing was "
        "changed",
    ]  # fmt: skip
    after = sys_.gather()
    assert after["engine"]["models"] == before["engine"]["models"]
    assert after["engine"]["selection"] == before["engine"]["selection"]
    assert pids(after) == pids(before)


def test_removing_a_running_component_is_refused_where_it_is_written(system, bus, tmp_path):
    sys_ = system()
    before = sys_.gather()
    assert "direct" in before["engine"]["running"]
    pkg = copy(RELAY, tmp_path)
    text = edit(pkg, "system.yaml", "  - name: direct\n    implementation: rra_agent.nodes."
                "generic.Relay\n    optional: true\n    binding: runtime\n    parameters:\n"
                "      offset: {type: float, value: 0.0}\n    ports:\n      - {name: in, "
                "direction: subscribe, type: Sample}\n      - {name: out, direction: publish, "
                "type: Sample}\n", "")  # fmt: skip
    edit(pkg, "system.yaml", "  - {from: source.out, to: direct.in}\n", "")
    edit(pkg, "system.yaml", "  - {from: direct.out, to: sink.in, optional: true, binding: "
         "runtime}\n", "")  # fmt: skip
    edit(pkg, "runtime.yaml", "  Direct:\n    - include_component: direct\n    - add_connection:"
         " {from: direct.out, to: sink.in}\n", "  Direct: []\n")  # fmt: skip
    edit(pkg, "runtime.yaml", "  state_transfer:\n    - {from: direct, to: filtered}\n", "")
    out = reload(bus, str(pkg))
    assert out.returncode == 1, out.stdout + out.stderr
    line, col = position(text, "components:")
    assert out.stderr.splitlines()[0] == (
        f"{pkg / 'system.yaml'}:{line}:{col}: component direct runs on host local: it cannot "
        "be removed while the system runs (select a configuration without it first)")
    after = sys_.gather()
    assert after["engine"]["models"] == before["engine"]["models"] and pids(after) == pids(before)


def test_a_reload_during_an_adaptation_waits_for_it(system, bus, tmp_path, monkeypatch):
    """Each plan is held 2 s before it executes (the benchmarks' emulated slow pipeline): a
    reload sent while the swap to Filtered waits is taken after that plan, never inside."""
    monkeypatch.setenv("RRA_EMULATED_SWAP_DELAY", "2")
    sys_ = system()
    watch = Watch(sys_.client)
    try:
        sys_.set_level(7.0)
        wait_until(lambda: any("Filtered" in x.features and x.changed for x in watch.selections),
                   15, "Filtered decided")  # fmt: skip
        sent = time.time()
        out = reload(bus, str(relay_rules(tmp_path, "6")))  # Level 7: still Filtered
        assert out.returncode == 0, out.stdout + out.stderr
        assert watch.applied_under_other_models() == []
    finally:
        watch.close()
    events = [e for e in sys_.events() if isinstance(e, m.AdaptationEvent)]
    swap = next(e for e in events if e.kind == "adaptation" and "Filtered" in e.message)
    done = next(e for e in events if e.kind == "reload")
    assert sent < swap.stamp <= done.stamp, (sent, swap, done)


def test_undo_goes_back_to_the_models_before(system, bus, tmp_path):
    sys_ = system()
    first = sys_.gather()["engine"]["models"]
    out = reload(bus, str(relay_rules(tmp_path)))
    assert out.returncode == 0, out.stdout + out.stderr
    sys_.wait(lambda s: "filtered" in s["engine"]["running"], "Filtered after the reload")
    out = reload(bus, "--undo")
    assert out.returncode == 0, out.stdout + out.stderr
    st = sys_.wait(lambda s: "direct" in s["engine"]["running"], "Direct after the undo")
    assert st["engine"]["models"] == first
    out = reload(bus, "--undo")
    assert out.returncode == 1 and "nothing to undo" in out.stderr


@pytest.mark.parametrize("fault", ["flood", "adaptation_killed", "resolution_killed"])
def test_a_reload_under_a_flood_or_a_failover_never_mixes_models(
    system, bus, procs, tmp_path: Path, fault: str
) -> None:
    """The reload races a flood of source samples (2000/s, levels 0..99: the Path rule
    flips all the time), or the kill of the Adaptation or Resolution Engine leader. No
    selection decided under one version is applied under the other, every replica ends on
    the new models, and each replica's record replays to the same decisions."""
    sys_ = system()
    client = sys_.client
    watch = Watch(client)
    try:
        if fault == "flood":
            procs.spawn([sys.executable, str(ROOT / "tools" / "flood.py"), bus.connect[0],
                         RELAY_KEYS.data("source/out"), "2000"], name="flood")  # fmt: skip
            wait_until(lambda: len(watch.selections) > 20, 30, "the flood deciding")
        else:
            role = fault.split("_")[0]
            leader = sys_.leader(sys_.gather(), role)
            reply = client.host("local", m.SignalNode(node=leader, signal=int(signal.SIGKILL)))
            assert isinstance(reply, m.Ok), reply
        out = reload(bus, str(relay_rules(tmp_path, "50.5")))
        # A failover may take the reload's leader away: refused or not, never mixed.
        new = _new_models(out, client)
        st = sys_.wait(lambda s: _all_on(client, s, new), "every replica on the new models", 30)
        assert st["engine"]["models"] == new
        wait_until(lambda: any(s.models == new for s in watch.selections), 15,
                   "a selection under the new models")  # fmt: skip
        bad = watch.applied_under_other_models()
        assert bad == []
    finally:
        watch.close()
    client.close()
    assert sys_.stop() == 0
    result = replay(open_run(sys_.run_dir))
    assert result.difference is None, result.difference


def test_a_selection_decided_under_other_models_is_refused(system, bus) -> None:
    """A selection from the Adaptation Engine leader (its fence, the next sequence number)
    decided under other models than the Resolution Engine runs (one decided just before a
    reload and arriving after it) is refused and counted: nothing is applied."""
    sys_ = system()
    client = sys_.client
    watch = Watch(client)
    try:
        wait_until(lambda: watch.selections, 30, "a selection")
        with watch.lock:
            last = watch.selections[-1]
        swapped = [{"Direct": "Filtered", "Filtered": "Direct"}.get(f, f) for f in last.features]
        forged = msgspec.structs.replace(last, seq=last.seq + 1, features=swapped,
                                         changed=True, models="0123456789abcdef")  # fmt: skip
        before = _rejected(client)
        client.session.put(client.keys.selection, _SEL.encode(forged))
        wait_until(lambda: _rejected(client) > before, 15, "the selection refused")
        st = sys_.gather()
        assert set(st["engine"]["selection"]) & {"Direct", "Filtered"} == (
            set(last.features) & {"Direct", "Filtered"})
    finally:
        watch.close()


def _rejected(client: BusClient) -> int:
    reply = client.request(client.keys.engine_ctl("resolution"), m.Stats(), 2.0)
    assert isinstance(reply, m.Ok), reply
    result = reply.result if isinstance(reply.result, dict) else msgspec.to_builtins(reply.result)
    return int(result.get("rejected", 0))


def _new_models(out: subprocess.CompletedProcess[str], client: BusClient) -> str:
    if out.returncode == 0:
        line = next(x for x in out.stdout.splitlines() if x.startswith("rra reload: models "))
        return line.split()[3]
    # The leader that took the reload died on it: the system runs one version or the other.
    assert "rra reload:" in out.stderr, out.stderr
    return engine(client, "resolution")["models"]


def _all_on(client: BusClient, st: dict, models: str) -> bool:
    replicas = [n["node"] for n in st["nodes"]
                if n["node"].split("-")[0] in ("monitor", "adaptation", "resolution")]  # fmt: skip
    if len(replicas) < 6:
        return False
    try:
        return all(engine(client, r).get("models") == models for r in replicas)
    except (AssertionError, Exception):  # a restarted replica not answering yet
        return False


def test_a_reload_reaches_the_host_agents_before_a_plan_uses_it(system, bus, tmp_path):
    """A new implementation of the filtered relay (an Echo instead of a Relay) chosen by a
    new Run-time Resolution Model transformation: the host agent admits it (its catalog has
    the new models) and the swap runs it."""
    sys_ = system()
    pkg = relay_rules(tmp_path)
    edit(pkg, "system.yaml", "  - name: filtered\n    implementation: rra_agent.nodes.generic."
         "Relay\n", "  - name: filtered\n    implementation: rra_agent.nodes.generic.Relay\n"
         "    implementations: {echo: rra_agent.nodes.generic.Echo}\n")  # fmt: skip
    edit(pkg, "runtime.yaml", "    - include_component: filtered\n", "    - include_component: "
         "filtered\n    - set_implementation: {component: filtered, implementation: echo}\n")
    out = reload(bus, str(pkg))
    assert out.returncode == 0, out.stdout + out.stderr
    assert "  component filtered: implementation(s) added: echo" in out.stdout.splitlines()
    st = sys_.wait(lambda s: sys_.node(s, "filtered")["state"] == "RUNNING", "filtered running")
    reply = client_describe(sys_.client, "filtered")
    assert reply["implementation"] == "rra_agent.nodes.generic.Echo", reply
    assert not st["engine"]["failed"]


def client_describe(client: BusClient, node: str) -> dict:
    reply = client.node(node, m.Describe())
    assert isinstance(reply, m.Ok), reply
    return msgspec.to_builtins(reply.result)
