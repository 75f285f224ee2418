"""Reconfiguration time for 10/50/100 nodes, cold (stop-then-start) and standby.

A generated system: a ``source`` (Ticker), N workers ``w<i>a`` and N alternatives ``w<i>b``
(Relays, run-time optional, same peers) and a ``sink`` listening to whichever workers run.
A run-time feature ``Mode`` (A | B) selects one set; flipping it swaps all N workers and
rewires the sink, which is the reconfiguration measured: the Run-time Resolution Engine's
executor applying the plan through a real host agent on loopback, from the first action to
the last acknowledgement (``Outcome.seconds``).

- cold: stop N nodes, start N nodes (each a new Python process), rewire the sink;
- standby: every alternative is pre-started inactive; the switch is one concurrent batch of
  N activations, N deactivations and the sink's rewire;
- hot: every worker is a hot standby (``hot-standby``): the alternatives run active from
  deployment and the sink listens to all 2N workers' keys from the start, delivering the
  selected ones; the switch is one rewire of the sink (the swapped-out workers stay hot).

Goals (2-core machine, 100 nodes): cold <= 3 s, standby <= 30 ms (the issue's).

    .venv/bin/python tools/bench_reconfig.py [--sizes 10,50,100] [--repeat 5]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import msgspec
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _benchutil import interrupt, median, p99, print_table

from rra_agent.bus.client import wait_until
from rra_agent.bus.config import BusConfig, free_port
from rra_agent.bus.keys import Keys
from rra_agent.bus.session import open_session
from rra_agent.core import resolution as r
from rra_agent.core.plan import diff, standby_subscriptions, subscriptions, wiring
from rra_agent.deployment import deploy
from rra_agent.engines.actuator import ZenohActuator
from rra_agent.engines.executor import Executor, spec_for
from rra_agent.host import procfs


def write_package(
    root: Path, n: int, strategy: str, containers: int = 0, shared: bool = False
) -> None:
    """``containers`` > 0: worker i (both alternatives) runs in container ``box<i % K>``;
    ``shared``: both alternatives of worker i publish on one topic, so the sink's wiring
    never changes (a switch is activations and deactivations only)."""

    def relay(name: str) -> dict:
        i = int(name[1:-1])
        out: dict = {"name": "out", "direction": "publish", "type": "S"}
        if shared:
            out["topic"] = f"work/w{i}"
        return {
            "name": name,
            "implementation": "rra_agent.nodes.generic.Relay",
            "optional": True,
            "binding": "runtime",
            "ports": [{"name": "in", "direction": "subscribe", "type": "S"}, out],
            **({"container": f"box{i % containers}"} if containers else {}),
        }

    workers = [f"w{i}{v}" for v in "ab" for i in range(n)]
    system = {
        "system": "bench",
        "components": [
            {
                "name": "source",
                "implementation": "rra_agent.nodes.generic.Ticker",
                "parameters": {"rate_hz": {"type": "float", "value": 1.0}},
                "ports": [{"name": "out", "direction": "publish", "type": "S"}],
            },
            *[relay(w) for w in workers],
            {
                "name": "sink",
                "implementation": "rra_agent.nodes.generic.Relay",
                "ports": [
                    {"name": "in", "direction": "subscribe", "type": "S"},
                    {"name": "out", "direction": "publish", "type": "S"},
                ],
            },
        ],
        "connections": [{"from": "source.out", "to": f"{w}.in"} for w in workers]
        + [
            {"from": f"{w}.out", "to": "sink.in", "optional": True, "binding": "runtime"}
            for w in workers
        ],
    }
    runtime = {
        "features": {
            mode: [
                t
                for i in range(n)
                for t in (
                    {"include_component": f"w{i}{mode.lower()}"},
                    {"add_connection": {"from": f"w{i}{mode.lower()}.out", "to": "sink.in"}},
                )
            ]
            for mode in ("A", "B")
        },
        "replacement": {
            "default": "stop-then-start",
            "components": dict.fromkeys(workers, STRATEGY[strategy]) if strategy != "cold" else {},
        },
    }
    (root / "rra.yaml").write_text("name: bench\nadaptation: null\n")
    (root / "features.uvl").write_text(
        "features\n    Bench {abstract}\n        mandatory\n            Mode {binding 'runtime'}\n"
        "                alternative\n                    A {default}\n                    B\n"
    )
    (root / "system.yaml").write_text(yaml.safe_dump(system, sort_keys=False))
    (root / "deployment.yaml").write_text("features: {}\n")
    (root / "runtime.yaml").write_text(yaml.safe_dump(runtime, sort_keys=False))
    (root / "measurements.yaml").write_text(
        "data_types:\n  - name: S\n    fields: {seq: int, value: float}\n"
    )


def memory(root_pid: int) -> tuple[int, float, float]:
    """(processes, RSS MiB, PSS MiB) of ``root_pid`` and all its descendants."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            ppid = procfs.parent(int(entry))
            if ppid is not None:
                children.setdefault(ppid, []).append(int(entry))
    todo, pids = [root_pid], []
    while todo:
        pid = todo.pop()
        pids.append(pid)
        todo += children.get(pid, [])
    rss = pss = 0.0
    for pid in pids:
        try:
            with open(f"/proc/{pid}/smaps_rollup") as f:
                for line in f:
                    if line.startswith("Rss:"):
                        rss += int(line.split()[1])
                    elif line.startswith("Pss:"):
                        pss += int(line.split()[1])
        except OSError:
            continue
    return len(pids), rss / 1024, pss / 1024


#: The replacement strategy of every worker, per benchmark strategy.
STRATEGY = {"cold": "stop-then-start", "standby": "standby", "hot": "hot-standby"}


@dataclasses.dataclass
class Case:
    times: list[float]
    switch: list[float]
    start: float = 0.0
    procs: int = 0
    rss: float = 0.0
    pss: float = 0.0


def run_case(n: int, strategy: str, repeat: int, containers: int = 0, shared: bool = False) -> Case:
    """Reconfiguration times (s) and time to the switch (s) of ``repeat`` mode flips, the
    deployment's start time (s) and the memory of everything running then."""
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        write_package(root, n, strategy, containers, shared)
        standby = strategy != "cold"
        dep = deploy(root)
        port = free_port()
        bus = BusConfig(connect=[f"tcp/127.0.0.1:{port}"], multicast=False, lease_ms=2000)
        agent = subprocess.Popen(
            [sys.executable, "-m", "rra_agent.host.agent", "--package", str(root), "--host",
             "local", "--hub", "--log-dir", str(root / "logs"), "--connect", bus.connect[0],
             "--no-multicast", "--lease-ms", "2000"],
            env={**os.environ, "RERUN_ANALYTICS": "0"},
        )  # fmt: skip
        session = open_session(bus, wait_connected=True)
        keys = Keys("bench")
        try:
            wait_until(
                lambda: list(session.liveliness().get(keys.host_alive("local"), timeout=0.5)),
                20, "the host agent",
            )  # fmt: skip
            boxes = {c.name: c.container for c in dep.configured.components if c.container}
            act = ZenohActuator(session, keys, start_timeout=120.0, stop_timeout=60.0,
                                request_timeout=10.0, container_of=boxes)  # fmt: skip
            pkg = dep.package
            hot = [c.name for c in dep.configured.components if pkg.runtime.replacement.hot(c.name)]
            ex = Executor(act, keys, pkg.runtime.replacement, default_host="local",
                          standby_inputs=standby_subscriptions(dep.configured, hot))  # fmt: skip

            def target(mode: str):
                return r.resolve_runtime(dep.configured, pkg.runtime, pkg.features,
                                         {"Bench", "Mode", mode}, {})  # fmt: skip

            current = msgspec.structs.replace(target("A"), components=[], connections=[])
            t0 = time.perf_counter()
            out = ex.execute(diff(current, target("A")))
            assert out.ok, out.error
            current = target("A")
            if standby:
                pre = standby_specs(dep, keys, "b")
                assert ex.prestart_standby(pre).ok
            started = time.perf_counter() - t0
            procs, rss, pss = memory(agent.pid)
            times, switch = [], []
            mode = "A"
            for _ in range(repeat):
                mode = "B" if mode == "A" else "A"
                tgt = target(mode)
                out = ex.execute(diff(current, tgt))
                assert out.ok, out.error
                current = tgt
                times.append(out.seconds)
                if out.first_switch is not None:
                    switch.append(out.first_switch)
            ex.actuator.stop(list(ex.running.values()) + list(ex.standby.values()))
            act.close()
            return Case(times, switch, started, procs, rss, pss)
        finally:
            session.close()
            interrupt(agent)


def standby_specs(dep, keys, variant: str) -> list:
    """The alternatives ``w<i><variant>``, wired as the configured model connects them."""
    subs = subscriptions(dep.configured)
    return [
        spec_for(keys, c, **wiring(c, subs), default_host="local")
        for c in dep.configured.components
        if c.name.startswith("w") and c.name.endswith(variant)
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="10,50,100")
    ap.add_argument("--repeat", type=int, default=5, help="mode flips per case")
    ap.add_argument("--strategies", default="cold,standby,hot", help="of cold, standby, hot")
    ap.add_argument(
        "--containers", type=int, default=0,
        help="run the workers in this many component containers (0: a process each)",
    )  # fmt: skip
    ap.add_argument(
        "--shared-topics", action="store_true",
        help="both alternatives of a worker publish on one topic (no rewire)",
    )  # fmt: skip
    args = ap.parse_args()
    rows = []
    layout = f"{args.containers} containers" if args.containers else "a process each"
    for n in [int(x) for x in args.sizes.split(",")]:
        for strategy in args.strategies.split(","):
            flips = args.repeat if strategy == "cold" else args.repeat * 4
            case = run_case(n, strategy, flips, args.containers, args.shared_topics)
            rows.append(
                [
                    n,
                    strategy,
                    len(case.times),
                    median(case.times) * 1e3,
                    p99(case.times) * 1e3,
                    median(case.switch) * 1e3 if case.switch else float("nan"),
                    case.start,
                    case.procs,
                    case.rss,
                    case.pss,
                ]
            )
            print(f"  {n} workers {strategy}: median {rows[-1][3]:.1f} ms", flush=True)
    print()
    print(f"workers: {layout}; topics: {'shared' if args.shared_topics else 'one per worker'}")
    print_table(
        ["workers", "strategy", "runs", "reconfig median ms", "reconfig p99 ms",
         "switch median ms", "start s", "processes", "RSS MiB", "PSS MiB"],
        rows,
    )  # fmt: skip
    print("a standby or hot case starts 2 x workers (the alternatives pre-started)")
    print("goals: 100 workers cold <= 3000 ms, standby <= 30 ms; in containers: 1000 "
          "components started <= 10 s, a 100-component switch <= 100 ms")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
