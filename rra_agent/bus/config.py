"""Zenoh session configuration for every rra-agent process.

Topology, as Zenoh deployments do it (rmw_zenoh's convention): **one Zenoh router per host**,
run by that host's agent (``rra up`` on the first host, ``rra agent`` on the others). Every
other process of a host (nodes, engines, tools) is a Zenoh *client* of its own host's router
over loopback, so traffic between two processes of one host never leaves it; routers link
host to host (``rra agent --connect tcp/A:7447``). Clients rather than peers: measured with
60 processes on one host (docs/architecture.md), all up in 1.2 s instead of 5.1 s for a
gossiping peer mesh, one control request to each of the 60 in 8 ms instead of 126 ms, a
node's session closed in ~10 ms instead of ~1.8 s; the price is one router hop (~40 us).

Endpoints of a host agent: ``rra up`` listens on its hub endpoint (the first ``--connect``,
default ``tcp/127.0.0.1:7447``, where the tools find it) and on every ``--listen`` endpoint
(e.g. ``tls/0.0.0.0:7447`` for the other hosts); ``rra agent`` listens on ``--listen``
(default ``tcp/127.0.0.1:7447``) and connects to ``--connect`` (the other hosts' routers).
Its children connect to the loopback form of its first listen endpoint. Listening on or
connecting to anything but loopback without TLS is refused unless ``--insecure``.

Multicast scouting is off by default. The transport lease is 500 ms instead of Zenoh's 10 s,
so a frozen process loses its liveliness token in well under a second.

A `BusConfig` is built from defaults, an optional YAML/JSON file (``--bus-config``) and CLI
flags, in that order, and passed to child processes as JSON in ``RRA_BUS_CONFIG``.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
from pathlib import Path
from typing import Literal

import msgspec

from rra_agent.errors import RraError
from rra_agent.models.base import Model

DEFAULT_HUB = "tcp/127.0.0.1:7447"
ENV_VAR = "RRA_BUS_CONFIG"
#: Link protocols that authenticate and encrypt.
SECURE_PROTOCOLS = ("tls/", "quic/")


def _split(endpoint: str) -> tuple[str, str, str]:
    """``tcp/10.0.0.1:7447#opts`` -> ("tcp", "10.0.0.1", "7447")."""
    proto, _, addr = endpoint.partition("/")
    addr = addr.split("#", 1)[0].split("?", 1)[0]
    host, _, port = addr.rpartition(":")
    return proto, host.strip("[]"), port


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
        proto, host, port = _split(ep)
        if ep in out or (is_loopback(ep) and (proto, port) in wild):
            continue
        out.append(ep)
    return out


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (for a hub endpoint of a test or a tool)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class BusConfig(Model, frozen=True):
    mode: Literal["client", "peer", "router"] = "client"
    #: Endpoints this process listens on (routers and peers; clients listen on nothing).
    listen: list[str] = []
    #: Endpoints this process connects to (normally the hub).
    connect: list[str] = msgspec.field(default_factory=lambda: [DEFAULT_HUB])
    multicast: bool = False
    #: Transport lease: how long until a silent (e.g. frozen) peer is declared gone.
    lease_ms: int = 500
    #: How long to keep trying the connect endpoints at start-up.
    connect_timeout_ms: int = 10_000

    #: Allow plain-text links beyond loopback (`check_exposure`); warned about at start.
    insecure: bool = False

    def __post_init__(self) -> None:
        if self.lease_ms < 100:
            raise ValueError("lease_ms below 100 ms makes healthy peers time out")

    @property
    def hub(self) -> str:
        """Where this process finds its host's router (the first connect endpoint)."""
        return self.connect[0] if self.connect else DEFAULT_HUB

    def host_router(self, *, hub: bool) -> BusConfig:
        """The configuration of a host agent's router. ``hub`` (``rra up``): listen on the
        hub endpoint and ``listen``, connect to the rest of ``connect``; otherwise listen on
        ``listen`` (default loopback 7447) and connect to ``connect`` (other hosts)."""
        if hub:
            listen, connect = [self.hub, *self.listen], self.connect[1:]
        else:
            listen, connect = list(self.listen) or [DEFAULT_HUB], list(self.connect)
        cfg = msgspec.structs.replace(
            self, mode="router", listen=_without_shadowed(listen), connect=connect
        )
        cfg.check_exposure()
        return cfg

    def local_client(self) -> BusConfig:
        """How the processes of this router's host connect to it: loopback, as clients."""
        return msgspec.structs.replace(
            self, mode="client", listen=[], connect=[loopback_form(self.listen[0])]
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
        c.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast))
        c.insert_json5("scouting/delay", "0")
        c.insert_json5("transport/link/tx/lease", json.dumps(self.lease_ms))
        c.insert_json5("timestamping/enabled", "true")
        return c

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
        from rra_agent.models.yamlload import load_yaml

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
            )
            if v is not None
        }
        return msgspec.structs.replace(self, **changes)


def add_bus_arguments(parser) -> None:  # argparse.ArgumentParser
    """The bus flags every rra process accepts."""
    g = parser.add_argument_group("bus")
    g.add_argument("--bus-config", metavar="FILE", help="YAML/JSON BusConfig file")
    g.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/10.0.0.2:7447")
    g.add_argument("--listen", action="append", metavar="ENDPOINT")
    g.add_argument("--multicast", action=argparse.BooleanOptionalAction, default=None)
    g.add_argument("--lease-ms", type=int, metavar="MS", help="liveliness/transport lease")
    g.add_argument(
        "--insecure",
        action="store_true",
        default=None,
        help="allow plain-text links beyond loopback (no authentication: anyone who can "
        "reach the endpoint can run the system)",
    )


def bus_from_args(args) -> BusConfig:  # argparse.Namespace
    """Defaults, then $RRA_BUS_CONFIG, then --bus-config FILE, then the flags."""
    cfg = BusConfig.from_env()
    if getattr(args, "bus_config", None):
        cfg = BusConfig.load(args.bus_config)
    return cfg.override(
        listen=args.listen,
        connect=args.connect,
        multicast=args.multicast,
        lease_ms=args.lease_ms,
        insecure=getattr(args, "insecure", None),
    )
