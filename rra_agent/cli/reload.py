"""``rra reload PKG`` / ``rra reload --undo``: edited models into the running system.

The edited package is checked as ``rra validate`` checks it, then against what runs (the
running models, which the Run-time Resolution Engine leader gives, and its state):
`rra_agent.model_changes.compare` lists what changes and refuses, each at its place in the
edited files (``file:line:col``), what cannot change while the system runs; then nothing is
sent and the exit status is 1. Otherwise the models go to the leader (`Reload`), which has
every engine replica and host agent prepare them, switches, and applies what they change
without restarting what they do not touch. The command waits until the Adaptation Engine
decides under the new models (the new rules in effect) and says how long that took.
``--undo`` goes back to the models before the last reload.
"""

from __future__ import annotations

import argparse
import contextlib
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgspec

from rra_agent.bus import messages as m
from rra_agent.bus.client import BusClient, NoReply, connect_system, wait_for_leader
from rra_agent.bus.config import add_bus_arguments, bus_from_args
from rra_agent.cli.common import WIDTH, add_system_argument, cut
from rra_agent.cli.select import operator_name
from rra_agent.deployment import Deployment, deploy_package
from rra_agent.errors import ErrorGroup, LocatedError, RraError
from rra_agent.model_changes import Comparison, Running, compare
from rra_agent.package.bundle import ModelBundle, bundle_of, load_bundle, write_bundle

_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("package", nargs="?", metavar="PKG", help="the edited system package")
    p.add_argument("--undo", action="store_true", help="go back to the models before the last "
                   "reload")  # fmt: skip
    add_system_argument(p)
    p.add_argument("--timeout", type=float, default=60.0, metavar="S",
                   help="wait this long for the engines (default 60)")  # fmt: skip
    p.add_argument("--wide", action="store_true", help="lines wider than 100 columns")
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> int:
    if args.undo == (args.package is not None):
        raise RraError("give the edited package (PKG) or --undo")
    edited = None if args.undo else _load(args.package)
    with connect_system(bus_from_args(args), args.system) as client:
        try:
            wait_for_leader(client, min(args.timeout, 5.0))
        except TimeoutError:
            raise RraError(f"no Run-time Resolution Engine leads system {client.keys.system!r} "
                           "on this bus (right --system and --connect?)") from None  # fmt: skip
        return _reload(args, client, edited)


def _load(path: str) -> Any:
    """The edited package, checked as `rra validate` checks it (located errors)."""
    from rra_agent.package.loader import load_package
    from rra_agent.package.validate import validate_package

    pkg = load_package(path, validate=False)
    ErrorGroup.raise_if_any(validate_package(pkg, implementations=True))
    return pkg


def _reload(args: argparse.Namespace, client: BusClient, pkg: Any) -> int:
    state, deployment = _running(client, args.timeout)
    if pkg is None:
        request = m.Reload(undo=True, operator=operator_name())
    else:
        edited = deploy_package(pkg, deployment, bundle_of(pkg))
        if edited.models == state.models:
            print(f"rra reload: models {state.models} run already: nothing to do")
            return 0
        current = _current(client, pkg, deployment, args.timeout)
        comparison = compare(current, edited, _view(state))
        if not comparison.allowed:
            return _refused(comparison)
        for change in comparison.changes or ["nothing the engines use (comments, layout)"]:
            print(cut(f"  {change}", WIDTH, args.wide))
        assert edited.bundle is not None
        request = m.Reload(bundle=edited.bundle, base=state.models, operator=operator_name())
    return _send(args, client, request)


def _running(client: BusClient, timeout: float) -> tuple[m.EngineState, list[str]]:
    """The leader's state and the deployment-time selection the system runs with."""
    keys = client.keys
    try:
        state = client.request(keys.engine_ctl("resolution"), m.GetState(), timeout)
        status = client.request(keys.engine_ctl("resolution"), m.Status(), timeout)
    except NoReply as e:
        raise RraError(f"the Run-time Resolution Engine did not answer: {e}") from None
    if not isinstance(state, m.Ok) or not isinstance(status, m.Ok):
        raise RraError("the Run-time Resolution Engine refused to tell its state")
    return msgspec.convert(state.result, m.EngineState), list(status.result.get("deployment", []))


def _current(client: BusClient, pkg: Any, deployment: list[str], timeout: float) -> Deployment:
    """The models the system runs now, from the leader, loaded here."""
    reply = client.request(client.keys.engine_ctl("resolution"), m.GetModels(), timeout)
    if not isinstance(reply, m.Ok):
        raise RraError(f"the running models are not available: {reply.message}")  # type: ignore[union-attr]
    bundle = msgspec.convert(reply.result, ModelBundle).verified()
    folder = Path(tempfile.mkdtemp(prefix="rra-running-"))
    try:
        write_bundle(bundle, folder)
        running = load_bundle(folder, root=pkg.root)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return deploy_package(running, deployment, bundle)


def _view(state: m.EngineState) -> Running:
    specs = {s.name: s for s in (*state.standby, *state.running)}
    return Running(
        implementations={n: s.implementation for n, s in specs.items()},
        hosts={n: s.host for n, s in specs.items()},
        params={n: dict(s.params) for n, s in specs.items()},
        selection=frozenset(state.selection),
    )


def _refused(comparison: Comparison) -> int:
    for err in comparison.refusals:
        print(err.headline if isinstance(err, LocatedError) else str(err), file=sys.stderr)
    print(f"rra reload: refused ({len(comparison.refusals)} change(s) cannot be made while "
          "the system runs): nothing was changed", file=sys.stderr)  # fmt: skip
    return 1


def _send(args: argparse.Namespace, client: BusClient, request: m.Reload) -> int:
    """Send the reload; wait for the Adaptation Engine's first selection under the new
    models (the new rules in effect)."""
    watch = _SelectionWatch(client)
    t0 = time.perf_counter()
    try:
        reply = client.request(client.keys.engine_ctl("resolution"), request, args.timeout)
    except NoReply:
        watch.close()
        raise RraError("the Run-time Resolution Engine did not answer the reload: see "
                       "`rra events` for what it did") from None  # fmt: skip
    if isinstance(reply, m.Err):
        watch.close()
        for line in reply.message.splitlines():
            print(cut(f"rra reload: {line}", WIDTH, args.wide), file=sys.stderr)
        print("rra reload: refused: nothing was changed", file=sys.stderr)
        return 1
    committed = time.perf_counter() - t0
    result = reply.result if isinstance(reply.result, dict) else {}
    models, previous = result.get("models", "?"), result.get("previous", "?")
    seconds = watch.wait(models, min(args.timeout, 10.0))
    for line in result.get("plan") or []:
        print(cut(f"  plan: {line}", WIDTH, args.wide))
    print(f"rra reload: models {models} run (were {previous}), switched in {committed:.3f} s")
    if seconds is not None:
        print(f"rra reload: the Adaptation Engine decides under them {seconds - t0:.3f} s after "
              "the command")  # fmt: skip
    elif watch.adaptation:
        print("rra reload: no selection under them yet (see `rra status`)")
    return 0


class _SelectionWatch:
    """The first selection decided under given models (its arrival time)."""

    def __init__(self, client: BusClient) -> None:
        self.seen: dict[str, float] = {}
        self.cond = threading.Condition()
        self.adaptation = bool(list(client.session.liveliness().get(
            f"{client.keys.lead('adaptation')}/**", timeout=0.5)))  # fmt: skip
        self.sub = client.session.declare_subscriber(client.keys.selection, self._on)

    def _on(self, sample: Any) -> None:
        try:
            msg = _SEL.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        if isinstance(msg, m.Selection) and msg.models:
            with self.cond:
                self.seen.setdefault(msg.models, time.perf_counter())
                self.cond.notify_all()

    def wait(self, models: str, timeout: float) -> float | None:
        try:
            if not self.adaptation:
                return None
            with self.cond:
                self.cond.wait_for(lambda: models in self.seen, timeout)
                return self.seen.get(models)
        finally:
            self.close()

    def close(self) -> None:
        with contextlib.suppress(Exception):  # already undeclared
            self.sub.undeclare()
