"""Zenoh session configuration for every rra-agent process.

Topology: a star. One process per system (``rra up``, or the first ``rra agent --hub``) is a
Zenoh *router* listening on the hub endpoint; every other process (engines, nodes, tools) is
a Zenoh *client* of it. Measured on this 2-core machine with 60 processes (see
docs/architecture.md): all up in 1.2 s instead of 5.1 s for a gossiping peer mesh, one
control request to each of the 60 in 8 ms instead of 126 ms, a node's session closed in
~10 ms instead of ~1.8 s; a mesh opens a link between every pair of processes. The price
is one hop through the router: ~40 us more per round trip.

Multicast scouting is off by default (tests and single machines need none). The transport
lease is 500 ms instead of Zenoh's 10 s, so a frozen process loses its liveliness token in
well under a second.

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

    def __post_init__(self) -> None:
        if self.lease_ms < 100:
            raise ValueError("lease_ms below 100 ms makes healthy peers time out")

    def as_hub(self) -> BusConfig:
        """The configuration of the process that listens on the hub endpoint."""
        hub = self.connect[0] if self.connect else DEFAULT_HUB
        return msgspec.structs.replace(self, mode="router", listen=[hub], connect=self.connect[1:])

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
    ) -> BusConfig:
        """This config with the given (non-None) fields replaced, as CLI flags do."""
        changes = {
            k: v
            for k, v in (
                ("listen", listen),
                ("connect", connect),
                ("multicast", multicast),
                ("lease_ms", lease_ms),
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


def bus_from_args(args) -> BusConfig:  # argparse.Namespace
    """Defaults, then $RRA_BUS_CONFIG, then --bus-config FILE, then the flags."""
    cfg = BusConfig.from_env()
    if getattr(args, "bus_config", None):
        cfg = BusConfig.load(args.bus_config)
    return cfg.override(
        listen=args.listen, connect=args.connect, multicast=args.multicast, lease_ms=args.lease_ms
    )
