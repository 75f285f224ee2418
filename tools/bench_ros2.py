"""ROS 2 over rmw_zenoh: what rra-agent adds on the path of a ROS 2 sample and a lifecycle
switch. Everything on this machine, through an embedded Zenoh router on a free port.

  .venv/bin/python tools/bench_ros2.py [--samples 2000] [--switches 200]

1. sample -> measurement: zenoh-ros2-sdk (another process) publishes
   sensor_msgs/BatteryState at 200 Hz; rra's TopicField decodes it, takes ``percentage``
   and puts it as a msgpack measurement on an rra key, which a third session receives.
   Latency = arrival of the measurement - the sample's source timestamp (its attachment).
2. lifecycle switch: rra's LifecycleClient asks activate / deactivate in turn, of a
   zenoh-ros2-sdk ChangeState server (another process) and of rra's own LifecycleServer
   (another session); latency = the call, request to reply decoded.
3. rewiring a ROS 2 subscriber, two ways:
   relay: a relay forwarding /cmd_a to /cmd is switched to /cmd_b (both at 1 kHz); latency =
   switch() -> first /cmd_b sample forwarded;
   restart: a zenoh-ros2-sdk subscriber process (the stand-in for a ROS 2 node restarted
   with a new ``-r`` remapping) is started on the new topic while rra publishes on it at
   1 kHz; latency = start -> first sample printed by the new process.

Through the engines (``--engines``, the default; ``--no-engines`` skips it): ``rra up`` of
scenarios/ros2_rover (copied, with one more measurement ``BenchLev`` of ``ros2:/bench_battery``)
on a free loopback port, its ROS 2 nodes zenoh-ros2-sdk processes started by rra-agent:
4. sample -> measurement through the real Context Monitor: zenoh-ros2-sdk publishes
   BatteryState on /bench_battery at 200 Hz (a new percentage each time); latency = arrival
   of the monitor's ``BenchLev`` measurement at this script's session - the sample's source
   timestamp (the measurement's ``sources``, from the sample's attachment);
5. a lifecycle-node switch end to end: the battery driver's ``level`` set (SetParameters) to
   20 % and back to 100 % in turn; each time the Adaptation Engine selects the other power
   feature and the Run-time Resolution Engine swaps the managed planners (change_state
   deactivate / activate), rewires the controller's relay and sets its ``max_speed``
   (SetParameters). Latency = arrival of the adaptation event - the source timestamp of
   the first battery sample across the threshold (ROS 2 sample -> switch done); the event's
   own ``execute`` (the Executor, first action to last acknowledgement) beside it.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, gather, set_params, wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.ros2.bridge import TopicField
from rra_agent.ros2.endpoint import Received, Ros2Context
from rra_agent.ros2.params import LifecycleClient, LifecycleServer
from rra_agent.ros2.relay import Relay
from rra_agent.ros2.types import TypeRegistry

ROOT = Path(__file__).resolve().parent.parent
PEER = ROOT / "tests" / "data" / "ros2" / "sdk_peer.py"
ROVER = ROOT / "scenarios" / "ros2_rover"
TYPES = ["sensor_msgs/msg/BatteryState", "std_msgs/msg/String",
         "rcl_interfaces/srv/SetParameters", "rcl_interfaces/srv/GetParameters",
         "lifecycle_msgs/srv/ChangeState"]


def stats(name: str, ms: list[float]) -> None:
    ms = sorted(ms)
    p99 = ms[min(len(ms) - 1, int(len(ms) * 0.99))]
    print(f"{name:<44} n={len(ms):<5} median {statistics.median(ms):7.3f} ms   "
          f"p99 {p99:7.3f} ms")


def peer(port: int, msg_dir: Path, *args: str) -> subprocess.Popen[str]:
    p = subprocess.Popen([sys.executable, str(PEER), str(port), str(msg_dir), *args],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert p.stdout
    json.loads(p.stdout.readline())  # {"ready": ...}
    return p


def stop(p: subprocess.Popen[str]) -> None:
    assert p.stdin
    p.stdin.close()
    try:
        p.wait(10)
    except subprocess.TimeoutExpired:
        p.kill()


def sample_to_measurement(port: int, msg_dir: Path, ctx: Ros2Context,
                          other: zenoh.Session, n: int) -> None:
    lat: list[float] = []
    enc = msgspec.msgpack.Encoder()
    dec = msgspec.msgpack.Decoder()

    def arrived(sample: zenoh.Sample) -> None:
        _seq, ts = dec.decode(sample.payload.to_bytes())
        lat.append((time.time_ns() - ts) / 1e6)

    sub = other.declare_subscriber("rra/bench/ctx/battery", arrived)
    pub = ctx.session.declare_publisher("rra/bench/ctx/battery")

    def on_value(value: float, got: Received) -> None:
        assert got.attachment is not None
        pub.put(enc.encode([got.attachment.seq, got.attachment.timestamp_ns]))

    field = TopicField(ctx.node("monitor"), "/battery", "sensor_msgs/msg/BatteryState",
                       "percentage", on_value)
    p = peer(port, msg_dir, "pub_battery", "0.005")
    try:
        wait_until(lambda: len(lat) >= 50, 30, "first samples")
        lat.clear()
        wait_until(lambda: len(lat) >= n, 60 + n / 100, f"{n} samples")
    finally:
        stop(p)
        field.close()
        sub.undeclare()
        pub.undeclare()
    stats("SDK BatteryState -> rra measurement received", lat[:n])


def lifecycle(port: int, msg_dir: Path, ctx: Ros2Context, ctx2: Ros2Context, n: int) -> None:
    node = ctx.node("manager")
    LifecycleServer(ctx2.node("rra_managed"), state="inactive")
    p = peer(port, msg_dir, "serve")
    try:
        for target in ("/sdk_node", "/rra_managed"):
            client = LifecycleClient(node, target)
            wait_until(client.available, 20, f"{target}/change_state")
            lat = []
            for i in range(n):
                t0 = time.perf_counter()
                ok = client.change("activate" if i % 2 == 0 else "deactivate", timeout=2)
                lat.append((time.perf_counter() - t0) * 1e3)
                assert ok, (target, i)
            who = "zenoh-ros2-sdk" if target == "/sdk_node" else "rra"
            stats(f"lifecycle switch, {who} ChangeState server", lat)
    finally:
        stop(p)


def relay_switch(ctx: Ros2Context, ctx2: Ros2Context, n: int) -> None:
    src = ctx.node("sources")
    a = src.publisher("/cmd_a", "std_msgs/msg/String")
    b = src.publisher("/cmd_b", "std_msgs/msg/String")
    got: list[Received] = []
    ctx2.node("controller").subscription("/cmd", "std_msgs/msg/String", got.append)
    relay = Relay(ctx.node("relay"), "/cmd", "std_msgs/msg/String", "/cmd_a")
    lat = []
    stopping = threading.Event()

    def pump() -> None:
        while not stopping.wait(0.001):
            a.publish({"data": "a"})
            b.publish({"data": "b"})

    t = threading.Thread(target=pump, daemon=True)
    t.start()
    try:
        wait_until(lambda: got, 10, "relayed samples")
        for i in range(n):
            relay.switch("/cmd_b" if i % 2 == 0 else "/cmd_a")
            wait_until(lambda: relay.first_after_switch_ns, 5, "a sample after the switch")
            assert relay.switched_ns is not None and relay.first_after_switch_ns is not None
            lat.append((relay.first_after_switch_ns - relay.switched_ns) / 1e6)
    finally:
        stopping.set()
        t.join()
    stats("relay switch -> first sample of the new source", lat)


def restart_rewire(port: int, msg_dir: Path, ctx: Ros2Context, n: int) -> None:
    pub = ctx.node("driver").publisher("/battery_b", "sensor_msgs/msg/BatteryState")
    stopping = threading.Event()

    def pump() -> None:
        while not stopping.wait(0.001):
            pub.publish({"percentage": 0.5})

    t = threading.Thread(target=pump, daemon=True)
    t.start()
    lat = []
    try:
        for _ in range(n):
            t0 = time.perf_counter()
            p = subprocess.Popen(
                [sys.executable, str(PEER), str(port), str(msg_dir), "sub_battery", "/battery_b"],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
            assert p.stdout
            for line in p.stdout:
                if "percentage" in line:
                    break
            lat.append((time.perf_counter() - t0) * 1e3)
            stop(p)
    finally:
        stopping.set()
        t.join()
    stats("restart on the new topic -> first sample", lat)


# ---- 4 and 5: through the engines (rra up of the ros2_rover package) -------------------------
_CTX = m.Codec[m.CtxMessage](m.CtxMessage)
_EVT = m.Codec[m.EventMessage](m.EventMessage)
BENCH_MEASUREMENT = """
  # tools/bench_ros2.py: a measurement of its own publisher's topic
  - name: BenchLev
    type: float
    source: ros2:/bench_battery
    ros2_type: sensor_msgs/msg/BatteryState
    field: percentage
"""


class Rover:
    """``rra up`` of a copy of scenarios/ros2_rover on a free loopback port."""

    def __init__(self, work: Path) -> None:
        self.package = work / "ros2_rover"
        shutil.copytree(ROVER, self.package)
        with open(self.package / "measurements.yaml", "a") as f:
            f.write(BENCH_MEASUREMENT)
        self.port = free_port()
        endpoint = f"tcp/127.0.0.1:{self.port}"
        self.log = open(work / "up.log", "w")  # noqa: SIM115 (closed in stop)
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "rra_agent", "up", str(self.package), "--run-dir",
             str(work / "run"), "-q", "--connect", endpoint, "--no-multicast"],
            stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        self.client: BusClient | None = None
        wait_until(lambda: self._listening(), 60, "rra up listening", interval=0.05)
        bus = BusConfig(connect=[endpoint], multicast=False)
        self.client = BusClient(bus, "ros2_rover")
        wait_until(lambda: self._deployed(), 120, "the ros2_rover deployment", interval=0.2)

    def _listening(self) -> bool:
        if self.proc.poll() is not None:
            raise SystemExit(f"rra up exited: {self.proc.returncode} ({self.log.name})")
        with socket.socket() as s:
            s.settimeout(0.2)
            return s.connect_ex(("127.0.0.1", self.port)) == 0

    def _deployed(self) -> bool:
        if self.proc.poll() is not None:
            raise SystemExit(f"rra up exited: {self.proc.returncode} ({self.log.name})")
        assert self.client is not None
        eng = gather(self.client, timeout=1.0)["engine"]
        return bool(eng and eng.get("deployed") and eng.get("effective"))

    def stop(self) -> None:
        if self.client is not None:
            self.client.close()
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        self.log.close()


def through_monitor(rover: Rover, msg_dir: Path, n: int) -> None:
    assert rover.client is not None
    lat: list[float] = []

    def arrived(sample: zenoh.Sample) -> None:
        msg = _CTX.decode(sample.payload.to_bytes())
        if msg.sources:
            lat.append((time.time() - max(msg.sources.values())) * 1e3)

    sub = rover.client.session.declare_subscriber(rover.client.keys.ctx("BenchLev"), arrived)
    p = peer(rover.port, msg_dir, "pub_battery", "0.005", "/bench_battery")
    try:
        wait_until(lambda: len(lat) >= 50, 60, "first BenchLev measurements")
        lat.clear()
        wait_until(lambda: len(lat) >= n, 60 + n / 50, f"{n} BenchLev measurements")
    finally:
        stop(p)
        sub.undeclare()
    stats("SDK sample -> Context Monitor measurement", lat[:n])


class Switches:
    """The battery's crossings (BattLev measurements) and the adaptations they caused."""

    def __init__(self, client: BusClient) -> None:
        self.lock = threading.Lock()
        self.crossed: float | None = None  # source stamp of the first sample across
        self.low: bool | None = None
        self.events: list[tuple[float, m.AdaptationEvent]] = []
        s = client.session
        self.subs = [s.declare_subscriber(client.keys.ctx("BattLev"), self._level),
                     s.declare_subscriber(client.keys.events, self._event)]

    def _level(self, sample: zenoh.Sample) -> None:
        msg = _CTX.decode(sample.payload.to_bytes())
        low = float(msg.value) < 0.3
        with self.lock:
            if low != self.low and msg.sources:
                self.low, self.crossed = low, max(msg.sources.values())

    def _event(self, sample: zenoh.Sample) -> None:
        msg = _EVT.decode(sample.payload.to_bytes())
        if isinstance(msg, m.AdaptationEvent) and msg.kind == "adaptation" and msg.outcome:
            with self.lock:
                self.events.append((time.time(), msg))

    def close(self) -> None:
        for sub in self.subs:
            sub.undeclare()


def lifecycle_end_to_end(rover: Rover, n: int) -> None:
    assert rover.client is not None
    sw = Switches(rover.client)
    e2e: list[float] = []
    execute: list[float] = []
    try:
        for i in range(n):
            eco = i % 2 == 0
            with sw.lock:
                before = len(sw.events)
            set_params(rover.client, "battery", {"level": 20.0 if eco else 100.0}, timeout=10)
            wanted = re.compile(r"(?<!de)activate planner_" + ("eco" if eco else "fast"))

            def done(
                wanted: re.Pattern[str] = wanted, before: int = before
            ) -> m.AdaptationEvent | None:
                with sw.lock:
                    for _t, ev in sw.events[before:]:
                        if any(wanted.search(line) for line in ev.plan):
                            return ev
                return None

            try:
                ev = wait_until(done, 30, f"switch {i} ({wanted.pattern})")
            except TimeoutError:
                seen = [(e.kind, e.outcome, e.plan) for _t, e in sw.events]
                raise SystemExit(f"switch {i}: no adaptation event; seen: {seen}") from None
            with sw.lock:
                arrived = next(t for t, e in sw.events[before:] if e is ev)
                crossed = sw.crossed
            assert ev.outcome == "ok", ev
            assert crossed is not None
            e2e.append((arrived - crossed) * 1e3)
            execute.append(ev.durations.get("execute", 0.0) * 1e3)
    finally:
        sw.close()
    stats("lifecycle switch e2e: sample -> event", e2e)
    stats("lifecycle switch e2e: Executor execute", execute)


def through_engines(switches: int, samples: int) -> None:
    types = TypeRegistry()
    types.register_folder(str(ROVER / "interfaces"))
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        types.export(work / "msgs", TYPES)
        rover = Rover(work)
        try:
            through_monitor(rover, work / "msgs", samples)
            lifecycle_end_to_end(rover, switches)
        finally:
            rover.stop()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--switches", type=int, default=200)
    ap.add_argument("--restarts", type=int, default=10)
    ap.add_argument("--engine-switches", type=int, default=20,
                    help="lifecycle switches through the engines (5.)")
    ap.add_argument("--engines", action=argparse.BooleanOptionalAction, default=True,
                    help="run 4. and 5. (rra up of ros2_rover)")
    ap.add_argument("--only-engines", action="store_true", help="run only 4. and 5.")
    args = ap.parse_args()
    if not args.only_engines:
        direct(args)
    if args.engines or args.only_engines:
        through_engines(args.engine_switches, args.samples)


def direct(args: argparse.Namespace) -> None:
    """1 to 3: the library's own path, no engines."""
    port = free_port()
    ep = f"tcp/127.0.0.1:{port}"
    router = zenoh.open(BusConfig(mode="router", listen=[ep], connect=[]).to_zenoh())
    sessions = [zenoh.open(BusConfig(connect=[ep]).to_zenoh()) for _ in range(3)]
    types = TypeRegistry()
    ctx, ctx2 = Ros2Context(sessions[0], types), Ros2Context(sessions[1], types)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            msg_dir = Path(tmp)
            types.export(msg_dir, TYPES)
            sample_to_measurement(port, msg_dir, ctx, sessions[2], args.samples)
            lifecycle(port, msg_dir, ctx, ctx2, args.switches)
            relay_switch(ctx, ctx2, args.switches)
            restart_rewire(port, msg_dir, ctx, args.restarts)
    finally:
        ctx.close()
        ctx2.close()
        for s in sessions:
            s.close()
        router.close()


if __name__ == "__main__":
    main()
