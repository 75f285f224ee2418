"""The Node SDK: write a component as a subclass of `Node`; test it with `NodeHarness`.

Public API (docs/api.md, docs/nodes.md): `Node`, `NodeContext`, `NodeError`, `NodeHarness`,
`RawCallback`. ``python -m rra_agent.node`` runs one node as its own process
(`rra_agent.node.process`); the rest of this package is the runtime around a node: its core
(`core`), the bus transport (`runtime`), component containers (`container`), loading node
classes (`loading`).
"""

from rra_agent import _compat
from rra_agent.node.api import Node, NodeContext, NodeError, RawCallback
from rra_agent.node.harness import NodeHarness

__all__ = ["Node", "NodeContext", "NodeError", "NodeHarness", "RawCallback"]

__getattr__ = _compat.renamed(__name__)
