"""rra-agent against its peer dora-rs, side by side on this machine (goals: issue 25).

Each figure is measured on a fresh system per run, rra-agent and dora-rs alternately (A/B,
then B/A, ...) so both see the same machine load; the same Python node code on both sides as
far as their APIs allow (``tools/peer_nodes.py`` on rra-agent's Node SDK, started by ``rra up``
with its engines and their standbys; ``tools/peer_dora.py`` on dora's ``dora.Node``,
started by ``dora run``):

- **round trip**: a pinger node and an echo node, one 93-byte payload in flight at a time,
  ``--n`` measured round trips per run after ``--warm`` unmeasured ones (µs, timed inside
  the pinger, from just before the send to the echo's arrival in its hands);
- **restart**: a 100 Hz source node feeding a recorder node; the source is killed with
  SIGKILL; from the kill to the first sample of the new source process in the recorder (the
  recorder writes each sample's wall time and the sending process's id). rra-agent as
  shipped (the supervisor's defaults); dora with ``restart_policy: always``;
- **chain start**: a 10-node chain (a 100 Hz source, 8 echoes, a recorder): from starting
  ``rra up PKG`` / ``dora run dataflow.yml`` to the first sample at the recorder.

``--peer-nodes`` runs rra-agent's nodes as peers linked directly (``rra up --peer-nodes``)
instead of clients of the host's router.

Prints median and p99 of each side, the ratio rra/dora and the goal beside it, and the load
average before and after. dora-rs is an optional benchmark dependency (the ``peer`` extra:
``.venv/bin/pip install -e '.[peer]'``); without it the tool says so and exits 2.

    .venv/bin/python tools/bench_peer.py [--runs 3] [--n 2000] [--only roundtrip,restart,chain]
                                         [--peer-nodes]
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOOLS = ROOT / "tools"
sys.path.insert(0, str(TOOLS))
sys.path.insert(0, str(ROOT))

from _benchutil import median, p99, print_table  # noqa: E402

from rra_agent.bus.config import free_port  # noqa: E402

BIN = Path(sys.executable).parent
_PING = (
    "  - name: Ping\n    fields: {seq: int, stamp: float, frame: str, "
    "position: 'list[float]', value: float, ok: bool}\n"
)
#: dora's counterpart of rra-agent's restart as shipped: at once, every time.
_DORA_RESTART = "    restart_policy: always\n    restart_delay: 0.0\n"
_TICK = "  - name: Tick\n    fields: {pid: int, seq: int}\n"
#: Further flags of every ``rra up`` (``--peer-nodes``).
UP_FLAGS: list[str] = []


# ----------------------------------------------------------------------------- rra-agent


def _param(name: str, kind: str, value: object) -> str:
    return f"      {name}: {{type: {kind}, value: {value}}}\n"


def _component(name: str, cls: str, ports: list[str], params: str = "") -> str:
    text = f"  - name: {name}\n    implementation: peer_nodes.{cls}\n"
    if params:
        text += "    parameters:\n" + params
    text += "    ports:\n" + "".join(f"      - {p}\n" for p in ports)
    return text


def _port(name: str, direction: str, kind: str) -> str:
    return f"{{name: {name}, direction: {direction}, type: {kind}}}"


def rra_package(root: Path, figure: str, out: Path, n: int, warm: int) -> Path:
    """Write the rra-agent package of ``figure`` under ``root``; its folder."""
    pkg = root / f"rra-{figure}"
    pkg.mkdir()
    shutil.copy(TOOLS / "peer_nodes.py", pkg / "peer_nodes.py")
    (pkg / "rra.yaml").write_text("name: peer\ndefault_selection: [Base]\n")
    (pkg / "features.uvl").write_text("namespace Peer\n\nfeatures\n    Base {abstract}\n")
    (pkg / "deployment.yaml").write_text("features: {}\n")
    (pkg / "runtime.yaml").write_text("features: {}\n")
    (pkg / "measurements.yaml").write_text("data_types:\n" + _PING + _TICK)
    comps, conns = _rra_graph(figure, out, n, warm)
    (pkg / "system.yaml").write_text(
        "system: peer\ncomponents:\n" + "".join(comps) + "connections:\n" + "".join(conns)
    )
    return pkg


def _rra_graph(figure: str, out: Path, n: int, warm: int) -> tuple[list[str], list[str]]:
    if figure == "roundtrip":
        params = _param("n", "int", n) + _param("warm", "int", warm) + _param("out", "str", out)
        return [
            _component(
                "pinger", "Pinger", [_port("ping", "publish", "Ping"),
                                     _port("pong", "subscribe", "Ping")], params,
            ),
            _component(
                "echo", "Echo", [_port("in", "subscribe", "Ping"), _port("out", "publish", "Ping")]
            ),
        ], ["  - {from: pinger.ping, to: echo.in}\n",
            "  - {from: echo.out, to: pinger.pong}\n"]  # fmt: skip
    relays = 0 if figure == "restart" else 8
    names = ["source", *(f"relay{i}" for i in range(1, relays + 1)), "recorder"]
    comps = [_component("source", "Source", [_port("out", "publish", "Tick")])]
    comps += [
        _component(
            name, "Echo", [_port("in", "subscribe", "Tick"), _port("out", "publish", "Tick")]
        )
        for name in names[1:-1]
    ]
    comps.append(
        _component(
            "recorder", "Recorder", [_port("in", "subscribe", "Tick")], _param("out", "str", out)
        )
    )
    conns = [f"  - {{from: {a}.out, to: {b}.in}}\n" for a, b in itertools.pairwise(names)]
    return comps, conns


@contextlib.contextmanager
def rra_up(pkg: Path, run_dir: Path) -> Iterator[subprocess.Popen[bytes]]:
    """``rra up pkg`` (loopback, a free port, quiet), stopped with SIGINT at the end."""
    up = subprocess.Popen(
        [sys.executable, "-m", "rra_agent", "up", str(pkg), "--run-dir", str(run_dir), "-q",
         "--connect", f"tcp/127.0.0.1:{free_port()}", "--no-multicast", *UP_FLAGS],
        env={**os.environ, "RERUN_ANALYTICS": "0"},
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )  # fmt: skip
    try:
        yield up
    finally:
        _stop(up)


# ----------------------------------------------------------------------------- dora-rs


def _dora_node(node: str, args: str, inputs: dict[str, str], outputs: list[str],
               extra: str = "") -> str:  # fmt: skip
    text = f"  - id: {node}\n    path: {TOOLS / 'peer_dora.py'}\n    args: {args}\n"
    if inputs:
        text += "    inputs:\n" + "".join(f"      {k}: {v}\n" for k, v in inputs.items())
    if outputs:
        text += f"    outputs: [{', '.join(outputs)}]\n"
    return text + extra


def dora_dataflow(root: Path, figure: str, out: Path, n: int, warm: int) -> Path:
    """Write the dora dataflow of ``figure`` under ``root``; its file."""
    if figure == "roundtrip":
        nodes = [
            _dora_node("pinger", f"pinger {out} {n} {warm}",
                       {"pong": "echo/out", "tick": "dora/timer/millis/100"}, ["ping"]),
            _dora_node("echo", "echo", {"in": "pinger/ping"}, ["out"]),
        ]  # fmt: skip
    else:
        relays = 0 if figure == "restart" else 8
        restart = _DORA_RESTART if figure == "restart" else ""
        nodes = [_dora_node("source", "source", {"tick": "dora/timer/millis/10"}, ["out"], restart)]
        prev = "source"
        for i in range(1, relays + 1):
            nodes.append(_dora_node(f"relay{i}", "relay", {"in": f"{prev}/out"}, ["out"]))
            prev = f"relay{i}"
        nodes.append(_dora_node("recorder", f"recorder {out}", {"in": f"{prev}/out"}, []))
    path = root / f"dora-{figure}.yml"
    path.write_text("nodes:\n" + "".join(nodes))
    return path


@contextlib.contextmanager
def dora_run(dataflow: Path, run_dir: Path) -> Iterator[subprocess.Popen[bytes]]:
    """``dora run dataflow`` (its own daemon and coordinator), stopped at the end."""
    env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    with open(run_dir / "dora.log", "wb") as log:
        run = subprocess.Popen(
            [str(BIN / "dora"), "run", str(dataflow)], cwd=run_dir, env=env,
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
        )  # fmt: skip
        try:
            yield run
        finally:
            _stop(run)


def _stop(proc: subprocess.Popen[bytes]) -> None:
    """SIGINT to its process group, SIGKILL after 20 s (and to what is left of the group)."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGINT)
    try:
        proc.wait(20)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)


# ----------------------------------------------------------------------------- figures


def _wait(predicate: Callable[[], object], timeout: float, what: str,
          proc: subprocess.Popen[bytes]) -> object:  # fmt: skip
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        if proc.poll() is not None:
            raise RuntimeError(f"{what}: the system exited ({proc.returncode}) first")
        time.sleep(0.002)
    raise RuntimeError(f"{what}: not within {timeout:.0f} s")


def _records(out: Path) -> list[tuple[float, int]]:
    if not out.exists():
        return []
    rows = []
    for line in out.read_text().splitlines():
        parts = line.split()
        if len(parts) == 2:
            rows.append((float(parts[0]), int(parts[1])))
    return rows


Runner = Callable[[Path, str, Path, int, int], contextlib.AbstractContextManager]


def _system(side: str, tmp: Path, figure: str, out: Path, n: int, warm: int) -> Runner:
    if side == "rra":
        return rra_up(rra_package(tmp, figure, out, n, warm), tmp)  # type: ignore[return-value]
    return dora_run(dora_dataflow(tmp, figure, out, n, warm), tmp)  # type: ignore[return-value]


def roundtrip(side: str, n: int, warm: int) -> list[float]:
    """One run's round trips (µs)."""
    with tempfile.TemporaryDirectory(prefix=f"peer-{side}-") as tmp:
        out = Path(tmp) / "rtt.txt"
        with _system(side, Path(tmp), "roundtrip", out, n, warm) as proc:
            _wait(out.exists, 120 + n * 0.01, f"{side} round trips", proc)
        return [float(x) for x in out.read_text().split()]


def restart(side: str, kills: int) -> list[float]:
    """Kill the 100 Hz source ``kills`` times (each after it has run a second): ms from each
    kill to the first sample of its new process at the recorder. The first kill of a run is
    a first crash; later ones wait rra-agent's growing backoff (dora's ``restart_delay``)."""
    times: list[float] = []
    with tempfile.TemporaryDirectory(prefix=f"peer-{side}-") as tmp:
        out = Path(tmp) / "rec.txt"
        with _system(side, Path(tmp), "restart", out, 0, 0) as proc:
            for _ in range(kills):
                rows = _wait(lambda: len(_records(out)) > 100 and _records(out), 120,
                             f"{side} source running", proc)  # fmt: skip
                pid = rows[-1][1]  # type: ignore[index]
                out.write_text("")
                killed = time.time()
                os.kill(pid, signal.SIGKILL)
                new = _wait(_new_process(out, pid, killed), 30, f"{side} restarted", proc)
                times.append((new[0] - killed) * 1000)  # type: ignore[index]
                # The next kill only after a second, as a node that crashes now and then.
                time.sleep(1.0)
                out.write_text("")
        return times


def _new_process(out: Path, pid: int, after: float) -> Callable[[], list[float]]:
    """The arrival times of samples from another process than ``pid`` after ``after``."""
    return lambda: [t for t, p in _records(out) if p != pid and t > after]


def chain(side: str) -> float:
    """Seconds from starting the 10-node chain to the first sample at its end."""
    with tempfile.TemporaryDirectory(prefix=f"peer-{side}-") as tmp:
        out = Path(tmp) / "rec.txt"
        started = time.time()
        with _system(side, Path(tmp), "chain", out, 0, 0) as proc:
            first = _wait(lambda: _records(out), 120, f"{side} chain", proc)
        return first[0][0] - started  # type: ignore[index]


# ----------------------------------------------------------------------------- report


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}" if b else "-"


def bench(args: argparse.Namespace) -> int:
    figures = [f.strip() for f in args.only.split(",") if f.strip()]
    sides = ("rra", "dora")
    rtt: dict[str, list[float]] = {s: [] for s in sides}
    rst: dict[str, list[float]] = {s: [] for s in sides}
    chn: dict[str, list[float]] = {s: [] for s in sides}
    print(f"load average before: {_load()}")
    for run in range(args.runs):
        order = sides if run % 2 == 0 else sides[::-1]
        for side in order:
            if "roundtrip" in figures:
                rtt[side] += roundtrip(side, args.n, args.warm)
            if "restart" in figures:
                rst[side] += restart(side, args.kills)
            if "chain" in figures:
                chn[side].append(chain(side))
        print(f"run {run + 1}/{args.runs} done (load {_load()})", flush=True)
    print(f"load average after: {_load()}")
    rows: list[list[object]] = []
    ok = True
    if "roundtrip" in figures:
        ok &= _rows(rows, "round trip, µs", rtt, "p99 <= dora's", p99)
    if "restart" in figures:
        ok &= _rows(rows, "kill -9 -> new sample, ms", rst, "p99 <= 50 ms", None, 50.0)
    if "chain" in figures:
        ok &= _rows(rows, "10-node chain start, s", chn, "median <= dora's", median)
    print_table(
        ["figure", "rra median", "rra p99", "dora median", "dora p99", "ratio med", "ratio p99",
         "goal", ""],
        rows, digits=1,
    )  # fmt: skip
    return 0 if ok else 1


def _rows(rows: list[list[object]], name: str, data: dict[str, list[float]], goal: str,
          against: Callable[[list[float]], float] | None, limit: float = 0.0) -> bool:  # fmt: skip
    r, d = data["rra"], data["dora"]
    if not r or not d:
        return True
    passed = p99(r) <= limit if against is None else against(r) <= against(d)
    digits = 2 if name.endswith(", s") else 1
    rows.append([
        name, round(median(r), digits), round(p99(r), digits), round(median(d), digits),
        round(p99(d), digits), _ratio(median(r), median(d)), _ratio(p99(r), p99(d)), goal,
        "PASS" if passed else "FAIL",
    ])  # fmt: skip
    return passed


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3, help="runs per side and figure (3)")
    ap.add_argument("--n", type=int, default=2000, help="round trips measured per run (2000)")
    ap.add_argument("--warm", type=int, default=200, help="unmeasured round trips first (200)")
    ap.add_argument("--kills", type=int, default=1, help="kills per restart run (1)")
    ap.add_argument("--only", default="roundtrip,restart,chain", help="figures to measure")
    ap.add_argument(
        "--peer-nodes", action="store_true", help="rra-agent's nodes as peers (rra up --peer-nodes)"
    )
    args = ap.parse_args(argv)
    if args.peer_nodes:
        UP_FLAGS.append("--peer-nodes")
    print(f"rra-agent's nodes: {'peers (--peer-nodes)' if args.peer_nodes else 'clients'}")
    if not (BIN / "dora").exists():
        print("bench_peer: dora-rs is not installed: .venv/bin/pip install -e '.[peer]'")
        return 2
    try:
        return bench(args)
    except RuntimeError as exc:
        print(f"bench_peer: {exc}")
        return 2


if __name__ == "__main__":
    sys.exit(main())
