"""Zenoh session configuration for every rra-agent process.

Topology, as Zenoh deployments do it (rmw_zenoh's convention): **one Zenoh router per host**,
run by that host's agent (``rra up`` on the first host, ``rra agent`` on the others). Every
other process of a host (nodes, engines, tools) is a Zenoh *client* of its own host's router
over loopback, so traffic between two processes of one host never leaves it; routers link
host to host (``rra agent --connect tcp/A:7447``). Clients rather than peers: measured with
60 processes on one host (docs/performance.md), all up in 1.2 s instead of 5.1 s for a
gossiping peer mesh, one control request to each of the 60 in 8 ms instead of 126 ms, a
node's session closed in ~10 ms instead of ~1.8 s; the price is one router hop (~40 us).

Endpoints of a host agent: ``rra up`` listens on its hub endpoint (the first ``--connect``,
default ``tcp/127.0.0.1:7447``, where the tools find it) and on every ``--listen`` endpoint
(e.g. ``tls/0.0.0.0:7447`` for the other hosts); ``rra agent`` listens on ``--listen``
(default ``tcp/127.0.0.1:7447``) and connects to ``--connect`` (the other hosts' routers).
Its children connect to the loopback form of its first listen endpoint. Listening on or
connecting to anything but loopback without TLS is refused unless ``--insecure``.

Multicast scouting is off by default. The failure-detection budget is the transport lease:
2 s instead of Zenoh's 10 s, with a keep-alive every 250 ms (`KEEP_ALIVE` per lease). Zenoh
advertises the lease to the other end of each link, which drops the link after that long
without hearing anything, so one lease serves both ends: a process silent for less than
`BusConfig.budget_ms` (1.75 s: the lease minus one keep-alive period) never loses a link or a
liveliness token, a stall of its host's router (the host agent) included; one silent for
longer than the lease (a frozen process, a cut cable) loses them, and a killed one at once
(its connections close). It is one value for every link, because both ends of a link
must outlast the stall: with the router's lease long and its clients' short, a router
resumed after a 1 s stall still dropped its clients (measured: 18 tokens lost in 5
stalls), and the other way round the clients dropped it (21). Zenoh's implicit
shared memory for samples above 3 KiB (``transport_optimization``, a 16 MiB pool per
sending process) is off: ``zenoh: {transport/shared_memory/transport_optimization/enabled:
true}`` in ``--bus-config`` turns it on for systems that send large buffers.

Nodes as peers (``peer_nodes``, ``--peer-nodes``; off by default): the nodes of a host are
Zenoh *peers* that connect to the host's router, learn of each other from it (gossip, one
hop) and link to each other directly over loopback, as rmw_zenoh's nodes do; data between
two nodes of a host then skips the router (a round trip in half the time, `tools/bench_peer.py`)
while engines and tools stay clients. Nodes on other hosts are still reached through the
routers. Refused on a bus with certificates: access control is enforced by each host's
router, which direct links would bypass.

A `BusConfig` is built from defaults, an optional YAML/JSON file (``--bus-config``) and CLI
flags, in that order, and passed to child processes as JSON in ``RRA_BUS_CONFIG``.

Security (`rra_agent.security`): ``--certs DIR`` gives a process its mTLS identity (`Tls`:
the system CA and its role's certificate from ``rra certs``; Zenoh's ``transport/link/tls``
settings, ``enable_mtls``) and makes the default endpoints ``tls/``. A node's session gets a
fixed Zenoh id (`node_zid`), which the access-control configuration of its host's router
names together with the node certificate; the session of a ROS 2 executable a node starts
has one of its own (`ros2_zid`). ``zenoh`` carries any other Zenoh setting verbatim
(key path -> JSON value, e.g. ``access_control`` or ``transport/shared_memory/enabled``), so
``--bus-config FILE`` accepts Zenoh's own TLS and ACL settings.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import re
import socket
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

import msgspec

from rra_agent.bus.counters import MAX_MESSAGE_SIZE, MAX_PAYLOAD, router_limits
from rra_agent.errors import RraError
from rra_agent.models.base import FrozenModel

DEFAULT_HUB = "tcp/127.0.0.1:7447"
#: The default hub once the process has certificates (``--certs``).
TLS_HUB = "tls/127.0.0.1:7447"
ENV_VAR = "RRA_BUS_CONFIG"
#: Zenoh's connect retry: first after 250 ms, doubling to at most 1 s.
RETRY = {"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}
#: Zenoh's implicit shared memory for large samples: off unless ``zenoh`` turns it on.
SHM_OPTIMIZATION = "transport/shared_memory/transport_optimization/enabled"
#: Keep-alive messages per lease on an idle link (Zenoh's default is 4): the lease minus one
#: period is the longest silence never taken for a failure.
KEEP_ALIVE = 8
#: Link protocols that authenticate and encrypt.
SECURE_PROTOCOLS = ("tls/", "quic/")
#: Zenoh settings of a host's router (its payload limits), not of its clients; a node that
#: is a peer applies them too (`BusConfig.for_nodes`).
ROUTER_ONLY = frozenset({"low_pass_filter", MAX_MESSAGE_SIZE})
#: Where a node that is a peer (``peer_nodes``) listens for the other nodes of its host.
PEER_LISTEN = "tcp/127.0.0.1:0"
#: A peer learns of the other peers of its host's router from the router (one hop, never
#: beyond it) and links to them and to routers.
GOSSIP = {
    "enabled": True,
    "multihop": False,
    "autoconnect": {"router": [], "peer": ["router", "peer"]},
}


def _split(endpoint: str) -> tuple[str, str, str]:
    """``tcp/10.0.0.1:7447#opts`` -> ("tcp", "10.0.0.1", "7447")."""
    proto, _, addr = endpoint.partition("/")
    addr = addr.split("#", 1)[0].split("?", 1)[0]
    host, _, port = addr.rpartition(":")
    return proto, host.strip("[]"), port


def split_endpoint(endpoint: str) -> tuple[str, str, str]:
    """``tcp/10.0.0.1:7447#opts`` -> ("tcp", "10.0.0.1", "7447"): protocol, host, port."""
    return _split(endpoint)


def is_loopback(endpoint: str) -> bool:
    proto, host, _ = _split(endpoint)
    if proto in ("unixsock-stream", "unixpipe", "shm"):
        return True
    return host == "localhost" or host == "::1" or host.startswith("127.")


def loopback_form(endpoint: str) -> str:
    """The endpoint a process of this host uses to reach a router listening on ``endpoint``
    (a wildcard address becomes loopback)."""
    proto, host, port = _split(endpoint)
    if host in ("0.0.0.0", ""):
        host = "127.0.0.1"
    elif host == "::":
        host = "[::1]"
    elif ":" in host:
        host = f"[{host}]"
    return f"{proto}/{host}:{port}"


def _without_shadowed(listen: list[str]) -> list[str]:
    """Drop duplicates, and loopback endpoints a wildcard one on the same port covers."""
    wild = {(p, port) for p, h, port in map(_split, listen) if h in ("0.0.0.0", "::", "")}
    out: list[str] = []
    for ep in listen:
        proto, _, port = _split(ep)
        if ep in out or (is_loopback(ep) and (proto, port) in wild):
            continue
        out.append(ep)
    return out


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (for a hub endpoint of a test or a tool)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


_ZID = re.compile(r"^[1-9a-f][0-9a-f]{0,31}$")


def node_zid(system: str, node: str) -> str:
    """The fixed Zenoh id of node ``node`` of ``system``: 128 bits of a hash, lowercase hex
    without leading zeros (what Zenoh accepts as ``id``); the ACL names it."""
    digest = hashlib.sha256(f"rra/{system}/node/{node}".encode()).hexdigest()[:32]
    return digest.lstrip("0") or "1"


def ros2_zid(system: str, node: str) -> str:
    """The fixed Zenoh id of the session of the ROS 2 executable that node ``node`` of
    ``system`` starts (its own session, not the node's: distinct from `node_zid`, as a node
    name has no ``/``); the ACL names it."""
    return node_zid(system, f"{node}/ros2")


class Tls(FrozenModel, frozen=True):
    """A process's mTLS identity (paths, made by ``rra certs``): the system CA it trusts and
    its own certificate and private key, used both to listen and to connect."""

    ca: str
    cert: str
    key: str

    def zenoh_settings(self) -> dict[str, Any]:
        """The Zenoh ``transport/link/tls`` settings of this identity, mutual TLS enabled."""
        t = "transport/link/tls/"
        return {
            t + "root_ca_certificate": self.ca,
            t + "listen_certificate": self.cert,
            t + "listen_private_key": self.key,
            t + "connect_certificate": self.cert,
            t + "connect_private_key": self.key,
            t + "enable_mtls": True,
            t + "verify_name_on_connect": True,
        }


class BusConfig(FrozenModel, frozen=True):
    mode: Literal["client", "peer", "router"] = "client"
    #: Endpoints this process listens on (routers and peers; clients listen on nothing).
    listen: list[str] = []
    #: Endpoints this process connects to (normally the hub).
    connect: list[str] = msgspec.field(default_factory=lambda: [DEFAULT_HUB])
    multicast: bool = False
    #: Transport lease: how long until a silent (e.g. frozen) peer is declared gone; also
    #: how long a stall may last without being taken for a failure (`budget_ms`).
    lease_ms: int = 2000
    #: How long to keep trying the connect endpoints at start-up.
    connect_timeout_ms: int = 10_000

    #: Allow plain-text links beyond loopback (`check_exposure`); warned about at start.
    insecure: bool = False

    #: This process's mTLS identity (``--certs``); needed for ``tls/`` endpoints.
    tls: Tls | None = None
    #: The Zenoh id of the session (hex, at most 32 digits); None = random. Nodes get a
    #: fixed one (`node_zid`) so that their host's access control can tell them apart.
    zid: str | None = None
    #: Raw Zenoh settings, key path -> JSON value, inserted verbatim after rra's own (they
    #: win): e.g. ``{"access_control": {...}, "transport/link/tls/enable_mtls": true}``.
    zenoh: dict[str, Any] = {}
    #: The largest data sample of the system (its largest port limit), set by the host
    #: agent from the model; None: the default (`rra_agent.bus.counters.MAX_PAYLOAD`).
    max_data_bytes: int | None = None
    #: A host agent's nodes are Zenoh peers linked to each other directly (`for_nodes`).
    peer_nodes: bool = False

    def __post_init__(self) -> None:
        if self.lease_ms < 100:
            raise ValueError("lease_ms below 100 ms makes healthy peers time out")
        if self.zid is not None and not _ZID.match(self.zid):
            raise ValueError(
                f"zid {self.zid!r} is not a Zenoh id (1 to 32 lowercase hex digits, no "
                "leading zero)"
            )

    @property
    def budget_ms(self) -> int:
        """The failure-detection budget: a silence shorter than this never expires a link
        (the other end heard a keep-alive at most one keep-alive period before it began)."""
        return self.lease_ms - self.lease_ms // KEEP_ALIVE

    @property
    def hub(self) -> str:
        """Where this process finds its host's router (the first connect endpoint)."""
        return self.connect[0] if self.connect else DEFAULT_HUB

    def host_router(
        self, *, hub: bool, system: str | None = None, topics: Mapping[str, int] | None = None
    ) -> BusConfig:
        """The configuration of a host agent's router. ``hub`` (``rra up``): listen on the
        hub endpoint and ``listen``, connect to the rest of ``connect``; otherwise listen on
        ``listen`` (default loopback 7447) and connect to ``connect`` (other hosts).

        The router enforces the payload limits of every key family (Zenoh's low-pass filter
        and largest reassembled message, `rra_agent.bus.counters.router_limits`); ``topics``:
        the data topics of ``system`` -> their limit (a port's ``max_bytes``)."""
        if hub:
            listen, connect = [self.hub, *self.listen], self.connect[1:]
        else:
            listen, connect = list(self.listen) or [DEFAULT_HUB], list(self.connect)
        limits = router_limits(system, topics)
        cfg = msgspec.structs.replace(
            self,
            mode="router",
            listen=_without_shadowed(listen),
            connect=connect,
            zenoh={**limits, **self.zenoh},
            max_data_bytes=max([MAX_PAYLOAD["data"], *(topics or {}).values()]),
        )
        cfg.check_exposure()
        return cfg

    def local_client(self) -> BusConfig:
        """How the processes of this router's host connect to it: loopback, as clients (the
        router's own limits are not theirs to apply)."""
        return msgspec.structs.replace(
            self,
            mode="client",
            listen=[],
            connect=[loopback_form(self.listen[0])],
            zenoh={k: v for k, v in self.zenoh.items() if k not in ROUTER_ONLY},
        )

    def for_nodes(self, router: Mapping[str, Any] | None = None) -> BusConfig:
        """How the nodes of this (client) configuration's host join the bus: as clients of
        its router, or with ``peer_nodes`` as peers that also listen on loopback for the
        other nodes of the host (the router stays their way to everything else). A peer
        applies the payload limits of ``router`` (its host router's Zenoh settings) on its
        own links: what two nodes exchange directly never meets the router's."""
        if not self.peer_nodes or self.mode != "client":
            return self
        limits = {k: v for k, v in (router or {}).items() if k in ROUTER_ONLY}
        return msgspec.structs.replace(
            self, mode="peer", listen=[PEER_LISTEN], zenoh={**limits, **self.zenoh}
        )

    def check_peer_nodes(self) -> None:
        """Refuse nodes as peers on a bus with certificates (the routers enforce its access
        control; direct links between nodes would bypass it)."""
        if self.peer_nodes and self.tls is not None:
            raise RraError(
                "--peer-nodes needs a bus without certificates: access control is enforced "
                "by each host's router, which direct links between nodes would bypass"
            )

    def exposed(self) -> list[str]:
        """Endpoints that reach beyond this host without TLS."""
        return [
            ep
            for ep in (*self.listen, *self.connect)
            if not ep.startswith(SECURE_PROTOCOLS) and not is_loopback(ep)
        ]

    def check_exposure(self) -> None:
        """Refuse a plain-text link beyond this host unless ``insecure`` says so."""
        exposed = self.exposed()
        if exposed and not self.insecure:
            raise RraError(
                f"refusing to use {', '.join(exposed)} without TLS: anyone who reaches it "
                "could run the system; make certificates with `rra certs` and pass "
                "--certs DIR (tls/ endpoints), or pass --insecure on a network you trust"
            )

    def to_zenoh(self):  # -> zenoh.Config (zenoh imported lazily: the core never needs it)
        import zenoh

        c = zenoh.Config()
        c.insert_json5("mode", json.dumps(self.mode))
        if self.mode != "client":
            c.insert_json5("listen/endpoints", json.dumps(self.listen or ["tcp/127.0.0.1:0"]))
        c.insert_json5("connect/endpoints", json.dumps(self.connect))
        c.insert_json5("connect/timeout_ms", json.dumps(self.connect_timeout_ms))
        c.insert_json5("connect/exit_on_failure", "false")
        # Retry a lost endpoint (another host's router after a partition) at least every
        # second, not every 4 s (Zenoh's default maximum): a host is back within ~1 s.
        c.insert_json5("connect/retry", json.dumps(RETRY))
        c.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast))
        if self.mode == "peer":
            c.insert_json5("scouting/gossip", json.dumps(GOSSIP))
        c.insert_json5("scouting/delay", "0")
        c.insert_json5("transport/link/tx/lease", json.dumps(self.lease_ms))
        c.insert_json5("transport/link/tx/keep_alive", json.dumps(KEEP_ALIVE))
        c.insert_json5("timestamping/enabled", "true")
        # Zenoh 1.x copies every sample above 3 KiB into a 16 MiB shared-memory pool of the
        # sender's ("transport optimisation"): ~48 MiB PSS of the object-storing system for
        # samples of ~10 KiB, which it does not make faster (docs/performance.md).
        c.insert_json5(SHM_OPTIMIZATION, "false")
        if self.tls is not None:
            for key, value in self.tls.zenoh_settings().items():
                c.insert_json5(key, json.dumps(value))
        elif not any(k.startswith("transport") for k in self.zenoh):
            tls = [ep for ep in (*self.listen, *self.connect) if ep.startswith("tls/")]
            if tls:
                raise RraError(
                    f"{', '.join(tls)} needs certificates: pass --certs DIR (from `rra certs`)"
                )
        if self.zid is not None:
            c.insert_json5("id", json.dumps(self.zid))
        for key, value in self.zenoh.items():
            try:
                c.insert_json5(key, json.dumps(value))
            except zenoh.ZError as e:
                raise RraError(f"bus config: zenoh setting {key!r}: {e}") from None
        return c

    def with_identity(self, certs_dir: str | Path, role: str) -> BusConfig:
        """This config with the mTLS identity of ``role`` from a folder of ``rra certs``:
        ``DIR/ca.pem``, ``DIR/<role>.pem``, ``DIR/<role>.key`` (a host folder with role
        ``agent``, ``engine`` or ``node``; the operator folder with role ``operator``)."""
        folder = Path(certs_dir).expanduser().resolve()
        paths = {
            "ca": folder / "ca.pem",
            "cert": folder / f"{role}.pem",
            "key": folder / f"{role}.key",
        }
        missing = [p.name for p in paths.values() if not p.is_file()]
        if missing:
            raise RraError(
                f"no {role} identity in {folder} ({', '.join(missing)} missing): make it with "
                "`rra certs PKG --out DIR` and pass DIR/<host> (DIR/operator for the tools)"
            )
        tls = Tls(**{k: str(v) for k, v in paths.items()})
        return msgspec.structs.replace(self, tls=tls)

    def to_env(self) -> str:
        return msgspec.json.encode(self).decode()

    @classmethod
    def from_env(cls) -> BusConfig:
        raw = os.environ.get(ENV_VAR)
        if not raw:
            return cls()
        try:
            return msgspec.json.decode(raw, type=cls)
        except msgspec.ValidationError as e:
            raise RraError(f"{ENV_VAR}: {e}") from None

    @classmethod
    def load(cls, path: str | Path) -> BusConfig:
        from rra_agent.package.yamlload import load_yaml

        cfg, _ = load_yaml(path, cls)
        return cfg

    def override(
        self,
        *,
        listen: list[str] | None = None,
        connect: list[str] | None = None,
        multicast: bool | None = None,
        lease_ms: int | None = None,
        insecure: bool | None = None,
        peer_nodes: bool | None = None,
    ) -> BusConfig:
        """This config with the given (non-None) fields replaced, as CLI flags do."""
        changes = {
            k: v
            for k, v in (
                ("listen", listen),
                ("connect", connect),
                ("multicast", multicast),
                ("lease_ms", lease_ms),
                ("insecure", insecure),
                ("peer_nodes", peer_nodes),
            )
            if v is not None
        }
        return msgspec.structs.replace(self, **changes)


# ---- what a failure of the bus means, in one actionable line ------------------------------
#: What to try when no system answers at an endpoint (the tools' hub by default).
START_HINT = "start one with `rra up PKG` or give --connect ENDPOINT"
#: What to try when a certificate file is unusable.
CERTS_HINT = "make the certificates again with `rra certs PKG --out DIR`"


def accepts_tcp(endpoint: str, timeout: float = 1.0) -> bool | None:
    """Whether anything accepts a TCP connection at a ``tcp/`` or ``tls/`` endpoint right now:
    False when it is refused (nothing listens: a definite answer, at once, even on a loaded
    machine), True when accepted, None when it cannot tell (another protocol, a wildcard
    address, or no answer within ``timeout``: a firewall or a host that is down)."""
    proto, host, port = _split(endpoint)
    if proto not in ("tcp", "tls") or not port.isdigit() or host in ("", "0.0.0.0", "::"):
        return None
    try:
        with socket.create_connection((host, int(port)), timeout=timeout):
            return True
    except ConnectionRefusedError:
        return False
    except OSError:
        return None


def tls_file_problem(tls: Tls) -> str | None:
    """The first certificate file of ``tls`` that is not what it should be, as
    ``PATH: what is wrong``; None when all three parse (the CA and the certificate as PEM
    certificates, the key as a PEM private key, the certificate signed by the CA)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    loaded: dict[str, Any] = {}
    for what, path in (("ca", tls.ca), ("cert", tls.cert), ("key", tls.key)):
        try:
            data = Path(path).read_bytes()
        except OSError as e:
            return f"{path}: cannot read it ({e.strerror or e})"
        try:
            if what == "key":
                loaded[what] = serialization.load_pem_private_key(data, password=None)
            else:
                loaded[what] = x509.load_pem_x509_certificate(data)
        except (ValueError, TypeError) as e:
            kind = "a PEM private key" if what == "key" else "a PEM certificate"
            return f"{path}: not {kind} ({str(e).splitlines()[0] if str(e) else 'unreadable'})"
    try:
        loaded["cert"].verify_directly_issued_by(loaded["ca"])
    except Exception:  # signature, issuer name or key type: all mean "not from this CA"
        return f"{tls.cert}: not signed by the CA of {tls.ca}"
    return None


def _zenoh_text(error: Exception) -> str:
    """A Zenoh error without its source locations (``... at /root/.cargo/...rs:61.``)."""
    return re.sub(r"\s*at /\S+\.rs:\d+\.?", "", str(error)).strip()


def explain_open_failure(error: Exception, bus: BusConfig, *, hub: bool = False) -> RraError:
    """One actionable line (what, where, what to try) for a Zenoh session that could not be
    opened with ``bus``: a port in use, a TLS identity Zenoh refused (naming the file), no
    Zenoh router at the connect endpoints. ``hub``: ``bus`` is the router of ``rra up``,
    whose first listen endpoint is the hub (moved with ``--connect``, not ``--listen``)."""
    if isinstance(error, RraError):
        return error
    text = _zenoh_text(error)
    if "Address already in use" in text:
        endpoint = next(
            (ep for ep in bus.listen if f":{_split(ep)[2]}" in text),
            bus.listen[0] if bus.listen else bus.hub,
        )
        proto, host, port = _split(endpoint)
        other = f"{proto}/{host}:{int(port) + 1}" if port.isdigit() else f"{proto}/{host}:PORT"
        move = (
            f"--connect {other} here and for the tools"
            if hub and bus.listen and endpoint == bus.listen[0]
            else f"--listen {other}"
        )
        return RraError(
            f"cannot listen on {endpoint}: port {port} is already in use (another `rra up`? "
            f"`ss -ltnp 'sport = :{port}'` shows which program); stop it, or use another "
            f"port: {move}"
        )
    if "Cannot assign requested address" in text:
        endpoint = next((ep for ep in bus.listen if _split(ep)[1] in text), bus.listen[0])
        return RraError(
            f"cannot listen on {endpoint}: no network interface of this machine has the "
            f"address {_split(endpoint)[1]} (`ip -brief address` lists them); listen on one "
            "of them, or on 0.0.0.0 for all"
        )
    if bus.tls is not None and re.search(r"TLS|certificate|private key|trust anchor", text):
        problem = tls_file_problem(bus.tls)
        if problem is not None:
            return RraError(f"bad TLS identity: {problem}; {CERTS_HINT}")
        return RraError(f"TLS refused the certificates of {Path(bus.tls.cert).parent}: {text}")
    if "Unable to connect" in text:
        return no_system(bus, reachable=any(accepts_tcp(ep) for ep in bus.connect))
    where = ", ".join(bus.listen or bus.connect)
    return RraError(f"cannot open the bus session on {where}: {text}")


def no_system(bus: BusConfig, *, reachable: bool | None = None) -> RraError:
    """Nothing usable answers at the connect endpoints. ``reachable``: something accepted a
    TCP connection there but no Zenoh session could be opened with it."""
    where = ", ".join(bus.connect) or DEFAULT_HUB
    if bus.tls is not None:
        problem = tls_file_problem(bus.tls)
        if problem is not None:
            return RraError(f"bad TLS identity: {problem}; {CERTS_HINT}")
    if reachable:
        hint = (
            "the TLS handshake was refused: are the certificates of --certs from this "
            "system's `rra certs`?"
            if bus.tls is not None
            else "it is not an rra hub (or it needs TLS: --certs DIR)"
        )
        return RraError(f"something listens at {where} but no Zenoh session opens: {hint}")
    return RraError(f"no rra system answers at {where}; {START_HINT}")


def add_peer_nodes_argument(group) -> None:  # an argparse group of a host agent's flags
    """``--peer-nodes``, the flag of the commands that run a host agent."""
    group.add_argument(
        "--peer-nodes",
        action="store_true",
        default=None,
        help="this host's nodes link to each other directly (Zenoh peers found through the "
        "host's router, as rmw_zenoh's nodes); not with --certs",
    )


def add_bus_arguments(parser) -> None:  # argparse.ArgumentParser
    """The bus flags every rra process accepts."""
    g = parser.add_argument_group("bus")
    g.add_argument("--bus-config", metavar="FILE", help="YAML/JSON BusConfig file")
    g.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/10.0.0.2:7447")
    g.add_argument("--listen", action="append", metavar="ENDPOINT")
    g.add_argument("--multicast", action=argparse.BooleanOptionalAction, default=None)
    g.add_argument(
        "--lease-ms",
        type=int,
        metavar="MS",
        help="transport lease (default 2000): a stall shorter than 7/8 of it is not a failure; "
        "a frozen process or a cut link is seen after it",
    )
    g.add_argument(
        "--certs",
        metavar="DIR",
        help="certificate folder from `rra certs` (this host's DIR/<host>, or DIR/operator "
        "for the tools): mutual TLS, tls/ default endpoints",
    )
    g.add_argument(
        "--insecure",
        action="store_true",
        default=None,
        help="allow plain-text links beyond loopback (no authentication: anyone who can "
        "reach the endpoint can run the system)",
    )


def bus_from_args(args, role: str = "operator") -> BusConfig:  # argparse.Namespace
    """Defaults, then $RRA_BUS_CONFIG, then --bus-config FILE, then the flags.

    ``--certs DIR`` gives the process the identity of ``role`` (``operator`` for the tools,
    ``agent`` for a host agent) and turns the default endpoints into ``tls/`` ones: the
    default hub becomes `TLS_HUB`, and a host agent that is not the hub (``args.hub``
    false) listens on `TLS_HUB` unless told otherwise. Explicit endpoints are left alone.
    """
    cfg = BusConfig.from_env()
    if getattr(args, "bus_config", None):
        cfg = BusConfig.load(args.bus_config)
    cfg = cfg.override(
        listen=args.listen,
        connect=args.connect,
        multicast=args.multicast,
        lease_ms=args.lease_ms,
        insecure=getattr(args, "insecure", None),
        peer_nodes=getattr(args, "peer_nodes", None),
    )
    certs = getattr(args, "certs", None)
    if not certs:
        return cfg
    cfg = cfg.with_identity(certs, role)
    cfg.check_peer_nodes()
    connect = [TLS_HUB if ep == DEFAULT_HUB else ep for ep in cfg.connect]
    listen = [TLS_HUB if ep == DEFAULT_HUB else ep for ep in cfg.listen]
    if role == "agent" and not listen and getattr(args, "hub", True) is False:
        listen = [TLS_HUB]
    return cfg.override(listen=listen, connect=connect)
