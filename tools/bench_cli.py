"""Benchmark of the tools' failures: how long ``rra status`` / ``rra param`` take to say that
nothing useful answers, against the 0.5 s goal (and one success, for scale).

Cases (each a fresh tool session, in this process: ``rra_agent.cli.main``, the interpreter's
start not counted; ``--subprocess`` runs each as ``python -m rra_agent`` instead and counts it):

- ``param nosuch``: a node name the running system (``rra up`` of tests/data/relay_system)
  does not have;
- ``status --certs`` at a hub without TLS (a Zenoh router on ``tcp/``, dialled ``tls/``);
- ``status`` without certificates at a TLS hub (dialled ``tcp/``);
- ``status --certs`` of another system's CA at a TLS hub;
- ``status`` where nothing listens (``tcp/`` and ``tls/``);
- ``status`` of the running system (a success).

Run: ``.venv/bin/python tools/bench_cli.py [--runs N] [--subprocess]``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT))

from _benchutil import interrupt, median, p99  # noqa: E402

from rra_agent.bus.config import BusConfig, Tls, free_port  # noqa: E402
from rra_agent.bus.session import open_session  # noqa: E402
from rra_agent.cli import main as rra  # noqa: E402

RELAY = ROOT / "tests" / "data" / "relay_system"
GOAL_S = 0.5


def _listening(port: int) -> bool:
    import socket

    with socket.socket() as s:
        s.settimeout(0.2)
        return s.connect_ex(("127.0.0.1", port)) == 0


@contextlib.contextmanager
def relay_system(tmp: Path) -> Iterator[str]:
    """``rra up`` of the relay system on a free port, until it deploys; its hub endpoint."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    proc = subprocess.Popen(
        [sys.executable, "-m", "rra_agent", "up", str(RELAY), "--connect", ep, "-q",
         "--no-multicast", "--run-dir", str(tmp / "run")],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while _quiet(["param", "sink", "--connect", ep]) != 0:
            if time.monotonic() > deadline or proc.poll() is not None:
                raise SystemExit("rra up of the relay system did not come up")
            time.sleep(0.2)
        yield ep
    finally:
        interrupt(proc)


@contextlib.contextmanager
def router(endpoint: str, tls: Tls | None = None) -> Iterator[None]:
    """A bare Zenoh router (a hub that runs no system) listening on ``endpoint``."""
    session = open_session(BusConfig(mode="router", listen=[endpoint], connect=[], tls=tls))
    try:
        yield
    finally:
        session.close()


def _quiet(argv: list[str]) -> int:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return rra(argv)


def _timed(argv: list[str], subprocess_: bool) -> tuple[float, int]:
    t0 = time.perf_counter()
    if subprocess_:
        rc = subprocess.run(
            [sys.executable, "-m", "rra_agent", *argv], capture_output=True, check=False,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        ).returncode  # fmt: skip
    else:
        rc = _quiet(argv)
    return time.perf_counter() - t0, rc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=20, help="runs per case")
    ap.add_argument("--subprocess", action="store_true", help="each run a new `rra` process")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="rra-bench-cli-") as tmp_:
        tmp = Path(tmp_)
        for out in ("certs", "other"):
            _quiet(["certs", str(RELAY), "--out", str(tmp / out)])
        local, op, other = tmp / "certs" / "local", tmp / "certs" / "operator", tmp / "other"
        agent = Tls(ca=str(local / "ca.pem"), cert=str(local / "agent.pem"),
                    key=str(local / "agent.key"))  # fmt: skip
        plain, tls, none = free_port(), free_port(), free_port()
        with (
            relay_system(tmp) as hub,
            router(f"tcp/127.0.0.1:{plain}"),
            router(f"tls/127.0.0.1:{tls}", agent),
        ):
            cases: list[tuple[str, list[str], Callable[[int], bool]]] = [
                ("param nosuch (running system)", ["param", "nosuch", "--connect", hub],
                 lambda rc: rc == 1),
                ("status --certs at a hub without TLS", ["status", "--certs", str(op),
                 "--system", "relay_system", "--connect", f"tls/127.0.0.1:{plain}"],
                 lambda rc: rc == 1),
                ("status without certs at a TLS hub", ["status", "--connect",
                 f"tcp/127.0.0.1:{tls}"], lambda rc: rc == 1),
                ("status --certs of another CA at a TLS hub", ["status", "--certs",
                 str(other / "operator"), "--connect", f"tls/127.0.0.1:{tls}"],
                 lambda rc: rc == 1),
                ("status, nothing at tcp/", ["status", "--connect", f"tcp/127.0.0.1:{none}"],
                 lambda rc: rc == 1),
                ("status --certs, nothing at tls/", ["status", "--certs", str(op), "--connect",
                 f"tls/127.0.0.1:{none}"], lambda rc: rc == 1),
                ("status of the running system (success)", ["status", "--connect", hub],
                 lambda rc: rc == 0),
            ]  # fmt: skip
            how = "a new process each (interpreter start included)" if args.subprocess else (
                "in process (rra_agent.cli.main)")  # fmt: skip
            print(f"load average: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores; {how}")
            print(f"{'case':<42} {'median':>8} {'p99':>8}  goal")
            for name, argv, ok in cases:
                samples = []
                for _ in range(args.runs):
                    elapsed, rc = _timed(argv, args.subprocess)
                    if not ok(rc):
                        raise SystemExit(f"{name}: unexpected exit status {rc}")
                    samples.append(elapsed)
                med, top = median(samples), p99(samples)
                verdict = "ok" if med < GOAL_S else "OVER"
                print(f"{name:<42} {med:>7.3f}s {top:>7.3f}s  {GOAL_S} s {verdict}")


if __name__ == "__main__":
    main()
