"""Starting a ROS 2 executable as a component: its command line and environment.

An implementation ``ros2: PACKAGE EXECUTABLE`` runs ``ros2 run PACKAGE EXECUTABLE`` with
``--ros-args``: the node's name and namespace, a remapping per port (``-r from:=to``) and
its parameters (``-p name:=value``). The environment makes it an rmw_zenoh node of the
system's ROS domain whose Zenoh session connects to its host's router
(``RMW_IMPLEMENTATION=rmw_zenoh_cpp``, ``ROS_DOMAIN_ID``, ``ZENOH_CONFIG_OVERRIDE``).

On a bus with certificates the router listens on TLS only and admits a session only with a
certificate of the system: the host agent writes the executable a Zenoh session
configuration (`session_config`, `write_session_config`: client mode, the router's TLS
endpoint, the CA and the host's node certificate with mutual TLS, multicast scouting off,
a fixed Zenoh id the router's access control names) and the environment points at it
(``ZENOH_SESSION_CONFIG_URI``, what rmw_zenoh_cpp and zenoh-ros2-sdk read). Both apply
``ZENOH_CONFIG_OVERRIDE`` on top of that file, so it keeps the connect endpoint, the same as
the file's: zenoh-ros2-sdk replaces the file's endpoints with ``tcp/`` of the router address
its code is given, and an override inherited from the environment would win otherwise.
`command` is pure: the host agent supervises the command like any external one.
"""

from __future__ import annotations

import json
import re
import shlex
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rra_agent.files import write_atomic
from rra_agent.ros2.errors import BadName, FieldError
from rra_agent.ros2.names import check_domain, check_namespace, check_node_name, qualify

PREFIX = "ros2:"
#: The environment variable naming a ROS 2 process's Zenoh session configuration file.
SESSION_CONFIG_ENV = "ZENOH_SESSION_CONFIG_URI"
_WORD = re.compile(r"[A-Za-z0-9_.\-]+")


@dataclass(frozen=True, slots=True)
class Ros2Run:
    """What to start: ``ros2 run package executable`` or, without a package, ``argv``."""

    package: str | None = None
    executable: str | None = None
    argv: tuple[str, ...] = field(default=())

    @property
    def base(self) -> list[str]:
        if self.package is not None and self.executable is not None:
            return ["ros2", "run", self.package, self.executable]
        return list(self.argv)


def parse_implementation(text: str) -> Ros2Run | None:
    """``ros2: PACKAGE EXECUTABLE`` -> its `Ros2Run`; None when ``text`` is not a ROS 2
    implementation; `BadName` when the package or executable is not a plain word."""
    if not text.startswith(PREFIX):
        return None
    words = shlex.split(text[len(PREFIX):])
    if len(words) != 2 or not all(_WORD.fullmatch(w) for w in words):
        raise BadName(f"{text!r}: expected 'ros2: PACKAGE EXECUTABLE' (plain words)")
    return Ros2Run(words[0], words[1])


def param_arg(value: Any) -> str:
    """A parameter value as ``--ros-args -p name:=VALUE`` reads it (YAML)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value) if not value or not _WORD.fullmatch(value) else value
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(param_arg(v) for v in value) + "]"
    raise FieldError(f"{value!r} cannot be a ROS 2 parameter value on a command line")


def command(
    run: Ros2Run,
    *,
    node: str | None = None,
    namespace: str | None = None,
    remaps: Mapping[str, str] | None = None,
    params: Mapping[str, Any] | None = None,
    domain: int = 0,
    router: str = "tcp/127.0.0.1:7447",
    extra: Sequence[str] = (),
    session_config: str | None = None,
) -> tuple[list[str], dict[str, str]]:
    """The argv and the environment additions that start ``run`` as a node of the system;
    ``session_config``: its Zenoh session configuration file (`write_session_config`)."""
    args: list[str] = []
    if node is not None:
        args += ["-r", f"__node:={check_node_name(node)}"]
    if namespace is not None:
        args += ["-r", f"__ns:={check_namespace(namespace)}"]
    for src, dst in (remaps or {}).items():
        args += ["-r", f"{_remap_name(src)}:={_remap_name(dst)}"]
    for name, value in (params or {}).items():
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_.]*", name):
            raise BadName(f"ROS 2 parameter name {name!r} is not valid")
        args += ["-p", f"{name}:={param_arg(value)}"]
    argv = [*run.base, *extra]
    if args:
        argv += ["--ros-args", *args]
    env = {
        "RMW_IMPLEMENTATION": "rmw_zenoh_cpp",
        "ROS_DOMAIN_ID": str(check_domain(domain)),
        "ZENOH_CONFIG_OVERRIDE": f"connect/endpoints={json.dumps([router])}",
    }
    if session_config is not None:
        env[SESSION_CONFIG_ENV] = session_config
    return argv, env


def session_config(
    router: str,
    *,
    zid: str,
    ca: str,
    cert: str,
    key: str,
    lease_ms: int = 2000,
    keep_alive: int = 8,
) -> dict[str, Any]:
    """The Zenoh session configuration of a ROS 2 executable on a bus with certificates:
    a client of its host's router at ``router`` (a ``tls/`` endpoint) with mutual TLS
    (the system's CA ``ca``, the certificate ``cert`` and key ``key`` of the host's node
    identity), Zenoh id ``zid``, multicast scouting off, rra's lease on its link."""
    return {
        "id": zid,
        "mode": "client",
        "connect": {"endpoints": [router]},
        "scouting": {"multicast": {"enabled": False}, "delay": 0},
        "timestamping": {"enabled": True},
        "transport": {
            "link": {
                "tx": {"lease": lease_ms, "keep_alive": keep_alive},
                "tls": {
                    "root_ca_certificate": ca,
                    "connect_certificate": cert,
                    "connect_private_key": key,
                    "enable_mtls": True,
                    "verify_name_on_connect": True,
                },
            },
        },
    }


def write_session_config(path: str | Path, config: Mapping[str, Any]) -> Path:
    """Write ``config`` to ``path`` (JSON, which is JSON5 too), readable by its owner only
    (mode 0600, also when the file was there before), replaced whole; the path written."""
    return write_atomic(path, (json.dumps(config, indent=2) + "\n").encode(), 0o600)


def _remap_name(name: str) -> str:
    return name if not name.startswith("/") else qualify(name)
