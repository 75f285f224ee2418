"""Zenoh round trip between two client sessions: an echo and a pinger.

- ``zping.py echo --connect EP --name NAME``: a client session of the router at ``EP``; a
  callback subscriber on ``rra/zping/<NAME>/ping`` republishes every sample (payload
  unchanged) on ``rra/zping/<NAME>/pong``. Prints ``zping echo NAME ready`` and runs until
  SIGINT/SIGTERM.
- ``zping.py ping --connect EP --name NAME --n N``: publishes a small payload with a sequence
  number on ``.../ping`` and waits for the matching ``.../pong`` (one at a time), after
  warming up until the echo answers (``--ready-timeout``); prints one JSON line
  ``{"rtt": [seconds...], "lost": k}`` and exits 0.

Publishers are reliable, ``CongestionControl.BLOCK`` and express (unbatched), as the Node
SDK's data publishers. Sessions come from `rra_agent.bus.config.BusConfig` (client mode,
multicast off) and are closed in ``finally``; replies arrive in a callback that only hands
them to a `queue.SimpleQueue` (no thread blocked in a Zenoh ``recv`` at exit).

Used by tests/test_netns.py and tools/bench_hosts.py inside network namespaces.
"""

from __future__ import annotations

import argparse
import json
import queue
import signal
import struct
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh

from rra_agent.bus.config import BusConfig

_SEQ = struct.Struct("<Q")
PAD = b"\x00" * 92  # ~100-byte samples


def keys(name: str) -> tuple[str, str]:
    return f"rra/zping/{name}/ping", f"rra/zping/{name}/pong"


def session(connect: str) -> zenoh.Session:
    return zenoh.open(BusConfig(mode="client", connect=[connect]).to_zenoh())


def publisher(s: zenoh.Session, key: str) -> zenoh.Publisher:
    return s.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK, express=True)


def run_echo(connect: str, name: str) -> int:
    stop = threading.Event()

    def on_signal(_signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    ping, pong = keys(name)
    s = session(connect)
    try:
        pub = publisher(s, pong)
        sub = s.declare_subscriber(ping, lambda sample: pub.put(sample.payload))
        print(f"zping echo {name} ready", flush=True)
        while not stop.wait(0.5):  # a timed wait: the signal handler runs between waits
            pass
        sub.undeclare()
        pub.undeclare()
    finally:
        s.close()
    return 0


def run_ping(connect: str, name: str, n: int, timeout: float, ready_timeout: float) -> int:
    ping, pong = keys(name)
    replies: queue.SimpleQueue[tuple[int, float]] = queue.SimpleQueue()

    def on_pong(sample: zenoh.Sample) -> None:
        t = time.perf_counter()
        replies.put((_SEQ.unpack_from(sample.payload.to_bytes())[0], t))

    s = session(connect)
    rtts: list[float] = []
    lost = 0
    try:
        sub = s.declare_subscriber(pong, on_pong)
        pub = publisher(s, ping)
        seq = 0

        def once(wait: float) -> float | None:
            nonlocal seq
            seq += 1
            t0 = time.perf_counter()
            pub.put(_SEQ.pack(seq) + PAD)
            end = t0 + wait
            while True:
                left = end - time.perf_counter()
                if left <= 0:
                    return None
                try:
                    got, t1 = replies.get(timeout=left)
                except queue.Empty:
                    return None
                if got == seq:
                    return t1 - t0

        # Warm up: until the echo answers (routes through the routers are in place), then a
        # few unmeasured round trips.
        deadline = time.monotonic() + ready_timeout
        while once(0.5) is None:
            if time.monotonic() >= deadline:
                print(json.dumps({"error": f"no echo {name!r} within {ready_timeout:g} s"}))
                return 1
        for _ in range(5):
            once(timeout)
        for _ in range(n):
            rtt = once(timeout)
            if rtt is None:
                lost += 1
            else:
                rtts.append(rtt)
        sub.undeclare()
        pub.undeclare()
    finally:
        s.close()
    print(json.dumps({"rtt": rtts, "lost": lost}), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("mode", choices=("echo", "ping"))
    p.add_argument("--connect", required=True, help="the router, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--name", default="echo", help="the echo's name (its key expressions)")
    p.add_argument("--n", type=int, default=100, help="round trips to measure")
    p.add_argument("--timeout", type=float, default=2.0, help="per round trip (s)")
    p.add_argument("--ready-timeout", type=float, default=20.0, help="for the echo (s)")
    a = p.parse_args(argv)
    if a.mode == "echo":
        return run_echo(a.connect, a.name)
    return run_ping(a.connect, a.name, a.n, a.timeout, a.ready_timeout)


if __name__ == "__main__":
    sys.exit(main())
