"""Several machines for real: hosts in Linux network namespaces (tests/netns.py), the `rra` CLI
in each, a link delay from tools/delay_proxy.py.

Topology as deployed (rra_agent/bus/config.py): one Zenoh router per host, run by its agent —
``rra up`` on A (hub ``tcp/127.0.0.1:7447`` and ``tcp/<A>:7447`` for the other hosts),
``rra agent --connect tcp/<A>:7447 --listen tcp/127.0.0.1:7447`` on B and C — and every
process of a host a client of its own host's router over loopback. Each namespace has its own
loopback, so every host uses port 7447. The system is tests/data/relay_system: a Ticker
``source`` whose value is the measurement Level; Level above 5 selects Filtered (swap
``direct`` -> ``filtered``, rewire ``sink.in`` from ``direct.out`` to ``filtered.out``), and
the CV Gain follows Level into ``sink.offset``.

Deadlines, never sleeps; the ``network`` fixture fails a test that leaves a process in a
namespace or one that ignored SIGINT, and deletes the namespaces whatever happens. Skipped
where namespaces cannot be made (not root).

Run as a script, this file is what the tests start inside a namespace (see `probe`): ``serve``
(one client session of the host's router answering ``status`` — what ``rra status --json``
prints —, ``describe NODE``, ``samples TOPIC MIN`` on stdin, so that polling does not start a
process per poll), ``tcp-serve`` and ``tcp-client``.
"""

from __future__ import annotations

import json
import os
import select
import socket
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.append(str(ROOT / "tools"))

import netns  # noqa: E402
from delay_proxy import DelayProxy  # noqa: E402
from netns import Network, tcp_peers, wait_for  # noqa: E402

network = netns.network  # the fixture: network("A", "B", ...) -> Network

SYSTEM = "relay_system"
PORT = 7447  # every host's router, on its own loopback (and A's also on its address)
HUB = f"tcp/127.0.0.1:{PORT}"
TLS_HUB = f"tls/127.0.0.1:{PORT}"
LOCAL_ROUTER = ("127.0.0.1", PORT)
DELAY_MS = 20.0

pytestmark = [
    pytest.mark.system,
    pytest.mark.skipif(sys.platform != "linux", reason="network namespaces: Linux"),
]


# ---- clients inside a namespace -----------------------------------------------------------
class Lines:
    """Lines of a process's unbuffered binary stdout, each with a deadline."""

    def __init__(self, proc: subprocess.Popen) -> None:
        self.fd = proc.stdout.fileno()  # type: ignore[union-attr]
        self.buf = b""

    def read(self, timeout: float) -> str | None:
        """The next line; None if none within ``timeout`` (or at EOF)."""
        deadline = time.monotonic() + timeout
        while b"\n" not in self.buf:
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.fd], [], [], left)[0]:
                return None
            chunk = os.read(self.fd, 1 << 16)
            if not chunk:
                return None
            self.buf += chunk
        line, _, self.buf = self.buf.partition(b"\n")
        return line.decode().strip()


class Rra:
    """A host's view of the system: `rra` commands and a long-lived probe (this file run as a
    script, one client session for all its requests: no process start per poll), both
    clients of the host's own router."""

    def __init__(self, net: Network, host: str = "A", certs: Path | None = None) -> None:
        self.net, self.host = net, host
        #: With certificates: the operator's identity, TLS to the host's router (the `rra`
        #: commands and the probe read it from RRA_BUS_CONFIG).
        self.hub = TLS_HUB if certs else HUB
        self.env: dict[str, str] = {}
        if certs is not None:
            from rra_agent.bus.config import ENV_VAR, BusConfig

            bus = BusConfig(connect=[TLS_HUB]).with_identity(certs / "operator", "operator")
            self.env[ENV_VAR] = bus.to_env()
        self._probe: subprocess.Popen | None = None
        self._lines: Lines | None = None

    def cli(self, *args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
        """``python ARGS`` in the host's namespace, to completion."""
        proc = self.net.python(self.host, *args, stdout=subprocess.PIPE, env=self.env,
                               stderr=subprocess.PIPE, text=True)  # fmt: skip
        try:
            out, err = proc.communicate(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.net.stop(proc, 2)
            raise AssertionError(f"{' '.join(args)}: no answer in {timeout} s") from None
        return subprocess.CompletedProcess(args, proc.returncode, out, err)

    def status_cli(self) -> dict:
        """``rra status --json``."""
        done = self.cli("-m", "rra_agent", "status", "--system", SYSTEM, "--connect", self.hub,
                        "--json")  # fmt: skip
        assert done.returncode == 0, done.stderr
        return json.loads(done.stdout)

    def param(self, node: str, *assignments: str) -> str:
        """``rra param NODE NAME=VALUE...``."""
        done = self.cli("-m", "rra_agent", "param", "--system", SYSTEM, "--connect", self.hub, node,
                        *assignments)  # fmt: skip
        assert done.returncode == 0, done.stderr
        return done.stdout

    def call(self, *request: str, timeout: float = 30):
        """One request to the probe (started on first use): its JSON answer."""
        if self._probe is None:
            with (self.net.log_dir / f"probe-{self.host}.log").open("ab") as err:
                self._probe = self.net.python(
                    self.host, str(Path(__file__)), "serve", name=f"probe-{self.host}",
                    env=self.env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=err,
                    bufsize=0,
                )  # fmt: skip
            self._lines = Lines(self._probe)
            ready = self._lines.read(30)
            assert ready == "ready", f"probe in {self.host}: {ready!r}\n{self.net.logs()}"
        assert self._probe.stdin is not None and self._lines is not None
        self._probe.stdin.write(json.dumps(request).encode() + b"\n")
        line = self._lines.read(timeout)
        assert line is not None, f"probe {request}: no answer in {timeout} s\n{self.net.logs()}"
        answer = json.loads(line)
        assert "error" not in answer, f"probe {request}: {answer['error']}"
        return answer["ok"]

    def close(self) -> None:
        """End the probe (EOF on its stdin): it closes its session and exits 0."""
        if self._probe is not None:
            probe, self._probe = self._probe, None
            probe.stdin.close()  # type: ignore[union-attr]
            try:
                probe.wait(10)
            except subprocess.TimeoutExpired:
                self.net.stop(probe, 2)
            assert probe.returncode == 0, self.net.log(f"probe-{self.host}")

    def status(self) -> dict:
        """What ``rra status --json`` prints (`rra_agent.bus.client.gather`)."""
        return self.call("status")

    def wait(self, pred, what: str, timeout: float = 30) -> dict:
        last: dict = {}

        def check():
            nonlocal last
            last = self.status()
            return last if pred(last) else None

        try:
            return wait_for(check, timeout, what, 0.2)
        except TimeoutError as e:
            raise AssertionError(f"{e}; last status: {last}\n{self.net.logs()}") from None


def running(st: dict) -> dict:
    """The engine's running components (empty while the engine does not answer)."""
    return (st.get("engine") or {}).get("running", {})


def node(st: dict, name: str) -> dict:
    return next((n for n in st.get("nodes", []) if n["node"] == name), {"state": "ABSENT"})


def deployed(st: dict) -> bool:
    return "sink" in running(st) and not st["engine"].get("failed")


def placed(tmp_path: Path, hosts: dict[str, str]) -> Path:
    """A copy of relay_system with hosts A, B, ... and each component on ``hosts[name]``
    (default A)."""
    from conftest import edit_yaml, package_copy

    pkg = package_copy(tmp_path)
    names = sorted({"A", *hosts.values()})

    def place(data: dict) -> None:
        data["hosts"] = [{"name": h} for h in names]
        for c in data["components"]:
            c["host"] = hosts.get(c["name"], "A")

    edit_yaml(pkg / "system.yaml", place)
    return pkg


def certificates(net: Network, pkg: Path, tmp_path: Path) -> Path:
    """``rra certs``: the system CA, each host's certificates (A's also for its address, which
    the other hosts dial) and the operator's."""
    out = tmp_path / "certs"
    done = subprocess.run([sys.executable, "-m", "rra_agent", "certs", str(pkg), "--out",
                           str(out), "--san", f"A={net.addr('A')}"], capture_output=True,
                          text=True, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    return out


def start_system(
    net: Network, pkg: Path, tmp_path: Path, others: list[str], *up_args: str,
    certs: Path | None = None, agent_args: tuple[str, ...] = (),
):  # fmt: skip
    """``rra up`` in A, ``rra agent`` in every other host; (up, {host: agent}). With
    ``certs``: mutual TLS on every link and the model's access control on every router."""
    a = net.addr("A")
    proto = "tls" if certs else "tcp"

    def secure(host: str) -> list[str]:
        return ["--certs", str(certs / host)] if certs else ["--insecure"]

    agents = {
        h: net.python(h, "-m", "rra_agent", "agent", "--system", SYSTEM, "--host", h,
                      "--package", str(pkg), "--connect", f"{proto}/{a}:{PORT}",
                      "--listen", f"{proto}/127.0.0.1:{PORT}", *secure(h), *agent_args,
                      "--log-dir", str(tmp_path / f"{h}-logs"), name=f"agent-{h}")
        for h in others
    }  # fmt: skip
    up = net.python("A", "-m", "rra_agent", "up", str(pkg), "--host", "A", "-q",
                    "--run-dir", str(tmp_path / "run"), "--connect", f"{proto}/127.0.0.1:{PORT}",
                    "--listen", f"{proto}/{a}:{PORT}", *secure("A"), *up_args,
                    name="up")  # fmt: skip
    net.wait_listening("A", PORT, a, proc=up)
    for h, proc in agents.items():
        net.wait_listening(h, PORT, "127.0.0.1", proc=proc)
    return up, agents


def assert_local_clients(net: Network, host: str, st: dict, names: list[str]) -> None:
    """Every established connection of these nodes is to their own host's router."""
    for name in names:
        n = node(st, name)
        assert n["host"] == host and n["state"] == "RUNNING", n
        assert tcp_peers(n["pid"], net.ns(host)) == {LOCAL_ROUTER}, (name, host)


def stop_all(net: Network, up, agents: dict, *clients: Rra) -> None:
    """The clients end; Ctrl-C of every host agent (the other hosts first): each exits 0."""
    for c in clients:
        c.close()
    for h, proc in agents.items():
        assert net.stop(proc) == 0, f"agent {h}:\n{net.logs()}"
    assert net.stop(up) == 0, net.logs()
    assert not net.processes(), "processes left in the namespaces"


# ---- the delay proxy ------------------------------------------------------------------------
def _echo_server() -> socket.socket:
    srv = socket.create_server(("127.0.0.1", 0))

    def serve() -> None:
        while True:
            try:
                conn, _ = srv.accept()
            except OSError:
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

            def echo(c: socket.socket = conn) -> None:
                with c:
                    while data := c.recv(1 << 16):
                        c.sendall(data)

            threading.Thread(target=echo, daemon=True).start()

    threading.Thread(target=serve, daemon=True).start()
    return srv


def test_delay_proxy_delays_each_direction_without_limiting_throughput():
    srv = _echo_server()
    with (
        srv,
        DelayProxy(("127.0.0.1", 0), srv.getsockname(), DELAY_MS) as proxy,
        socket.create_connection(("127.0.0.1", proxy.port)) as s,
    ):
        s.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        rtts = []
        for i in range(20):
            msg = f"{i:08d}".encode() * 8
            t0 = time.perf_counter()
            s.sendall(msg)
            got = b""
            while len(got) < len(msg):
                got += s.recv(len(msg) - len(got))
            rtts.append(time.perf_counter() - t0)
            assert got == msg
        assert min(rtts) >= 2 * DELAY_MS / 1e3
        assert statistics.median(rtts) < (2 * DELAY_MS + 10) / 1e3, rtts
        # 16 MB each way: one delay, not one per chunk (a stop-and-wait relay of 256 KB
        # chunks would take 64 x 40 ms).
        blob = os.urandom(1 << 20) * 16
        t0 = time.perf_counter()
        sender = threading.Thread(target=lambda: (s.sendall(blob), s.shutdown(socket.SHUT_WR)))
        sender.start()
        received = bytearray()
        while data := s.recv(1 << 20):
            received += data
        sender.join()
        assert received == blob
        assert time.perf_counter() - t0 < 1.5
    assert proxy.accepted == 1


# ---- the network itself -----------------------------------------------------------------------
def test_a_cut_link_is_a_pulled_cable_and_tcp_survives_it(network):
    net = network("A", "B")
    a = net.addr("A")
    assert a != net.addr("B") and net.ns("A") != net.ns("B")
    server = net.python("A", str(Path(__file__)), "tcp-serve", a, "9000", name="tcp-serve")
    net.wait_listening("A", 9000, a, proc=server)
    client = net.python("B", str(Path(__file__)), "tcp-client", a, "9000", name="tcp-client",
                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, bufsize=0)  # fmt: skip
    lines = Lines(client)

    def say(text: str) -> None:
        client.stdin.write(text.encode() + b"\n")  # type: ignore[union-attr]
        client.stdin.flush()  # type: ignore[union-attr]

    assert lines.read(10) == "connected"
    say("one")
    assert lines.read(5) == "ok one"
    net.cut("B")
    say("two")
    # Silence, not an error: no RST, no "unreachable" on either side.
    assert lines.read(1.0) is None
    assert server.poll() is None and client.poll() is None
    net.restore("B")
    assert lines.read(10) == "ok two"  # the same connection, retransmitted
    say("three")
    assert lines.read(5) == "ok three"
    client.stdin.close()  # type: ignore[union-attr]
    assert client.wait(5) == 0
    assert "connection from" in net.log("tcp-serve")


def test_teardown_kills_and_reports_what_outlives_its_stop(tmp_path):
    # A process that ignores SIGINT, and a grandchild that left the process group.
    stubborn = (
        "import os, signal, subprocess, sys, time\n"
        "signal.signal(signal.SIGINT, signal.SIG_IGN)\n"
        "subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'],"
        " start_new_session=True)\n"
        "print('ready', flush=True)\n"
        "time.sleep(60)\n"
    )
    try:
        net = Network(("A",), log_dir=tmp_path, stop_timeout=0.5).__enter__()
    except netns.NetnsUnavailable as e:
        pytest.skip(f"network namespaces unavailable: {e}")
    names = [net.ns("A"), net.bridge_ns]
    proc = net.python("A", "-c", stubborn, name="stubborn")
    wait_for(lambda: "ready" in net.log("stubborn"), 10, "the stubborn process")
    wait_for(lambda: len(net.processes()) == 2, 5, "its grandchild")
    pids = net.processes()
    problems = net.close()
    assert len(problems) == 2, problems
    assert "stubborn: ignored SIGINT" in problems[0]
    assert problems[1].startswith("left in the namespaces: ") and "sleep(60)" in problems[1]
    assert proc.returncode == -9
    assert not any(netns.pid_alive(pid) for pid in pids)  # gone or a zombie of init
    listed = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert not any(n in listed.split() for n in names)


# ---- the runtime on several hosts ------------------------------------------------------------
def test_two_hosts_each_runs_its_nodes_and_a_swap_happens_on_b(network, tmp_path):
    net = network("A", "B")
    pkg = placed(tmp_path, {"direct": "B", "filtered": "B", "sink": "B"})
    up, agents = start_system(net, pkg, tmp_path, ["B"], "--rerun", "save")
    rra = Rra(net, "A")
    st = rra.wait(deployed, "the deployment")
    # One Rerun recording for all hosts: B's agent took the run's configuration from the
    # engine, its nodes write under B's log folder.
    recording = st["engine"]["rerun"]["recording_id"]
    rerun_dir = tmp_path / "B-logs" / "rerun" / recording
    assert rerun_dir.is_dir() and f"Rerun files of this host in {rerun_dir}" in net.log("agent-B")
    hosts = {n["node"]: n["host"] for n in st["nodes"]}
    assert hosts["source"] == "A" and hosts["resolution-a"] == "A"
    assert hosts["direct"] == "B" and hosts["sink"] == "B"
    assert set(st["hosts"]) == {"A", "B"}
    assert (tmp_path / "B-logs" / "sink.log").exists()
    assert not (tmp_path / "run" / "logs" / "sink.log").exists()
    # B's nodes are clients of B's router only; B's router is linked to A's.
    assert_local_clients(net, "B", st, ["direct", "sink"])
    assert (net.addr("A"), PORT) in tcp_peers(agents["B"].pid, net.ns("B"))
    sink_pid = node(st, "sink")["pid"]

    rra.param("source", "value=7")
    st = rra.wait(lambda s: "filtered" in running(s)
                  and node(s, "filtered").get("state") == "RUNNING"
                  and node(s, "direct").get("state") == "STOPPED", "the swap on B")  # fmt: skip
    assert "direct" not in st["engine"]["running"]
    assert node(st, "filtered")["host"] == "B"
    assert node(st, "sink")["pid"] == sink_pid  # rewired in place
    assert_local_clients(net, "B", st, ["filtered", "sink"])
    # `rra status --json` in A shows the same.
    cli = rra.status_cli()
    assert {n["node"]: n["host"] for n in cli["nodes"] if n["state"] == "RUNNING"} == {
        n["node"]: n["host"] for n in st["nodes"] if n["state"] == "RUNNING"
    }
    assert set(cli["engine"]["running"]) == {"source", "filtered", "sink"}
    stop_all(net, up, agents, rra)


def test_peer_nodes_link_to_each_other_on_their_host_and_reach_other_hosts_via_routers(
    network, tmp_path
):
    """``--peer-nodes`` on both hosts: B's nodes link to B's router and directly to each
    other, all on loopback, never to A; A's source still reaches B's sink through the two
    routers, and a swap on B rewires B's sink."""
    net = network("A", "B")
    pkg = placed(tmp_path, {"direct": "B", "filtered": "B", "sink": "B"})
    up, agents = start_system(net, pkg, tmp_path, ["B"], "--peer-nodes",
                              agent_args=("--peer-nodes",))  # fmt: skip
    rra, on_b = Rra(net, "A"), Rra(net, "B")
    st = rra.wait(deployed, "the deployment")
    got = on_b.call("samples", "sink/out", "1")  # A's source -> B's direct -> B's sink
    assert got["relay"] == "sink"
    for name in ("direct", "sink"):
        n = node(st, name)
        links = tcp_peers(n["pid"], net.ns("B"))
        assert LOCAL_ROUTER in links, (name, links)
        assert {addr for addr, _ in links} == {"127.0.0.1"}, (name, links)  # never to A
        assert len(links) >= 2, (name, links)  # and to the other node of B, directly
    rra.param("source", "value=7")
    rra.wait(lambda s: "filtered" in running(s) and node(s, "filtered").get("state") == "RUNNING"
             and node(s, "direct").get("state") == "STOPPED", "the swap on B")  # fmt: skip
    got = on_b.call("samples", "sink/out", "114")  # 7 + 100 (filtered) + 7 (the CV Gain)
    assert got["relay"] == "sink" and got["value"] >= 114
    stop_all(net, up, agents, rra, on_b)


def test_round_trip_on_b_stays_local_when_the_link_to_a_is_slow(network, tmp_path):
    net = network("A", "B")
    pkg = placed(tmp_path, {})
    a = net.addr("A")
    proxy = net.python("A", str(ROOT / "tools" / "delay_proxy.py"), "--listen", f"{a}:7448",
                       "--target", f"{a}:{PORT}", "--delay-ms", f"{DELAY_MS:g}",
                       name="delay-proxy")  # fmt: skip
    agent_a = net.python("A", "-m", "rra_agent", "agent", "--system", SYSTEM, "--host", "A",
                         "--package", str(pkg), "--hub", "--connect", HUB,
                         "--listen", f"tcp/{a}:{PORT}", "--insecure",
                         "--log-dir", str(tmp_path / "A-logs"), name="agent-A")  # fmt: skip
    net.wait_listening("A", 7448, a, proc=proxy)
    net.wait_listening("A", PORT, a, proc=agent_a)
    agent_b = net.python("B", "-m", "rra_agent", "agent", "--system", SYSTEM, "--host", "B",
                         "--package", str(pkg), "--connect", f"tcp/{a}:7448",
                         "--listen", HUB, "--insecure",
                         "--log-dir", str(tmp_path / "B-logs"), name="agent-B")  # fmt: skip
    net.wait_listening("B", PORT, "127.0.0.1", proc=agent_b)
    zping = str(ROOT / "tools" / "zping.py")
    net.python("B", zping, "echo", "--connect", HUB, "--name", "onB", name="echo-B")
    net.python("A", zping, "echo", "--connect", HUB, "--name", "onA", name="echo-A")

    def ping(name: str, n: int) -> list[float]:
        done = Rra(net, "B").cli(zping, "ping", "--connect", HUB, "--name", name, "--n", str(n),
                                 timeout=60)  # fmt: skip
        assert done.returncode == 0, done.stdout + done.stderr
        out = json.loads(done.stdout)
        assert not out["lost"], out
        return out["rtt"]

    far = ping("onA", 30)  # B -> A -> B: the link twice
    near = ping("onB", 200)  # B -> B: B's router only
    # B's router reaches A only through the proxy.
    assert wait_for(lambda: (a, 7448) in tcp_peers(agent_b.pid, net.ns("B")), 5, "B -> proxy")
    assert (a, PORT) not in tcp_peers(agent_b.pid, net.ns("B"))
    assert min(far) >= 2 * DELAY_MS / 1e3, far
    assert statistics.median(far) < (2 * DELAY_MS + 30) / 1e3, far
    assert statistics.median(near) < 5e-3, sorted(near)[::20]
    for proc in (agent_b, agent_a):
        assert net.stop(proc) == 0, net.logs()


def partition_package(tmp_path: Path) -> Path:
    """relay_system with ``sink`` on B and a rule on B's reachability: while B is cut off,
    A swaps to the Filtered path (on A); B's ``sink`` is needed in both variants."""
    pkg = placed(tmp_path, {"sink": "B"})
    with (pkg / "measurements.yaml").open("a") as f:
        f.write("  - {name: BUp, type: bool, reachable: B}\n")
    (pkg / "adaptation.rra").write_text(
        "import relay.contextDepMeasModel as cdm\n\n"
        "rule PathRule period 0 ms:\n"
        "    if (cdm.BUp == false)\n"
        "        activate_feature(Filtered)\n"
        "    else activate_feature(Direct)\n"
    )
    return pkg


def events(tmp_path: Path) -> list[dict]:
    path = tmp_path / "run" / "events.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


@pytest.mark.parametrize(
    "outage",
    # 75 s: past TCP's retransmissions and Zenoh's lease many times over (pytest -m slow).
    [pytest.param(5.0, id="5s"), pytest.param(75.0, id="75s", marks=pytest.mark.slow)],
)
def test_a_cut_link_is_context_not_a_crash(network, tmp_path, outage):
    """B's link is cut (a pulled cable) for 5 s and for 75 s: B's node keeps running under
    B's own router and agent (same pid, no restart, never FATAL); the engines on A see B
    unreachable within the lease, publish it (BUp false, an event) and the rule acts on A
    (Filtered), the rewire of B's sink is deferred; on reconnection BUp is true again, the
    rule switches back and the reconcile loop converges without restarting anything."""
    net = network("A", "B")
    pkg = partition_package(tmp_path)
    certs = certificates(net, pkg, tmp_path)
    up, agents = start_system(net, pkg, tmp_path, ["B"], certs=certs)
    rra = Rra(net, "A", certs)
    st = rra.wait(lambda s: deployed(s) and "Direct" in s["engine"]["selection"]
                  and node(s, "sink")["state"] == "RUNNING", "deployment, B up")  # fmt: skip
    sink = node(st, "sink")
    assert sink["host"] == "B"
    wait_for(lambda: rra.call("measurements").get("BUp") is True, 10, "BUp true", 0.2)

    net.cut("B")
    t_cut = time.monotonic()
    st = rra.wait(lambda s: "Filtered" in s["engine"]["selection"]
                  and "filtered" in running(s), "the rule acting on B's absence", 15)  # fmt: skip
    acted = time.monotonic() - t_cut
    wait_for(lambda: rra.call("measurements").get("BUp") is False, 5, "BUp false", 0.1)
    assert "B" in st["engine"]["unreachable"], st["engine"]["unreachable"]
    assert acted < 5.0, f"acted {acted:.1f} s after the cut"  # the lease (2 s) + a plan
    wait_for(lambda: time.monotonic() - t_cut >= outage, outage + 1, "the outage", 0.5)
    assert netns.pid_alive(sink["pid"]), "B's node died during the outage"
    net.restore("B")
    st = rra.wait(lambda s: "Direct" in s["engine"]["selection"] and "direct" in running(s)
                  and not s["engine"]["unreachable"]
                  and node(s, "sink")["state"] == "RUNNING", "B back, Direct", 60)  # fmt: skip
    wait_for(lambda: rra.call("measurements").get("BUp") is True, 10, "BUp true again", 0.2)
    after = node(st, "sink")
    assert after["pid"] == sink["pid"] and after.get("restarts", 0) == 0, after
    assert not any(n["state"] == "FATAL" for n in st["nodes"]), st["nodes"]
    kinds = [e.get("kind") for e in events(tmp_path)]
    assert "host_unreachable" in kinds and "host_reachable" in kinds, kinds
    assert "deferred" in kinds, kinds
    b_states = [e for e in events(tmp_path) if e.get("node") == "sink"]
    assert all(e["state"] not in ("BACKOFF", "FATAL", "UNRESPONSIVE") for e in b_states), b_states
    stop_all(net, up, agents, rra)


def test_three_hosts_swap_on_b_and_rewire_on_c(network, tmp_path):
    net = network("A", "B", "C")
    pkg = placed(tmp_path, {"direct": "B", "filtered": "B", "sink": "C"})
    up, agents = start_system(net, pkg, tmp_path, ["B", "C"])
    rra = Rra(net, "A")
    st = rra.wait(deployed, "the deployment")
    assert {n["node"]: n["host"] for n in st["nodes"] if n["node"] in ("source", "direct",
            "sink")} == {"source": "A", "direct": "B", "sink": "C"}  # fmt: skip
    assert set(st["hosts"]) == {"A", "B", "C"}
    sink_pid = node(st, "sink")["pid"]
    on_c = Rra(net, "C")
    assert on_c.call("describe", "sink")["ports"]["in"] == [f"rra/{SYSTEM}/data/direct/out"]

    rra.param("source", "value=7")
    st = rra.wait(lambda s: "filtered" in running(s)
                  and node(s, "filtered").get("state") == "RUNNING"
                  and node(s, "direct").get("state") == "STOPPED", "the swap on B")  # fmt: skip
    assert "Filtered" in st["engine"]["selection"]
    assert node(st, "filtered")["host"] == "B"
    # C's sink was rewired in place (same process) to B's filtered, and got the CV value.
    assert node(st, "sink")["pid"] == sink_pid
    info = on_c.call("describe", "sink")
    assert info["ports"]["in"] == [f"rra/{SYSTEM}/data/filtered/out"]
    assert info["params"]["offset"] == pytest.approx(7.0)
    # What C's sink publishes comes from A's source through B's filtered: 7 + 100 + 7.
    got = on_c.call("samples", "sink/out", "114")
    assert got["relay"] == "sink" and got["value"] >= 114
    assert_local_clients(net, "B", st, ["filtered"])
    assert_local_clients(net, "C", st, ["sink"])
    stop_all(net, up, agents, rra, on_c)


# ---- the probe: run inside a namespace by the tests above -------------------------------------
def serve(client, request: list[str]):
    """One probe request: ``status`` | ``describe NODE`` | ``samples TOPIC MIN``."""
    import msgspec

    from rra_agent.bus import messages as m
    from rra_agent.bus.client import gather, wait_until
    from rra_agent.bus.data import decode_data

    match request:
        case ["status"]:
            return msgspec.to_builtins(gather(client, timeout=1.0))
        case ["measurements"]:  # the Context Monitor leader's newest values
            reply = client.request(client.keys.engine_ctl("monitor"), m.Status(), 2.0)
            return reply.result.get("measurements", {}) if isinstance(reply, m.Ok) else {}
        case ["describe", name]:
            wait_until(lambda: name in {n for _, n in client.alive()}, 10, f"{name}'s token")
            reply = client.node(name, m.Describe())
            if not isinstance(reply, m.Ok):
                raise RuntimeError(f"describe {name}: {reply}")
            out = msgspec.to_builtins(reply.result)
            out["ports"] = {p["name"]: p["keys"] for p in out["ports"]}
            return out
        case ["samples", topic, least]:
            seen: list[dict] = []
            sub = client.session.declare_subscriber(
                client.keys.data(topic), lambda s: seen.append(decode_data(s.payload.to_bytes()))
            )
            try:
                return wait_until(
                    lambda: next((d for d in seen if d.get("value", 0) >= float(least)), None),
                    10, f"a sample >= {least} on {topic}",
                )  # fmt: skip
            finally:
                sub.undeclare()
    raise ValueError(f"unknown request {request!r}")


def probe(argv: list[str]) -> int:
    """``serve``: JSON requests on stdin (see `serve`), one JSON answer line each, from one
    client session of this host's router; ``tcp-serve ADDR PORT`` | ``tcp-client ADDR
    PORT``: a TCP echo server and a client sending each stdin line, printing ``ok LINE``."""
    cmd, args = argv[0], argv[1:]
    if cmd == "tcp-serve":
        srv = socket.create_server((args[0], int(args[1])))
        while True:
            conn, peer = srv.accept()
            print(f"connection from {peer}", flush=True)
            with conn:
                while data := conn.recv(1 << 16):
                    conn.sendall(data)
    if cmd == "tcp-client":
        with socket.create_connection((args[0], int(args[1])), timeout=10) as s:
            s.settimeout(None)
            print("connected", flush=True)
            for line in sys.stdin:
                s.sendall(line.encode())
                got = b""
                while not got.endswith(b"\n"):
                    chunk = s.recv(1 << 16)
                    if not chunk:
                        print("error: closed by the peer", flush=True)
                        return 1
                    got += chunk
                print(f"ok {got.decode().strip()}", flush=True)
        return 0
    if cmd != "serve":
        raise SystemExit(f"unknown probe command {cmd!r}")
    from rra_agent.bus.client import BusClient
    from rra_agent.bus.config import ENV_VAR, BusConfig

    bus = BusConfig.from_env() if os.environ.get(ENV_VAR) else BusConfig(connect=[HUB])
    client = BusClient(bus, SYSTEM)
    try:
        print("ready", flush=True)
        for line in sys.stdin:  # until EOF (or SIGINT at teardown)
            try:
                answer = {"ok": serve(client, json.loads(line))}
            except Exception as e:
                answer = {"error": f"{type(e).__name__}: {e}"}
            print(json.dumps(answer), flush=True)
    finally:
        client.close()
    return 0


if __name__ == "__main__":
    sys.exit(probe(sys.argv[1:]))
