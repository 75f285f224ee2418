"""One component node as its own process: ``python -m rra_agent.node``.

The node's `NodeSpec` comes as JSON in ``RRA_NODE_SPEC`` (or ``--spec FILE``) and the bus
configuration in ``RRA_BUS_CONFIG``; both are set by the host agent that starts it. Exit
status: 0 after a clean shutdown, 1 when the node's own code raised (with a failure
report), 2 when the spec or implementation is unusable (the supervisor does not restart
it). The host agent's fork server runs `run_node` in a forked interpreter instead."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

import msgspec

from rra_agent import trace
from rra_agent.bus import failure
from rra_agent.bus.messages import SPEC_ENV as _SPEC_ENV
from rra_agent.bus.messages import NodeSpec
from rra_agent.errors import RraError
from rra_agent.models.system import CONTAINER as _CONTAINER
from rra_agent.node.loading import load_node_class

# ---- the process entry point ----------------------------------------------------------
SPEC_ENV = _SPEC_ENV

#: A start gate: called with "was the node told to stop?", True once the node may start.
Gate = Callable[[Callable[[], bool]], bool]


#: Exit status of a node whose spec or implementation is unusable (not restarted at once).
EXIT_CONFIG = 2


def read_spec(path: str | None) -> NodeSpec:
    raw = Path(path).read_bytes() if path else os.environ.get(SPEC_ENV, "").encode()
    if not raw:
        raise ValueError(f"no node spec: set {SPEC_ENV} or pass --spec FILE")
    return msgspec.json.decode(raw, type=NodeSpec)


#: The implementation of a component container's process (defined with the models).
CONTAINER = _CONTAINER


def run_node(spec: NodeSpec, gate: Gate | None = None) -> int:
    """Run a node (Python implementation) until it is told to stop; its exit status.

    The bus configuration comes from ``RRA_BUS_CONFIG``. Used by ``python -m rra_agent.node``
    and by the host agent's fork server. An exception that ends the node (in its import, its
    constructor, ``import_state``, ``on_start``, or a ``sys.exit`` with a non-zero status) is
    printed to its log with its traceback and reported to its host agent
    (`rra_agent.bus.failure`): exit status 2 when the spec or implementation is unusable, 1
    for any other exception. ``gate``: a replacement's start gate (`rra_agent.host.gate`):
    called once the session is open and the data ports are declared, it returns when the
    node's code may run (False: stop without running it).
    """
    try:
        return _run_node(spec, gate)
    except SystemExit as e:
        if e.code not in (None, 0):
            _crashed(spec, e, "run")
        raise
    except Exception as e:
        _crashed(spec, e, "run")
        return EXIT_FAILED


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m rra_agent.node", description=__doc__)
    parser.add_argument("--spec", help="node spec JSON file (default: $RRA_NODE_SPEC)")
    args = parser.parse_args(argv)
    try:
        spec = read_spec(args.spec)
    except (ValueError, OSError, msgspec.DecodeError) as e:
        print(f"rra node: {e}", file=sys.stderr)
        return EXIT_CONFIG
    return run_node(spec)


#: Exit status of a node ended by an exception of its code (as Python's own).
EXIT_FAILED = 1


def _run_node(spec: NodeSpec, gate: Gate | None = None) -> int:
    from rra_agent.bus.config import BusConfig

    if spec.implementation == CONTAINER:
        from rra_agent.node.container import run_container

        return run_container(spec, BusConfig.from_env())
    if spec.ros2 is not None and spec.ros2.executable:
        from rra_agent.node.ros2 import run_ros2_executable

        return run_ros2_executable(spec, BusConfig.from_env())
    try:
        if not isinstance(spec.implementation, str):
            raise ValueError("an external-command implementation is run directly, not here")
        trace.mark("node:import", spec.name)
        node_cls = load_node_class(spec.implementation, spec.path)
        bus = BusConfig.from_env()
        trace.mark("node:imported", spec.name)
    except (ValueError, RraError) as e:
        _crashed(spec, e, "import")
        return EXIT_CONFIG

    from rra_agent.node.runtime import NodeRuntime

    runtime = NodeRuntime(spec, node_cls, bus, gate=gate)
    try:
        return runtime.run()
    finally:
        core = runtime.core
        if core is not None and core.stop_failure is not None:  # a later report replaces it
            failure.write_report(core.stop_failure)


def _crashed(spec: NodeSpec, e: BaseException, during: str) -> None:
    """The node ends by ``e``: its summary and traceback to the log, the report written."""
    f = failure.describe(e, during, spec.path)
    print(f"rra node {spec.name}: {failure.summary(f)}", file=sys.stderr, flush=True)
    print(failure.formatted(e), file=sys.stderr, flush=True)
    failure.write_report(f)
