"""ROS 2 parameters and lifecycle over rmw_zenoh: clients for a node's standard services,
and servers so that an rra-agent node answers them too.

Parameters: ``<node>/get_parameters`` and ``<node>/set_parameters``
(``rcl_interfaces/srv/GetParameters``, ``SetParameters``); values cross as
``rcl_interfaces/msg/ParameterValue`` (`to_value` / `from_value`). Lifecycle (managed
nodes): ``<node>/change_state`` and ``<node>/get_state`` (``lifecycle_msgs/srv/...``), with
the transitions of ``lifecycle_msgs/msg/Transition``. Every client call has a deadline.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from typing import Any

from rra_agent.ros2.endpoint import Message, Ros2Node
from rra_agent.ros2.errors import FieldError, ServiceFailed

# rcl_interfaces/msg/ParameterType
_BY_TYPE = {
    1: "bool_value",
    2: "integer_value",
    3: "double_value",
    4: "string_value",
    5: "byte_array_value",
    6: "bool_array_value",
    7: "integer_array_value",
    8: "double_array_value",
    9: "string_array_value",
}

#: lifecycle_msgs/msg/State primary states.
STATES = {0: "unknown", 1: "unconfigured", 2: "inactive", 3: "active", 4: "finalized"}
#: lifecycle_msgs/msg/Transition ids of the transitions a manager asks for, and where each
#: goes from where (shutdown's id depends on the state it leaves).
TRANSITIONS = {"configure": 1, "cleanup": 2, "activate": 3, "deactivate": 4}
_SHUTDOWN = {"unconfigured": 5, "inactive": 6, "active": 7}
_MOVES = {
    ("unconfigured", "configure"): "inactive",
    ("inactive", "cleanup"): "unconfigured",
    ("inactive", "activate"): "active",
    ("active", "deactivate"): "inactive",
    ("unconfigured", "shutdown"): "finalized",
    ("inactive", "shutdown"): "finalized",
    ("active", "shutdown"): "finalized",
}


def to_value(value: Any) -> Message:
    """A Python value as a ``ParameterValue`` dict (None: NOT_SET)."""
    if value is None:
        return {"type": 0}
    if isinstance(value, bool):
        return {"type": 1, "bool_value": value}
    if isinstance(value, int):
        return {"type": 2, "integer_value": value}
    if isinstance(value, float):
        return {"type": 3, "double_value": value}
    if isinstance(value, str):
        return {"type": 4, "string_value": value}
    if isinstance(value, (bytes, bytearray)):
        return {"type": 5, "byte_array_value": list(value)}
    if isinstance(value, (list, tuple)) and value:
        for kind, field in ((bool, 6), (int, 7), (float, 8), (str, 9)):
            if all(type(v) is kind for v in value):
                return {"type": field, _BY_TYPE[field]: list(value)}
    raise FieldError(f"{value!r} cannot be a ROS 2 parameter value")


def from_value(value: Mapping[str, Any]) -> Any:
    """A ``ParameterValue`` dict as a Python value (None for NOT_SET)."""
    kind = value.get("type", 0)
    if kind == 0:
        return None
    if kind not in _BY_TYPE:
        raise FieldError(f"unknown ROS 2 parameter type {kind}")
    out = value.get(_BY_TYPE[kind])
    return bytes(out) if kind == 5 and out is not None else out


class ParameterClient:
    """Get and set the parameters of ROS 2 node ``target`` (fully qualified name)."""

    def __init__(self, node: Ros2Node, target: str) -> None:
        self.target = target
        self._get = node.client(f"{target}/get_parameters", "rcl_interfaces/srv/GetParameters")
        self._set = node.client(f"{target}/set_parameters", "rcl_interfaces/srv/SetParameters")

    def available(self) -> bool:
        """Whether both services are reachable now (a node's services can show in the graph
        a moment before calls reach them)."""
        return self._get.available() and self._set.available()

    def get(self, names: list[str], timeout: float = 2.0) -> dict[str, Any]:
        reply = self._get.call({"names": list(names)}, timeout)
        values = reply["values"]
        if len(values) != len(names):
            raise ServiceFailed(
                f"{self.target}/get_parameters returned {len(values)} values for {len(names)}"
            )
        return {n: from_value(v) for n, v in zip(names, values, strict=True)}

    def set(self, values: Mapping[str, Any], timeout: float = 2.0) -> dict[str, str | None]:
        """Set parameters; name -> None when set, or the node's reason for refusing."""
        params = [{"name": n, "value": to_value(v)} for n, v in values.items()]
        results = self._set.call({"parameters": params}, timeout)["results"]
        if len(results) != len(params):
            raise ServiceFailed(
                f"{self.target}/set_parameters returned {len(results)} results for {len(params)}"
            )
        return {
            n: None if r["successful"] else (r["reason"] or "refused")
            for n, r in zip(values, results, strict=True)
        }


class ParameterServer:
    """Answers ``get_parameters`` / ``set_parameters`` for ``node`` from a dict; ``on_set``
    checks and applies a change (None: accepted, or a reason to refuse it)."""

    def __init__(
        self,
        node: Ros2Node,
        values: dict[str, Any],
        on_set: Callable[[str, Any], str | None] | None = None,
    ) -> None:
        self.values = values
        self.on_set = on_set
        self._lock = threading.Lock()
        base = node.fq_name
        self._srv = [
            node.service(f"{base}/get_parameters", "rcl_interfaces/srv/GetParameters", self._get),
            node.service(f"{base}/set_parameters", "rcl_interfaces/srv/SetParameters", self._set),
        ]

    def _get(self, req: Message) -> Message:
        with self._lock:
            return {"values": [to_value(self.values.get(n)) for n in req["names"]]}

    def _set(self, req: Message) -> Message:
        results = []
        for p in req["parameters"]:
            try:
                value = from_value(p["value"])
                reason = self.on_set(p["name"], value) if self.on_set else None
            except Exception as e:
                reason = str(e) or type(e).__name__
            if reason is None:
                with self._lock:
                    self.values[p["name"]] = value
            results.append({"successful": reason is None, "reason": reason or ""})
        return {"results": results}


class LifecycleClient:
    """Drive the lifecycle of managed ROS 2 node ``target``."""

    def __init__(self, node: Ros2Node, target: str) -> None:
        self.target = target
        self._change = node.client(f"{target}/change_state", "lifecycle_msgs/srv/ChangeState")
        self._get = node.client(f"{target}/get_state", "lifecycle_msgs/srv/GetState")

    def available(self) -> bool:
        """Whether ``change_state`` is reachable now."""
        return self._change.available()

    def state(self, timeout: float = 2.0) -> str:
        reply = self._get.call({}, timeout)["current_state"]
        return str(reply["label"] or STATES.get(reply["id"], "unknown"))

    def change(self, transition: str, timeout: float = 2.0, current: str | None = None) -> bool:
        """Ask for ``transition`` (configure, activate, deactivate, cleanup, shutdown);
        whether the node made it. Shutdown's id depends on ``current`` (asked if None)."""
        if transition == "shutdown":
            tid = _SHUTDOWN.get(current or self.state(timeout), 5)
        elif transition in TRANSITIONS:
            tid = TRANSITIONS[transition]
        else:
            raise FieldError(f"unknown lifecycle transition {transition!r}: one of "
                             f"{', '.join([*TRANSITIONS, 'shutdown'])}")
        reply = self._change.call({"transition": {"id": tid, "label": transition}}, timeout)
        return bool(reply["success"])


class LifecycleServer:
    """Makes ``node`` a managed node: ``change_state`` / ``get_state`` with the standard
    state machine; ``on_transition(name)`` does the work (False refuses it)."""

    def __init__(
        self,
        node: Ros2Node,
        on_transition: Callable[[str], bool] | None = None,
        state: str = "unconfigured",
    ) -> None:
        self.state = state
        self.on_transition = on_transition
        self._lock = threading.Lock()
        base = node.fq_name
        self._srv = [
            node.service(f"{base}/change_state", "lifecycle_msgs/srv/ChangeState", self._change),
            node.service(f"{base}/get_state", "lifecycle_msgs/srv/GetState", self._get),
        ]

    def _name(self, transition: Mapping[str, Any]) -> str | None:
        tid = transition.get("id", 0)
        names = {v: k for k, v in TRANSITIONS.items()} | {v: "shutdown" for v in _SHUTDOWN.values()}
        return names.get(tid) or (transition.get("label") or None)

    def _change(self, req: Message) -> Message:
        name = self._name(req["transition"])
        with self._lock:
            target = _MOVES.get((self.state, name or ""))
            if target is None:
                return {"success": False}
            ok = self.on_transition(name or "") if self.on_transition else True
            if ok:
                self.state = target
        return {"success": bool(ok)}

    def _get(self, _req: Message) -> Message:
        ids = {v: k for k, v in STATES.items()}
        with self._lock:
            return {"current_state": {"id": ids.get(self.state, 0), "label": self.state}}
