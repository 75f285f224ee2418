"""The actuator takes a node as started when it sees the node's own liveliness token, newer
than the start request: the token is declared once the node's declarations and ``on_start``
are done, so waiting for its host agent's ``RUNNING`` as well would add a hop (the cold
path's readiness, issue 25 item 3). In process: a fake session, the samples fed by hand."""

from __future__ import annotations

import threading
from types import SimpleNamespace
from typing import Any

import pytest
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.engines.actuator import ZenohActuator
from rra_agent.engines.executor import StepFailed

K = Keys("ready")


class _Session:
    def declare_subscriber(self, *_: Any, **__: Any) -> Any:
        return SimpleNamespace(undeclare=lambda: None)

    def liveliness(self) -> Any:
        return self


def _token(node: str, kind: zenoh.SampleKind = zenoh.SampleKind.PUT) -> Any:
    return SimpleNamespace(key_expr=K.alive("h1", node), kind=kind)


def _actuator(timeout: float) -> ZenohActuator:
    act = ZenohActuator(_Session(), K, start_timeout=timeout)  # type: ignore[arg-type]
    act._host = lambda spec, req, what: {"pid": 1, "state": "STARTING"}  # type: ignore[method-assign]
    return act


SPEC = m.NodeSpec(system="ready", name="n", host="h1", implementation="x.Y")


def test_a_node_is_started_when_its_token_appears_without_waiting_for_running() -> None:
    act = _actuator(timeout=30.0)
    done = threading.Event()
    t = threading.Thread(target=lambda: (act.start([SPEC]), done.set()), daemon=True)
    t.start()
    # The token appears (again and again, until the request has been sent and it counts).
    for _ in range(1000):
        act._on_alive(_token("n"))
        if done.wait(0.01):
            break
    assert done.is_set(), "started on the token alone"


def test_a_token_from_before_the_request_is_not_readiness() -> None:
    act = _actuator(timeout=0.3)
    act._on_alive(_token("n"))  # an earlier instance's token, still seen
    with pytest.raises(StepFailed, match="timed out"):
        act.start([SPEC])
