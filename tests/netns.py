"""Several machines on one: Linux network namespaces joined by a bridge, for multi-host tests.

`Network` builds, for hosts ``A``, ``B``, ... (root needed; nothing is added to the root
namespace)::

    ip netns add rra<pid><n>br                        # the switch, in a namespace of its own
    ip -n rra<pid><n>br link add br0 type bridge; ... link set br0 up
    ip netns add rra<pid><n>a                         # one namespace per host, lo up
    ip -n rra<pid><n>a link add eth0 type veth peer name v0 netns rra<pid><n>br
    ip -n rra<pid><n>br link set v0 master br0; ... link set v0 up
    ip -n rra<pid><n>a addr add 10.<k>.0.1/24 dev eth0; ... link set eth0 up

so host ``i`` (1-based, in the order given) is ``10.<k>.0.<i>`` on its ``eth0``, and has its
own loopback (a router on ``127.0.0.1:7447`` in each host does not clash).

- `Network.cut` / `Network.restore` set the host's port *on the bridge* down / up: the
  host's ``eth0`` loses its carrier but keeps its address and route, so, as with a pulled
  cable, packets both ways vanish silently (no RST, no "unreachable" error on either side)
  and TCP connections survive a short cut (retransmission resumes them).
- `Network.run` starts a process in a host's namespace (``ip netns exec``, which execs the
  program: the Popen's pid is the program's), in its own process group, output in
  ``<log_dir>/<name>.log`` unless ``stdout`` is given; `Network.close` (the context exit)
  sends SIGINT to every group, SIGKILL after ``stop_timeout``, reaps them, kills (and
  reports) any process still inside one of its namespaces, and deletes the namespaces,
  even after a failure.

The namespaces' prefix is ``rra`` unless ``RRA_NETNS_PREFIX`` says otherwise (the pid keeps
two runs apart anyway).

pytest: ``from netns import network`` in a test module gives the ``network`` fixture, a
factory ``network("A", "B")`` -> `Network`; the test is skipped (with ``ip``'s own error)
where namespaces cannot be made, and fails if a process outlived it.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

from rra_agent.bus.client import wait_until as wait_for
from rra_agent.host import procfs

ROOT = Path(__file__).resolve().parents[1]
PYTHON = str(ROOT / ".venv" / "bin" / "python") if (ROOT / ".venv").exists() else sys.executable
_counter = itertools.count(1)
_NAME = re.compile(r"^rra(\d+)n\d+")


class NetnsUnavailable(RuntimeError):
    """Network namespaces cannot be made here (not root, no ``ip``, the kernel refuses)."""


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    proc = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30)
    if check and proc.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {proc.stderr.strip() or proc.returncode}")
    return proc


def pid_alive(pid: int) -> bool:
    return procfs.state(pid) not in ("", "Z")


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            return f.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return "?"


def _all_pids() -> list[int]:
    return [int(d) for d in os.listdir("/proc") if d.isdigit()]


def _netns_inode(pid: int) -> int | None:
    try:
        link = os.readlink(f"/proc/{pid}/ns/net")  # "net:[4026532177]"
    except OSError:
        return None
    return int(link[5:-1])


def _group_members(pgid: int) -> list[int]:
    out = []
    for pid in _all_pids():
        fields = procfs.stat(pid)
        if fields is not None and fields[0] != "Z" and int(fields[2]) == pgid:
            out.append(pid)
    return out


def remove_stale_namespaces() -> list[str]:
    """Delete namespaces this module made in a process that no longer exists."""
    gone = []
    out = _ip("netns", "list", check=False).stdout
    for line in out.splitlines():
        name = line.split()[0] if line.split() else ""
        if (m := _NAME.match(name)) and not pid_alive(int(m.group(1))):
            _ip("netns", "del", name, check=False)
            gone.append(name)
    return gone


def tcp_peers(pid: int, ns: str | None) -> set[tuple[str, int]]:
    """The remote (addr, port) of every established TCP connection of process ``pid``, from
    ``ss -Htnp`` inside namespace ``ns`` (None: this process's namespace)."""
    cmd = ["ss", "-Htnp", "state", "established"]
    if ns:
        cmd = ["ip", "netns", "exec", ns, *cmd]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=10).stdout
    peers = set()
    for line in out.splitlines():
        if f"pid={pid}," not in line:
            continue
        # Recv-Q Send-Q Local:Port Peer:Port Process (with a state filter: no State column)
        addr, _, port = line.split()[3].rpartition(":")
        addr = addr.strip("[]").removeprefix("::ffff:")
        peers.add((addr, int(port)))
    return peers


class Proc:
    """A process `Network.run` started."""

    def __init__(self, name: str, host: str, popen: subprocess.Popen, log: Path | None):
        self.name, self.host, self.popen, self.log = name, host, popen, log

    def tail(self, lines: int = 40) -> str:
        if self.log is None or not self.log.exists():
            return ""
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])


class Network:
    """Hosts in network namespaces joined by a bridge; see the module docstring."""

    def __init__(
        self,
        hosts: Sequence[str] = ("A", "B"),
        *,
        log_dir: str | Path | None = None,
        stop_timeout: float = 10.0,
    ) -> None:
        if not hosts or len(set(hosts)) != len(hosts) or len(hosts) > 250:
            raise ValueError(f"hosts must be 1..250 distinct names, not {hosts!r}")
        n = next(_counter)
        # ``RRA_NETNS_PREFIX`` names them apart from other users of the machine's namespaces
        self.prefix = f"{os.environ.get('RRA_NETNS_PREFIX', 'rra')}{os.getpid()}n{n}"
        self.subnet = 1 + (n - 1) % 250  # the k of 10.<k>.0.<i>
        self.hosts = list(hosts)
        self.bridge_ns = f"{self.prefix}br"
        self._ns = {h: f"{self.prefix}{chr(ord('a') + i) if i < 26 else i}" for i, h in
                    enumerate(self.hosts)}  # fmt: skip
        self._addr = {h: f"10.{self.subnet}.0.{i + 1}" for i, h in enumerate(self.hosts)}
        self._port = {h: f"v{i}" for i, h in enumerate(self.hosts)}
        self.log_dir = Path(log_dir) if log_dir else Path(f"/tmp/{self.prefix}-logs")
        self.stop_timeout = stop_timeout
        self.procs: list[Proc] = []
        self._made: list[str] = []
        #: Problems found at `close` (processes that outlived their stop, left in a namespace).
        self.problems: list[str] = []

    # ---- names ----------------------------------------------------------------------------
    def ns(self, host: str) -> str:
        """The namespace of ``host``."""
        return self._ns[host]

    def addr(self, host: str) -> str:
        """The IPv4 address of ``host`` on the bridge (its ``eth0``)."""
        return self._addr[host]

    # ---- build / tear down -------------------------------------------------------------
    def __enter__(self) -> Network:
        try:
            self.up()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def _add_ns(self, name: str) -> None:
        proc = _ip("netns", "add", name, check=False)
        if proc.returncode != 0:
            raise NetnsUnavailable(f"ip netns add {name}: {proc.stderr.strip()}")
        self._made.append(name)
        _ip("-n", name, "link", "set", "lo", "up")

    def up(self) -> None:
        try:
            subprocess.run(["ip", "-V"], capture_output=True, check=True)
        except (OSError, subprocess.CalledProcessError) as e:
            raise NetnsUnavailable(f"no usable `ip` command: {e}") from None
        remove_stale_namespaces()
        self.log_dir.mkdir(parents=True, exist_ok=True)
        br = self.bridge_ns
        self._add_ns(br)
        try:
            _ip("-n", br, "link", "add", "br0", "type", "bridge")
        except RuntimeError as e:
            raise NetnsUnavailable(str(e)) from None
        _ip("-n", br, "link", "set", "br0", "up")
        for host in self.hosts:
            ns, port = self._ns[host], self._port[host]
            self._add_ns(ns)
            try:
                _ip("-n", ns, "link", "add", "eth0", "type", "veth", "peer", "name", port,
                    "netns", br)  # fmt: skip
            except RuntimeError as e:
                raise NetnsUnavailable(str(e)) from None
            _ip("-n", br, "link", "set", port, "master", "br0")
            _ip("-n", br, "link", "set", port, "up")
            _ip("-n", ns, "addr", "add", f"{self._addr[host]}/24", "dev", "eth0")
            _ip("-n", ns, "link", "set", "eth0", "up")

    def inodes(self) -> dict[int, str]:
        """The namespace inode -> name of every namespace of this network."""
        out = {}
        for name in self._made:
            with contextlib.suppress(OSError):
                out[os.stat(f"/run/netns/{name}").st_ino] = name
        return out

    def processes(self) -> list[int]:
        """Every (non-zombie) process inside one of this network's namespaces."""
        inodes = self.inodes()
        return [pid for pid in _all_pids() if _netns_inode(pid) in inodes and pid_alive(pid)]

    def stop(self, proc: subprocess.Popen | Proc, timeout: float | None = None) -> int | None:
        """SIGINT to the process's group; SIGKILL to the group after ``timeout``; its status."""
        popen = proc.popen if isinstance(proc, Proc) else proc
        timeout = self.stop_timeout if timeout is None else timeout
        with contextlib.suppress(ProcessLookupError):
            os.killpg(popen.pid, signal.SIGINT)
        return self._finish([popen], timeout)[0]

    def _finish(self, popens: list[subprocess.Popen], timeout: float) -> list[int | None]:
        deadline = time.monotonic() + timeout
        for p in popens:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(max(0.0, deadline - time.monotonic()))
        # The leader may be gone with members of its group left (its children).
        with contextlib.suppress(TimeoutError):
            wait_for(lambda: not any(_group_members(p.pid) for p in popens),
                     max(0.0, deadline - time.monotonic()), "groups empty", 0.05)  # fmt: skip
        for p in popens:
            members = _group_members(p.pid)
            if members:
                name = next((x.name for x in self.procs if x.popen is p), str(p.pid))
                self.problems.append(
                    f"{name}: ignored SIGINT for {timeout:g} s; killed: "
                    + "; ".join(f"{pid} {_cmdline(pid)}" for pid in members)
                )
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
        for p in popens:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(5)
        return [p.returncode for p in popens]

    def close(self) -> list[str]:
        """Stop every process, kill what is left in the namespaces, delete them. Returns
        the problems (empty: everything exited on SIGINT and nothing was left behind)."""
        try:
            live = [p.popen for p in self.procs if p.popen.poll() is None]
            for p in live:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGINT)
            self._finish([p.popen for p in self.procs], self.stop_timeout)
            left = self.processes()
            if left:
                self.problems.append(
                    "left in the namespaces: " + "; ".join(f"{pid} {_cmdline(pid)}" for pid in left)
                )
                for pid in left:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
                with contextlib.suppress(TimeoutError):
                    wait_for(lambda: not self.processes(), 5, "namespaces empty", 0.05)
        finally:
            for name in reversed(self._made):
                _ip("netns", "del", name, check=False)
            if kept := [n for n in self._made if os.path.exists(f"/run/netns/{n}")]:
                self.problems.append(f"namespaces not deleted: {', '.join(kept)}")
            self._made = []
        if unreaped := [p.name for p in self.procs if p.popen.returncode is None]:
            self.problems.append(f"not reaped: {', '.join(unreaped)}")
        return self.problems

    # ---- links ---------------------------------------------------------------------------
    def cut(self, host: str) -> None:
        """Pull ``host``'s cable: its port on the bridge goes down (silence both ways)."""
        _ip("-n", self.bridge_ns, "link", "set", self._port[host], "down")

    def restore(self, host: str) -> None:
        _ip("-n", self.bridge_ns, "link", "set", self._port[host], "up")

    # ---- processes -----------------------------------------------------------------------
    def run(
        self, host: str, argv: Sequence[str], *, name: str | None = None, **popen_kw: Any
    ) -> subprocess.Popen:
        """Start ``argv`` in ``host``'s namespace, in its own process group, tracked and
        stopped at `close`. Output goes to ``<log_dir>/<name>.log`` unless ``stdout`` is
        given; ``env`` entries are added to this process's environment."""
        name = name or f"{host}-{Path(argv[0]).name}-{len(self.procs)}"
        env = {**os.environ, "RERUN_ANALYTICS": "0", **(popen_kw.pop("env", None) or {})}
        log = None
        if "stdout" not in popen_kw:
            log = self.log_dir / f"{name}.log"
            with log.open("ab") as f:
                return self._spawn(host, argv, name, log, env, stdout=f,
                                   stderr=subprocess.STDOUT, **popen_kw)  # fmt: skip
        return self._spawn(host, argv, name, log, env, **popen_kw)

    def _spawn(self, host, argv, name, log, env, **kw) -> subprocess.Popen:
        kw.setdefault("stdin", subprocess.DEVNULL)
        kw.setdefault("cwd", ROOT)
        popen = subprocess.Popen(
            ["ip", "netns", "exec", self._ns[host], *argv],
            env=env,
            start_new_session=True,
            **kw,
        )
        self.procs.append(Proc(name, host, popen, log))
        return popen

    def python(self, host: str, *args: str, name: str | None = None, **popen_kw: Any):
        """``run`` of this repository's Python (the venv's) with ``args``."""
        return self.run(host, [PYTHON, *args], name=name, **popen_kw)

    def log(self, name: str) -> str:
        p = self.log_dir / f"{name}.log"
        return p.read_text(errors="replace") if p.exists() else ""

    def logs(self) -> str:
        """The tail of every process's log (for a failure message)."""
        return "\n".join(
            f"--- {p.name} ({p.host}, pid {p.popen.pid}, status {p.popen.poll()})\n{p.tail()}"
            for p in self.procs
            if p.log is not None
        )

    def listening(self, host: str, port: int, addr: str | None = None) -> bool:
        """True if something listens on TCP ``port`` (on ``addr`` if given) in ``host``."""
        out = subprocess.run(
            ["ip", "netns", "exec", self._ns[host], "ss", "-Htln"],
            capture_output=True, text=True, timeout=10,
        ).stdout  # fmt: skip
        for line in out.splitlines():
            local = line.split()[3]  # State Recv-Q Send-Q Local:Port Peer:Port
            a, _, p = local.rpartition(":")
            if p == str(port) and (addr is None or a.strip("[]") in (addr, "*", "0.0.0.0")):
                return True
        return False

    def wait_listening(
        self, host: str, port: int, addr: str | None = None, *, proc=None, timeout: float = 30
    ) -> None:
        """Until ``port`` listens in ``host``; fails at once if ``proc`` exited."""

        def ready() -> bool:
            if proc is not None and proc.poll() is not None:
                raise AssertionError(
                    f"exited ({proc.returncode}) before listening on {port}:\n{self.logs()}"
                )
            return self.listening(host, port, addr)

        try:
            wait_for(ready, timeout, f"{host} listening on {addr or '*'}:{port}", 0.05)
        except TimeoutError as e:
            raise AssertionError(f"{e}\n{self.logs()}") from None


# ---- pytest -------------------------------------------------------------------------------
try:
    import pytest
except ImportError:  # tools import this module without pytest installed
    pytest = None  # type: ignore[assignment]

if pytest is not None:

    @pytest.fixture
    def network(tmp_path: Path) -> Iterator[Callable[..., Network]]:
        """``network("A", "B", ...)``: a `Network` torn down (and checked) after the test."""
        made: list[Network] = []

        def make(*hosts: str, stop_timeout: float = 10.0) -> Network:
            net = Network(hosts or ("A", "B"), log_dir=tmp_path / f"net{len(made)}",
                          stop_timeout=stop_timeout)  # fmt: skip
            made.append(net)
            try:
                net.up()
            except NetnsUnavailable as e:
                net.close()
                pytest.skip(f"network namespaces unavailable: {e}")
            except BaseException:
                net.close()
                raise
            return net

        yield make
        problems = [p for net in made for p in net.close()]
        assert not problems, "\n".join(problems)
