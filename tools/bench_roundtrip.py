"""Node SDK round trip vs raw zenoh-python round trip in one run (goal: ratio <= 1.15).

Layout (loopback, a free port, multicast scouting off, the same `BusConfig` session settings
for every process): this process is the *pinger* and listens on the hub endpoint; three *echo*
processes connect to it, all started before measuring and all kept running:

- **raw**: a plain zenoh-python process (this script with ``--echo raw``): a callback
  subscriber on ``rra/bench/data/raw/in`` that republishes the sample's payload and attachment
  unchanged on ``rra/bench/data/raw/out`` (publisher with ``CongestionControl.BLOCK``,
  express);
- **floor**: the same plain zenoh-python process (``--echo floor``), doing in one function
  what any Python node must do per sample and nothing else: read the sender's stamp from the
  attachment, check the size, decode the msgpack map, encode it again and publish it with a
  new send-time stamp. No SDK code: the least a node written in Python can cost;
- **sdk**: a real node process, ``python -m rra_agent.node`` with ``RRA_NODE_SPEC`` /
  ``RRA_BUS_CONFIG``, running `rra_agent.nodes.generic.Relay` (``--impl`` to change) with
  port ``in`` on ``rra/bench/data/sdk/in`` and ``out`` on ``rra/bench/data/sdk/out``. The
  SDK decodes the msgpack map, the node copies it and adds two fields, and the SDK encodes
  it and publishes it with a send-time attachment.

The pinger sends the same ~100-byte msgpack map (with an 8-byte send-time attachment) in all
modes, waits for the echo, checks its ``seq`` and sends the next one: one round trip at a
time, timed with `time.perf_counter` from just before ``put`` to the reply's arrival in the
pinger's callback queue. Before measuring it waits for each echo's liveliness token (ready)
and ``publisher.matching_status.matching``, then warms up. The modes are measured in
interleaved blocks (raw, floor, sdk, sdk, floor, raw, ...), each block after a few
unmeasured round trips, so a change of machine load affects all alike.

The pinger here is plain zenoh (the SDK's echo is measured, not a node at both ends):
``--node-to-node RUNS`` measures instead a node pinging a node, both rra-agent nodes under
``rra up`` (`tools/bench_peer.py`'s round trip, rra-agent's side; that tool puts dora-rs's
beside it).

Run: ``.venv/bin/python tools/bench_roundtrip.py [--n N] [--layouts split,same]``. Prints
median and p99 (µs) per CPU layout and mode; per layout the medians of SDK, raw and floor,
the ratio SDK / raw with PASS if <= 1.15 (exit status 1 if any layout FAILs), and the SDK's
overhead in µs split into the floor's share and the rest (the SDK's and the node's own
work). Last, the same three callbacks timed in this process with hot caches (no bus: a
sample object made here, a publisher nobody listens to), per sample.

CPU placement dominates the figures on a 2-core machine, and left to the scheduler each echo
process lands where it happens to (so the modes need not even share a layout: a single
unpinned run gave SDK/raw = 0.78). So the same processes are measured in fixed layouts, one
after the other, by setting the CPU affinity of every thread of every process:

- ``split``: the pinger on one CPU, the echoes on another (cross-CPU wake-ups);
- ``same``: every process on one CPU (the SDK's extra Python work shows fully, the worst
  case for the ratio);
- ``none``: all CPUs, the scheduler decides (as deployed; varies from run to run).

Reading ``same``: on one CPU a round trip costs the sum of the CPU time of every thread it
wakes (pinger and echo), and a few µs of Python work in the echo's callback cost several
times as much there: the callback thread, having run longer than the raw echo's, is
preempted by Zenoh's sending thread at ``put`` instead of finishing first, and the extra
context switches land on both processes. The in-process figures give the work itself.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import itertools
import os
import queue
import signal
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import msgspec  # noqa: E402
import zenoh  # noqa: E402
from _benchutil import Stats, median, p99, print_table  # noqa: E402

from rra_agent.bus import messages as m  # noqa: E402
from rra_agent.bus.config import ENV_VAR as BUS_ENV  # noqa: E402
from rra_agent.bus.config import BusConfig, free_port  # noqa: E402
from rra_agent.bus.counters import MAX_PAYLOAD  # noqa: E402
from rra_agent.bus.keys import Keys  # noqa: E402
from rra_agent.node.process import SPEC_ENV  # noqa: E402

TARGET = 1.15
SYSTEM = "bench"
HOST = "bench"
KEYS = Keys(SYSTEM)
RAW_IN, RAW_OUT = KEYS.data("raw/in"), KEYS.data("raw/out")
FLOOR_IN, FLOOR_OUT = KEYS.data("floor/in"), KEYS.data("floor/out")
SDK_IN, SDK_OUT = KEYS.data("sdk/in"), KEYS.data("sdk/out")
RAW_NAME, FLOOR_NAME, SDK_NAME = "raw-echo", "floor-echo", "sdk-echo"
RAW, FLOOR, SDK = "raw zenoh-python", "floor: zenoh-python + msgpack", "Node SDK"
DEFAULT_IMPL = "rra_agent.nodes.generic.Relay"

_ENC = msgspec.msgpack.Encoder()
_DEC = msgspec.msgpack.Decoder()


def make_payload(seq: int) -> bytes:
    """A ~100-byte msgpack map, like a small sensor sample."""
    return _ENC.encode(
        {
            "seq": seq,
            "stamp": 1.7e9 + seq * 1e-3,
            "frame": "base_link",
            "position": [0.125, -1.5, 2.75],
            "value": 41.5,
            "ok": True,
        }
    )


# ---- the plain zenoh-python echoes -------------------------------------------------------
EchoFactory = Callable[[zenoh.Publisher], Callable[[zenoh.Sample], None]]


def raw_echo(pub: zenoh.Publisher) -> Callable[[zenoh.Sample], None]:
    """Republish every sample's payload and attachment unchanged."""

    def echo(sample: zenoh.Sample) -> None:
        pub.put(sample.payload, attachment=sample.attachment)

    return echo


def floor_echo(pub: zenoh.Publisher) -> Callable[[zenoh.Sample], None]:
    """What any Python node must do per sample, in one function: the sender's stamp, the size
    check, decode, encode, a new send-time stamp (as the SDK does, without its code)."""
    stamp = struct.Struct("<d")
    pack, unpack, now = stamp.pack, stamp.unpack, time.time
    dec, enc, limit = msgspec.msgpack.Decoder(), msgspec.msgpack.Encoder(), MAX_PAYLOAD["data"]
    last: list[float | None] = [None]  # the sender's stamp, kept as a node would see it

    def echo(sample: zenoh.Sample) -> None:
        att = sample.attachment
        last[0] = unpack(att.to_bytes())[0] if att is not None and len(att) == 8 else None
        payload = sample.payload.to_bytes()
        if len(payload) > limit:
            return
        try:
            data = dec.decode(payload)
        except msgspec.DecodeError:
            return
        if isinstance(data, dict):
            pub.put(enc.encode(data), attachment=pack(now()))

    return echo


ECHOES: dict[str, EchoFactory] = {"raw": raw_echo, "floor": floor_echo}


def run_echo(kind: str, key_in: str, key_out: str, name: str) -> int:
    """A plain zenoh-python echo process (``kind``: raw or floor), until signalled."""
    stop = threading.Event()

    def on_signal(_signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    session = zenoh.open(BusConfig.from_env().to_zenoh())
    try:
        pub = session.declare_publisher(
            key_out, congestion_control=zenoh.CongestionControl.BLOCK, express=True
        )
        sub = session.declare_subscriber(key_in, ECHOES[kind](pub))
        token = session.liveliness().declare_token(KEYS.alive(HOST, name))
        while not stop.wait(1.0):  # a timed wait: the signal handler runs between waits
            pass
        token.undeclare()
        sub.undeclare()
        pub.undeclare()
    finally:
        session.close()
    return 0


# ---- child processes ----------------------------------------------------------------------
def _die_with_parent() -> None:  # between fork and exec: the echo dies if the pinger does
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


LAYOUTS = ("split", "same", "none")


def cpu_layout(name: str, cpus: list[int]) -> tuple[set[int], set[int]]:
    """CPUs of (the pinger, the echoes) in layout ``name``, out of ``cpus``."""
    if name == "same":
        return {cpus[-1]}, {cpus[-1]}
    if name == "split":
        if len(cpus) < 2:
            raise SystemExit("layout 'split' needs two CPUs")
        return {cpus[0]}, {cpus[1]}
    return set(cpus), set(cpus)


def pin(pid: int, cpus: set[int]) -> None:
    """Set the CPU affinity of every thread of process ``pid`` (threads created later inherit it
    from their creator)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(ProcessLookupError, FileNotFoundError):  # a thread that ended
            os.sched_setaffinity(int(tid), cpus)


@dataclass
class Child:
    name: str
    proc: subprocess.Popen[bytes]
    log: Path

    def tail(self, lines: int = 20) -> str:
        text = self.log.read_text(errors="replace") if self.log.exists() else ""
        return "\n".join(text.splitlines()[-lines:])


def spawn(name: str, args: list[str], env: dict[str, str], log_dir: Path) -> Child:
    log = log_dir / f"{name}.log"
    with log.open("wb") as f:
        proc = subprocess.Popen(
            args,
            env={**os.environ, **env},
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
            stdout=f,
            stderr=subprocess.STDOUT,
            preexec_fn=_die_with_parent if sys.platform == "linux" else None,
        )
    return Child(name, proc, log)


def stop_children(children: list[Child], timeout: float = 5.0) -> list[str]:
    """SIGINT every child, wait, SIGKILL on timeout; problems as text (empty: all clean)."""
    problems = []
    for c in children:
        if c.proc.poll() is None:
            c.proc.send_signal(signal.SIGINT)
    for c in children:
        try:
            rc = c.proc.wait(timeout)
        except subprocess.TimeoutExpired:
            c.proc.kill()
            c.proc.wait()
            problems.append(f"{c.name} ignored SIGINT for {timeout:g} s and was killed")
            continue
        if rc != 0:
            problems.append(f"{c.name} exited with status {rc}:\n{c.tail()}")
    return problems


# ---- the pinger ---------------------------------------------------------------------------
@dataclass
class Channel:
    """The pinger's side of one echo: a publisher to it and a queue of what comes back."""

    name: str
    pub: zenoh.Publisher
    replies: queue.SimpleQueue[bytes] = field(default_factory=queue.SimpleQueue)
    sub: Any = None

    def on_reply(self, sample: zenoh.Sample) -> None:
        self.replies.put(sample.payload.to_bytes())

    def once(self, seq: int, timeout: float) -> float:
        """One round trip; its duration in seconds. Raises on a timeout or a wrong reply."""
        payload = make_payload(seq)
        attachment = m.pack_stamp(time.time())
        t0 = time.perf_counter()
        self.pub.put(payload, attachment=attachment)
        try:
            reply = self.replies.get(timeout=timeout)
        except queue.Empty:
            raise TimeoutError(f"{self.name}: no echo of seq {seq} within {timeout:g} s") from None
        dt = time.perf_counter() - t0
        got = _DEC.decode(reply).get("seq")
        if got != seq:
            raise RuntimeError(f"{self.name}: sent seq {seq}, got {got}")
        return dt

    def settle(self, seq: int, timeout: float, tries: int = 20) -> None:
        """Ping until an echo comes back (the echo's publisher may not match us yet)."""
        for _ in range(tries):
            self.pub.put(make_payload(seq), attachment=m.pack_stamp(time.time()))
            deadline = time.monotonic() + timeout
            while (left := deadline - time.monotonic()) > 0:
                try:
                    reply = self.replies.get(timeout=left)
                except queue.Empty:
                    break
                if _DEC.decode(reply).get("seq") == seq:
                    self.drain()
                    return
            seq -= 1
        raise TimeoutError(f"{self.name}: no echo after {tries} tries")

    def drain(self) -> None:
        with contextlib.suppress(queue.Empty):
            while True:
                self.replies.get_nowait()


def wait_for(predicate: Callable[[], Any], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.002)


def measure(
    channels: list[Channel],
    n: int,
    block: int,
    warmup: int,
    per_block_warmup: int,
    timeout: float,
    seq: Iterator[int],
) -> dict[str, list[float]]:
    """Warm up, then ``n`` timed round trips per channel in interleaved blocks."""
    samples: dict[str, list[float]] = {ch.name: [] for ch in channels}
    for ch in channels:
        ch.settle(-next(seq), timeout=0.5)
        for _ in range(warmup):
            ch.once(next(seq), timeout)
    gc.collect()
    gc.disable()  # the pinger's own collections are no part of the round trip
    try:
        done = 0
        b = 0
        while done < n:
            size = min(block, n - done)
            for ch in channels if b % 2 == 0 else channels[::-1]:
                for _ in range(per_block_warmup):
                    ch.once(next(seq), timeout)
                out = samples[ch.name]
                for _ in range(size):
                    out.append(ch.once(next(seq), timeout))
            done += size
            b += 1
    finally:
        gc.enable()
    return samples


def node_spec(impl: str) -> m.NodeSpec:
    return m.NodeSpec(
        system=SYSTEM,
        name=SDK_NAME,
        host=HOST,
        implementation=impl,
        ports={
            "in": m.PortSpec(direction="subscribe", type="Bench", keys=[SDK_IN]),
            "out": m.PortSpec(direction="publish", type="Bench", keys=[SDK_OUT]),
        },
    )


def start_echoes(impl: str, env: dict[str, str], log_dir: Path) -> list[Child]:
    py = sys.executable
    me = str(Path(__file__).resolve())
    spec = {SPEC_ENV: msgspec.json.encode(node_spec(impl)).decode()}
    return [
        spawn(RAW_NAME, [py, me, "--echo", "raw", RAW_IN, RAW_OUT, RAW_NAME], env, log_dir),
        spawn(
            FLOOR_NAME, [py, me, "--echo", "floor", FLOOR_IN, FLOOR_OUT, FLOOR_NAME], env, log_dir
        ),
        spawn(SDK_NAME, [py, "-m", "rra_agent.node"], {**env, **spec}, log_dir),
    ]


# ---- the same callbacks in this process -----------------------------------------------------
@dataclass
class _Sample:
    """What the callbacks read of a `zenoh.Sample`."""

    payload: zenoh.ZBytes
    attachment: zenoh.ZBytes


def per_sample_us(fn: Callable[[Any], None], sample: Any, n: int = 20000, reps: int = 15) -> float:
    """The best of ``reps`` mean durations of ``fn(sample)`` over ``n`` calls, µs."""
    for _ in range(n // 10):
        fn(sample)
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        for _ in range(n):
            fn(sample)
        best = min(best, (time.perf_counter() - t0) / n)
    return best * 1e6


def in_process(session: zenoh.Session, impl: str, n: int = 20000) -> dict[str, float]:
    """Hot-cache cost per sample of each mode's callback (the SDK's: `ZenohTransport`'s, with
    a `NodeCore` running ``impl``), each publishing on a key nobody listens to."""
    from rra_agent.node.core import NodeCore
    from rra_agent.node.loading import load_node_class
    from rra_agent.node.runtime import ZenohTransport

    sample = _Sample(zenoh.ZBytes(make_payload(1)), zenoh.ZBytes(m.pack_stamp(time.time())))
    key = KEYS.data("inproc/out")
    pub = session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK, express=True
    )
    transport = ZenohTransport(session)
    spec = node_spec(impl)
    spec.ports["out"] = m.PortSpec(direction="publish", type="Bench", keys=[key])
    core = NodeCore(spec, load_node_class(impl), transport)
    transport.rebind("out", "publish", [key])
    core.start()
    transport.core = core
    try:
        return {
            RAW: per_sample_us(raw_echo(pub), sample, n),
            FLOOR: per_sample_us(floor_echo(pub), sample, n),
            SDK: per_sample_us(transport._on_sample("in", SDK_IN), sample, n),
        }
    finally:
        core.stop()
        transport.close()
        pub.undeclare()


def report(
    args: argparse.Namespace,
    results: dict[str, dict[str, Stats]],
    cpus: list[int],
    hot: dict[str, float],
) -> int:
    print(
        f"round trip of a {len(make_payload(0))}-byte msgpack map + 8-byte attachment, "
        f"pinger <-> echo process on loopback; n={args.n} per mode and layout, interleaved in "
        f"blocks of {args.block}, after {args.warmup} warm-up round trips; "
        f"SDK echo: {args.impl}"
    )
    rows = []
    for layout, stats in results.items():
        pinger, echoes = cpu_layout(layout, cpus)
        where = f"{layout}: pinger CPU {sorted(pinger)}, echoes CPU {sorted(echoes)}"
        for mode, st in stats.items():
            rows.append([where, mode, st.median_us, st.p99_us, st.min_us, st.mean_us, st.max_us])
            where = ""
    print_table(["CPU layout", "mode", "median µs", "p99 µs", "min µs", "mean µs", "max µs"], rows)
    failed = False
    for layout, stats in results.items():
        raw, floor, sdk = stats[RAW].median_us, stats[FLOOR].median_us, stats[SDK].median_us
        ratio, p99s = sdk / raw, stats[SDK].p99_us / stats[RAW].p99_us
        verdict = "PASS" if ratio <= TARGET else "FAIL"
        failed |= verdict == "FAIL"
        print(
            f"{layout:>5}: SDK {sdk:.1f} µs, raw {raw:.1f} µs, floor {floor:.1f} µs (medians); "
            f"SDK / raw {ratio:.3f} (goal <= {TARGET}): {verdict}; SDK overhead "
            f"{sdk - raw:.1f} µs per round trip = floor {floor - raw:.1f} µs (floor / raw "
            f"{floor / raw:.3f}) + SDK and node code {sdk - floor:.1f} µs (SDK / floor "
            f"{sdk / floor:.3f}); ratio of p99s SDK / raw {p99s:.3f}"
        )
    print(
        "in this process, hot caches, per sample: "
        + ", ".join(f"{mode} {us:.2f} µs" for mode, us in hot.items())
    )
    return 1 if failed else 0


def bench(args: argparse.Namespace) -> int:
    cpus = sorted(os.sched_getaffinity(0))
    layouts = [x.strip() for x in args.layouts.split(",") if x.strip()]
    for layout in layouts:
        if layout not in LAYOUTS:
            raise SystemExit(f"unknown layout {layout!r}: choose from {', '.join(LAYOUTS)}")
        cpu_layout(layout, cpus)  # fails early if the machine cannot do it
    hub = f"tcp/127.0.0.1:{free_port()}"
    child_bus = BusConfig(connect=[hub], multicast=False, lease_ms=500)
    env = {BUS_ENV: child_bus.to_env(), "PYTHONUNBUFFERED": "1"}
    log_dir = Path(tempfile.mkdtemp(prefix="bench_roundtrip-"))
    children: list[Child] = []
    session = zenoh.open(child_bus.host_router(hub=True).to_zenoh())
    try:
        alive: set[str] = set()

        def on_alive(sample: zenoh.Sample) -> None:
            parsed = KEYS.parse_alive(str(sample.key_expr))
            if parsed is not None and sample.kind == zenoh.SampleKind.PUT:
                alive.add(parsed[1])

        alive_sub = session.liveliness().declare_subscriber(KEYS.alive_all, on_alive, history=True)
        channels = []
        for name, key_in, key_out in (
            (RAW, RAW_IN, RAW_OUT),
            (FLOOR, FLOOR_IN, FLOOR_OUT),
            (SDK, SDK_IN, SDK_OUT),
        ):
            pub = session.declare_publisher(
                key_in, congestion_control=zenoh.CongestionControl.BLOCK, express=True
            )
            ch = Channel(name, pub)
            ch.sub = session.declare_subscriber(key_out, ch.on_reply)
            channels.append(ch)

        children = start_echoes(args.impl, env, log_dir)
        for child in children:
            try:
                wait_for(
                    lambda c=child: c.name in alive or c.proc.poll() is not None, 30, child.name
                )
            except TimeoutError:
                raise TimeoutError(f"{child.name} not ready:\n{child.tail()}") from None
            if child.proc.poll() is not None:
                raise RuntimeError(f"{child.name} exited early:\n{child.tail()}")
        for ch in channels:
            wait_for(lambda c=ch: c.pub.matching_status.matching, 10, f"{ch.name} subscriber")

        seq = itertools.count(1)
        results: dict[str, dict[str, Stats]] = {}
        for layout in layouts:
            pinger_cpus, echo_cpus = cpu_layout(layout, cpus)
            pin(os.getpid(), pinger_cpus)
            for child in children:
                pin(child.proc.pid, echo_cpus)
            samples = measure(
                channels, args.n, args.block, args.warmup, args.block_warmup, args.timeout, seq
            )
            results[layout] = {name: Stats.of(s) for name, s in samples.items()}
        alive_sub.undeclare()
        pin(os.getpid(), set(cpus))
        return report(args, results, cpus, in_process(session, args.impl))
    finally:
        problems = stop_children(children)
        session.close()
        for p in problems:
            print(f"warning: {p}", file=sys.stderr)
        if not problems and not args.keep_logs:
            for f in log_dir.iterdir():
                f.unlink()
            log_dir.rmdir()
        else:
            print(f"child logs kept in {log_dir}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=5000, help="round trips per mode and layout")
    parser.add_argument("--warmup", type=int, default=500, help="warm-up round trips per mode")
    parser.add_argument("--block", type=int, default=250, help="round trips per block (250)")
    parser.add_argument(
        "--block-warmup", type=int, default=5, help="unmeasured round trips starting each block"
    )
    parser.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for an echo")
    parser.add_argument(
        "--layouts",
        default="split,same",
        help=f"CPU layouts to measure, in order, from {', '.join(LAYOUTS)} (default split,same)",
    )
    parser.add_argument("--keep-logs", action="store_true", help="keep the echoes' logs")
    parser.add_argument("--impl", default=DEFAULT_IMPL, help=f"SDK echo node ({DEFAULT_IMPL})")
    parser.add_argument(
        "--node-to-node",
        type=int,
        metavar="RUNS",
        default=0,
        help="instead: an rra node pinging an rra node under rra up, RUNS fresh systems",
    )
    parser.add_argument(
        "--echo", nargs=4, metavar=("KIND", "IN", "OUT", "NAME"), help=argparse.SUPPRESS
    )
    args = parser.parse_args(argv)
    if args.echo:
        return run_echo(*args.echo)
    if args.n < 1 or args.block < 1:
        parser.error("--n and --block must be positive")
    if args.node_to_node:
        return node_to_node(args.node_to_node, args.n, args.warmup)
    return bench(args)


def node_to_node(runs: int, n: int, warm: int) -> int:
    """Node to node: `tools/bench_peer.py`'s round trip, rra-agent's side only (a Pinger node
    and an Echo node of ``tools/peer_nodes.py`` under ``rra up``, a fresh system per run)."""
    import bench_peer

    samples: list[float] = []
    for _ in range(runs):
        samples += bench_peer.roundtrip("rra", n, warm)
    print(f"node to node (rra up, {runs} runs of {n}): median {median(samples):.1f} µs, "
          f"p99 {p99(samples):.1f} µs (goal: p99 <= dora's, tools/bench_peer.py)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
