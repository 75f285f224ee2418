"""Round trips between hosts: does a slow link to another host slow a host's local traffic?

Builds two hosts A and B in Linux network namespaces (tests/netns.py's `Network`: a bridge in
its own namespace, ``10.<k>.0.1`` and ``10.<k>.0.2``; root needed) and runs the deployed
topology in them: one Zenoh router per host, run by its host agent — ``rra agent --hub`` on
A (``tcp/127.0.0.1:7447`` and ``tcp/<A>:7447``), ``rra agent`` on B (``--listen
tcp/127.0.0.1:7447 --connect tcp/<A>:...``) — with every other process a Zenoh client of its
own host's router. The round trips are measured with tools/zping.py: an echo (client
session) republishes ~100-byte samples, a pinger (client session) sends one at a time and
times the answer (``--runs`` round trips after a warm-up).

Layouts, each measured in the same run:

- ``one host``: echo and pinger on A (two clients of A's router);
- ``B local``: echo and pinger on B, B's router linked straight to A's;
- ``B local, 20 ms link``: the same, with B's router linked to A's through
  tools/delay_proxy.py (20 ms each way, run in A), B's agent and echo restarted;
- ``B -> A -> B`` without and with the delay: pinger on B, echo on A (over the link twice).

The goal beside each figure: traffic between two processes of B stays on B, so ``B local``
is the same with a slow link to A (median < 5 ms, and within 1 ms of the undelayed median),
while a round trip over the delayed link takes at least 2 x 20 ms.

Run (as root): ``.venv/bin/python tools/bench_hosts.py [--runs 200] [--delay-ms 20]``.
Prints median and p99 (ms) per layout with the goal and PASS/FAIL; exit status 1 on a FAIL.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "tools"))

from _benchutil import median, p99  # noqa: E402
from netns import PYTHON, NetnsUnavailable, Network  # noqa: E402

PORT = 7447
PROXY_PORT = 7448
HUB = f"tcp/127.0.0.1:{PORT}"
PACKAGE = ROOT / "tests" / "data" / "relay_system"
ZPING = str(ROOT / "tools" / "zping.py")


def agent(net: Network, host: str, log_dir: Path, *bus: str, name: str):
    return net.python(host, "-m", "rra_agent", "agent", "--system", "relay_system",
                      "--host", host, "--package",
                      str(PACKAGE), "--log-dir", str(log_dir / f"{host}-nodes"), "--insecure",
                      *bus, name=name)  # fmt: skip


def ping(net: Network, host: str, echo: str, runs: int) -> list[float]:
    proc = net.python(host, ZPING, "ping", "--connect", HUB, "--name", echo, "--n", str(runs),
                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    out, err = proc.communicate(timeout=120 + runs)
    result = json.loads(out) if out.strip() else {"error": err}
    if proc.returncode != 0 or "rtt" not in result:
        raise SystemExit(f"ping {echo} from {host} failed: {result}\n{net.logs()}")
    if result["lost"]:
        print(f"warning: {result['lost']} of {runs} round trips lost ({host} -> {echo})")
    return result["rtt"]


def measure(runs: int, delay_ms: float, log_dir: Path) -> dict[str, list[float]]:
    out: dict[str, list[float]] = {}
    with Network(("A", "B"), log_dir=log_dir) as net:
        a = net.addr("A")
        hub = agent(net, "A", log_dir, "--hub", "--connect", HUB, "--listen", f"tcp/{a}:{PORT}",
                    name="agent-A")  # fmt: skip
        proxy = net.python("A", str(ROOT / "tools" / "delay_proxy.py"), "--listen",
                           f"{a}:{PROXY_PORT}", "--target", f"{a}:{PORT}", "--delay-ms",
                           f"{delay_ms:g}", name="delay-proxy")  # fmt: skip
        net.wait_listening("A", PORT, a, proc=hub)
        net.wait_listening("A", PROXY_PORT, a, proc=proxy)
        net.python("A", ZPING, "echo", "--connect", HUB, "--name", "onA", name="echo-A")
        out["one host (A)"] = ping(net, "A", "onA", runs)
        for delayed in (False, True):
            port = PROXY_PORT if delayed else PORT
            tag = "delayed" if delayed else "direct"
            b = agent(net, "B", log_dir, "--connect", f"tcp/{a}:{port}", "--listen", HUB,
                      name=f"agent-B-{tag}")  # fmt: skip
            net.wait_listening("B", PORT, "127.0.0.1", proc=b)
            echo_b = net.python("B", ZPING, "echo", "--connect", HUB, "--name", "onB",
                                name=f"echo-B-{tag}")  # fmt: skip
            suffix = f", {delay_ms:g} ms link" if delayed else ""
            out[f"B local{suffix}"] = ping(net, "B", "onB", runs)
            out[f"B -> A -> B{suffix}"] = ping(net, "B", "onA", runs)
            for proc in (echo_b, b):
                if net.stop(proc) != 0:
                    raise SystemExit(f"{proc.args} did not exit cleanly:\n{net.logs()}")
    problems = net.problems
    if problems:
        raise SystemExit("\n".join(problems))
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=200, help="round trips per layout")
    p.add_argument("--delay-ms", type=float, default=20.0, help="one-way delay of the link")
    p.add_argument("--keep-logs", action="store_true", help="print where the logs are")
    args = p.parse_args(argv)
    log_dir = Path(tempfile.mkdtemp(prefix="bench_hosts-"))
    try:
        rtt = measure(args.runs, args.delay_ms, log_dir)
    except NetnsUnavailable as e:
        print(f"bench_hosts: network namespaces unavailable: {e}", file=sys.stderr)
        return 2
    ms = 1e3
    d = args.delay_ms
    local = median(rtt["B local"]) * ms
    goals = {
        "one host (A)": ("median < 5 ms", lambda s: median(s) * ms < 5),
        "B local": ("median < 5 ms", lambda s: median(s) * ms < 5),
        f"B local, {d:g} ms link": (
            f"median < 5 ms, within 1 ms of B local ({local:.2f})",
            lambda s: median(s) * ms < 5 and abs(median(s) * ms - local) < 1,
        ),
        "B -> A -> B": ("median < 5 ms (no delay)", lambda s: median(s) * ms < 5),
        f"B -> A -> B, {d:g} ms link": (
            f"min >= {2 * d:g} ms (2 x delay)",
            lambda s: min(s) * ms >= 2 * d,
        ),
    }
    print(f"round trip, {args.runs} runs per layout, ~100-byte samples, client sessions "
          f"of each host's router ({PYTHON})")  # fmt: skip
    print(f"{'layout':<28} {'median ms':>10} {'p99 ms':>9} {'min ms':>8}  goal")
    failed = False
    for name, samples in rtt.items():
        text, ok = goals[name]
        verdict = "PASS" if ok(samples) else "FAIL"
        failed |= verdict == "FAIL"
        print(f"{name:<28} {median(samples) * ms:>10.3f} {p99(samples) * ms:>9.3f} "
              f"{min(samples) * ms:>8.3f}  {text}: {verdict}")  # fmt: skip
    if args.keep_logs:
        print(f"logs in {log_dir}")
    else:
        shutil.rmtree(log_dir, ignore_errors=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
