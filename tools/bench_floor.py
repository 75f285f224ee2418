"""The floor of inter-process latency on this machine: raw zenoh-python, no rra-agent code.

A ping-pong round trip (one ~100-byte message in flight at a time) between this process (the
*pinger*) and one *echo* child process (this script with ``--echo MODE ...``), so that other
figures (a Node SDK round trip, a controller switch of ~3 cross-process hops and 2
request/reply round trips) can be compared to what Zenoh itself costs. Layouts:

- ``pipe``: no Zenoh at all, two OS pipes; the pinger writes and blocks in ``read``, the echo
  reads and writes back (the kernel's own wake-up floor, with Python on both ends);
- ``peer-to-peer``: two sessions in mode ``peer``, the echo listening on
  ``tcp/127.0.0.1:<free port>``, the pinger connecting to it;
- ``via router``: a third process is a Zenoh router (a free loopback port); pinger and echo
  are both clients of it (how rra-agent deploys: one router per host);
- ``peer-to-peer, shm`` and ``via router, shm``: the same with Zenoh shared memory
  (``transport/shared_memory/enabled: true``; every payload, both ways, allocated from a
  ``zenoh.shm.ShmProvider``; the allocation and copy are inside the round trip). Skipped,
  with the reason, if this zenoh-python has no SHM.

In every Zenoh layout the echo counts the pings that arrived as SHM buffers
(``ZBytes.as_shm()``) and the pinger the pongs; the counts are printed (all in the shm layouts,
none in the others, or a warning). A zenoh-python process that used SHM can leave a
``/dev/shm/<id>.zenoh`` segment behind; the ones of this run that no process holds are
removed at the end (what Zenoh's own orphan sweep would do at the next SHM start).

The plain Zenoh layouts set ``transport/shared_memory/enabled: false`` (Zenoh's default is
``true``, but a payload made of ``bytes`` below the 3 KiB ``transport_optimization``
threshold never goes through SHM anyway). Multicast scouting is off everywhere. Publishers are
reliable (``CongestionControl.BLOCK``) and express. A round trip is timed with
`time.perf_counter` from just before ``put`` to the pong's arrival in the pinger's subscriber
callback (which hands it to the main thread through a `queue.SimpleQueue`); for ``pipe``, from
just before ``write`` to the return of ``read``.

Each layout is measured in two CPU placements (the affinity of every thread of every process,
set after the sessions are open): ``split``, the pinger on CPU 0 and the echo and the router on
CPU 1 (cross-CPU wake-ups), and ``same``, every process on CPU 0. Before measuring, the
pinger waits for ``publisher.matching_status.matching`` and an answered ping, then warms up
(``--warmup``, 200 round trips per placement).

Run: ``.venv/bin/python tools/bench_floor.py [--n 3000] [--load]``. ``--load`` runs
``tools/cpuhog.py`` (one busy loop per core) during the measurements. Prints median, p99 and
min of the round trip (µs) per layout and placement, and a one-way estimate (median / 2).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import gc
import importlib.metadata
import json
import os
import queue
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

TOOLS = Path(__file__).resolve().parent
ROOT = TOOLS.parent
sys.path.insert(0, str(TOOLS))
sys.path.insert(0, str(ROOT))

import zenoh  # noqa: E402
from _benchutil import Stats, print_table  # noqa: E402

from rra_agent.bus.config import free_port  # noqa: E402

PING_KEY, PONG_KEY = "rra/bench/floor/ping", "rra/bench/floor/pong"
SIZE = 100  # bytes per message: an 8-byte sequence number and padding
_SEQ = struct.Struct("<q")
PAD = b"\x00" * (SIZE - _SEQ.size)
SHM_POOL = 1 << 20  # bytes of each process's SHM pool
READY = "ready"
PLACEMENTS = ("split", "same")


@dataclass(frozen=True)
class Layout:
    name: str
    kind: str  # "pipe", "peer" or "router"
    shm: bool = False


LAYOUTS = (
    Layout("pipe (no zenoh)", "pipe"),
    Layout("peer-to-peer", "peer"),
    Layout("via router", "router"),
    Layout("peer-to-peer, shm", "peer", shm=True),
    Layout("via router, shm", "router", shm=True),
)


# ---- sessions and SHM -----------------------------------------------------------------------
def zenoh_config(
    mode: str, *, listen: list[str] | None = None, connect: list[str] | None = None, shm: bool
) -> zenoh.Config:
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("listen/endpoints", json.dumps(listen or []))
    c.insert_json5("connect/endpoints", json.dumps(connect or []))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/delay", "0")
    c.insert_json5("transport/shared_memory/enabled", json.dumps(shm))
    return c


def publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    return session.declare_publisher(
        key, congestion_control=zenoh.CongestionControl.BLOCK, express=True
    )


def shm_support() -> tuple[Any, str]:
    """(the ``zenoh.shm`` module or None, a one-line explanation)."""
    version = importlib.metadata.version("eclipse-zenoh")
    try:
        import zenoh.shm as zshm
    except ImportError as e:
        return None, f"zenoh-python {version}: no zenoh.shm in this build ({e})".replace("\n", " ")
    if not hasattr(zshm, "ShmProvider"):
        return None, f"zenoh-python {version}: no ShmProvider in this build"
    try:
        default = zenoh.Config().get_json("transport/shared_memory/enabled")
        zshm.ShmProvider.default_backend(4096).alloc(SIZE)
    except (zenoh.ZError, AttributeError) as e:
        return None, f"zenoh-python {version}: SHM present but unusable: {e}"
    return zshm, (
        f"zenoh-python {version}: zenoh.shm.ShmProvider present and allocates "
        f"(transport/shared_memory/enabled defaults to {default})"
    )


class Sender:
    """Puts a payload as plain bytes, or copied into a buffer of an SHM provider."""

    def __init__(self, pub: zenoh.Publisher, shm: bool) -> None:
        self.pub = pub
        self.provider = None
        if shm:
            import zenoh.shm as zshm

            self.provider = zshm.ShmProvider.default_backend(SHM_POOL)
            self.policy = zshm.GarbageCollect()

    def put(self, payload: bytes) -> None:
        if self.provider is None:
            self.pub.put(payload)
            return
        buf = self.provider.alloc(len(payload), self.policy)
        buf[0 : len(payload)] = payload
        self.pub.put(buf)


# ---- child processes ------------------------------------------------------------------------
def die_with_parent() -> None:
    """The child gets SIGKILL if the pinger dies (even SIGKILLed): no orphan."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG


def stop_event() -> threading.Event:
    stop = threading.Event()

    def on_signal(_signum: int, _frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    return stop


def wait_stop(stop: threading.Event) -> None:
    while not stop.wait(0.5):  # a timed wait: the signal handler runs between waits
        pass


def run_pipe_echo(rfd: int, wfd: int) -> int:
    print(READY, flush=True)
    while data := os.read(rfd, 4096):  # until the pinger closes its end
        os.write(wfd, data)
    return 0


def run_router(endpoint: str, shm: bool) -> int:
    stop = stop_event()
    session = zenoh.open(zenoh_config("router", listen=[endpoint], shm=shm))
    try:
        print(READY, flush=True)
        wait_stop(stop)
    finally:
        session.close()
    return 0


def run_zenoh_echo(mode: str, endpoint: str, shm: bool) -> int:
    """Republish every ping as a pong (copied into SHM with ``shm``), until signalled."""
    stop = stop_event()
    if mode == "peer":
        config = zenoh_config("peer", listen=[endpoint], shm=shm)
    else:
        config = zenoh_config("client", connect=[endpoint], shm=shm)
    session = zenoh.open(config)
    counts = {"pings": 0, "shm": 0}
    sub = pub = None
    try:
        pub = publisher(session, PONG_KEY)
        sender = Sender(pub, shm)

        def echo(sample: zenoh.Sample) -> None:
            payload = sample.payload
            counts["pings"] += 1
            if payload.as_shm() is not None:
                counts["shm"] += 1
            sender.put(payload.to_bytes())

        sub = session.declare_subscriber(PING_KEY, echo)
        print(READY, flush=True)
        wait_stop(stop)
    finally:
        for entity in (sub, pub):
            if entity is not None:
                entity.undeclare()
        session.close()
    print(json.dumps(counts), flush=True)
    return 0


@dataclass
class Child:
    name: str
    proc: subprocess.Popen[str]

    def wait_ready(self, timeout: float) -> None:
        """Until the child prints its ready line; raises if it exits or is too slow."""
        assert self.proc.stdout is not None
        ready, _, _ = select.select([self.proc.stdout], [], [], timeout)
        line = self.proc.stdout.readline().strip() if ready else ""
        if line != READY:
            raise RuntimeError(f"{self.name} not ready within {timeout:g} s (got {line!r})")


def spawn(name: str, args: list[str], pass_fds: tuple[int, ...] = ()) -> Child:
    proc = subprocess.Popen(
        [sys.executable, str(Path(__file__).resolve()), *args],
        cwd=ROOT,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        text=True,
        pass_fds=pass_fds,
    )
    return Child(name, proc)


def stop_children(children: list[Child], timeout: float = 5.0) -> dict[str, str]:
    """SIGTERM (in reverse order of start), wait, SIGKILL on timeout; each child's output."""
    out = {}
    for c in reversed(children):
        if c.proc.poll() is None:
            c.proc.terminate()
        try:
            text, _ = c.proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            c.proc.kill()
            text, _ = c.proc.communicate()
            print(f"warning: {c.name} ignored SIGTERM for {timeout:g} s, killed", file=sys.stderr)
        if c.proc.returncode not in (0, None):
            print(f"warning: {c.name} exited with {c.proc.returncode}", file=sys.stderr)
        out[c.name] = text or ""
    return out


# ---- CPU placement --------------------------------------------------------------------------
def placement_cpus(placement: str, cpus: list[int]) -> tuple[set[int], set[int]]:
    """CPUs of (the pinger, the echo and router) in ``placement``."""
    if placement == "same":
        return {cpus[0]}, {cpus[0]}
    return {cpus[0]}, {cpus[1]}


def pin(pid: int, cpus: set[int]) -> None:
    """Set the affinity of every thread of ``pid`` (threads created later inherit it)."""
    for tid in os.listdir(f"/proc/{pid}/task"):
        with contextlib.suppress(ProcessLookupError, FileNotFoundError):
            os.sched_setaffinity(int(tid), cpus)


# ---- measuring ------------------------------------------------------------------------------
RoundTrip = Callable[[int], float]  # seq -> seconds


def sample_round_trips(once: RoundTrip, n: int, warmup: int, seq: Iterator[int]) -> list[float]:
    for _ in range(warmup):
        once(next(seq))
    gc.collect()
    gc.disable()  # the pinger's own collections are no part of the round trip
    try:
        return [once(next(seq)) for _ in range(n)]
    finally:
        gc.enable()


def measure_placements(
    once: RoundTrip, pids: list[int], args: argparse.Namespace, seq: Iterator[int]
) -> dict[str, Stats]:
    cpus = sorted(os.sched_getaffinity(0))
    out = {}
    for placement in PLACEMENTS:
        mine, theirs = placement_cpus(placement, cpus)
        pin(os.getpid(), mine)
        for pid in pids:
            pin(pid, theirs)
        out[placement] = Stats.of(sample_round_trips(once, args.n, args.warmup, seq))
    pin(os.getpid(), set(cpus))
    return out


def bench_pipe(args: argparse.Namespace, seq: Iterator[int]) -> dict[str, Stats]:
    to_echo_r, to_echo_w = os.pipe()
    to_me_r, to_me_w = os.pipe()
    child = None
    try:
        fds = (to_echo_r, to_me_w)
        try:
            child = spawn("pipe echo", ["--echo", "pipe", str(to_echo_r), str(to_me_w)], fds)
        finally:
            os.close(to_echo_r)  # the echo's ends: only the echo holds them now
            os.close(to_me_w)
        child.wait_ready(20)

        def once(n: int) -> float:
            msg = _SEQ.pack(n) + PAD
            t0 = time.perf_counter()
            os.write(to_echo_w, msg)
            got = b""
            while len(got) < SIZE:
                chunk = os.read(to_me_r, SIZE - len(got))
                if not chunk:
                    raise RuntimeError("pipe echo closed its end")
                got += chunk
            dt = time.perf_counter() - t0
            if _SEQ.unpack_from(got)[0] != n:
                raise RuntimeError(f"sent seq {n}, got {_SEQ.unpack_from(got)[0]}")
            return dt

        once(-1)
        return measure_placements(once, [child.proc.pid], args, seq)
    finally:
        for fd in (to_echo_w, to_me_r):
            os.close(fd)  # EOF: the echo exits
        if child is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                child.proc.wait(5)
            stop_children([child])


class Pinger:
    """The pinger's session: a publisher of pings, a callback subscriber of pongs."""

    def __init__(self, config: zenoh.Config, shm: bool, timeout: float) -> None:
        self.timeout = timeout
        self.replies: queue.SimpleQueue[tuple[int, float]] = queue.SimpleQueue()
        self.pongs = self.shm_pongs = 0
        self.session = zenoh.open(config)
        self.sub: zenoh.Subscriber | None = None
        self.pub: zenoh.Publisher | None = None
        try:
            self.sub = self.session.declare_subscriber(PONG_KEY, self.on_pong)
            self.pub = publisher(self.session, PING_KEY)
            self.sender = Sender(self.pub, shm)
        except BaseException:
            self.close()
            raise

    def on_pong(self, sample: zenoh.Sample) -> None:
        t = time.perf_counter()
        payload = sample.payload
        self.pongs += 1
        if payload.as_shm() is not None:
            self.shm_pongs += 1
        self.replies.put((_SEQ.unpack_from(payload.to_bytes())[0], t))

    def once(self, seq: int) -> float:
        msg = _SEQ.pack(seq) + PAD
        t0 = time.perf_counter()
        self.sender.put(msg)
        try:
            got, t1 = self.replies.get(timeout=self.timeout)
        except queue.Empty:
            raise TimeoutError(f"no pong for seq {seq} within {self.timeout:g} s") from None
        if got != seq:
            raise RuntimeError(f"sent seq {seq}, got {got}")
        return t1 - t0

    def wait_echo(self, timeout: float) -> None:
        """Until the echo subscribes (matching) and a ping is answered."""
        assert self.pub is not None
        deadline = time.monotonic() + timeout
        while not self.pub.matching_status.matching:
            if time.monotonic() > deadline:
                raise TimeoutError("the echo's subscriber never matched")
            time.sleep(0.005)
        seq = 0
        while True:
            seq -= 1
            self.sender.put(_SEQ.pack(seq) + PAD)
            with contextlib.suppress(queue.Empty):
                while True:  # late answers of earlier tries are skipped
                    if self.replies.get(timeout=0.2)[0] == seq:
                        return
            if time.monotonic() > deadline:
                raise TimeoutError("no answer from the echo")

    def close(self) -> None:
        for entity in (self.sub, self.pub):
            if entity is not None:
                with contextlib.suppress(zenoh.ZError):
                    entity.undeclare()
        self.sub = self.pub = None
        self.session.close()


def bench_zenoh(layout: Layout, args: argparse.Namespace, seq: Iterator[int]) -> dict[str, Stats]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    flag = ["--shm"] if layout.shm else []
    children: list[Child] = []
    pinger = None
    try:
        if layout.kind == "router":
            children.append(spawn("router", ["--router", endpoint, *flag]))
            children[-1].wait_ready(20)
            echo_mode, config = "client", zenoh_config("client", connect=[endpoint], shm=layout.shm)
        else:
            echo_mode, config = "peer", zenoh_config("peer", connect=[endpoint], shm=layout.shm)
        children.append(spawn("echo", ["--echo", echo_mode, endpoint, *flag]))
        children[-1].wait_ready(20)
        pinger = Pinger(config, layout.shm, args.timeout)
        pinger.wait_echo(20)
        results = measure_placements(pinger.once, [c.proc.pid for c in children], args, seq)
    finally:
        if pinger is not None:
            pinger.close()
        outputs = stop_children(children)
    report_shm(layout, pinger, outputs.get("echo", ""))
    return results


def report_shm(layout: Layout, pinger: Pinger | None, echo_output: str) -> None:
    lines = [x for x in echo_output.splitlines() if x.startswith("{")]
    counts = json.loads(lines[-1]) if lines else {}
    pongs, shm_pongs = (pinger.pongs, pinger.shm_pongs) if pinger else (0, 0)
    expected = (counts.get("pings"), pongs) if layout.shm else (0, 0)
    ok = pongs > 0 and (counts.get("shm"), shm_pongs) == expected
    print(
        f"{layout.name}: {counts.get('shm', '?')}/{counts.get('pings', '?')} pings and "
        f"{shm_pongs}/{pongs} pongs arrived as SHM buffers"
        + ("" if ok else f"  <-- WARNING: expected {expected[0]} and {expected[1]}"),
        flush=True,
    )


def shm_files_held_by_others() -> set[str]:
    """Paths under /dev/shm that some other process holds open or mapped."""
    held: set[str] = set()
    me = str(os.getpid())
    for pid in filter(str.isdigit, os.listdir("/proc")):
        if pid == me:
            continue
        with contextlib.suppress(OSError):
            for fd in os.listdir(f"/proc/{pid}/fd"):
                with contextlib.suppress(OSError):
                    held.add(os.readlink(f"/proc/{pid}/fd/{fd}"))
        with contextlib.suppress(OSError), open(f"/proc/{pid}/maps") as maps:
            held.update(line.split()[-1] for line in maps if "/dev/shm/" in line)
    return held


def sweep_shm_orphans(since: float) -> int:
    """Remove the ``/dev/shm/*.zenoh`` segments made since ``since`` that no other process
    holds (all sessions are closed: this process no longer uses them, and an unlinked segment
    stays valid for whoever still maps it).

    A zenoh-python process that used SHM can leave its ~1.25 MiB segment behind at exit (and
    the pinger maps the echo's); Zenoh removes such orphans itself when SHM is next initialised
    in any process, which is all this does, for this run's segments."""
    held = shm_files_held_by_others()
    removed = 0
    for path in Path("/dev/shm").glob("*.zenoh"):
        with contextlib.suppress(OSError):
            if path.stat().st_ctime >= since and str(path) not in held:
                path.unlink()
                removed += 1
    return removed


# ---- main -----------------------------------------------------------------------------------
def start_load() -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, str(TOOLS / "cpuhog.py")], stdin=subprocess.DEVNULL, cwd=ROOT
    )


def stop_load(hog: subprocess.Popen[bytes]) -> None:
    hog.send_signal(signal.SIGINT)  # cpuhog kills its busy loops in a finally
    try:
        hog.wait(5)
    except subprocess.TimeoutExpired:
        hog.kill()
        hog.wait()


def print_results(results: dict[str, dict[str, Stats]], args: argparse.Namespace) -> None:
    cpus = sorted(os.sched_getaffinity(0))
    where = {p: placement_cpus(p, cpus) for p in PLACEMENTS}
    print(
        f"\nround trip of a {SIZE}-byte message, pinger <-> echo process on this host; "
        f"n={args.n} per row after {args.warmup} warm-up round trips; "
        f"load: {'ON (cpuhog.py, one busy loop per core)' if args.load else 'off'}"
    )
    print(
        "placements: "
        + "; ".join(
            f"{p}: pinger CPU {sorted(a)}, echo+router CPU {sorted(b)}"
            for p, (a, b) in where.items()
        )
    )
    rows = []
    for layout, stats in results.items():
        for placement, st in stats.items():
            rows.append([layout, placement, st.median_us, st.p99_us, st.min_us, st.median_us / 2])
    headers = ["layout", "CPUs", "median µs", "p99 µs", "min µs", "one-way µs (median/2)"]
    print_table(headers, rows)


def bench(args: argparse.Namespace) -> int:
    if len(os.sched_getaffinity(0)) < 2:
        raise SystemExit("placement 'split' needs two CPUs")
    zshm, why = shm_support()
    print(f"SHM: {why}" + ("" if zshm else "; skipping the shm layouts"), flush=True)
    seq = iter(range(1, 1 << 62))
    results: dict[str, dict[str, Stats]] = {}
    started = time.time()
    hog = start_load() if args.load else None
    try:
        if hog is not None:
            time.sleep(0.5)  # the busy loops are running
        for layout in LAYOUTS:
            if layout.shm and zshm is None:
                continue
            if layout.kind == "pipe":
                results[layout.name] = bench_pipe(args, seq)
            else:
                results[layout.name] = bench_zenoh(layout, args, seq)
    finally:
        if hog is not None:
            stop_load(hog)
        if zshm is not None:
            sweep_shm_orphans(started - 1.0)
    print_results(results, args)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=int, default=3000, help="round trips per row (3000)")
    parser.add_argument("--warmup", type=int, default=200, help="warm-up round trips per row")
    parser.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for a pong")
    parser.add_argument("--load", action="store_true", help="run tools/cpuhog.py meanwhile")
    parser.add_argument("--echo", nargs="+", metavar="ARG", help=argparse.SUPPRESS)
    parser.add_argument("--router", metavar="ENDPOINT", help=argparse.SUPPRESS)
    parser.add_argument("--shm", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.echo or args.router:
        die_with_parent()
        if args.router:
            return run_router(args.router, args.shm)
        if args.echo[0] == "pipe":
            return run_pipe_echo(int(args.echo[1]), int(args.echo[2]))
        return run_zenoh_echo(args.echo[0], args.echo[1], args.shm)
    if args.n < 1:
        parser.error("--n must be positive")
    return bench(args)


if __name__ == "__main__":
    sys.exit(main())
