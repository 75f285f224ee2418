"""Run a scenario case against a real system and judge it on what was recorded.

`run_case` starts ``rra up --host <first host>`` as a subprocess (its own free loopback
port, multicast off, its own run folder) and, for every other host of the case, an
``rra agent`` (log folder ``hosts/<host>/`` of the run folder) whose router joins the first
host's through a `Link` the runner owns: ``cut_link``/``restore_link`` steps pull and plug
its cable, a network partition on one machine. The agents start first (their links hold
them until ``rra up`` listens); the run starts once every agent's token is seen. The runner
connects to the first host's bus and records what the expectations need: every event
(``AdaptationEvent``, ``NodeState``), selection and conflict report, every context
measurement, the data topics the expectations name, the parameters of the nodes they name
(sampled every ``sample_period``), and at the end every host agent's node list (the pids a
cut-off host's events could not report). Time 0 is the deployment: the Run-time Resolution
Engine's ``deploy`` event. The timeline is applied on schedule (each step at ``t0 + at``);
after ``duration`` seconds every process started is stopped (SIGINT, as Ctrl-C) and the run
is checked for processes that outlived it (every process of the run carries a marker in its
environment; each is started in a session of its own, with a parent-death signal).

Evaluation is separate and pure: `evaluate_case` takes the case and the `Recording` and
returns one `Row` per expectation (plus one per timeline step that could not be applied).
The recording is saved as ``recording.msgpack`` next to the system's ``events.jsonl`` and
logs; `run_case` returns it with the rows in a `CaseRun`. A node that failed with a report
(an exception of its code, an external command's last output: `NodeState.failure`) is a
*crash*: its log is copied to ``crashed/<node>.log`` of the run folder, kept even when the
case passes (`prune`), and the verdict names what it raised and where (`render_crashes`).
"""

from __future__ import annotations

import contextlib
import heapq
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import yaml
import zenoh

from rra_agent import text
from rra_agent.bus import failure
from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply, decoded, wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.bus.data import decode_data, encode_data
from rra_agent.bus.session import NoPeer
from rra_agent.engines.events import read_events
from rra_agent.errors import RraError
from rra_agent.host.processes import die_with_parent
from rra_agent.package.yamlload import SafeLoader
from rra_agent.scenario import expectations as x
from rra_agent.scenario.link import Link
from rra_agent.scenario.model import ENGINES, ScenarioCase, TimedStep

MARKER_ENV = "RRA_SCENARIO_RUN"
_EVT = m.Codec[m.EventMessage](m.EventMessage)
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
_CTX = m.Codec[m.CtxMessage](m.CtxMessage)
_STATE = m.Codec[m.StateMessage](m.StateMessage)
_INJ = m.Codec[m.Injection](m.Injection)
_SIGNALS = {"kill": signal.SIGKILL, "freeze": signal.SIGSTOP, "resume": signal.SIGCONT}


class RunError(Exception):
    """The run itself failed (the system did not come up, or died)."""


# ---- results ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Row:
    """One line of the verdict: an expectation (or a timeline step) and its outcome."""

    text: str
    where: str
    outcome: x.Outcome
    expectation: x.Expectation | None = None


@dataclass(frozen=True)
class Crash:
    """A node that failed during the run, with what it raised, and its log as kept."""

    node: str
    host: str
    state: str
    failure: m.Failure
    log: Path | None


@dataclass
class CaseRun:
    case: ScenarioCase
    run_dir: Path
    rows: list[Row] = field(default_factory=list)
    error: str | None = None
    seconds: float = 0.0
    recording: x.Recording | None = None
    crashes: list[Crash] = field(default_factory=list)

    @property
    def passed(self) -> bool:
        return self.error is None and all(r.outcome.passed for r in self.rows)

    @property
    def failures(self) -> list[Row]:
        return [r for r in self.rows if not r.outcome.passed]

    @property
    def events_log(self) -> Path:
        return self.run_dir / "events.jsonl"

    def artifacts(self) -> list[Path]:
        """What to look at after a failure: the events log, recordings, the run's log."""
        out = [self.events_log, *sorted(self.run_dir.rglob("*.rrd"))]
        out += [self.run_dir / "recording.msgpack", self.run_dir / "up.log"]
        out += sorted(self.run_dir.glob("hosts/*/agent.log"))
        out += [c.log for c in self.crashes if c.log is not None]
        return [p for p in out if p.exists()]


CRASHED = "crashed"
RESULTS = "results.txt"


def crashed_states(events: list[m.EventMessage]) -> list[m.NodeState]:
    """The last failure (a `NodeState` with a ``failure``) of each node, in the order the
    nodes first failed."""
    last: dict[str, m.NodeState] = {}
    for ev in sorted(events, key=lambda e: e.stamp):
        if isinstance(ev, m.NodeState) and ev.failure is not None:
            last[ev.node] = ev
    return list(last.values())


def keep_crash_logs(
    run_dir: Path, states: list[m.NodeState], hosts: tuple[str, ...]
) -> list[Crash]:
    """Copy each crashed node's log (the one its failure names, else its host's copy in the
    run folder) to ``crashed/<node>.log``."""
    out = []
    for st in states:
        assert st.failure is not None
        kept = None
        candidates = [Path(st.failure.log)] if st.failure.log else []
        candidates += [run_dir / "logs" / f"{st.node}.log"]
        candidates += [host_dir(run_dir, h) / "logs" / f"{st.node}.log" for h in hosts]
        src = next((c for c in candidates if c.is_file()), None)
        if src is not None:
            kept = run_dir / CRASHED / f"{st.node}.log"
            kept.parent.mkdir(exist_ok=True)
            with contextlib.suppress(OSError):
                shutil.copyfile(src, kept)
        out.append(Crash(st.node, st.host, st.state, st.failure, kept))
    return out


def prune(run: CaseRun) -> None:
    """Remove a passed case's run folder, but for its crashed nodes' logs and its verdict."""
    if not run.crashes:
        shutil.rmtree(run.run_dir, ignore_errors=True)
        return
    for entry in run.run_dir.iterdir():
        if entry.name in (CRASHED, RESULTS):
            continue
        if entry.is_dir() and not entry.is_symlink():
            shutil.rmtree(entry, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                entry.unlink()


def evaluate_case(case: ScenarioCase, rec: x.Recording) -> list[Row]:
    """Judge every expectation of ``case`` on ``rec`` (pure: no I/O)."""
    idx = x.Index(rec)
    rows = []
    applied = {a.name: a for a in rec.injections}
    for t in case.timeline:
        a = applied.get(t.name)
        if a is not None and not a.ok:
            where = f"{t.location.file}:{t.location.line}"
            rows.append(
                Row(f"step {t.name} ({t.step.action})", where, x.Outcome(False, a.detail, a.at))
            )
    for e in case.expectations:
        rows.append(Row(e.text, e.where(), x.evaluate(e, idx), e))
    return rows


# ---- the package a case runs -----------------------------------------------------------------
def prepare_package(case: ScenarioCase, run_dir: Path) -> Path:
    """The package to run: the case's own, or a copy with the replacement strategies of the
    scenario written into its Run-time Resolution Model."""
    if case.replacement is None:
        return case.package
    dst = run_dir / "package"
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(
        case.package, dst, ignore=shutil.ignore_patterns("*.scenario.yaml", "__pycache__")
    )
    runtime = dst / case.runtime_file
    data = yaml.load(runtime.read_text(encoding="utf-8"), SafeLoader) if runtime.exists() else None
    data = data or {}
    data["replacement"] = msgspec.to_builtins(case.replacement)
    runtime.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return dst


def up_command(case: ScenarioCase, package: Path, run_dir: Path, endpoint: str) -> list[str]:
    cmd = [sys.executable, "-m", "rra_agent", "up", str(package), "--run-dir", str(run_dir)]
    cmd += ["--host", case.host, "--connect", endpoint, "--no-multicast", "--lease-ms", "500", "-q"]
    if case.select:
        cmd += ["--select", ",".join(case.select)]
    if not case.adaptation:
        cmd.append("--no-adaptation")
    return cmd + list(case.up_args)


def agent_command(
    case: ScenarioCase, host: str, package: Path, run_dir: Path, link: str
) -> list[str]:
    """``rra agent`` for ``host``: its router listens on a free loopback port and joins the
    first host's router through ``link``."""
    cmd = [sys.executable, "-m", "rra_agent", "agent", "--host", host, "--package", str(package)]
    cmd += ["--system", case.system, "--log-dir", str(host_dir(run_dir, host) / "logs")]
    cmd += ["--listen", f"tcp/127.0.0.1:{free_port()}", "--connect", link]
    if case.select:  # the same deployment-time selection as `rra up`: the same model
        cmd += ["--select", ",".join(case.select)]
    return [*cmd, "--no-multicast", "--lease-ms", "500"]


def host_dir(run_dir: Path, host: str) -> Path:
    """Where the agent of another host keeps its log and its nodes' logs."""
    return run_dir / "hosts" / host


# ---- recording -------------------------------------------------------------------------------
class Recorder:
    """Bus callbacks (on Zenoh's thread) appending what they receive."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.events: list[m.EventMessage] = []
        self.selections: list[m.SelectionMessage] = []
        self.effects: list[x.Effect] = []
        self._effect_seen: tuple[int, str, int] | None = None
        self.measurements: list[m.Measurement] = []
        self.data: list[x.DataSample] = []
        self.params: list[x.ParamSample] = []
        self.deployed = threading.Event()
        self.deploy_event: m.AdaptationEvent | None = None
        self.hosts: dict[str, str] = {}
        #: The host agents' node lists at the end of the run.
        self.nodes: list[m.NodeState] = []
        self._merged_size = 0

    def on_event(self, sample: Any) -> None:
        try:
            ev = _EVT.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        self.add_event(ev)

    def add_event(self, ev: m.EventMessage) -> None:
        with self.lock:
            self.events.append(ev)
            if isinstance(ev, m.NodeState):
                self.hosts[ev.node] = ev.host
        if isinstance(ev, m.AdaptationEvent) and ev.kind == "deploy" and self.deploy_event is None:
            self.deploy_event = ev
            self.deployed.set()

    def on_selection(self, sample: Any) -> None:
        with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
            msg = _SEL.decode(sample.payload.to_bytes())
            with self.lock:
                self.selections.append(msg)

    def on_state(self, sample: Any) -> None:
        """What is in effect, from the Run-time Resolution Engine leader's state (each
        version once: the leader republishes it unchanged every second)."""
        with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
            st = _STATE.decode(sample.payload.to_bytes())
            if not st.stamp:
                return
            version = (st.fence.epoch, st.fence.leader, st.version)
            with self.lock:
                if version != self._effect_seen:
                    self._effect_seen = version
                    self.effects.append(
                        x.Effect(st.stamp, list(st.effective), dict(st.effective_cv))
                    )

    def on_ctx(self, sample: Any) -> None:
        with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
            msg = _CTX.decode(sample.payload.to_bytes())
            with self.lock:
                self.measurements.append(msg)

    def on_data(self, topic: str) -> Callable[[Any], None]:
        def callback(sample: Any) -> None:
            try:
                value = decode_data(sample.payload.to_bytes())
            except ValueError:
                return
            att = sample.attachment
            stamp = m.unpack_stamp(att.to_bytes() if att else None) or time.time()
            with self.lock:
                self.data.append(x.DataSample(stamp, topic, value))

        return callback

    def merge_log(self, path: Path) -> None:
        """Add the events of the system's log that the subscription missed."""
        size = path.stat().st_size if path.exists() else 0
        if size == self._merged_size:
            return
        self._merged_size = size
        enc = msgspec.msgpack.Encoder()
        with self.lock:
            seen = {enc.encode(e) for e in self.events}
        for ev in read_events(path):
            if enc.encode(ev) not in seen:
                self.add_event(ev)


# ---- processes of the run ---------------------------------------------------------------------
def marked_pids(marker: str) -> list[int]:
    """Live (non-zombie) processes whose environment holds ``RRA_SCENARIO_RUN=marker``."""
    needle = f"{MARKER_ENV}={marker}".encode()
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if needle not in (entry / "environ").read_bytes().split(b"\0"):
                continue
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        if stat.rsplit(")", 1)[1].split()[0] != "Z":
            out.append(int(entry.name))
    return sorted(out)


def _wait_listening(port: int, proc: subprocess.Popen[bytes], timeout: float) -> None:
    """Until ``rra up`` accepts connections on ``port`` (RunError if it exits first)."""

    def listening() -> bool:
        if proc.poll() is not None:
            raise RunError(f"rra up exited with status {proc.returncode} before listening")
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.settimeout(0.2)
            return s.connect_ex(("127.0.0.1", port)) == 0

    try:
        wait_until(listening, timeout, f"rra up to listen on port {port}", interval=0.02)
    except TimeoutError as e:
        raise RunError(str(e)) from None


def _tail(path: Path, lines: int = 15) -> str:
    if not path.exists():
        return ""
    text = path.read_text(errors="replace").splitlines()[-lines:]
    return "\n".join("    " + t for t in text)


def _log_tails(run_dir: Path, hosts: tuple[str, ...]) -> str:
    """The end of ``rra up``'s log and of every agent's, for a run that failed."""
    logs = [("rra up", run_dir / "up.log")]
    logs += [(f"rra agent {h}", host_dir(run_dir, h) / "agent.log") for h in hosts]
    return "".join(
        f"\n  {what} log ({path}):\n{tail}" for what, path in logs if (tail := _tail(path))
    )


# ---- the run ---------------------------------------------------------------------------------
class _Run:
    def __init__(self, case: ScenarioCase, run_dir: Path, startup_timeout: float) -> None:
        self.case = case
        self.run_dir = run_dir
        self.startup_timeout = startup_timeout
        self.rec = Recorder()
        self.marker = uuid.uuid4().hex
        self.applied: dict[str, x.Applied] = {}
        #: Engine role -> the replica a freeze step stopped (what its resume continues).
        self.frozen: dict[str, str] = {}
        self.t0: float | None = None
        self.end: float = 0.0
        self.orphans: list[int] | None = None
        #: The other hosts' links to the first host, by host.
        self.links: dict[str, Link] = {}
        #: Every process started: ``rra up`` under the first host's name, the agents under theirs.
        self.procs: dict[str, subprocess.Popen[bytes]] = {}

    def execute(self) -> None:
        case, run_dir = self.case, self.run_dir
        package = prepare_package(case, run_dir)
        port = free_port()
        endpoint = f"tcp/127.0.0.1:{port}"
        try:
            for host in case.hosts:  # first: each link holds its agent until rra up listens
                link = self.links[host] = Link(("127.0.0.1", port))
                link.start()
                cmd = agent_command(case, host, package, run_dir, link.endpoint)
                self.spawn(host, cmd, host_dir(run_dir, host) / "agent.log")
            up = self.spawn(
                case.host, up_command(case, package, run_dir, endpoint), run_dir / "up.log"
            )
            _wait_listening(port, up, self.startup_timeout)
            self.record(endpoint)
        finally:
            self.stop()
            for link in self.links.values():
                link.close()

    def spawn(self, host: str, cmd: list[str], log_path: Path) -> subprocess.Popen[bytes]:
        """Start one process of the run: marked, in a session of its own (a Ctrl-C of the
        test runner reaches the runner, not it), killed if the runner dies."""
        env = {**os.environ, MARKER_ENV: self.marker, "RERUN_ANALYTICS": "0"}
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with log_path.open("wb") as log:
            proc = subprocess.Popen(
                cmd,
                env=env,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=die_with_parent if sys.platform == "linux" else None,
            )
        self.procs[host] = proc
        return proc

    def check_alive(self, what: str) -> None:
        """RunError if a process of the run exited (``what``: what it had not done yet)."""
        for host, proc in self.procs.items():
            if proc.poll() is not None:
                name = "rra up" if host == self.case.host else f"the agent of host {host}"
                raise RunError(f"{name} exited with status {proc.returncode} before {what}")

    def record(self, endpoint: str) -> None:
        # The recorder's own link keeps the shipped lease (2 s), whatever the system under
        # test runs with: a recorder starved for more than 500 ms (a loaded test machine)
        # had its link dropped by the router and lost every sample of that second.
        bus = BusConfig(connect=[endpoint], multicast=False)
        with BusClient(bus, self.case.system) as client:
            self.wait_hosts(client)
            keys, s, rec = client.keys, client.session, self.rec
            subs = [
                s.declare_subscriber(keys.events, rec.on_event),
                s.declare_subscriber(keys.selection, rec.on_selection),
                s.declare_subscriber(keys.state("resolution"), rec.on_state),
                s.declare_subscriber(keys.ctx_all, rec.on_ctx),
            ]
            topics = self.case.data_topics()
            subs += [s.declare_subscriber(keys.data(t), rec.on_data(t)) for t in topics]
            block = zenoh.CongestionControl.BLOCK
            publishers = {
                k: s.declare_publisher(f"{keys.prefix}/{k}", congestion_control=block)
                for k in {t.key for t in self.case.timeline if t.key}
                | {f"inject/{t.step.inject.kind}" for t in self.case.timeline if t.step.inject}
            }
            try:
                self.t0 = self.wait_deployed()
                # The query for the measurements published before we listened runs beside
                # the timeline: waiting for its replies (up to 1 s on a loaded machine) would
                # delay every step due at 0 s.
                latest = threading.Thread(
                    target=self.latest_measurements, args=(client,), name="ctx-latest"
                )
                latest.start()
                sampler = _Sampler(client, rec, self.case, self.t0)
                sampler.start()
                try:
                    self.play(client, publishers, self.t0)
                finally:
                    sampler.stop()
                    latest.join()
                self.end = time.time() - self.t0
                nodes = self.list_nodes(client)
                with rec.lock:
                    rec.nodes = nodes
            finally:
                for sub in subs:
                    sub.undeclare()
                for pub in publishers.values():
                    pub.undeclare()

    def wait_hosts(self, client: BusClient) -> None:
        """Until the first host's router sees every other host's agent (RunError if not)."""
        want = set(self.case.hosts)

        def joined() -> bool:
            self.check_alive("every host joined")
            replies = client.session.liveliness().get(client.keys.host_alive_all, timeout=0.5)
            seen = {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}
            return want <= seen

        if not want:
            return
        try:
            wait_until(joined, self.startup_timeout, f"the agents of {sorted(want)} to join")
        except TimeoutError as e:
            raise RunError(str(e)) from None

    def latest_measurements(self, client: BusClient) -> None:
        """Add the Context Monitor's newest value of each measurement not recorded yet: one
        published before the runner listened and not since (a host's reachability is
        published on change only)."""
        latest: dict[str, m.Measurement] = {}
        for msg in decoded(client.session.get(client.keys.ctx_all, timeout=1.0), _CTX):
            latest.setdefault(msg.name, msg)
        with self.rec.lock:
            seen = {ms.name for ms in self.rec.measurements}
            self.rec.measurements += [ms for n, ms in latest.items() if n not in seen]

    def list_nodes(self, client: BusClient) -> list[m.NodeState]:
        """Every host agent's nodes as it lists them now (a host that does not answer: none)."""
        out: list[m.NodeState] = []
        for host in (self.case.host, *self.case.hosts):
            try:
                reply = client.host(host, m.ListNodes(), 2.0)
            except NoReply:
                continue
            if isinstance(reply, m.Ok) and isinstance(reply.result, list):
                with contextlib.suppress(msgspec.ValidationError):
                    out += msgspec.convert(reply.result, list[m.NodeState])
        return out

    def wait_deployed(self) -> float:
        deadline = time.monotonic() + self.startup_timeout
        log = self.run_dir / "events.jsonl"
        while not self.rec.deployed.wait(0.1):
            self.rec.merge_log(log)  # in case the deploy event came before we listened
            if self.rec.deployed.is_set():
                break
            self.check_alive("deploying")
            if time.monotonic() >= deadline:
                raise RunError(f"no deployment within {self.startup_timeout:g} s")
        ev = self.rec.deploy_event
        assert ev is not None
        if ev.outcome != "ok":
            raise RunError(f"deployment failed: {ev.message}")
        return ev.stamp

    # -- the timeline
    def schedule(self) -> Iterator[tuple[float, int, TimedStep]]:
        """(time, order, step) of every action, publish repeats expanded."""
        for i, t in enumerate(self.case.timeline):
            yield t.step.at, i, t
            pub = t.step.publish
            if pub is not None and pub.every:
                until = min(self.case.duration, pub.until if pub.until is not None else 1e9)
                n = 1
                while t.step.at + n * pub.every <= until + 1e-9:
                    yield t.step.at + n * pub.every, i, t
                    n += 1

    def play(self, client: BusClient, publishers: dict[str, Any], t0: float) -> None:
        queue = list(self.schedule())
        heapq.heapify(queue)
        end = t0 + self.case.duration
        while queue:
            at, _, step = heapq.heappop(queue)
            _sleep_until(t0 + at)
            stamp = time.time()
            ok, detail = self.apply(client, publishers, step, stamp)
            if step.name not in self.applied:  # a repeated publish: its first time counts
                self.applied[step.name] = x.Applied(
                    name=step.name, at=at, stamp=stamp, ok=ok, detail=detail
                )
        _sleep_until(end)

    def apply(
        self, client: BusClient, publishers: dict[str, Any], t: TimedStep, stamp: float
    ) -> tuple[bool, str]:
        step = t.step
        try:
            if step.set_params is not None:
                sp = step.set_params
                from rra_agent.bus.client import set_params

                try:  # as an operator does: kept in the model, re-applied after restarts
                    set_params(client, sp.node, dict(sp.params))
                except RraError as e:
                    return False, str(e)
                return True, ""
            if step.publish is not None:
                publishers[t.key].put(
                    encode_data(step.publish.data), attachment=m.pack_stamp(stamp)
                )
                return True, ""
            if step.malformed is not None:
                publishers[t.key].put(bytes.fromhex(step.malformed.hex))
                return True, ""
            if step.inject is not None:
                inj = step.inject
                msg = m.Inject(kind=inj.kind, target=inj.target, args=dict(inj.args), stamp=stamp)
                publishers[f"inject/{inj.kind}"].put(_INJ.encode(msg))
                return True, ""
            if step.cut_link is not None:
                self.links[step.cut_link].cut()
                return True, ""
            if step.restore_link is not None:
                self.links[step.restore_link].restore()
                return True, ""
            action = step.action
            node = self.process_of(client, getattr(step, action), action)
            host = self.rec.hosts.get(node, self.case.host)
            return _reply(client.host(host, m.SignalNode(node=node, signal=int(_SIGNALS[action]))))
        except NoReply as e:
            return False, str(e)

    def process_of(self, client: BusClient, name: str, action: str) -> str:
        """A component's process, or for an engine role (``resolution``...) its leader's
        (the one frozen before, for ``resume``)."""
        if name not in ENGINES:
            return name
        if action == "resume" and name in self.frozen:
            return self.frozen.pop(name)
        reply = client.request(client.keys.engine_ctl(name), m.Status(), 2.0)
        if not isinstance(reply, m.Ok) or not reply.result.get("replica"):
            raise NoReply(f"no leader of the {name} engine answered")
        replica = str(reply.result["replica"])
        if action == "freeze":
            self.frozen[name] = replica
        return replica

    # -- the end
    def stop(self) -> None:
        """SIGINT to every process started, all at once (each stops its own nodes); SIGKILL
        of the process group of any still running after 30 s."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + 30.0
        for proc in self.procs.values():
            try:
                proc.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
        survivors = marked_pids(self.marker)
        for pid in survivors:  # ours, by the marker: never leave them behind
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        self.orphans = survivors

    def recording(self) -> x.Recording | None:
        if self.t0 is None:
            return None
        rec, case = self.rec, self.case
        rec.merge_log(self.run_dir / "events.jsonl")
        with rec.lock:
            return x.Recording(
                system=case.system,
                t0=self.t0,
                end=self.end,
                deployment=sorted(case.deployment),
                initial_features=sorted(case.initial_features),
                initial_cv=dict(case.initial_cv),
                swap_pairs=list(case.swap_pairs),
                events=list(rec.events),
                selections=list(rec.selections),
                effects=list(rec.effects),
                measurements=list(rec.measurements),
                data=list(rec.data),
                params=list(rec.params),
                injections=list(self.applied.values()),
                orphans=self.orphans,
                nodes=list(rec.nodes),
            )


class _Sampler:
    """Samples the parameters of the nodes the expectations read, every ``sample_period``."""

    def __init__(self, client: BusClient, rec: Recorder, case: ScenarioCase, t0: float) -> None:
        self.client, self.rec, self.case, self.t0 = client, rec, case, t0
        self.nodes = sorted(case.param_nodes())
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._run, name="param-sampler", daemon=True)

    def start(self) -> None:
        if self.nodes:
            self.thread.start()

    def stop(self) -> None:
        self.done.set()
        if self.thread.is_alive():
            self.thread.join()

    def _run(self) -> None:
        period = self.case.sample_period
        n = 0
        while not self.done.is_set():
            for node in self.nodes:
                stamp = time.time()
                try:
                    reply = self.client.node(node, m.Describe(), timeout=min(1.0, 4 * period))
                except NoReply:
                    continue
                if isinstance(reply, m.Ok) and isinstance(reply.result, dict):
                    params = reply.result.get("params", {})
                    with self.rec.lock:
                        self.rec.params.append(x.ParamSample(stamp, node, dict(params)))
            n += 1
            # The schedule: sample k at t0 + k * period (skipping any missed while blocked).
            next_at = self.t0 + n * period
            while next_at < time.time():
                n += 1
                next_at = self.t0 + n * period
            self.done.wait(next_at - time.time())


def _reply(reply: m.Reply) -> tuple[bool, str]:
    if isinstance(reply, m.Err):
        return False, f"{reply.message} ({reply.code})"
    return True, ""


def _sleep_until(wall: float) -> None:
    """Wait for a scheduled wall-clock time (the timeline is a schedule, not a sync)."""
    delay = wall - time.time()
    if delay > 0:
        time.sleep(delay)


def run_case(case: ScenarioCase, run_dir: Path, *, startup_timeout: float = 60.0) -> CaseRun:
    """Run ``case`` in ``run_dir`` (created; the system's logs and events go there too)."""
    started = time.monotonic()
    run_dir.mkdir(parents=True, exist_ok=True)
    run = _Run(case, run_dir, startup_timeout)
    error = None
    try:
        run.execute()
    except RunError as e:
        error = f"{e}" + _log_tails(run_dir, case.hosts)
    except NoPeer as e:
        error = f"cannot connect to the system: {e}"
    rec = run.recording()
    result = CaseRun(case, run_dir, error=error, recording=rec)
    if rec is not None:
        (run_dir / "recording.msgpack").write_bytes(x.save_recording(rec))
        result.rows = evaluate_case(case, rec)
    run.rec.merge_log(run_dir / "events.jsonl")  # a run that never deployed has events too
    with run.rec.lock:
        states = crashed_states(list(run.rec.events))
    result.crashes = keep_crash_logs(run_dir, states, case.hosts)
    result.seconds = time.monotonic() - started
    verdict = "\n\n".join(t for t in (render_rows([result]), render_crashes([result])) if t)
    (run_dir / RESULTS).write_text(verdict + "\n", encoding="utf-8")
    return result


# ---- the verdict as a table --------------------------------------------------------------------
def render_rows(runs: list[CaseRun], *, wide: bool = False) -> str:
    """``SCENARIO  EXPECTATION  OUTCOME  OBSERVED`` for every row of every run, in `WIDTH`
    columns: the expectation and what was observed wrapped in their columns (``wide``: one
    line per row)."""
    table = [("SCENARIO", "EXPECTATION", "OUTCOME", "OBSERVED")]
    for run in runs:
        if run.error is not None:
            table.append((run.case.id, "(the run)", "ERROR", run.error.splitlines()[0]))
        for r in run.rows:
            table.append(
                (run.case.id, r.text, "pass" if r.outcome.passed else "FAIL", r.outcome.observed)
            )
    return text.table(table, wrapping=(0, 1, 3), wide=wide)


def render_crashes(runs: list[CaseRun], *, wide: bool = False) -> str:
    """One line per node that crashed in ``runs``: what it raised and where, then its kept
    log (nothing when none did); wrapped at `WIDTH` unless ``wide``."""
    lines = []
    for run in runs:
        for c in run.crashes:
            head = f"{run.case.id}: node {c.node} crashed ({c.state}): {failure.summary(c.failure)}"
            lines += text.wrap(head, indent="    ", wide=wide)
            lines.append(f"    log: {c.log}" if c.log else "    log: not found")
    return "\n".join(lines)


def describe_failure(run: CaseRun, *, wide: bool = False) -> str:
    """What failed, where (scenario file:line) and what was observed; the nodes that
    crashed, with what they raised; the kept artefacts. The ``file:line: expectation
    failed`` lines stay whole (editors jump to them); the rest is wrapped at `WIDTH`."""
    lines = text.wrap(
        f"scenario {run.case.id} ({run.case.file}) failed after {run.seconds:.1f} s:", wide=wide
    )
    if run.error is not None:
        first, *rest = f"  the run failed: {run.error}".splitlines()
        lines += text.wrap(first, indent="    ", wide=wide) + rest
    for r in run.failures:
        lines.append(f"{r.where}: expectation failed: {r.text}")
        lines += text.wrap(f"    observed: {r.outcome.observed}", indent="      ", wide=wide)
    for c in run.crashes:
        crashed = f"  node {c.node} crashed ({c.state}): {failure.summary(c.failure)}"
        lines += text.wrap(crashed, indent="    ", wide=wide)
    for p in run.artifacts():
        lines.append(f"  kept: {p}")
    return "\n".join(lines)
