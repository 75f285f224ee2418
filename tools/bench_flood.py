"""Overload benchmark: an adaptation's latency while another key is flooded with valid samples.

A copy of the tests' relay_system (``rra up``, every engine with its standby): measurement
Level (from ``source.out``) above 5 swaps ``direct`` for ``filtered`` and sets ``sink.offset``
through the CV Gain; a second measurement, Noise (from ``noise.out``), is read by no rule
but computed by the Context Monitor and published to the Adaptation Engine like any other.
Neither ``source`` nor ``noise`` publishes by itself (Relays without input): this script
publishes as ``source`` (the cause, stamped) and ``tools/flood.py`` publishes as ``noise``.

After one untimed warm-up flip, for each run the level flips (7 <-> 2); the latency is
from the put of the level sample to the Run-time Resolution Engine's `AdaptationEvent`
(outcome ok) that applied it: monitor, Adaptation Engine, resolution, plan execution and the
event, all real processes on loopback.
Measured quiet, then with ``--rate`` valid samples/s (default 10 000) on ``noise.out`` from a
separate process. Prints median and p99 beside the goal (flooded: <= 100 ms), the flood rate
achieved and what the Context Monitor coalesced.

    .venv/bin/python tools/bench_flood.py [--runs 20] [--rate 10000] [--load]

``--load`` also runs a busy loop on every core (``tools/cpuhog.py``) for both phases.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import yaml
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _benchutil import median, p99, print_table

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, gather, wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.bus.data import encode_data
from rra_agent.bus.keys import Keys

ROOT = Path(__file__).resolve().parents[1]
SYSTEM = "relay_system"
K = Keys(SYSTEM)
GOAL_MS = 100.0
_EVT = m.Codec[m.EventMessage](m.EventMessage)


def write_package(root: Path) -> Path:
    pkg = root / "pkg"
    shutil.copytree(ROOT / "tests" / "data" / "relay_system", pkg)
    system = yaml.safe_load((pkg / "system.yaml").read_text())
    silent_relay = {
        "implementation": "rra_agent.nodes.generic.Relay",
        "ports": [
            {"name": "in", "direction": "subscribe", "type": "Sample"},
            {"name": "out", "direction": "publish", "type": "Sample"},
        ],
    }
    for c in system["components"]:
        if c["name"] == "source":
            c.clear()
            c.update(name="source", **silent_relay)
    system["components"].append({"name": "noise", **silent_relay})
    (pkg / "system.yaml").write_text(yaml.safe_dump(system, sort_keys=False))
    meas = yaml.safe_load((pkg / "measurements.yaml").read_text())
    for mm in meas["measurements"]:
        mm.pop("max_age_ms", None)  # the level is put once per run, not kept fresh
    meas["measurements"].append(
        {"name": "Noise", "type": "float", "source": "noise.out", "field": "value"}
    )
    (pkg / "measurements.yaml").write_text(yaml.safe_dump(meas, sort_keys=False))
    return pkg


class Adaptations:
    """Adaptation events of the Run-time Resolution Engine, as this session receives them."""

    def __init__(self, session: zenoh.Session) -> None:
        self.cond = threading.Condition()
        self.items: list[m.AdaptationEvent] = []
        self.sub = session.declare_subscriber(K.events, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        try:
            ev = _EVT.decode(sample.payload.to_bytes())
        except Exception:
            return
        if isinstance(ev, m.AdaptationEvent) and ev.kind == "adaptation" and ev.outcome == "ok":
            with self.cond:
                self.items.append(ev)
                self.cond.notify_all()

    def first_after(self, t0: float, timeout: float) -> m.AdaptationEvent | None:
        deadline = time.monotonic() + timeout
        with self.cond:
            while True:
                done = [e for e in self.items if e.stamp >= t0 and e.plan]
                if done:
                    return done[0]
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self.cond.wait(left)


def runs(client: BusClient, events: Adaptations, n: int, level: list[float]) -> list[float]:
    """``n`` level flips; the latency (s) of each from the put to the applied adaptation."""
    pub = client.session.declare_publisher(K.data("source/out"), express=True)
    out: list[float] = []
    try:
        for i in range(n):
            level[0] = 7.0 if level[0] < 5 else 2.0
            t0 = time.time()
            pub.put(
                encode_data({"seq": i, "value": level[0], "relay": "bench", "count": i}),
                attachment=m.pack_stamp(t0),
            )
            ev = events.first_after(t0, 10.0)
            if ev is None:
                raise SystemExit(f"run {i}: no adaptation within 10 s of level {level[0]}")
            out.append(ev.stamp - t0)
            want = "filtered" if level[0] > 5 else "direct"
            wait_until(
                lambda w=want: w in (gather(client, 1.0)["engine"] or {}).get("running", {}),
                10,
                f"{want} running",
                interval=0.02,
            )
    finally:
        pub.undeclare()
    return out


def monitor_stats(client: BusClient) -> dict:
    st = gather(client, 1.0)["stats"]
    leader = next(
        (v for v in st.values() if v["role"] == "monitor" and v["counters"].get("leading")), {}
    )
    return {"received": leader.get("received", 0), **leader.get("counters", {})}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--rate", type=float, default=10_000.0, help="flood samples per second")
    ap.add_argument("--load", action="store_true", help="a busy loop on every core as well")
    args = ap.parse_args()
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    procs: list[subprocess.Popen] = []
    with tempfile.TemporaryDirectory() as tmp:
        pkg = write_package(Path(tmp))
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        bus_args = ["--connect", endpoint, "--no-multicast", "--lease-ms", "500"]
        if args.load:
            procs.append(subprocess.Popen([sys.executable, str(ROOT / "tools" / "cpuhog.py")]))
        up = subprocess.Popen(
            [sys.executable, "-m", "rra_agent", "up", str(pkg), "--run-dir", f"{tmp}/run", "-q",
             *bus_args],
            env=env,
        )  # fmt: skip
        procs.append(up)
        client = BusClient(BusConfig(connect=[endpoint], multicast=False, lease_ms=500), SYSTEM)
        try:
            wait_until(
                lambda: "sink" in ((gather(client, 1.0)["engine"] or {}).get("running") or {}),
                60,
                "the system deployed",
                interval=0.1,
            )
            events = Adaptations(client.session)
            level = [2.0]
            runs(client, events, 1, level)  # warm-up: the first adaptation of a run, not timed
            quiet = runs(client, events, args.runs, level)
            before = monitor_stats(client)
            flood_cmd = [ROOT / "tools" / "flood.py", endpoint, K.data("noise/out"), args.rate]
            flood = subprocess.Popen(
                [sys.executable, *map(str, flood_cmd)],
                stdout=subprocess.PIPE,
                text=True,
                env=env,
            )
            procs.append(flood)
            wait_until(
                lambda: monitor_stats(client).get("received", 0) > before.get("received", 0) + 1000,
                20,
                "the flood reaching the Context Monitor",
                interval=0.1,
            )
            flooded = runs(client, events, args.runs, level)
            after = monitor_stats(client)
            flood.send_signal(signal.SIGINT)
            rate_out, _ = flood.communicate(timeout=20)
            events.sub.undeclare()
        finally:
            client.close()
            for p in reversed(procs):
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
            for p in procs:
                try:
                    p.wait(30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    load = " under a CPU hog on every core" if args.load else ""
    print(f"\nAdaptation latency, level put -> adaptation applied (ms){load}:")
    rows = []
    for name, xs, goal in (("quiet", quiet, None), (f"flood {args.rate:.0f}/s", flooded, GOAL_MS)):
        med, top = median(xs) * 1e3, p99(xs) * 1e3
        verdict = "" if goal is None else ("PASS" if top <= goal else "FAIL")
        rows.append([name, len(xs), med, top, max(xs) * 1e3, goal or "", verdict])
    print_table(["case", "runs", "median", "p99", "max", "goal (p99)", "verdict"], rows)
    received = after.get("received", 0) - before.get("received", 0)
    coalesced = after.get("coalesced", 0) - before.get("coalesced", 0)
    print(
        f"flood achieved {rate_out.strip() or '?'} samples/s; the Context Monitor leader received "
        f"{received} samples during the flooded runs and coalesced {coalesced} of them"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
