"""The bus side of a reload (``rra reload``), run by the Run-time Resolution Engine leader.

A reload is two phases. *Prepare*: every engine replica (of the three roles, standbys
included) and, when the system model changed, every host agent gets the new models
(`PrepareModels`) and loads them beside its own: a replica compiles its next core, a host
agent admits the components and implementations of both versions (its catalog) from then
on. Nothing decides under them yet. *Commit*: the leader switches and publishes its
`EngineState` naming the new models; every replica switches when its leader's state (or,
for an Adaptation Engine standby, its leader's selection) names them, and a host agent
keeps only the new catalog (`CommitModels`). A replica that did not prepare (frozen,
restarted) loads the models when it sees them named (the run's record, else the leader).
"""

from __future__ import annotations

from typing import Any

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.client import decoded
from rra_agent.bus.keys import Keys
from rra_agent.deployment import Deployment
from rra_agent.model_changes import Running
from rra_agent.package.bundle import ModelBundle

_ANY = m.Codec[Any](Any)
_REPLY = m.Codec[m.Reply](m.Reply)
#: How long a replica or a host agent may take to load the new models.
PREPARE_TIMEOUT = 10.0


def engine_replicas(session: zenoh.Session, keys: Keys) -> list[str]:
    """Every engine replica whose member token this session sees."""
    out = set()
    for reply in session.liveliness().get(f"{keys.prefix}/member/*/*", timeout=1.0):
        if reply.ok is not None:
            out.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
    return sorted(out)


def prepare_all(
    session: zenoh.Session,
    keys: Keys,
    bundle: ModelBundle,
    fence: m.Fence | None,
    *,
    replicas: list[str],
    hosts: list[str],
    timeout: float = PREPARE_TIMEOUT,
) -> tuple[list[str], list[str]]:
    """Send `PrepareModels` to the replicas and hosts at once. Returns (refusals, silent):
    what refused (``who: why``) and who did not answer."""
    payload = _ANY.encode(m.PrepareModels(bundle=bundle, fence=fence))
    targets = [(r, keys.engine_ctl(r)) for r in replicas]
    targets += [(f"host {h}", keys.host_ctl(h)) for h in hosts]
    handlers = [(who, session.get(key, payload=payload, timeout=timeout)) for who, key in targets]
    refused: list[str] = []
    silent: list[str] = []
    for who, handler in handlers:
        answer = _first(handler)
        if answer is None:
            silent.append(who)
        elif isinstance(answer, m.Err) and answer.code != "busy":
            refused.append(f"{who}: {answer.message}")
        elif isinstance(answer, m.Err):
            silent.append(who)
    return refused, silent


def commit_hosts(
    session: zenoh.Session, keys: Keys, digest: str, fence: m.Fence | None, hosts: list[str]
) -> list[str]:
    """`CommitModels` to every host (the hosts that did not take it)."""
    payload = _ANY.encode(m.CommitModels(digest=digest, fence=fence))
    handlers = [(h, session.get(keys.host_ctl(h), payload=payload, timeout=2.0)) for h in hosts]
    return [h for h, handler in handlers if not isinstance(_first(handler), m.Ok)]


def _first(handler: Any) -> m.Reply | None:
    return next(decoded(handler, _REPLY), None)


def running_view(
    running: dict[str, m.NodeSpec], standby: dict[str, m.NodeSpec], selection: frozenset[str]
) -> Running:
    """What runs, for `rra_agent.model_changes.compare`."""
    specs = {**standby, **running}
    return Running(
        implementations={n: s.implementation for n, s in specs.items()},
        hosts={n: s.host for n, s in specs.items()},
        params={n: dict(s.params) for n, s in specs.items()},
        selection=selection,
    )


def system_changed(old: Deployment, new: Deployment) -> bool:
    """Whether what the host agents admit may differ (the configured model changed)."""
    return msgspec.to_builtins(old.configured) != msgspec.to_builtins(new.configured)


def changed_decls(
    old: Deployment, new: Deployment, running: dict[str, m.NodeSpec]
) -> dict[str, dict[str, m.ParamDecl]]:
    """Running node -> the parameter declarations a reload changed (bounds)."""
    out: dict[str, dict[str, m.ParamDecl]] = {}
    for name in running:
        a, b = old.configured.component(name), new.configured.component(name)
        if a is None or b is None:
            continue
        changed = {
            k: m.ParamDecl(type=p.type, min=p.min, max=p.max)
            for k, p in b.parameters.items()
            if k in a.parameters and (a.parameters[k].min, a.parameters[k].max) != (p.min, p.max)
        }
        if changed:
            out[name] = changed
    return out
