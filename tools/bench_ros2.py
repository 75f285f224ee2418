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
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgspec
import zenoh

from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.ros2.bridge import TopicField
from rra_agent.ros2.endpoint import Received, Ros2Context
from rra_agent.ros2.params import LifecycleClient, LifecycleServer
from rra_agent.ros2.relay import Relay
from rra_agent.ros2.types import TypeRegistry

PEER = Path(__file__).resolve().parent.parent / "tests" / "data" / "ros2" / "sdk_peer.py"
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--switches", type=int, default=200)
    ap.add_argument("--restarts", type=int, default=10)
    args = ap.parse_args()
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
