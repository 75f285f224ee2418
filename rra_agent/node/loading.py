"""Import a node class by its dotted path, the system package's folder first."""

from __future__ import annotations

from collections.abc import Iterable

from rra_agent.bus import failure
from rra_agent.node.api import Node, NodeError


def load_node_class(path: str, folders: Iterable[str] = ()) -> type[Node]:
    """Import ``pkg.module.ClassName`` (or ``pkg.module:ClassName``) and check it is a Node.

    ``folders``: the system package's folder(s), appended to ``sys.path``
    (`rra_agent.package.imports`): a package may ship its own node classes; one of its
    modules hidden by a module of the same name elsewhere is an error saying so."""
    import importlib

    from rra_agent.package.imports import add_package_path, shadowed_problem

    folders = list(folders)
    add_package_path(folders)
    mod_name, sep, cls_name = path.replace(":", ".").rpartition(".")
    if not sep:
        raise NodeError(f"implementation {path!r} is not a dotted path 'pkg.module.Class'")
    try:
        module = importlib.import_module(mod_name)
    except ImportError as e:
        err = NodeError(f"cannot import {mod_name!r} for implementation {path!r}: {e}")
        raise failure.tag(err, "import") from e
    except Exception as e:  # the module itself raised (or does not compile)
        failure.tag(e, "import")
        raise
    hidden = shadowed_problem(module, folders)
    if hidden is not None:
        raise NodeError(f"implementation {path!r}: {hidden}")
    cls = getattr(module, cls_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Node)):
        raise NodeError(f"{path!r} is not a subclass of rra_agent.node.Node")
    return cls
