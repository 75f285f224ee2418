"""Data the Context Monitor can trust, end to end (`rra up` of tests/data/relay_system).

The measurement Level is the field ``value`` of ``source.out`` (a ``Sample``: seq int, value
float; plausible within [-1000, 1000]); Level above 5 selects Filtered. Forged samples that
would select it if they were believed (a value of 9, inf or 1e9) are ill-typed, truncated,
non-finite or implausible: each is refused, counted per source and reason in ``rra status``,
and no selection ever names Filtered. Oversized payloads on every key family are stopped by
the host's Zenoh router before any process sees them, and leave the memory of the system
where it was.
"""

from __future__ import annotations

import contextlib
import json
import math
import subprocess
import sys
import threading
from collections.abc import Callable

import msgspec
import pytest
import zenoh
from conftest import RELAY_KEYS as K
from conftest import ROOT

from rra_agent.bus import messages as m
from rra_agent.bus.client import wait_until
from rra_agent.bus.counters import MAX_PAYLOAD, MiB
from rra_agent.bus.data import encode_data
from rra_agent.bus.session import open_session

sys.path.insert(0, str(ROOT / "tools"))
from bench_memory import descendants, pss_kib

SOURCE = "source.out"
GOOD = {"seq": 1, "value": 9.0}
#: Reason -> forged samples on source.out; each would select Filtered were it believed.
FORGED: dict[str, list[bytes]] = {
    "missing_field": [encode_data({"value": 9.0})],
    "wrong_type": [encode_data({"seq": "1", "value": 9.0}), encode_data({**GOOD, "seq": True})],
    "malformed": [encode_data(GOOD)[:-3]],  # truncated msgpack
    "not_a_map": [encode_data([1, 9.0])],
    "non_finite": [encode_data({**GOOD, "value": v}) for v in (math.inf, math.nan)],
    "implausible": [encode_data({**GOOD, "value": 1e9})],
}
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
BLOCK = zenoh.CongestionControl.BLOCK


class Selections:
    """Every selection the Adaptation Engine replicas publish while the test runs."""

    def __init__(self, session: zenoh.Session) -> None:
        self.seen: list[m.Selection] = []
        self.sub = session.declare_subscriber(K.selection, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):  # --hostile
            sel = _SEL.decode(sample.payload.to_bytes())
            if sel.fence is not None and sel.fence.leader.startswith("adaptation"):
                self.seen.append(sel)  # not one forged by tools/hostile.py (--hostile)

    def named(self, feature: str) -> list[m.Selection]:
        return [s for s in self.seen if feature in s.features]


def refused(sys_) -> dict[tuple[str, str], int]:
    """(source, reason) -> count, as the Context Monitor leader reports them."""
    stats = sys_.gather()["stats"].values()
    monitors = sorted((v for v in stats if v["role"] == "monitor"),
                      key=lambda v: not v["counters"].get("leading"))  # fmt: skip
    rows = monitors[0].get("refused", []) if monitors else []
    return {(r["source"], r["reason"]): r["count"] for r in rows}


def rra_status(bus, *extra: str) -> str:
    out = subprocess.run(
        [sys.executable, "-m", "rra_agent", "status", "--system", "relay_system",
         "--connect", bus.connect[0], *extra],
        capture_output=True, text=True, timeout=60, cwd=ROOT,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    return out.stdout


def test_ill_typed_non_finite_and_implausible_samples_are_refused_counted_and_never_adapt(
    system, bus
):
    sys_ = system()
    selections = Selections(sys_.client.session)
    pub = sys_.client.session.declare_publisher(K.data("source/out"))
    try:
        for reason, payloads in FORGED.items():

            def counted(r: str = reason, ps: list[bytes] = payloads) -> bool:
                for p in ps:  # again on each look: a put before the route is known is lost
                    pub.put(p, attachment=m.pack_stamp(1.0))
                return refused(sys_).get((SOURCE, r), 0) >= len(ps)

            wait_until(counted, 30, f"the {reason} samples refused", interval=0.2)
        # The newest good samples still make measurements: the operator's 7 selects Filtered.
        assert not selections.named("Filtered"), "a forged sample reached the rules"
        assert sys_.gather()["engine"]["selection"] == ["Direct", "Path", "Tuning"]
        sys_.set_level(7.0)
        sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the real swap to Filtered")
        wait_until(lambda: selections.named("Filtered"), 10, "the real selection seen")
    finally:
        pub.undeclare()
        selections.sub.undeclare()
    # Nothing non-finite or out of bounds was ever selected as a CV value either.
    assert all(math.isfinite(v) and abs(v) <= 1000 for s in selections.seen for v in s.cv.values())
    text = rra_status(bus)
    assert max(len(line) for line in text.splitlines()) <= 100
    table = text[text.index("REFUSED SAMPLES OF") :].splitlines()
    assert table[0].split() == ["REFUSED", "SAMPLES", "OF", "REASON", "COUNT", "LAST"]
    shown = {(row.split()[0], row.split()[1]) for row in table[1:]}
    assert {(SOURCE, r) for r in FORGED} <= shown
    as_json = json.loads(rra_status(bus, "--json"))
    rows = [r for st in as_json["stats"].values() for r in st.get("refused", [])]
    assert {r["reason"] for r in rows if r["source"] == SOURCE} >= set(FORGED)
    logs = "".join(f.read_text() for f in (sys_.run_dir / "logs").glob("monitor-*.log"))
    assert "refused (implausible): source.out: Level would be 1000000000.0" in logs
    assert "dropped (malformed): source.out: not msgpack" in logs


def node_counters(sys_, name: str) -> dict[str, int]:
    """A node's counters (``rejected``, ``dropped`` and the further ones by name)."""
    stats = sys_.gather()["stats"].get(f"node:{name}")
    if stats is None:
        return {}
    counts = {"rejected": stats.get("rejected", 0), "dropped": stats.get("dropped", 0)}
    return {**counts, **stats.get("counters", {})}  # a zero count is left out


def test_a_node_s_typed_input_refuses_forged_samples_so_it_never_relays_them(system):
    """``direct`` (a Relay, its input of type Sample) gets the forged samples on source.out:
    each is refused and counted per reason in its own counters, and nothing it publishes is
    ill-typed or non-finite (on the old code it relayed them as they came, NaN included)."""
    sys_ = system()
    relayed: list[bytes] = []
    sub = sys_.client.session.declare_subscriber(
        K.data("direct/out"), lambda s: relayed.append(s.payload.to_bytes())
    )
    pub = sys_.client.session.declare_publisher(K.data("source/out"))
    node_reasons = ("missing_field", "wrong_type", "non_finite", "malformed", "not_a_map")

    def counted() -> bool:
        for reason in node_reasons:  # again on each look: a put before the route is lost
            for p in FORGED[reason]:
                pub.put(p, attachment=m.pack_stamp(1.0))
        got = node_counters(sys_, "direct")
        return all(got.get(r, 0) >= len(FORGED[r]) for r in node_reasons)

    try:
        wait_until(counted, 30, "direct's refusals of every forged kind", interval=0.2)
        wait_until(lambda: len(own(relayed)) >= 3, 10, "direct relaying the source's ticks")
    finally:
        pub.undeclare()
        sub.undeclare()
    got = node_counters(sys_, "direct")
    assert got["rejected"] >= 5 and got["dropped"] >= 2, got
    bad = [s for s in own(relayed) if not well_typed(s)]
    assert not bad, f"direct relayed {len(bad)} forged samples, e.g. {bad[:3]}"


def own(relayed: list[bytes]) -> list[dict]:
    """What ``direct`` itself published (a Relay names itself in ``relay``); a hostile
    client's forgeries on its key (``--hostile``) do not."""
    out = []
    for raw in relayed:
        with contextlib.suppress(msgspec.DecodeError):
            sample = msgspec.msgpack.decode(raw)
            if isinstance(sample, dict) and sample.get("relay") == "direct":
                out.append(sample)
    return out


def well_typed(sample: dict) -> bool:
    seq, value = sample.get("seq"), sample.get("value")
    return (
        type(seq) is int
        and type(sample.get("count")) is int
        and type(value) in (int, float)
        and math.isfinite(value)
    )


_CTX = m.Codec[m.CtxMessage](m.CtxMessage)


def test_forged_measurements_on_the_bus_are_refused_by_the_adaptation_engine(system):
    """Measurements put straight on ``ctx/Level`` (not from the Context Monitor) that would
    select Filtered: non-finite, implausible, of the wrong type, or of a name the model does
    not declare. The Adaptation Engine replicas refuse each (logged once per kind)."""
    sys_ = system()
    selections = Selections(sys_.client.session)
    forged = {
        "non_finite": ("Level", math.inf),
        "implausible": ("Level", 1e9),
        "wrong_type": ("Level", "9"),
        "unknown": ("Nope", 9.0),
    }
    logs = sys_.run_dir / "logs"

    def refused_all() -> bool:
        for name, value in forged.values():  # again on each look, until all are refused
            msg = m.Measurement(name=name, value=value, stamp=1.0)
            sys_.client.session.put(K.ctx(name), _CTX.encode(msg))
        text = "".join(f.read_text() for f in logs.glob("adaptation-*.log"))
        return all(f"refused ({reason}): measurement" in text for reason in forged)

    try:
        wait_until(refused_all, 30, "every forged measurement refused", interval=0.2)
        sys_.set_level(7.0)  # the monitor's measurements are still believed
        sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the real swap to Filtered")
        wait_until(lambda: selections.named("Filtered"), 10, "the real selection seen")
        first = selections.named("Filtered")[0]
        assert first.cv["Gain"] == pytest.approx(7.0), first  # the operator's, not a forged one
    finally:
        selections.sub.undeclare()


def oversized() -> dict[str, tuple[str, bytes]]:
    """Family -> (key, a payload 1 KiB over its limit); a control family's is a query's."""
    over = {f: b"\x00" * (n + 1024) for f, n in MAX_PAYLOAD.items()}
    return {
        "data": (K.data("source/out"), over["data"]),
        "ctx": (K.ctx("Level"), over["ctx"]),
        "selection": (K.selection, over["selection"]),
        "events": (K.events, over["events"]),
        "state": (K.state("resolution"), over["state"]),
        "inject": (K.inject("motor/2"), over["inject"]),
        "node_ctl": (K.node_ctl("sink"), over["node_ctl"]),
        "host_ctl": (K.host_ctl("local"), over["host_ctl"]),
        "engine_ctl": (K.engine_ctl("resolution"), over["engine_ctl"]),
    }


QUERIED = ("node_ctl", "host_ctl", "engine_ctl")


class Spy:
    """A session of its own on the system's bus: the largest payload it saw on each key."""

    def __init__(self, bus) -> None:
        self.session = open_session(bus)
        self.lock = threading.Lock()
        self.largest: dict[str, int] = {}
        self.sub = self.session.declare_subscriber(f"{K.prefix}/**", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        with self.lock:
            key = str(sample.key_expr)
            self.largest[key] = max(self.largest.get(key, -1), len(sample.payload))

    def saw(self, key: str) -> int:
        with self.lock:
            return self.largest.get(key, -1)

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def test_oversized_payloads_on_every_key_family_are_stopped_by_the_router(system, bus):
    """Nothing over its family's limit is delivered to any process: a spy subscribed to
    everything sees the small put that follows each big one, never the big one; an oversized
    query is never answered (the node, host agent or engine never got it), a small junk one
    is (Err: malformed). The system adapts as before."""
    sys_ = system()
    attacker = sys_.client.session
    spy = Spy(bus)
    try:
        for family, (key, payload) in oversized().items():
            if family in QUERIED:
                replies = list(attacker.get(key, payload=payload, timeout=2.0))
                assert not [r for r in replies if r.ok is not None], f"{family} was answered"
                small = list(attacker.get(key, payload=b"\xc1", timeout=5.0))
                assert any(r.ok is not None for r in small), f"{family}: no answer to junk"
                continue

            def followed(k: str = key, p: bytes = payload) -> bool:
                attacker.put(k, p, congestion_control=BLOCK)  # never dropped by the sender
                attacker.put(k, b"\xc1", congestion_control=BLOCK)  # after it: in order
                return spy.saw(k) >= 1

            wait_until(followed, 20, f"the small put after the {family} one", interval=0.2)
            assert spy.saw(key) < len(payload), f"{len(payload)} bytes on {key} delivered"
    finally:
        spy.close()
    st = sys_.gather()
    monitor = [v for v in st["stats"].values() if v["role"] == "monitor"]
    assert not [r for v in monitor for r in v.get("refused", []) if r["reason"] == "too_large"]
    sys_.set_level(7.0)
    sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the swap after the attack")


def system_pss_mib(pid: int) -> float:
    return sum(pss_kib(p) for p in descendants(pid)) / 1024


@pytest.mark.parametrize(
    ("what", "puts"),
    [
        ("three 10 MB samples on each of four keys", [(key, 10_000_000) for key in (
            K.data("source/out"), K.data("direct/out"), K.ctx("Level"), K.selection)] * 3),
        ("an 11 MB sample on a data key", [(K.data("source/out"), 11_000_000)]),
    ],
    ids=["4x3x10MB", "11MB"],
)  # fmt: skip
def test_a_flood_of_oversized_samples_leaves_the_memory_where_it_was(
    system, bus, what: str, puts: list[tuple[str, int]]
):
    """Before the routers stopped them, three 10 MB samples on four keys grew this system
    by 250 MiB PSS and one 11 MB sample by 42 MiB (reassembled by every subscriber's Zenoh,
    then kept by its allocator); the object-storing figures: tools/bench_memory.py --flood.
    A generous bound: 24 MiB."""
    sys_ = system()
    spy = Spy(bus)
    try:
        measure: Callable[[], float] = lambda: system_pss_mib(sys_.proc.pid)  # noqa: E731
        sys_.wait(lambda s: all(n["state"] in ("RUNNING", "STOPPED") for n in s["nodes"]),
                  "every process running")  # fmt: skip
        before = measure()
        for key, size in puts:
            sys_.client.session.put(key, b"\x00" * size, congestion_control=BLOCK)
        for key in {k for k, _ in puts}:  # the router has dealt with every big one
            wait_until(lambda k=key: sys_.client.session.put(k, b"\xc1") or spy.saw(k) >= 1,
                       20, f"the put after the flood on {key}", interval=0.2)  # fmt: skip
        sys_.gather()  # every process answers: each has had its turn with what it got
        after = measure()
    finally:
        spy.close()
    assert after - before <= 24.0, f"{what}: {before:.0f} -> {after:.0f} MiB PSS"
    assert max(spy.largest.values()) < MiB
