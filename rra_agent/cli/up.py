"""``rra up PKG --select ...``: run a whole system on this machine until Ctrl-C.

This process is the local host agent and the bus hub. It supervises the three engines as
processes of their own — Context Monitor, Adaptation Engine, Run-time Resolution Engine, each
as ``--replicas`` replicas (default 2: a leader and a hot standby, named ``<engine>-a``,
``<engine>-b``...) — and, through the resolution engine's requests, every component node.
Ctrl-C (or SIGTERM) stops all of them with the SIGINT -> SIGTERM -> SIGKILL escalation and
exits only when none is left (a second Ctrl-C kills what is left at once); a SIGKILL of this
process takes its children with it (parent-death signal).
Logs go to the run folder: one file per process and ``events.jsonl``.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.config import (
    DEFAULT_HUB,
    TLS_HUB,
    BusConfig,
    add_bus_arguments,
    add_peer_nodes_argument,
    bus_from_args,
    loopback_form,
)
from rra_agent.bus.counters import topic_limits
from rra_agent.cli.common import add_wide_argument
from rra_agent.deployment import Deployment, deploy_apart
from rra_agent.host.agent import HostAgent, schedule_self, security, state_printer
from rra_agent.host.catalog import Catalog
from rra_agent.host.forkserver import trim_heap
from rra_agent.host.links import LinkWatch, banner, printer
from rra_agent.models.system import Command, Supervision

if TYPE_CHECKING:
    from rra_agent.viz.rerun_log import RerunConfig

ENGINES = ("monitor", "adaptation", "resolution")
REPLICA_NAMES = "abcdefgh"
#: Engines keep no state of their own a restart could lose (they resume from the system) and
#: restart in well under a second: a larger restart budget than a component's default.
ENGINE_SUPERVISION = Supervision(max_restarts=20, restart_window=60.0, cooldown=5.0)


def replica_names(engine: str, replicas: int) -> list[str]:
    """``monitor-a``, ``monitor-b``...: never the role's own name (its leader's endpoint)."""
    return [f"{engine}-{REPLICA_NAMES[i]}" for i in range(replicas)]


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("package", metavar="PKG", help="system package folder")
    p.add_argument(
        "--select",
        "-s",
        action="append",
        default=[],
        help="deployment-time features, comma separated (default: the manifest's)",
    )
    p.add_argument("--run-dir", help="logs and events of this run (default: .rra/<system>-<time>)")
    p.add_argument("--host", default="local", help="this machine's host name (default: local)")
    p.add_argument(
        "--no-adaptation",
        action="store_true",
        help="do not run the adaptation engine (a scenario's control case)",
    )
    p.add_argument(
        "--replicas",
        type=int,
        default=2,
        choices=range(1, len(REPLICA_NAMES) + 1),
        metavar="N",
        help="replicas of each engine: a leader and N-1 hot standbys (default 2)",
    )
    p.add_argument(
        "--no-reflexes",
        action="store_true",
        help="never delegate a planned decision to a node (docs/architecture.md, Reflexes)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress lines")
    p.add_argument(
        "--no-record",
        action="store_true",
        help="do not record the run for `rra replay` (<run-dir>/record/, docs/recording.md)",
    )
    add_wide_argument(p, "the banner and progress lines")
    # -- Rerun logging (rra_agent.viz) --
    p.add_argument(
        "--rerun",
        nargs="*",
        metavar="MODE",
        help="log the run to Rerun, one recording for all processes: `save [PATH.rrd]` "
        "(the default mode; PATH default <run-dir>/recording.rrd), `connect [URL]` (a running "
        "viewer), `off` (the default); put it after PKG",
    )
    add_bus_arguments(p)
    add_peer_nodes_argument(p)


def engine_specs(
    dep: Deployment,
    names: list[str],
    run_dir: Path,
    host: str,
    adaptation: bool,
    replicas: int = 2,
    reflexes: bool = True,
    record: bool = True,
) -> list[m.NodeSpec]:
    """The engines as supervised processes (their command lines are their implementations)."""
    select = ["--select", ",".join(names)] if names else []
    select += [] if record else ["--no-record"]
    specs = []
    for engine in ENGINES:
        if engine == "adaptation" and (not adaptation or dep.package.adaptation is None):
            continue
        cmd = [
            sys.executable,
            "-m",
            f"rra_agent.engines.{engine}",
            "--package",
            str(dep.package.root),
            *select,
            "--run-dir",
            str(run_dir),
            # No Adaptation Engine, no decision to confirm a reflex with: none is installed.
            *(["--no-reflexes"] if engine == "resolution" and not (reflexes and adaptation)
              else []),
        ]
        specs += [
            m.NodeSpec(
                system=dep.system,
                name=name,
                host=host,
                implementation=Command(command=cmd),
                supervision=ENGINE_SUPERVISION,
                scheduling=dep.package.manifest.engines.scheduling,
            )
            for name in replica_names(engine, replicas)
        ]
    return specs


def begin_record(dep: Deployment, run_dir: Path, host: str) -> bool:
    """Begin the run's record (``<run-dir>/record/``: its models and what it runs); False
    (with a line saying why) when the models cannot be recorded."""
    from rra_agent.record.run import RunInfo, begin

    if dep.bundle is None:
        print("rra up: not recorded: a model file lies outside the package folder",
              file=sys.stderr, flush=True)  # fmt: skip
        return False
    info = RunInfo(system=dep.system, deployment=sorted(dep.selection), started=time.time(),
                   models=dep.models, host=host, package=str(dep.package.root))  # fmt: skip
    begin(run_dir, info, dep.bundle)
    return True


def print_partitions(session: zenoh.Session, key: str) -> zenoh.Subscriber[None]:
    """Print each ``host_unreachable`` / ``host_reachable`` event (the Context Monitor
    leader's, one per transition) on this console, as node-state changes are."""
    codec = m.Codec[m.EventMessage](m.EventMessage)

    def on_event(sample: zenoh.Sample) -> None:
        try:
            ev = codec.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        if isinstance(ev, m.AdaptationEvent) and ev.kind in ("host_unreachable", "host_reachable"):
            print(f"[{time.strftime('%H:%M:%S')}] {ev.message}", flush=True)

    return session.declare_subscriber(key, on_event)


def print_banner(
    args: argparse.Namespace,
    dep: Deployment,
    bus: BusConfig,
    agent: HostAgent,
    run_dir: Path,
    keep: list[Any],
) -> None:
    """What runs where (``Ctrl-C to stop`` on its first line): the system, its router's
    endpoints and links, where the tools find it, the run folder; then a line whenever a
    link to another router comes (or does not: `LinkWatch`)."""
    default = TLS_HUB if bus.tls is not None else DEFAULT_HUB
    tools = f"find it at {bus.hub}" + (
        " (their default)" if bus.hub == default else f": give them --connect {bus.hub}"
    )
    head = (
        f"rra up: system {dep.system!r} ({', '.join(sorted(dep.selection))}) on host "
        f"{args.host}; Ctrl-C to stop"
    )
    router = agent.session_bus
    fields = [("tools", tools), ("logs", str(run_dir))]
    text, linked = banner(head, router, agent.session, fields, wide=args.wide)
    print(text, flush=True)
    if agent.session is not None:
        say = printer("rra up: ", wide=args.wide)
        keep.append(LinkWatch(agent.session, router.connect, say, linked=linked).start())


def hub_bus(args: argparse.Namespace) -> BusConfig:
    """The bus of ``rra up``: the flags' (`bus_from_args`), its hub (the first connect
    endpoint, where the tools find it) the first ``--listen`` endpoint (its loopback form)
    when ``--listen`` is given without ``--connect``: a second system on this machine,
    started with its own ``--listen``, does not collide with the first on the default hub's
    port (tcp/127.0.0.1:7447)."""
    bus: BusConfig = bus_from_args(args, role="agent")
    if bus.listen and not args.connect and bus.connect in ([DEFAULT_HUB], [TLS_HUB]):
        bus = bus.override(connect=[loopback_form(bus.listen[0])])
    return bus


def run(args: argparse.Namespace) -> int:
    names = [n.strip() for v in args.select for n in v.split(",") if n.strip()]
    # Loaded in a fork (this process runs for the whole run: it keeps the deployment, not
    # the parsers and what loading left), before any thread starts.
    dep = deploy_apart(args.package, names)
    bus = hub_bus(args)
    bus.host_router(hub=True)  # a refused endpoint fails here, before the run folder exists
    stamp = time.strftime("%Y%m%d-%H%M%S")
    run_dir = Path(args.run_dir or Path(".rra") / f"{dep.system}-{stamp}").resolve()
    #: The folders this run makes (removed again if the hub cannot even start).
    made = [p for p in (run_dir, *run_dir.parents) if not p.exists()]
    run_dir.mkdir(parents=True, exist_ok=True)
    started: list[bool] = []
    try:
        return _run(args, dep, names, bus, run_dir, started)
    finally:
        if not started:  # nothing ran (e.g. the hub's port is taken): no empty run folder
            for folder in made:
                shutil.rmtree(folder, ignore_errors=True)


def _run(
    args: argparse.Namespace,
    dep: Deployment,
    names: list[str],
    bus: BusConfig,
    run_dir: Path,
    started: list[bool],
) -> int:
    """Run the system with its run folder made; ``started`` gets an item once it starts."""
    # A new run starts from the default selection; the engine's state file only carries the
    # applied selection across a restart of the engine *within* a run.
    (run_dir / "resolution-state.json").unlink(missing_ok=True)
    # -- Rerun logging (rra_agent.viz): the children inherit the configuration --
    from rra_agent.viz import recording

    try:
        rerun_config, rerun_out = recording.rerun_option(args.rerun, dep.system, run_dir)
    except ValueError as e:
        print(f"rra up: --rerun: {e}", file=sys.stderr)
        return 2
    recording.attach_blueprint(rerun_config, dep.package)
    recording.export(rerun_config)
    record = begin_record(dep, run_dir, args.host) if not args.no_record else False
    specs = engine_specs(
        dep, names, run_dir, args.host, not args.no_adaptation, replicas=args.replicas,
        reflexes=not args.no_reflexes,
        record=record,
    )  # fmt: skip
    schedule_self(dep.package.manifest.agents, "rra up")
    agent = _hub_agent(args, dep, bus, run_dir, specs)
    keep: list[Any] = []  # declared entities live as long as they are referenced

    def start_engines() -> None:
        started.append(True)
        trim_heap()  # what loading the package freed
        for spec in specs:
            agent.handle(m.StartNode(spec=spec))
        if not args.quiet and agent.session is not None:
            keep.append(print_partitions(agent.session, agent.keys.events))
        if not args.quiet:
            print_banner(args, dep, bus, agent, run_dir, keep)

    agent.run(on_ready=start_engines)
    if record:
        from rra_agent.record.run import seal

        seal(run_dir)  # every engine has stopped: the record is whole
    if not args.quiet:
        print("rra up: all processes stopped", flush=True)
    if rerun_out is None:
        return 0
    return _merge_recording(rerun_config, rerun_out, quiet=args.quiet)


def _hub_agent(
    args: argparse.Namespace,
    dep: Deployment,
    bus: BusConfig,
    run_dir: Path,
    specs: list[m.NodeSpec],
) -> HostAgent:
    """The host agent of ``rra up``'s host: the hub (its router), which starts the engines
    (``specs``) and prints the nodes' states as they change."""
    catalog = Catalog.of(dep, args.host, default_host=True)
    catalog.add_builtins(specs)
    agent = HostAgent(
        dep.system,
        args.host,
        bus,
        run_dir / "logs",
        hub=True,
        catalog=catalog,
        data_topics=topic_limits(dep.package.system),
        engines=True,
        models=dep,
        **security(args, dep, args.host),
    )
    agent.observers.append(state_printer(quiet=args.quiet, wide=args.wide))
    return agent


def _merge_recording(config: RerunConfig, out: Path, *, quiet: bool) -> int:
    """Merge the processes' Rerun files into ``out``, once all have exited (rra_agent.viz);
    the exit status: 1 if the recording could not be made."""
    from rra_agent.viz import recording

    try:
        for warning in recording.finish(config, out):
            print(f"rra up: rerun: {warning}", file=sys.stderr)
    except recording.RecordingError as e:
        print(f"rra up: rerun recording FAILED: {e}", file=sys.stderr)
        print(f"rra up: the processes' files are in {config.dir}", file=sys.stderr)
        return 1
    if not quiet:
        print(f"rra up: Rerun recording saved to {out}", flush=True)
    return 0
