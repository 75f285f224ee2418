"""``python -m rra_agent.node``: run one component node as its own Zenoh peer process.

The node's `NodeSpec` comes as JSON in ``RRA_NODE_SPEC`` (or ``--spec FILE``) and the bus
configuration in ``RRA_BUS_CONFIG``; both are set by the host agent that starts the node.
Exit status: 0 after a clean shutdown, 2 when the spec or implementation is unusable (the
supervisor treats that as fatal rather than restarting it forever).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import msgspec

from rra_agent.bus.messages import NodeSpec

SPEC_ENV = "RRA_NODE_SPEC"
EXIT_CONFIG = 2


def read_spec(path: str | None) -> NodeSpec:
    raw = Path(path).read_bytes() if path else os.environ.get(SPEC_ENV, "").encode()
    if not raw:
        raise ValueError(f"no node spec: set {SPEC_ENV} or pass --spec FILE")
    return msgspec.json.decode(raw, type=NodeSpec)


def run_node(spec: NodeSpec) -> int:
    """Run a node (Python implementation) until it is told to stop; its exit status.

    The bus configuration comes from ``RRA_BUS_CONFIG``. Used by ``python -m rra_agent.node``
    and by the host agent's fork server.
    """
    from rra_agent.bus.config import BusConfig
    from rra_agent.bus.node import load_node_class
    from rra_agent.errors import RraError

    try:
        if not isinstance(spec.implementation, str):
            raise ValueError("an external-command implementation is run directly, not here")
        node_cls = load_node_class(spec.implementation)
        bus = BusConfig.from_env()
    except (ValueError, RraError) as e:
        print(f"rra node {spec.name}: {e}", file=sys.stderr)
        return EXIT_CONFIG

    from rra_agent.bus.runtime import NodeRuntime

    return NodeRuntime(spec, node_cls, bus).run()


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


if __name__ == "__main__":
    sys.exit(main())
