"""Zero trust on the bus: `rra certs`, Zenoh mTLS, and the access control generated from the
system model, with real processes, real certificates and real Zenoh TLS links.

One router process (a host agent's router: TLS listener on loopback, the ACL of host
``local`` of relay_system, a host-control queryable and a liveliness subscriber of its own)
serves the bus tests; every client is a Zenoh session of this test process with a role's
certificate (and, for nodes, the node's Zenoh id).
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import stat
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import msgspec
import pytest
import zenoh
from conftest import run_rra, stop_process
from cryptography import x509
from cryptography.x509.oid import NameOID

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, wait_until
from rra_agent.bus.config import (
    SHM_OPTIMIZATION,
    BusConfig,
    Tls,
    add_bus_arguments,
    bus_from_args,
    free_port,
    node_zid,
)
from rra_agent.bus.data import decode_data, encode_data
from rra_agent.bus.keys import Keys
from rra_agent.bus.session import data_publisher, open_session
from rra_agent.cli import main
from rra_agent.deployment import deploy
from rra_agent.engines.executor import spec_for
from rra_agent.errors import RraError
from rra_agent.security.acl import access_control
from rra_agent.security.certs import issue, verify

#: Every test here starts processes or opens Zenoh sessions (pytest -m 'not system').
pytestmark = pytest.mark.system

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "tests" / "data" / "relay_system"
SYSTEM = "relay_system"
KEYS = Keys(SYSTEM)
HOST = "local"
#: How long a refused query or sample is given to show up anyway.
REFUSED = 0.6

#: The router process: opens the Zenoh router of ``RRA_BUS_CONFIG``, answers host control
#: like a host agent, prints the liveliness tokens it sees, and on "get KEY" queries KEY
#: from its own session (as a host agent probes a node).
ROUTER = r"""
import sys, zenoh
from rra_agent.bus.config import BusConfig
host_ctl, alive = sys.argv[1], sys.argv[2]
session = zenoh.open(BusConfig.from_env().to_zenoh())
try:
    session.declare_queryable(host_ctl, lambda q: q.reply(q.key_expr, b"host"))
    def on_token(s):
        sign = "+" if s.kind == zenoh.SampleKind.PUT else "-"
        print(f"alive{sign} {s.key_expr}", flush=True)
    session.liveliness().declare_subscriber(alive, on_token)
    print("ready", flush=True)
    for line in sys.stdin:
        cmd, key = line.split()
        replies = [r.ok.payload.to_string() for r in session.get(key, timeout=2.0) if r.ok]
        print(f"got {key} {','.join(replies) or '-'}", flush=True)
finally:
    session.close()
"""


# ---- certificates ---------------------------------------------------------------------------
def _rra(*args: str) -> subprocess.CompletedProcess[str]:
    return run_rra(*args, cwd=ROOT)


def _cn(cert: x509.Certificate) -> str:
    return str(cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value)


def _rra_here(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """``rra ARGS`` in this process (the package's parsers are built once per process)."""
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def test_rra_certs_writes_the_layout_and_is_idempotent(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "certs"
    san = ("--san", "local=10.1.2.3,robot.lan")
    run = _rra("certs", str(PKG), "--out", str(out), *san)
    assert run.returncode == 0, run.stderr
    files = {
        "ca": ["ca.pem", "ca.key"],
        HOST: [
            "ca.pem",
            *(f"{r}.{e}" for r in ("agent", "engine", "node") for e in ("pem", "key")),
        ],
        "operator": ["ca.pem", "operator.pem", "operator.key"],
    }
    assert sorted(p.name for p in out.iterdir()) == sorted(files)
    for folder, names in files.items():
        assert sorted(p.name for p in (out / folder).iterdir()) == sorted(names)
        for name in names:
            mode = stat.S_IMODE((out / folder / name).stat().st_mode)
            if name.endswith(".key"):
                assert mode == 0o600, f"{folder}/{name} has mode {mode:o}"
            else:
                assert not mode & 0o022
        assert (out / folder / "ca.pem").read_bytes() == (out / "ca" / "ca.pem").read_bytes()
    ca = out / "ca" / "ca.pem"
    for role in ("agent", "engine", "node"):
        cert = verify(out / HOST / f"{role}.pem", ca)
        assert _cn(cert) == f"{role}.{HOST}"
        sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert {str(v) for v in sans.get_values_for_type(x509.IPAddress)} >= {
            "127.0.0.1",
            "::1",
            "10.1.2.3",
        }
        assert {"localhost", HOST, "robot.lan"} <= set(sans.get_values_for_type(x509.DNSName))
    assert _cn(verify(out / "operator" / "operator.pem", ca)) == "operator"
    with pytest.raises(RraError, match="not signed"):
        other = tmp_path / "other"
        issue(other, [HOST])
        verify(other / HOST / "node.pem", ca)

    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    code, stdout, stderr = _rra_here(capsys, "certs", str(PKG), "--out", str(out), *san)
    assert code == 0, stderr
    assert "0 file(s) written" in stdout
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before

    (out / HOST / "node.key").unlink()
    code, stdout, stderr = _rra_here(capsys, "certs", str(PKG), "--out", str(out), *san)
    assert code == 0, stderr
    assert "2 file(s) written" in stdout
    changed = {p for p in out.rglob("*") if p.is_file() and p.read_bytes() != before.get(p)}
    assert changed == {out / HOST / "node.key", out / HOST / "node.pem"}
    assert (out / "ca" / "ca.key").read_bytes() == before[out / "ca" / "ca.key"]
    verify(out / HOST / "node.pem", ca)

    code, _, stderr = _rra_here(
        capsys, "certs", str(PKG), "--out", str(out), "--san", "mars=1.2.3.4"
    )
    assert code == 1
    assert stderr.strip() == "rra certs: --san for unknown host(s) mars (hosts: local)"


# ---- the bus configuration ------------------------------------------------------------------
def test_bus_config_identity_and_raw_zenoh_settings(tmp_path: Path) -> None:
    issue(tmp_path, [HOST])
    parser = argparse.ArgumentParser()
    add_bus_arguments(parser)
    args = parser.parse_args(["--certs", str(tmp_path / HOST)])
    agent = bus_from_args(args, role="agent")
    assert agent.tls == Tls(
        ca=str(tmp_path / HOST / "ca.pem"),
        cert=str(tmp_path / HOST / "agent.pem"),
        key=str(tmp_path / HOST / "agent.key"),
    )
    assert agent.connect == ["tls/127.0.0.1:7447"]
    args.hub = False  # `rra agent` without --hub: its router listens on TLS by default
    assert bus_from_args(args, role="agent").listen == ["tls/127.0.0.1:7447"]
    explicit = bus_from_args(
        parser.parse_args(["--certs", str(tmp_path / HOST), "--connect", "tcp/127.0.0.1:9"]),
        role="node",
    )
    assert explicit.connect == ["tcp/127.0.0.1:9"]
    assert explicit.tls is not None and explicit.tls.cert.endswith("node.pem")
    with pytest.raises(RraError, match=r"no operator identity .*operator\.pem, operator\.key"):
        bus_from_args(args)  # the host folder holds no operator certificate
    with pytest.raises(RraError, match="needs certificates"):
        BusConfig(connect=["tls/127.0.0.1:9"]).to_zenoh()

    zid = node_zid(SYSTEM, "sink")
    assert zid == node_zid(SYSTEM, "sink") != node_zid(SYSTEM, "source")
    cfg = BusConfig(
        tls=agent.tls,
        zid=zid,
        zenoh={"transport/shared_memory/enabled": False, "access_control": {"enabled": True}},
    ).to_zenoh()
    assert cfg.get_json("id") == f'"{zid}"'
    assert cfg.get_json("transport/link/tls/enable_mtls") == "true"
    assert cfg.get_json("transport/link/tls/connect_certificate") == f'"{agent.tls.cert}"'
    assert cfg.get_json("transport/shared_memory/enabled") == "false"
    assert cfg.get_json("access_control/enabled") == "true"
    # Zenoh's implicit shared memory for large samples is off unless the settings say so
    assert BusConfig().to_zenoh().get_json(SHM_OPTIMIZATION) == "false"
    assert BusConfig(zenoh={SHM_OPTIMIZATION: True}).to_zenoh().get_json(SHM_OPTIMIZATION) == "true"
    # --bus-config FILE takes Zenoh's own settings (here TLS and ACL) under `zenoh`
    acl = {"enabled": True, "default_permission": "deny"}
    tls_ca = str(tmp_path / HOST / "ca.pem")
    conf = tmp_path / "bus.json"
    conf.write_text(
        json.dumps(
            {"zenoh": {"access_control": acl, "transport/link/tls/root_ca_certificate": tls_ca}}
        )
    )
    from_file = bus_from_args(parser.parse_args(["--bus-config", str(conf)])).to_zenoh()
    assert json.loads(from_file.get_json("access_control"))["default_permission"] == "deny"
    assert from_file.get_json("transport/link/tls/root_ca_certificate") == f'"{tls_ca}"'
    with pytest.raises(RraError, match="'access_control'"):
        BusConfig(zenoh={"access_control": {"nonsense": 1}}).to_zenoh()
    with pytest.raises(ValueError, match="Zenoh id"):
        BusConfig(zid="0abc")


def test_access_control_covers_every_run_time_variant() -> None:
    acl = access_control(deploy(PKG), HOST)
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}
    assert acl["default_permission"] == "deny"
    # direct and filtered are run-time optional; sink.in is wired to them only at run time
    for node in ("source", "direct", "filtered", "sink"):
        assert subjects[f"node:{node}"] == {
            "id": f"node:{node}",
            "cert_common_names": ["node.local"],
            "zids": [node_zid(SYSTEM, node)],
        }
    assert rules["node:sink/subscribe"]["key_exprs"] == [
        KEYS.data("direct/out"),
        KEYS.data("filtered/out"),
        KEYS.inject_all,
    ]
    # Its data, and the report of a reflex it fires (its own key only).
    assert rules["node:sink/publish"]["key_exprs"] == [KEYS.data("sink/out"), KEYS.reflex("sink")]
    assert rules["node:source/alive"]["key_exprs"] == [KEYS.alive(HOST, "source")]
    assert "node:source/subscribe" in rules  # injections only: source has no input
    assert rules["node:source/subscribe"]["key_exprs"] == [KEYS.inject_all]


# ---- a router with the generated access control --------------------------------------------
class Router:
    """The router subprocess and the lines it prints."""

    def __init__(self, bus: BusConfig) -> None:
        self.endpoint = bus.listen[0]
        self.lines: queue.Queue[str] = queue.Queue()
        self.seen: list[str] = []
        self.proc = subprocess.Popen(
            [sys.executable, "-c", ROUTER, KEYS.host_ctl(HOST), KEYS.alive_all],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, "RRA_BUS_CONFIG": bus.to_env()},
            cwd=ROOT,
        )
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line.strip())

    def expect(self, predicate: Callable[[str], bool], timeout: float, what: str) -> str:
        deadline = time.monotonic() + timeout
        while True:
            for line in self.seen:
                if predicate(line):
                    return line
            left = deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError(f"router: no {what} within {timeout:g} s (saw {self.seen})")
            try:
                self.seen.append(self.lines.get(timeout=left))
            except queue.Empty:
                continue

    def get(self, key: str) -> str:
        """Query ``key`` from the router's own session; the replies, or '-'."""
        assert self.proc.stdin is not None
        self.seen = [s for s in self.seen if not s.startswith(f"got {key} ")]
        self.proc.stdin.write(f"get {key}\n")
        self.proc.stdin.flush()
        return self.expect(lambda s: s.startswith(f"got {key} "), 10, f"reply to {key}").split()[2]

    def stop(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("certs")
    issue(out / "system", [HOST])
    issue(out / "foreign", [HOST])
    return out


@pytest.fixture(scope="module")
def router(certs: Path) -> Iterator[Router]:
    """The router process of host ``local``: TLS on loopback, the generated ACL."""
    endpoint = f"tls/127.0.0.1:{free_port()}"
    bus = BusConfig(
        mode="router",
        listen=[endpoint],
        connect=[],
        zenoh={"access_control": access_control(deploy(PKG), HOST)},
    ).with_identity(certs / "system" / HOST, "agent")
    r = Router(bus)
    try:
        r.expect(lambda s: s == "ready", 20, "ready")
        yield r
    finally:
        r.stop()


def _session(
    endpoint: str,
    folder: Path | None,
    role: str = "",
    *,
    zid: str | None = None,
    timeout_ms: int = 5000,
    **raw: object,
) -> zenoh.Session:
    bus = BusConfig(connect=[endpoint], connect_timeout_ms=timeout_ms, zid=zid, zenoh=dict(raw))
    if folder is not None:
        bus = bus.with_identity(folder, role)
    return open_session(bus, wait_connected=True)


def _node(certs: Path, endpoint: str, node: str, zid_of: str | None = None) -> zenoh.Session:
    return _session(endpoint, certs / "system" / HOST, "node", zid=node_zid(SYSTEM, zid_of or node))


def _engine(certs: Path, endpoint: str) -> zenoh.Session:
    return _session(endpoint, certs / "system" / HOST, "engine")


def _operator(certs: Path, endpoint: str) -> zenoh.Session:
    return _session(endpoint, certs / "system" / "operator", "operator")


def _answers(session: zenoh.Session, key: str, timeout: float = REFUSED) -> list[str]:
    return [r.ok.payload.to_string() for r in session.get(key, timeout=timeout) if r.ok]


def _answered(session: zenoh.Session, key: str) -> list[str]:
    """Replies to ``key``, asking again until some come (a fresh queryable propagates)."""
    return wait_until(lambda: _answers(session, key, 0.5), 10, f"a reply from {key}")


class Sessions:
    """Sessions opened by one test, all closed at its end."""

    def __init__(self) -> None:
        self.open: list[zenoh.Session] = []

    def __call__(self, session: zenoh.Session) -> zenoh.Session:
        self.open.append(session)
        return session

    def close(self) -> None:
        for s in reversed(self.open):
            s.close()


@pytest.fixture
def sessions() -> Iterator[Sessions]:
    s = Sessions()
    try:
        yield s
    finally:
        s.close()


def test_a_client_without_a_certificate_is_refused(router: Router, certs: Path) -> None:
    ca = str(certs / "system" / HOST / "ca.pem")
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        s = _session(
            router.endpoint, None, timeout_ms=1500, **{"transport/link/tls/root_ca_certificate": ca}
        )
        s.close()


def test_a_client_of_another_ca_is_refused(router: Router, certs: Path, sessions: Sessions) -> None:
    foreign = certs / "foreign" / HOST
    ca = str(certs / "system" / HOST / "ca.pem")
    with pytest.raises(zenoh.ZError, match="Unable to connect"):
        # it trusts the router (the system CA); the router does not trust its certificate
        s = _session(
            router.endpoint,
            foreign,
            "engine",
            timeout_ms=1500,
            **{"transport/link/tls/root_ca_certificate": ca},
        )
        s.close()
    sessions(_engine(certs, router.endpoint))  # the same client with the system's certificate


def test_a_node_publishes_only_on_its_own_ports(
    router: Router, certs: Path, sessions: Sessions
) -> None:
    engine = sessions(_engine(certs, router.endpoint))
    got: list[tuple[str, str]] = []

    def on_sample(s: zenoh.Sample) -> None:
        got.append((str(s.key_expr), s.payload.to_string()))

    engine.declare_subscriber(f"{KEYS.prefix}/data/source/out", on_sample)
    engine.declare_subscriber(f"{KEYS.prefix}/data/direct/out", on_sample)
    engine.declare_subscriber(f"{KEYS.prefix}/data/sink/out", on_sample)
    engine.declare_subscriber(KEYS.inject_all, on_sample)
    reader = sessions(_operator(certs, router.endpoint))
    read: list[str] = []
    reader.declare_subscriber(f"{KEYS.prefix}/data/**", lambda s: read.append(str(s.key_expr)))
    source = sessions(_node(certs, router.endpoint, "source"))
    own = data_publisher(source, KEYS.data("source/out"))
    theirs = data_publisher(source, KEYS.data("direct/out"))
    # a node identity is the node certificate AND the node's id: the node certificate with
    # another node's id is not source, the operator certificate with sink's id is not sink
    # (source's own id is taken while source is connected: Zenoh refuses a second session)
    direct = sessions(_node(certs, router.endpoint, "direct"))
    operator = sessions(
        _session(
            router.endpoint,
            certs / "system" / "operator",
            "operator",
            zid=node_zid(SYSTEM, "sink"),
        )
    )
    source_out = KEYS.data("source/out")

    def round_trip() -> bool:
        """Each session sends what it must not, then what it may (delivered in order)."""
        theirs.put("forged by source")
        own.put("own")
        direct.put(source_out, "forged by direct")
        direct.put(KEYS.data("direct/out"), "direct marker")
        operator.put(KEYS.data("sink/out"), "forged by operator")
        operator.put(KEYS.inject("marker"), "operator marker")
        payloads = {p for _, p in got}
        return {"own", "direct marker", "operator marker"} <= payloads and source_out in read

    try:
        wait_until(round_trip, 10, "the allowed samples", interval=0.02)
    except TimeoutError:
        raise AssertionError(sorted(set(got))) from None
    assert not [p for _, p in got if p.startswith("forged")], got
    assert {k for k, p in got if p == "own"} == {source_out}


def test_a_node_subscribes_only_where_it_can_be_wired(
    router: Router, certs: Path, sessions: Sessions
) -> None:
    sink = sessions(_node(certs, router.endpoint, "sink"))
    got: list[str] = []
    for topic in ("source/out", "direct/out"):  # sink.in: direct.out or filtered.out
        sink.declare_subscriber(KEYS.data(topic), lambda s: got.append(str(s.key_expr)))
    engine = sessions(_engine(certs, router.endpoint))

    def both() -> bool:
        engine.put(KEYS.data("source/out"), b"x")
        engine.put(KEYS.data("direct/out"), b"x")
        return KEYS.data("direct/out") in got

    wait_until(both, 10, "direct/out at the sink", interval=0.02)
    assert KEYS.data("source/out") not in got


def test_control_is_for_engines_only(router: Router, certs: Path, sessions: Sessions) -> None:
    engine = sessions(_engine(certs, router.endpoint))
    sink = sessions(_node(certs, router.endpoint, "sink"))
    sink.declare_queryable(KEYS.node_ctl("sink"), lambda q: q.reply(q.key_expr, "sink"))
    replica = sessions(_engine(certs, router.endpoint))
    replica.declare_queryable(KEYS.engine_ctl("resolution"), lambda q: q.reply(q.key_expr, "eng"))
    # the engine reaches all three; so does the host agent (the router's own session)
    assert _answered(engine, KEYS.node_ctl("sink")) == ["sink"]
    assert _answered(engine, KEYS.host_ctl(HOST)) == ["host"]
    assert _answered(engine, KEYS.engine_ctl("resolution")) == ["eng"]
    assert router.get(KEYS.node_ctl("sink")) == "sink"

    source = sessions(_node(certs, router.endpoint, "source"))
    assert _answers(source, KEYS.host_ctl(HOST)) == []
    assert _answers(source, KEYS.node_ctl("sink")) == []
    operator = sessions(_operator(certs, router.endpoint))
    assert _answered(operator, KEYS.engine_ctl("resolution")) == ["eng"]
    assert _answers(operator, KEYS.host_ctl(HOST)) == []
    assert _answers(operator, KEYS.node_ctl("sink")) == []
    # a node cannot pose as another node's control endpoint
    source.declare_queryable(KEYS.node_ctl("filtered"), lambda q: q.reply(q.key_expr, "fake"))
    assert _answers(engine, KEYS.node_ctl("filtered"), 1.0) == []


def test_liveliness_tokens_only_on_the_nodes_own_key(
    router: Router, certs: Path, sessions: Sessions
) -> None:
    direct = sessions(_node(certs, router.endpoint, "direct"))
    tokens = [  # kept: a dropped token is undeclared
        direct.liveliness().declare_token(KEYS.alive(HOST, "filtered")),
        direct.liveliness().declare_token(KEYS.alive(HOST, "direct")),
    ]
    router.expect(lambda s: s == f"alive+ {KEYS.alive(HOST, 'direct')}", 10, "direct's token")
    operator = sessions(_operator(certs, router.endpoint))
    seen = wait_until(
        lambda: {
            str(r.ok.key_expr)
            for r in operator.liveliness().get(KEYS.alive_all, timeout=0.5)
            if r.ok is not None
        },
        10,
        "tokens seen by the operator",
    )
    assert seen == {KEYS.alive(HOST, "direct")}
    assert not any("filtered" in s for s in router.seen), router.seen
    for token in tokens:
        token.undeclare()


def test_a_node_process_runs_under_its_acl(router: Router, certs: Path, sessions: Sessions) -> None:
    """A node process (`rra_agent.node.main`) with the node identity does all it must under
    the ACL, and a rewire to a key its port can never be wired to receives nothing there."""
    sink = deploy(PKG).configured.component("sink")
    assert sink is not None
    spec = spec_for(KEYS, sink, {"in": ("direct/out",)}, {"out": "sink/out"}, default_host=HOST)
    bus = BusConfig(connect=[router.endpoint], zid=node_zid(SYSTEM, "sink"))
    env = {
        **os.environ,
        "RRA_NODE_SPEC": msgspec.json.encode(spec).decode(),
        "RRA_BUS_CONFIG": bus.with_identity(certs / "system" / HOST, "node").to_env(),
    }
    # `python -m rra_agent.node`, but importing the module once (run as __main__, its Node
    # class is not the one the implementations derive from)
    run = "import sys; from rra_agent.node import main; sys.exit(main())"
    proc = subprocess.Popen([sys.executable, "-c", run], env=env, cwd=ROOT)
    try:
        router.expect(lambda s: s == f"alive+ {KEYS.alive(HOST, 'sink')}", 20, "sink's token")
        engine = sessions(_engine(certs, router.endpoint))
        client = BusClient(bus, SYSTEM, session=engine)
        described = client.node("sink", m.Describe())
        assert isinstance(described, m.Ok), described
        relayed: list[float] = []

        def on_relayed(s: zenoh.Sample) -> None:
            relayed.append(decode_data(s.payload.to_bytes())["value"])

        engine.declare_subscriber(KEYS.data("sink/out"), on_relayed)
        both = [KEYS.data("source/out"), KEYS.data("direct/out")]  # source.out: never sink's
        reply = client.node("sink", m.Rewire(port="in", keys=both))
        assert isinstance(reply, m.Ok), reply

        def round_trip() -> bool:
            engine.put(KEYS.data("source/out"), encode_data({"seq": 0, "value": 100.0}))
            engine.put(KEYS.data("direct/out"), encode_data({"seq": 0, "value": 1.0}))
            return bool(relayed)

        wait_until(round_trip, 10, "a sample relayed by the sink", interval=0.02)
        assert set(relayed) == {1.0}, relayed  # never the one on source/out
        assert isinstance(client.node("sink", m.Shutdown()), m.Ok)
        assert proc.wait(10) == 0
    finally:
        stop_process(proc)


def test_components_in_containers_are_refused_with_certs(tmp_path):
    """A container's components share one Zenoh identity: with --certs (one identity and one
    access control per node) they are refused with one line, before anything starts."""
    import shutil

    import yaml

    from rra_agent.deployment import deploy
    from rra_agent.errors import RraError
    from rra_agent.host.agent import security

    pkg = tmp_path / "pkg"
    shutil.copytree(Path(__file__).parent / "data" / "relay_system", pkg)
    system = yaml.safe_load((pkg / "system.yaml").read_text())
    system["components"][1]["container"] = "box"
    (pkg / "system.yaml").write_text(yaml.safe_dump(system))
    args = argparse.Namespace(certs=str(tmp_path / "certs"))
    with pytest.raises(RraError, match=r"--certs: direct run in component containers"):
        security(args, deploy(pkg), "local")


def test_operators_may_force_features_and_nodes_may_not(
    router: Router, certs: Path, sessions: Sessions
) -> None:
    """``rra select`` asks the Adaptation Engine (``engine/adaptation/ctl``): an operator
    certificate may, a node's may not (the ACL's ``engine/**`` control rule)."""
    acl = access_control(deploy(PKG), HOST)
    control = next(r for r in acl["rules"] if r["id"] == "operator/control")
    assert f"{KEYS.prefix}/engine/**" in control["key_exprs"]
    replica = sessions(_engine(certs, router.endpoint))
    replica.declare_queryable(
        KEYS.engine_ctl("adaptation"), lambda q: q.reply(q.key_expr, "adaptation")
    )
    operator = sessions(_operator(certs, router.endpoint))
    assert _answered(operator, KEYS.engine_ctl("adaptation")) == ["adaptation"]
    source = sessions(_node(certs, router.endpoint, "source"))
    assert _answers(source, KEYS.engine_ctl("adaptation")) == []
