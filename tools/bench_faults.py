"""Fault benchmark: how fast each fault is detected and repaired, and whether state survives.

Every run is a real system: ``rra up tests/data/relay_system`` on a free loopback port (the
Zenoh hub, the local host agent, the three engines in two replicas each, and the nodes
``source``, ``direct``, ``sink``), observed from a session of this script: the
`NodeState`/`AdaptationEvent` stream on ``rra/<system>/events``, the engines' leader tokens
and the selections. An operator's value (``sink.offset = 4.0``, set through the Run-time
Resolution Engine) is the state that must survive. Faults, one row each:

1. ``kill -9`` of a node (sink): detected <= 20 ms (the host agent reaps its child),
   running again <= 1 s, the operator's value in the restarted node;
2. ``SIGSTOP`` of a node for good (frozen): killed after its heartbeat deadline and a failed
   probe, within deadline + 1 s (4 + 1 s by default, `Supervision`); running again within
   deadline + 2 s; the operator's value kept;
3. ``SIGSTOP`` of the hub (the ``rra up`` process) for 1.0 s: nothing restarted (same pids,
   same restart counters, no FATAL), the operator's value kept;
4. ``kill -9`` of the Run-time Resolution Engine leader: the standby leads within 100 ms,
   keeps the model (selection, operator values) and still adapts (Level 7 -> ``filtered``);
5. ``kill -9`` of the Adaptation Engine leader: the standby leads within 100 ms and
   publishes the selection in force (no default selection, no swap);
   in both, the killed replica comes back as a standby and must not take the lead back;
6. ``kill -9`` of the host agent's fork server: no node dies, a ``fork_server`` event is
   published, and the next node restart (``kill -9`` of sink) still works;
7. a second ``rra up`` of the same package, linked to the first's router: refused in one
   line, nothing started, the first system undisturbed (same pids, same leader terms);
8. ``SIGSTOP`` of the Run-time Resolution Engine leader for longer than the budget: the
   standby takes over after the lease (not before the budget), the resumed one follows;
9. a partition: host h2 (the sink's) cut from the hub like a pulled cable for 3 s, with no
   ``reachable:`` measurement in the model: one ``host_unreachable`` and one
   ``host_reachable`` event, the sink keeps its process;
10. a replacement that cannot start (``filtered``'s class does not exist): Level 7 selects
    Filtered; its start fails and its swap is undone alone (Direct runs again), the
    implementation is unavailable and the Adaptation Engine decides Direct again;
11. forged source samples (a value missing, NaN, inf, 1e9, not msgpack) that would select
    Filtered if believed: refused and counted by the Context Monitor, no selection changes.

The systems run with the shipped bus configuration (the 2 s lease: the failure-detection
budget is 1.75 s, `BusConfig.budget_ms`); row 3's stall (1 s) must move no leadership.

Figures are medians and p99 (nearest rank) over ``--runs`` repetitions, in milliseconds
after the injection. They come from time stamps (the host agents' and engines' own, or the
arrival of a leader token at this script's session; the footnotes say which), not from
polling; polls with deadlines only wait for a condition, and the one sleep is the length of
the hub's stall. Rows 1, 2 and 6 start a fresh system per repetition (a node's restart
budget and its exponential backoff would otherwise carry over); rows 3, 4 and 5 reuse one
system for up to five repetitions. Every process started is in a process group of its own
and is stopped (SIGCONT, SIGINT, then SIGKILL of the group) at the end, on error or Ctrl-C.

``--load`` runs ``tools/cpuhog.py`` (a busy loop per core) for the whole benchmark.
``--runs 3`` takes a few minutes on a 2-core machine.

    .venv/bin/python tools/bench_faults.py [--runs 5] [--load] [--only kill-node ...]
                                           [--keep DIR] [-q]
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _benchutil import median, p99, print_table

from rra_agent.bus import messages as m
from rra_agent.bus.client import (
    BusClient,
    NoReply,
    gather,
    process_stats,
    set_params,
    wait_until,
)
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.bus.keys import Keys
from rra_agent.engines.events import read_events
from rra_agent.errors import RraError
from rra_agent.host import procfs
from rra_agent.host.processes import process_state
from rra_agent.models.system import Supervision

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "tests" / "data" / "relay_system"
K = Keys("relay_system")
#: A component's supervision (the relay system's nodes use the defaults).
SUPERVISION = Supervision()
DEADLINE = SUPERVISION.heartbeat_timeout
PROBE = SUPERVISION.probe_timeout
#: The operator's value that must survive every fault.
OFFSET = 4.0
#: Repetitions on one system at most (engines: 20 restarts a minute, growing backoff).
REUSE = 5
#: Length of the hub's stall (fault 3).
STALL = 1.0
#: The failure-detection budget and the lease it comes from (the shipped bus, seconds).
BUDGET = BusConfig().budget_ms / 1000.0
LEASE = BusConfig().lease_ms / 1000.0
#: How long h2's cable stays out (the partition row).
CUT = 3.0
#: Processes of one relay system: six engine replicas and three nodes.
PROCESSES = 9
ROLES = ("resolution", "adaptation", "monitor")
_EVT = m.Codec[m.EventMessage](m.EventMessage)
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)


class Fault(Exception):
    """A repetition that could not be completed (a condition not reached in time...)."""


# ---- processes: every one in a group of its own, all ended at exit ---------------------------
_GROUPS: dict[int, subprocess.Popen[bytes]] = {}


def spawn(args: list[str], log: Path | None) -> subprocess.Popen[bytes]:
    out = log.open("ab") if log is not None else subprocess.DEVNULL
    try:
        proc = subprocess.Popen(
            args,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            cwd=ROOT,
            env={**os.environ, "RERUN_ANALYTICS": "0"},
            start_new_session=True,  # a group of its own: a Ctrl-C here reaches only us
        )
    finally:
        if log is not None:
            out.close()  # type: ignore[union-attr]
    _GROUPS[proc.pid] = proc
    return proc


def _killpg(pgid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pgid, sig)


def end_group(proc: subprocess.Popen[bytes], grace: float = 30.0) -> int | None:
    """Resume the whole group (nothing stays stopped), SIGINT its leader and wait for it,
    then SIGKILL whatever is left of the group. The leader's exit status (None: killed)."""
    _killpg(proc.pid, signal.SIGCONT)
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        code: int | None = proc.wait(grace)
    except subprocess.TimeoutExpired:
        code = None
    _killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    _GROUPS.pop(proc.pid, None)
    return code


def end_all() -> None:
    """Every group still running, e.g. on Ctrl-C or an error (a second Ctrl-C is ignored)."""
    if not _GROUPS:
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        for proc in list(_GROUPS.values()):
            end_group(proc, grace=15.0)
    finally:
        signal.signal(signal.SIGINT, previous)


def _terminate(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def children(ppid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        if procfs.parent(int(entry)) == ppid:
            out.append(int(entry))
    return out


def cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


# ---- what this script's session sees ----------------------------------------------------
@dataclass(frozen=True)
class Claim:
    """A leader token of an engine role, as it reached this session (``at``: arrival)."""

    at: float
    role: str
    epoch: int
    replica: str
    alive: bool


class Watch:
    """Every event, leader token and selection this session receives, in order."""

    def __init__(self, client: BusClient) -> None:
        self.lock = threading.Lock()
        self.events: list[m.AdaptationEvent | m.NodeState] = []
        self.claims: list[Claim] = []
        self.selections: list[m.Selection] = []
        session = client.session
        lv = session.liveliness()
        self._keep = [
            session.declare_subscriber(K.events, self._on_event),
            session.declare_subscriber(K.selection, self._on_selection),
            *(
                lv.declare_subscriber(
                    f"{K.lead(role)}/**", lambda s, r=role: self._on_claim(r, s), history=True
                )
                for role in ROLES
            ),
        ]

    def close(self) -> None:
        for entity in self._keep:
            with contextlib.suppress(Exception):
                entity.undeclare()
        self._keep = []

    def _on_event(self, sample: zenoh.Sample) -> None:
        try:
            msg = _EVT.decode(sample.payload.to_bytes())
        except Exception:
            return
        with self.lock:
            self.events.append(msg)

    def _on_selection(self, sample: zenoh.Sample) -> None:
        try:
            msg = _SEL.decode(sample.payload.to_bytes())
        except Exception:
            return
        if isinstance(msg, m.Selection):
            with self.lock:
                self.selections.append(msg)

    def _on_claim(self, role: str, sample: zenoh.Sample) -> None:
        at = time.time()
        parts = str(sample.key_expr).removeprefix(K.lead(role) + "/").split("/")
        if len(parts) != 3 or not parts[0].isdigit():  # <epoch>/<replica>/<instance>
            return
        epoch, replica = int(parts[0]), parts[1]
        alive = sample.kind == zenoh.SampleKind.PUT
        with self.lock:
            self.claims.append(Claim(at, role, epoch, replica, alive))

    # ---- queries -----------------------------------------------------------------------
    def states(self, pred: Callable[[m.NodeState], bool]) -> list[m.NodeState]:
        with self.lock:
            return [e for e in self.events if isinstance(e, m.NodeState) and pred(e)]

    def left_running(self, node: str, after: float) -> m.NodeState | None:
        """The first transition of ``node`` out of RUNNING since ``after``."""
        found = self.states(
            lambda e: e.node == node and e.previous == "RUNNING" and e.stamp >= after
        )
        return found[0] if found else None

    def running_again(self, node: str, after: float, old_pid: int) -> m.NodeState | None:
        found = self.states(
            lambda e: e.node == node and e.state == "RUNNING" and e.pid != old_pid
            and e.stamp >= after
        )  # fmt: skip
        return found[0] if found else None

    def started(self, after: float, until: float) -> list[str]:
        """Every node (re)started in [after, until]: its transitions to STARTING."""
        return [
            e.node
            for e in self.states(lambda e: e.state == "STARTING" and after <= e.stamp <= until)
        ]

    def adaptation_events(
        self, kind: str, after: float, pred: Callable[[m.AdaptationEvent], bool] = lambda e: True
    ) -> list[m.AdaptationEvent]:
        with self.lock:
            return [
                e for e in self.events
                if isinstance(e, m.AdaptationEvent) and e.kind == kind and e.stamp >= after
                and pred(e)
            ]  # fmt: skip

    def new_claim(self, role: str, above: int) -> Claim | None:
        """The first live leader token of ``role`` with an epoch above ``above``."""
        with self.lock:
            return next(
                (c for c in self.claims if c.role == role and c.alive and c.epoch > above), None
            )

    def claim_gone(self, role: str, epoch: int, replica: str, after: float) -> Claim | None:
        """When the claim (epoch, replica) disappeared, at or after ``after``."""
        with self.lock:
            return next(
                (c for c in self.claims if c.role == role and not c.alive and c.epoch == epoch
                 and c.replica == replica and c.at >= after),
                None,
            )  # fmt: skip

    def selection_of(self, epoch: int, replica: str) -> m.Selection | None:
        """The first selection published under the fence (epoch, replica)."""
        with self.lock:
            return next(
                (s for s in self.selections if s.fence is not None
                 and (s.fence.epoch, s.fence.leader) == (epoch, replica)),
                None,
            )  # fmt: skip


def until(predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.005):
    """Poll ``predicate`` until it is truthy (its value); `Fault` after ``timeout``."""
    try:
        return wait_until(predicate, timeout, what, interval=interval)
    except TimeoutError as e:
        raise Fault(str(e)) from None


def running(st: dict) -> dict[str, int]:
    return {n["node"]: n["pid"] for n in st["nodes"] if n["state"] == "RUNNING"}


# ---- a system under test ------------------------------------------------------------------
class System:
    """``rra up`` of the relay system, in a process group of its own, and a session on it
    (the shipped bus configuration: its lease is the failure-detection budget measured)."""

    def __init__(self, work: Path, label: str, package: Path = PACKAGE) -> None:
        self.run_dir = work / label
        self.run_dir.mkdir(parents=True)
        self.endpoint = endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.before_up()
        self.proc = spawn(
            [sys.executable, "-m", "rra_agent", "up", str(package), "--run-dir",
             str(self.run_dir), "-q", "--connect", endpoint, "--no-multicast"],
            self.run_dir / "up.log",
        )  # fmt: skip
        self.client: BusClient | None = None
        self.watch: Watch | None = None
        self.exit_code: int | None = None
        try:
            bus = BusConfig(connect=[endpoint], multicast=False)
            self.client = until(lambda: self._connect(bus), 90.0, f"the hub on {endpoint}", 0.1)
            self.watch = Watch(self.client)
            self.wait(
                lambda s: s["engine"] and not s["engine"]["failed"]
                and "sink" in s["engine"]["running"] and len(running(s)) == PROCESSES,
                "the deployment, all nine processes running",
                timeout=90.0,
            )  # fmt: skip
            self.set_param("sink", {"offset": OFFSET})
        except BaseException:
            self.stop()
            raise

    def before_up(self) -> None:
        """What runs before ``rra up`` (another host's agent, `TwoHosts`)."""

    def _connect(self, bus: BusConfig) -> BusClient | None:
        """A session on the hub; None while it does not listen yet (a loaded machine)."""
        if self.proc.poll() is not None:
            raise Fault(f"rra up exited with {self.proc.returncode}; log: {self.run_dir}")
        try:
            return BusClient(bus, "relay_system")
        except Exception:  # zenoh.ZError: not listening yet (the connect timeout passed)
            return None

    @property
    def pid(self) -> int:
        return self.proc.pid

    def gather(self) -> dict:
        assert self.client is not None
        return gather(self.client, timeout=1.0)

    def wait(self, pred: Callable[[dict], Any], what: str, timeout: float = 30.0) -> dict:
        def check() -> dict | None:
            st = self.gather()
            return st if pred(st) else None

        if self.proc.poll() is not None:
            raise Fault(f"rra up exited with {self.proc.returncode}; log: {self.run_dir}")
        return until(check, timeout, what, interval=0.05)

    def set_param(self, node: str, params: dict[str, Any], timeout: float = 30.0) -> None:
        """As an operator (``rra param``), retried while the leadership may be moving."""
        assert self.client is not None
        client = self.client

        def attempt() -> bool:
            try:
                set_params(client, node, params)
            except (RraError, NoReply):
                return False
            return True

        until(attempt, timeout, f"{node} {params} set", interval=0.1)

    def param(self, node: str, name: str) -> Any:
        """A parameter as the running node reports it."""
        assert self.client is not None
        client = self.client
        until(lambda: node in {n for _, n in client.alive()}, 10, f"{node}'s token", 0.05)

        def describe() -> m.Reply | None:
            try:
                return client.node(node, m.Describe())
            except NoReply:  # its token can reach us before its control endpoint's route
                return None  # (a node of another host, just reconnected)

        reply = until(describe, 15, f"{node} answering", 0.1)
        return reply.result["params"].get(name) if isinstance(reply, m.Ok) else None

    def engine(self, name: str) -> dict | None:
        """The status of an engine role's leader (``adaptation``) or of a replica."""
        assert self.client is not None
        try:
            reply = self.client.request(K.engine_ctl(name), m.Status(), 1.0)
        except NoReply:
            return None
        return reply.result if isinstance(reply, m.Ok) and reply.result else None

    def leader_answers(self, role: str, replica: str) -> dict | None:
        """The status of ``role`` once ``replica`` answers for it, else None."""
        status = self.engine(role)
        return status if status and status["leader"][1:2] == [replica] else None

    def node_pid(self, st: dict, name: str) -> int | None:
        return next((n["pid"] for n in st["nodes"] if n["node"] == name), None)

    def standby_ready(self, st: dict, role: str) -> tuple[list, int] | None:
        """(leader term, leader pid) once both replicas run and the standby follows the
        leader with an up-to-date mirror; else None."""
        lead = (st["engine"] or {}).get("leader") if role == "resolution" else None
        if role != "resolution":
            status = self.engine(role)
            lead = status.get("leader") if status else None
        if not lead:
            return None
        replicas = [f"{role}-{r}" for r in "ab"]
        pids = running(st)
        if lead[1] not in replicas or any(r not in pids for r in replicas):
            return None
        (standby,) = [r for r in replicas if r != lead[1]]
        mine = self.engine(standby)
        if not mine or mine["leading"] or mine["leader"] != lead:
            return None
        if role == "resolution" and mine["version"] != st["engine"]["version"]:
            return None
        if role == "adaptation":
            theirs = self.engine(role)
            if not mine.get("resumed") or not theirs or mine["selection"] != theirs["selection"]:
                return None
        return lead, pids[lead[1]]

    def stop(self) -> None:
        if self.watch is not None:
            self.watch.close()
        if self.client is not None:
            with contextlib.suppress(Exception):
                self.client.close()
            self.client = None
        self.exit_code = end_group(self.proc)


# ---- one repetition of a fault -------------------------------------------------------------
@dataclass
class Sample:
    #: Seconds after the injection (None: not applicable).
    detected: float | None = None
    recovered: float | None = None
    restarted: list[str] = field(default_factory=list)
    state_ok: bool = False
    #: Conditions of the row's goal, each True when met.
    checks: dict[str, bool] = field(default_factory=dict)
    #: Further figures (seconds) and notes for the footnotes.
    extra: dict[str, float] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    error: str | None = None


def kill_node(sys_: System, _rep: int) -> Sample:
    st = sys_.wait(lambda s: len(running(s)) == PROCESSES, "all nine processes running")
    watch = sys_.watch
    assert watch is not None
    pid = running(st)["sink"]
    t0 = time.time()
    os.kill(pid, signal.SIGKILL)
    left = until(lambda: watch.left_running("sink", t0), 10, "sink's exit reported")
    back = until(lambda: watch.running_again("sink", t0, pid), 15, "sink running again")
    s = Sample(detected=left.stamp - t0, recovered=back.stamp - t0)
    s.checks["exit reported as the kill"] = "status -9" in left.reason
    s.state_ok = sys_.param("sink", "offset") == OFFSET
    s.restarted = watch.started(t0, time.time())
    return s


def freeze_node(sys_: System, _rep: int) -> Sample:
    st = sys_.wait(lambda s: len(running(s)) == PROCESSES, "all nine processes running")
    watch = sys_.watch
    assert watch is not None
    pid = running(st)["sink"]
    t0 = time.time()
    os.kill(pid, signal.SIGSTOP)
    try:
        killed = until(
            lambda: next(iter(watch.states(
                lambda e: e.node == "sink" and e.stamp >= t0
                and e.state in ("BACKOFF", "FATAL", "EXITED"))), None),
            DEADLINE + PROBE + 15, "the frozen sink killed",
        )  # fmt: skip
        back = until(lambda: watch.running_again("sink", t0, pid), 15, "sink running again")
    finally:
        if process_state(pid) in ("T", "t"):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
    s = Sample(detected=killed.stamp - t0, recovered=back.stamp - t0)
    unresponsive = watch.states(
        lambda e: e.node == "sink" and e.state == "UNRESPONSIVE" and e.stamp >= t0
    )
    if unresponsive:
        s.extra["heartbeat deadline seen"] = unresponsive[0].stamp - t0
    s.checks["killed as frozen"] = "frozen" in killed.reason
    s.state_ok = sys_.param("sink", "offset") == OFFSET
    s.restarted = watch.started(t0, time.time())
    return s


def stall_hub(sys_: System, _rep: int) -> Sample:
    def settled(s: dict) -> bool:
        """Nine processes running, every engine led, each standby following its leader."""
        return (
            len(running(s)) == PROCESSES
            and all(sys_.standby_ready(s, role) for role in ("resolution", "adaptation"))
            and all(leaders().values())
        )

    def leaders() -> dict[str, tuple | None]:
        """The term each role's leader answers with (its Status)."""
        out = {}
        for role in ROLES:
            status = sys_.engine(role)
            out[role] = tuple(status["leader"]) if status and status.get("leader") else None
        return out

    st = sys_.wait(settled, "every engine led, every standby following")
    watch = sys_.watch
    assert watch is not None
    before = running(st)
    restarts = {n["node"]: n.get("restarts", 0) for n in st["nodes"]}
    terms = leaders()
    t0 = time.time()
    os.kill(sys_.pid, signal.SIGSTOP)
    try:
        time.sleep(STALL)  # the fault: the hub, host agent and supervisor stall this long
    finally:
        os.kill(sys_.pid, signal.SIGCONT)
    resumed, resumed_mono = time.time(), time.monotonic()
    sys_.wait(lambda s: s["engine"] is not None and len(running(s)) == PROCESSES, "the bus back")
    bus_back = time.time() - resumed
    # A wrong verdict (a node taken for frozen) would come within a heartbeat deadline and
    # a probe after the resume: watch the events that long, or until something leaves RUNNING.
    window = resumed_mono + DEADLINE + PROBE

    def bad() -> list[m.NodeState]:
        return watch.states(
            lambda e: e.stamp >= t0 and (e.previous == "RUNNING" or e.state == "FATAL")
        )

    with contextlib.suppress(Fault):
        until(lambda: bad() or time.monotonic() >= window, DEADLINE + PROBE + 5, "", 0.05)
    st = sys_.wait(settled, "every engine led again, every standby following")
    s = Sample(restarted=watch.started(t0, time.time()))
    s.checks["same processes"] = running(st) == before
    s.checks["no restart counted"] = {
        n["node"]: n.get("restarts", 0) for n in st["nodes"]
    } == restarts
    s.checks["no FATAL"] = not [n for n in st["nodes"] if n["state"] == "FATAL"] and not any(
        e.state == "FATAL" for e in bad()
    )
    overrides = st["engine"]["overrides"]
    s.state_ok = (
        overrides.get("sink", {}).get("offset") == OFFSET and sys_.param("sink", "offset") == OFFSET
    )
    s.extra["bus back after the resume"] = bus_back
    now = leaders()
    moved = {r: (terms[r], now[r]) for r in ROLES if now[r] != terms[r]}
    s.extra["leader changes"] = len(moved)
    s.checks["no leadership moved"] = not moved
    s.notes += [f"{r} leader {a[:2]} -> {b[:2]}" for r, (a, b) in moved.items()]
    # The engine logs its takeovers itself (this session was cut off during the stall too).
    s.notes += [
        f"{e.source} took over at +{(e.stamp - t0) * 1e3:.0f} ms"
        for e in read_events(sys_.run_dir / "events.jsonl")
        if isinstance(e, m.AdaptationEvent) and e.kind == "takeover" and e.stamp >= t0
    ]
    s.notes += [f"{e.node} {e.previous}->{e.state} ({e.reason})" for e in bad()]
    return s


def kill_resolution_leader(sys_: System, _rep: int) -> Sample:
    watch = sys_.watch
    assert watch is not None
    ready = None

    def check(s: dict) -> bool:
        nonlocal ready
        ready = sys_.standby_ready(s, "resolution")
        return ready is not None

    st = sys_.wait(check, "a resolution standby following the leader")
    assert ready is not None
    (epoch, leader, *_), pid = ready
    selection, overrides = st["engine"]["selection"], st["engine"]["overrides"]
    t0 = time.time()
    os.kill(pid, signal.SIGKILL)
    claim = until(lambda: watch.new_claim("resolution", epoch), 10, "a new resolution leader")
    if claim.at < t0:
        raise Fault(f"{claim.replica} claimed the lead (epoch {claim.epoch}) before the kill")
    took = until(
        lambda: next(iter(watch.adaptation_events("takeover", t0)), None), 10, "its takeover"
    )
    s = Sample(detected=claim.at - t0, recovered=took.stamp - t0)
    gone = watch.claim_gone("resolution", epoch, leader, t0)
    if gone is not None:
        s.extra["old claim gone"] = gone.at - t0
    st = sys_.wait(
        lambda s: s["engine"] is not None and s["engine"]["leader"][1] == claim.replica,
        "the new leader answering",
    )
    kept = st["engine"]["selection"] == selection and st["engine"]["overrides"] == overrides
    back = until(lambda: watch.running_again(leader, t0, pid), 30, f"{leader} running again")
    s.extra["killed replica back"] = back.stamp - t0
    s.restarted = watch.started(t0, time.time())  # before the swap below starts a node
    # ... and it still adapts: the Level across 5, one way or the other.
    want = "filtered" if "direct" in st["engine"]["running"] else "direct"
    t_set = time.time()
    sys_.set_param("source", {"value": 7.0 if want == "filtered" else 2.0})
    swap = until(
        lambda: next(iter(watch.adaptation_events(
            "adaptation", t_set,
            lambda e: e.outcome == "ok" and any(p.startswith(f"start {want}") for p in e.plan),
        )), None),
        30, f"the swap to {want}",
    )  # fmt: skip
    s.extra["set -> swap"] = swap.stamp - t_set
    s.state_ok = kept
    settle(sys_, "resolution", leader, epoch, claim, s)
    return s


def settle(sys_: System, role: str, killed: str, epoch: int, claim: Claim, s: Sample) -> None:
    """Wait until the killed replica follows as a standby; check that the replica which
    took over still leads (the restarted one must not take the lead back)."""
    term: list = []

    def check(st: dict) -> bool:
        ready = sys_.standby_ready(st, role)
        if ready is not None:
            term[:] = ready[0]
        return ready is not None

    sys_.wait(check, f"{killed} following as a standby")
    s.checks["no flap back"] = term[:2] == [claim.epoch, claim.replica]
    s.notes.append(
        f"killed {killed} (epoch {epoch}), {claim.replica} took over (epoch {claim.epoch})"
        + ("" if s.checks["no flap back"] else f", then {term[1]} took it (epoch {term[0]})")
    )


def kill_adaptation_leader(sys_: System, _rep: int) -> Sample:
    watch = sys_.watch
    assert watch is not None
    if "filtered" not in sys_.gather()["engine"]["running"]:
        # A selection that is not the default one, so that a default would show.
        sys_.set_param("source", {"value": 7.0})
        sys_.wait(lambda s: "filtered" in s["engine"]["running"], "the swap to filtered")
    ready = None

    def check(s: dict) -> bool:
        nonlocal ready
        ready = (
            sys_.standby_ready(s, "adaptation") if "filtered" in s["engine"]["running"] else None
        )
        return ready is not None

    st = sys_.wait(check, "an adaptation standby following the leader")
    assert ready is not None
    (epoch, leader, *_), pid = ready
    status = sys_.engine("adaptation")
    assert status is not None
    selection, running_before = status["selection"], sorted(st["engine"]["running"])
    t0 = time.time()
    os.kill(pid, signal.SIGKILL)
    claim = until(lambda: watch.new_claim("adaptation", epoch), 10, "a new adaptation leader")
    if claim.at < t0:
        raise Fault(f"{claim.replica} claimed the lead (epoch {claim.epoch}) before the kill")
    first = until(lambda: watch.selection_of(claim.epoch, claim.replica), 10, "its first selection")
    s = Sample(detected=claim.at - t0, recovered=first.stamp - t0)
    gone = watch.claim_gone("adaptation", epoch, leader, t0)
    if gone is not None:
        s.extra["old claim gone"] = gone.at - t0
    # The role's endpoint answers for the new leader once it has taken over (a Status read
    # at once may still reach nobody, or the old term: not a lost state).
    now = until(lambda: sys_.leader_answers("adaptation", claim.replica), 10,
                "the new adaptation leader answering")  # fmt: skip
    back = until(lambda: watch.running_again(leader, t0, pid), 30, f"{leader} running again")
    s.extra["killed replica back"] = back.stamp - t0
    st = sys_.gather()
    swaps = watch.adaptation_events("adaptation", t0, lambda e: bool(e.plan))
    s.state_ok = (
        sorted(first.features) == selection
        and bool(now)
        and now["selection"] == selection
        and sorted(st["engine"]["running"]) == running_before
        and not swaps
    )
    s.notes += [f"swap after the takeover: {e.plan}" for e in swaps]
    if sorted(first.features) != selection or now["selection"] != selection:
        s.notes.append(f"selection {selection} -> {sorted(first.features)} / {now['selection']}")
    s.restarted = watch.started(t0, time.time())
    settle(sys_, "adaptation", leader, epoch, claim, s)
    return s


def fork_server(sys_: System) -> int | None:
    """The pid of ``rra up``'s fork server, as its host agent answers a Ping (a process
    table cannot tell it from its spare, a fork of it with the same command line)."""
    assert sys_.client is not None
    try:
        reply = sys_.client.host("local", m.Ping())
    except NoReply:
        return None
    return reply.result.get("fork_server") if isinstance(reply, m.Ok) else None


def kill_fork_server(sys_: System, _rep: int) -> Sample:
    st = sys_.wait(lambda s: len(running(s)) == PROCESSES, "all nine processes running")
    watch = sys_.watch
    assert watch is not None
    before = running(st)
    zygote = until(lambda: fork_server(sys_), 10, "the fork server's pid from its host agent")
    t0 = time.time()
    os.kill(zygote, signal.SIGKILL)
    ev = until(lambda: next(iter(watch.adaptation_events("fork_server", t0)), None), 10,
               "the fork_server event")  # fmt: skip
    s = Sample(detected=ev.stamp - t0)
    st = sys_.gather()
    died = watch.states(lambda e: e.stamp >= t0 and e.previous == "RUNNING")
    s.checks["no node died"] = running(st) == before and not died
    s.notes += [f"{e.node} {e.previous}->{e.state} ({e.reason})" for e in died]
    # The next restart needs a new fork server: kill -9 the sink.
    pid = before["sink"]
    t1 = time.time()
    os.kill(pid, signal.SIGKILL)
    back = until(lambda: watch.running_again("sink", t1, pid), 15, "sink running again")
    s.recovered = back.stamp - t1
    again = fork_server(sys_)
    s.checks["a new fork server"] = again is not None and again != zygote
    s.state_ok = sys_.param("sink", "offset") == OFFSET
    s.restarted = watch.started(t0, time.time())
    return s


# ---- one system, one set of engines; the budget; partitions --------------------------------
def terms_and_pids(sys_: System) -> tuple[dict[str, tuple | None], dict[str, int]]:
    """Every role's leader term and the nine processes, once both are settled."""
    out: list = []

    def check(st: dict) -> bool:
        terms = {role: tuple(e["leader"]) if (e := sys_.engine(role)) else None for role in ROLES}
        out[:] = [terms, running(st)]
        return len(running(st)) == PROCESSES and all(terms.values())

    sys_.wait(check, "nine processes running, every role led")
    return out[0], out[1]


def second_up(sys_: System, rep: int) -> Sample:
    """A second ``rra up`` of the same package, its router linked to the first one's."""
    watch = sys_.watch
    assert watch is not None
    terms, before = terms_and_pids(sys_)
    run_dir = sys_.run_dir.parent / f"{sys_.run_dir.name}-second-{rep}"
    log = sys_.run_dir / f"second-up-{rep}.log"
    t0, wall = time.monotonic(), time.time()
    proc = spawn(
        [sys.executable, "-m", "rra_agent", "up", str(PACKAGE), "--run-dir", str(run_dir),
         "--connect", f"tcp/127.0.0.1:{free_port()}", "--connect", sys_.endpoint,
         "--no-multicast"],
        log,
    )  # fmt: skip
    try:
        code: int | None = proc.wait(60)
    except subprocess.TimeoutExpired:
        code = None
    took = time.monotonic() - t0
    end_group(proc, grace=15.0)
    lines = log.read_text(errors="replace").strip().splitlines()
    s = Sample(detected=took)
    s.checks["refused (exit status not 0)"] = code not in (0, None)
    s.checks["one line"] = len(lines) == 1 and "already runs" in lines[0]
    s.checks["nothing started"] = not run_dir.exists()
    after_terms, after = terms_and_pids(sys_)
    s.checks["first system undisturbed"] = after_terms == terms and after == before
    s.state_ok = sys_.param("sink", "offset") == OFFSET
    s.restarted = watch.started(wall, time.time())
    if lines:
        s.notes.append(lines[0][:120] + ("..." if len(lines[0]) > 120 else ""))
    return s


def freeze_leader(sys_: System, _rep: int) -> Sample:
    """SIGSTOP of the Resolution Engine leader for longer than the budget, then SIGCONT."""
    watch = sys_.watch
    assert watch is not None
    ready = None

    def check(st: dict) -> bool:
        nonlocal ready
        ready = sys_.standby_ready(st, "resolution")
        return ready is not None

    st = sys_.wait(check, "a resolution standby following the leader")
    assert ready is not None
    (epoch, leader, *_), pid = ready
    selection, overrides = st["engine"]["selection"], st["engine"]["overrides"]
    t0 = time.time()
    os.kill(pid, signal.SIGSTOP)
    try:
        claim = until(lambda: watch.new_claim("resolution", epoch), 15, "a new resolution leader")
        took = until(lambda: next(iter(watch.adaptation_events("takeover", t0)), None), 10,
                     "its takeover")  # fmt: skip
    finally:
        os.kill(pid, signal.SIGCONT)
    s = Sample(detected=claim.at - t0, recovered=took.stamp - t0)
    s.checks["not before the budget"] = claim.at - t0 >= BUDGET * 0.98
    st = sys_.wait(lambda st: sys_.standby_ready(st, "resolution") is not None
                   and st["engine"]["leader"][1] == claim.replica,
                   f"the resumed {leader} following {claim.replica}")  # fmt: skip
    s.checks["the resumed one follows"] = sys_.node_pid(st, leader) == pid
    s.state_ok = st["engine"]["selection"] == selection and st["engine"]["overrides"] == overrides
    s.restarted = watch.started(t0, time.time())
    s.notes.append(f"froze {leader} (epoch {epoch}), {claim.replica} took over "
                   f"(epoch {claim.epoch})")  # fmt: skip
    return s


def two_host_package(work: Path) -> Path:
    """The relay system with its sink on a second host, h2 (no ``reachable:`` measurement)."""
    import yaml

    pkg = work / "relay_two_hosts"
    if not pkg.exists():
        shutil.copytree(PACKAGE, pkg, ignore=shutil.ignore_patterns("__pycache__"))
        model = yaml.safe_load((pkg / "system.yaml").read_text())
        model["hosts"] = [{"name": "local"}, {"name": "h2"}]
        for c in model["components"]:
            c["host"] = "h2" if c["name"] == "sink" else "local"
        (pkg / "system.yaml").write_text(yaml.safe_dump(model, sort_keys=False))
    return pkg


class TwoHosts(System):
    """The relay system with its sink on host h2, whose agent's router joins the hub through
    a cuttable relay (`rra_agent.scenario.link`: a pulled cable, no FIN or RST)."""

    def __init__(self, work: Path, label: str) -> None:
        from rra_agent.scenario.link import Link

        self.link: Link | None = None
        self.agent: subprocess.Popen[bytes] | None = None
        self.package = two_host_package(work)
        super().__init__(work, label, self.package)

    def before_up(self) -> None:
        from rra_agent.scenario.link import Link

        self.link = Link(("127.0.0.1", int(self.endpoint.rsplit(":", 1)[1])))
        self.link.start()
        self.agent = spawn(
            [sys.executable, "-m", "rra_agent", "agent", "--host", "h2", "--package",
             str(self.package), "--log-dir", str(self.run_dir / "h2"), "--connect",
             self.link.endpoint, "--listen", f"tcp/127.0.0.1:{free_port()}", "--no-multicast",
             "-q"],
            self.run_dir / "agent-h2.log",
        )  # fmt: skip

    def stop(self) -> None:
        super().stop()
        if self.agent is not None:
            end_group(self.agent)
            self.agent = None
        if self.link is not None:
            self.link.close()
            self.link = None


def partition(sys_: System, _rep: int) -> Sample:
    """h2's link cut for `CUT` seconds, then restored."""
    assert isinstance(sys_, TwoHosts) and sys_.link is not None
    watch = sys_.watch
    assert watch is not None
    st = sys_.wait(lambda s: len(running(s)) == PROCESSES and s["engine"]["hosts"].get("h2"),
                   "nine processes running, h2 reachable")  # fmt: skip
    sink = running(st)["sink"]
    t0 = time.time()
    sys_.link.cut()
    try:
        gone = until(lambda: next(iter(watch.adaptation_events("host_unreachable", t0)), None),
                     15, "the host_unreachable event")  # fmt: skip
        # The fault: the cable stays out this long (the event is seen before).
        time.sleep(max(0.0, t0 + CUT - time.time()))
    finally:
        t1 = time.time()
        sys_.link.restore()
    back = until(lambda: next(iter(watch.adaptation_events("host_reachable", t1)), None), 15,
                 "the host_reachable event")  # fmt: skip
    st = sys_.wait(lambda s: s["engine"]["hosts"].get("h2") is True and "sink" in running(s),
                   "h2 back, its sink running")  # fmt: skip
    s = Sample(detected=gone.stamp - t0, recovered=back.stamp - t1)
    s.checks["one event per transition"] = (
        len(watch.adaptation_events("host_unreachable", t0)) == 1
        and len(watch.adaptation_events("host_reachable", t0)) == 1
    )
    s.checks["sink kept its process"] = running(st)["sink"] == sink
    s.state_ok = sys_.param("sink", "offset") == OFFSET
    s.restarted = watch.started(t0, time.time())
    return s


def broken_package(work: Path) -> Path:
    """The relay system with Filtered's implementation broken: its node cannot start."""
    pkg = work / "broken-relay"
    if not pkg.exists():
        shutil.copytree(PACKAGE, pkg, ignore=shutil.ignore_patterns("__pycache__"))
        path = pkg / "system.yaml"
        text = path.read_text()
        head, _, tail = text.partition("  - name: filtered\n")
        tail = tail.replace(
            "implementation: rra_agent.nodes.generic.Relay",
            "implementation: rra_agent.nodes.generic.NoSuchNode", 1,
        )
        path.write_text(head + "  - name: filtered\n" + tail)
    return pkg


class BrokenFiltered(System):
    """The relay system whose ``filtered`` cannot start."""

    def __init__(self, work: Path, label: str) -> None:
        super().__init__(work, label, broken_package(work))


def cannot_start(sys_: System, _rep: int) -> Sample:
    """Detected: the adaptation event saying what failed; recovered: Direct decided again
    (the implementation taken as unavailable)."""
    sys_.wait(lambda s: len(running(s)) == PROCESSES, "all nine processes running")
    watch = sys_.watch
    assert watch is not None
    t0 = time.time()
    sys_.set_param("source", {"value": 7.0})
    failed = until(
        lambda: watch.adaptation_events(
            "adaptation", t0, lambda e: e.outcome in ("partial", "rolled_back")
        ),
        30.0, "the adaptation that could not start filtered",
    )  # fmt: skip
    st = sys_.wait(
        lambda s: s["engine"]["unavailable"] and "direct" in running(s)
        and s["engine"]["selection"] == s["engine"]["effective"]
        and "Direct" in s["engine"]["selection"],
        "Direct decided again, filtered unavailable",
    )  # fmt: skip
    back = until(lambda: direct_again(watch, t0), 10.0, "the selection of Direct again")
    s = Sample(detected=failed[0].stamp - t0, recovered=back.stamp - t0)
    s.checks["filtered unavailable"] = [
        u["component"] for u in st["engine"]["unavailable"]
    ] == ["filtered"]
    s.checks["the event says why"] = "filtered" in failed[0].message
    s.state_ok = sys_.param("sink", "offset") == OFFSET
    s.restarted = watch.started(t0, time.time())
    return s


def direct_again(watch: Watch, after: float) -> m.Selection | None:
    """The first selection of Direct after one of Filtered, since ``after``."""
    with watch.lock:
        since = [x for x in watch.selections if x.stamp >= after]
    first = next((i for i, x in enumerate(since) if "Filtered" in x.features), None)
    if first is None:
        return None
    return next((x for x in since[first:] if "Direct" in x.features), None)


FORGED = (
    {"seq": 1},  # the value missing
    {"seq": 2, "value": float("nan")},
    {"seq": 3, "value": float("inf")},
    {"seq": 4, "value": 1e9},  # outside Level's plausible bounds
)


def monitor_refusals(sys_: System) -> int:
    assert sys_.client is not None
    stats = process_stats(sys_.client, families=("node",))
    return max(
        (sum(r["count"] for r in v.get("refused") or []) for v in stats.values()
         if v.get("role") == "monitor"),
        default=0,
    )  # fmt: skip


def forged_samples(sys_: System, _rep: int) -> Sample:
    """Detected: every forged sample counted by the Context Monitor leader."""
    sys_.wait(lambda s: len(running(s)) == PROCESSES, "all nine processes running")
    watch = sys_.watch
    assert watch is not None and sys_.client is not None
    before = monitor_refusals(sys_)
    session = sys_.client.session
    t0 = time.time()
    for sample in FORGED:
        session.put(K.data("source/out"), msgspec.msgpack.encode(sample),
                    attachment=m.pack_stamp(time.time()))  # fmt: skip
    session.put(K.data("source/out"), b"\xc1 not msgpack")
    until(lambda: monitor_refusals(sys_) >= before + len(FORGED) + 1, 10.0,
          "every forged sample counted")  # fmt: skip
    s = Sample(detected=time.time() - t0)
    with watch.lock:
        filtered = [x for x in watch.selections if x.stamp >= t0 and "Filtered" in x.features]
    s.checks["no selection of Filtered"] = not filtered
    s.state_ok = sys_.param("sink", "offset") == OFFSET
    s.restarted = watch.started(t0, time.time())
    return s


# ---- the rows --------------------------------------------------------------------------------
@dataclass(frozen=True)
class Row:
    key: str
    title: str
    run: Callable[[System, int], Sample]
    fresh: bool
    #: Goals in milliseconds (None: not applicable).
    detect_goal: float | None
    recover_goal: float | None
    #: The system it runs on.
    kind: type[System] = System


ROWS = (
    Row("kill-node", "kill -9 sink", kill_node, True, 20.0, 1000.0),
    Row("freeze-node", "SIGSTOP sink (frozen)", freeze_node, True,
        (DEADLINE + PROBE) * 1e3, (DEADLINE + 2.0) * 1e3),
    Row("stall-hub", f"SIGSTOP hub {STALL:g} s", stall_hub, False, None, None),
    Row("kill-resolution", "kill -9 resolution leader", kill_resolution_leader, False,
        100.0, 100.0),
    Row("kill-adaptation", "kill -9 adaptation leader", kill_adaptation_leader, False,
        100.0, 100.0),
    Row("kill-forkserver", "kill -9 fork server", kill_fork_server, True, 20.0, 1000.0),
    Row("second-up", "second rra up, linked", second_up, False, 5000.0, None),
    Row("freeze-leader", f"SIGSTOP resolution leader > {BUDGET:g} s", freeze_leader, False,
        LEASE * 1e3 + 250.0, LEASE * 1e3 + 250.0),
    Row("partition", f"host h2 cut {CUT:g} s", partition, False, LEASE * 1e3 + 500.0, 2000.0,
        TwoHosts),
    Row("cannot-start", "filtered cannot start", cannot_start, True, 1000.0, 2000.0,
        BrokenFiltered),
    Row("forged", "forged samples x5", forged_samples, False, 1000.0, None),
)  # fmt: skip


def run_row(
    row: Row, runs: int, work: Path, say: Callable[[str], None]
) -> tuple[list[Sample], list[str]]:
    """The row's samples, and notes on the systems (an unclean shutdown)."""
    samples: list[Sample] = []
    notes: list[str] = []
    sys_: System | None = None
    used = 0

    def stop(s: System) -> None:
        s.stop()
        if s.exit_code != 0:
            notes.append(f"rra up of {s.run_dir.name} exited with {s.exit_code} on SIGINT")

    try:
        for rep in range(runs):
            try:
                if sys_ is not None and (row.fresh or used >= REUSE):
                    stop(sys_)
                    sys_ = None
                if sys_ is None:
                    started = time.monotonic()
                    sys_ = row.kind(work, f"{row.key}-{rep}")
                    used = 0
                    say(f"  {row.key} run {rep + 1}/{runs}: system up in "
                        f"{time.monotonic() - started:.1f} s")  # fmt: skip
                used += 1
                sample = row.run(sys_, rep)
            except Exception as e:  # a failed repetition is reported, the next one goes on
                text = str(e) if isinstance(e, Fault) else f"{type(e).__name__}: {e}"
                sample = Sample(error=text)
                if sys_ is not None:
                    sample.error = f"{text} (logs: {sys_.run_dir})"
                    stop(sys_)
                    sys_ = None
            samples.append(sample)
            say(f"  {row.key} run {rep + 1}/{runs}: {describe(sample)}")
    finally:
        if sys_ is not None:
            stop(sys_)
    return samples, notes


def describe(s: Sample) -> str:
    if s.error:
        return f"ERROR {s.error}"
    figures = [
        f"{name} {value * 1e3:.1f} ms"
        for name, value in (("detected", s.detected), ("recovered", s.recovered))
        if value is not None
    ]
    figures += [
        f"{k} {v * 1e3:.1f} ms" if k != "leader changes" else f"{k} {v:g}"
        for k, v in s.extra.items()
    ]
    failed = [k for k, ok in s.checks.items() if not ok]
    state = "state kept" if s.state_ok else "STATE LOST"
    return ", ".join([*figures, state, *(f"FAILED: {k}" for k in failed), *s.notes])


# ---- the table -------------------------------------------------------------------------------
def figure(values: list[float | None]) -> tuple[str, float | None]:
    """'median / p99' in ms and the p99 (s), or 'n/a'."""
    got = [v for v in values if v is not None]
    if not got:
        return "n/a", None
    return f"{median(got) * 1e3:.1f} / {p99(got) * 1e3:.1f}", p99(got)


def goal_cell(goal: float | None) -> str:
    return "n/a" if goal is None else f"<= {goal:g}"


def restarted_cell(samples: list[Sample]) -> str:
    counts = Counter(name for s in samples for name in s.restarted)
    if not counts:
        return "nothing"
    return ", ".join(f"{name} x{n}" for name, n in sorted(counts.items()))


def table_row(row: Row, samples: list[Sample]) -> list[str]:
    good = [s for s in samples if not s.error]
    detected, det_p99 = figure([s.detected for s in good])
    recovered, rec_p99 = figure([s.recovered for s in good])
    problems = []
    if len(good) < len(samples):
        problems.append(f"{len(samples) - len(good)} run(s) failed")
    if row.detect_goal is not None and (det_p99 is None or det_p99 * 1e3 > row.detect_goal):
        problems.append("detection")
    if row.recover_goal is not None and (rec_p99 is None or rec_p99 * 1e3 > row.recover_goal):
        problems.append("recovery")
    failed = sorted({k for s in good for k, ok in s.checks.items() if not ok})
    problems += failed
    kept = sum(s.state_ok for s in good)
    if kept < len(good):
        problems.append("state")
    restarted = restarted_cell(good)
    if row.key == "stall-hub":
        moves = sum(int(s.extra.get("leader changes", 0)) for s in good)
        restarts = sum(len(s.restarted) for s in good)
        restarted = f"{restarted} ({restarts} restarts, {moves} leadership moves)"
    state = f"{'yes' if good and kept == len(good) else 'NO'} ({kept}/{len(samples)})"
    verdict = "PASS" if not problems else "FAIL: " + ", ".join(problems)
    return [
        row.title, detected, goal_cell(row.detect_goal), recovered,
        goal_cell(row.recover_goal), restarted, state, verdict,
    ]  # fmt: skip


def extras(samples: list[Sample]) -> str:
    """Median of every extra figure of a row."""
    names: dict[str, list[float]] = {}
    for s in samples:
        if not s.error:
            for k, v in s.extra.items():
                names.setdefault(k, []).append(v)
    parts = []
    for k, vs in names.items():
        if k == "leader changes":
            parts.append(f"{k} {sum(vs):g} in {len(vs)} run(s)")
        else:
            parts.append(f"{k} {median(vs) * 1e3:.1f} / {p99(vs) * 1e3:.1f} ms")
    return "; ".join(parts)


FOOTNOTES = {
    "kill-node": "detected = NodeState leaving RUNNING (host agent stamp, reason 'status -9') "
    "- kill; recovered = NodeState RUNNING with a new pid - kill",
    "freeze-node": "detected = NodeState BACKOFF 'frozen ... killed' (stamp) - SIGSTOP; "
    f"recovered = RUNNING, new pid (stamp); deadline {DEADLINE:g} s + probe {PROBE:g} s",
    "stall-hub": "nothing to restart: NodeStates watched for deadline + probe after SIGCONT; "
    f"'bus back' is polled (rra status answers again); a leadership move (any role's leader "
    f"term changed) fails the row: the stall is shorter than the budget ({BUDGET:g} s)",
    "kill-resolution": "detected = the standby's leader token reaching this session (arrival "
    "time); recovered = its 'takeover' event (stamp: hosts fenced, model adopted); the 100 ms "
    "takeover goal for both; set -> swap = 'adaptation' event (stamp) - set source value",
    "kill-adaptation": "detected = the standby's leader token reaching this session (arrival "
    "time); recovered = stamp of its first selection (the engine's clock, no bus hop: it can "
    "precede 'detected'); the 100 ms takeover goal for both; state = same selection, no swap",
    "kill-forkserver": "detected = 'fork_server' event (stamp) - kill; recovered = the next "
    "restart: kill -9 sink -> RUNNING (stamp), through a new fork server; goals those of "
    "row 1 (the fork server is a reaped child; a node restart); the fork server's pid is its "
    "host agent's answer to a Ping",
    "second-up": "a second `rra up` of the package, its hub elsewhere, its router linked to "
    "the first's (--connect); detected = its start -> its exit, refused in one line (it waits "
    "for its link and for the other routers' tokens: 0.1-0.5 s); the first system: same pids, same "
    "leader terms",
    "freeze-leader": f"SIGSTOP of the resolution leader until its successor took over, then "
    f"SIGCONT; detected = the successor's leader token reaching this session, recovered = its "
    f"'takeover' event (stamp); goal: the lease ({LEASE:g} s) + 250 ms, and not before the "
    f"budget ({BUDGET:g} s: a shorter stall is no failure)",
    "partition": f"h2's router joins the hub through a relay that is cut like a pulled cable "
    f"(rra_agent.scenario.link: nothing passes, no FIN or RST) for {CUT:g} s; no network "
    f"namespace needed (tests/test_netns.py cuts a veth); detected = 'host_unreachable' "
    f"event (stamp) - cut, recovered = 'host_reachable' (stamp) - restore; goals: the lease "
    f"+ 500 ms, the routers' retry (<= 1 s) + 1 s; the model declares no reachable: "
    f"measurement",
    "cannot-start": "the relay system with filtered's class missing; the source's value set "
    "to 7 (Level > 5: Filtered); detected = the adaptation event that could not start "
    "filtered (stamp) - set; recovered = the Adaptation Engine's selection of Direct again "
    "(stamp: filtered taken as unavailable) - set; a fresh system per run (the "
    "implementation stays unavailable until its probe)",
    "forged": "a value missing, NaN, inf, 1e9 (outside Level's plausible bounds) and not "
    "msgpack, put on the source's key from this session; detected = all counted in the "
    "Context Monitor leader's refusals (polled) - the first put; no selection of Filtered",
}


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="repetitions per fault (default 5)")
    ap.add_argument("--load", action="store_true", help="run tools/cpuhog.py meanwhile")
    ap.add_argument("--only", choices=[r.key for r in ROWS], action="append", help="these only")
    ap.add_argument("--keep", metavar="DIR", help="keep the runs' logs in DIR")
    ap.add_argument("--quiet", "-q", action="store_true", help="the table only")
    args = ap.parse_args()
    if args.runs < 1:
        ap.error("--runs must be at least 1")

    def say(text: str) -> None:
        if not args.quiet:
            print(text, file=sys.stderr, flush=True)

    signal.signal(signal.SIGTERM, _terminate)
    signal.signal(signal.SIGHUP, _terminate)
    atexit.register(end_all)
    started = time.monotonic()
    work = Path(args.keep or tempfile.mkdtemp(prefix="rra-faults-")).resolve()
    work.mkdir(parents=True, exist_ok=True)
    results: list[tuple[Row, list[Sample]]] = []
    shutdowns: list[str] = []
    try:
        if args.load:
            spawn([sys.executable, str(ROOT / "tools" / "cpuhog.py")], None)
            say(f"load: tools/cpuhog.py, {os.cpu_count()} busy loops")
        for row in ROWS:
            if args.only and row.key not in args.only:
                continue
            say(f"{row.title}:")
            samples, notes = run_row(row, args.runs, work, say)
            results.append((row, samples))
            shutdowns += notes
    except KeyboardInterrupt:
        print("interrupted: stopping every process started", file=sys.stderr)
        end_all()
        return 130
    finally:
        end_all()
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    took = time.monotonic() - started
    title = f"Faults, {args.runs} run(s) each" + (" (under load)" if args.load else "")
    print()
    print(title)
    print_table(
        ["fault", "detected ms med/p99", "goal", "recovered ms med/p99", "goal", "restarted",
         "state survived", "verdict"],
        [table_row(row, samples) for row, samples in results],
    )  # fmt: skip
    print()
    for i, (row, samples) in enumerate(results, 1):
        more = extras(samples)
        print(f"[{i}] {row.title}: {FOOTNOTES[row.key]}" + (f". {more}" if more else ""))
        for n, s in enumerate(samples, 1):
            if s.error:
                print(f"    run {n} failed: {s.error}")
            elif s.notes:
                print(f"    run {n}: {'; '.join(s.notes)}")
    print(
        "state = the operator's sink.offset = 4.0 (set through the resolution engine) in the "
        "node after the fault (rows 1-3, 6, 7, 9), the new leader's model (4, 8) or "
        "selection (5)"
    )
    for note in shutdowns:
        print(f"note: {note}")
    errors = any(s.error for _, samples in results for s in samples)
    where = f"; logs in {work}" if args.keep else ""
    if errors and not args.keep:
        where = "; logs removed (--keep DIR keeps them)"
    print(f"took {took:.0f} s on {os.cpu_count()} cores{where}")
    failed = any(table_row(r, s)[-1] != "PASS" for r, s in results)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
