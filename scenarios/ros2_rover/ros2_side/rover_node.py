"""The ROS 2 side of the ros2_rover example: ROS 2 nodes played by zenoh-ros2-sdk.

zenoh-ros2-sdk is an independent pure-Python implementation of rmw_zenoh (a test dependency
of rra-agent), so these nodes are what a ROS 2 robot running ``rmw_zenoh_cpp`` would put on
Zenoh, without ROS installed. Each is started by rra-agent as a ROS 2 executable would be:

    rover_node.py ROLE --ros-args -r __node:=NAME -r PORT:=/topic -p name:=value ...

with ``ROS_DOMAIN_ID`` and ``ZENOH_CONFIG_OVERRIDE`` (the host router's endpoint) in its
environment, and on a system with certificates ``ZENOH_SESSION_CONFIG_URI`` (its Zenoh
session configuration: mutual TLS, its Zenoh id), read as rmw_zenoh reads it: that file,
then ``ZENOH_CONFIG_OVERRIDE`` on top. It reads its remappings and parameters as ``rclpy``
would, serves ``set_parameters`` and ``get_parameters`` (and ``change_state`` when managed)
and runs until SIGINT or SIGTERM. Offline: the message directory the SDK reads is exported from
rra-agent's type registry (`TypeRegistry.export`), with the package's own ``rover_msgs``.

Roles:
  battery      publishes sensor_msgs/BatteryState on port ``state`` at 10 Hz; parameter
               ``level`` (percent) is its charge
  planner      a managed (lifecycle) node: while active, publishes rover_msgs/Command on
               port ``cmd`` at 20 Hz (its node name, parameter ``speed``)
  controller   follows the rover_msgs/Command on port ``cmd``: publishes rover_msgs/Drive on
               port ``drive`` (the planner, its speed capped at parameter ``max_speed``);
               parameter ``mute_s``: set it, and it answers no parameter request for that
               many seconds (a service that never answers)
  saboteur     parameter ``mode``: ``wrong_type`` publishes std_msgs/String on /battery,
               ``truncated`` puts 7 bytes on /battery's BatteryState key, ``odd_token``
               declares a liveliness token with odd fields, ``off`` stops
"""

from __future__ import annotations

import json
import os
import signal
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
INTERFACES = HERE.parent / "interfaces"
TYPES = [
    "sensor_msgs/msg/BatteryState",
    "std_msgs/msg/String",
    "rover_msgs/msg/Command",
    "rover_msgs/msg/Drive",
    "rcl_interfaces/srv/SetParameters",
    "rcl_interfaces/srv/GetParameters",
    "lifecycle_msgs/srv/ChangeState",
]


def log(text: str) -> None:
    print(f"rover_node: {text}", file=sys.stderr, flush=True)


# ---- what rclpy would read: --ros-args --------------------------------------------------
class RosArgs:
    def __init__(self, argv: list[str]) -> None:
        self.node = "rover_node"
        self.namespace = "/"
        self.remaps: dict[str, str] = {}
        self.params: dict[str, Any] = {}
        args = argv[argv.index("--ros-args") + 1:] if "--ros-args" in argv else []
        for flag, value in zip(args[::2], args[1::2], strict=False):
            name, _, to = value.partition(":=")
            if flag == "-r" and name == "__node":
                self.node = to
            elif flag == "-r" and name == "__ns":
                self.namespace = to
            elif flag == "-r":
                self.remaps[name] = to
            elif flag == "-p":
                self.params[name] = json.loads(to) if to[:1] in "[\"" or _number(to) else (
                    to == "true" if to in ("true", "false") else to)

    def topic(self, name: str) -> str:
        """The topic a name of this node's code is on (remapped, else in its namespace)."""
        if name in self.remaps:
            return self.remaps[name]
        return name if name.startswith("/") else self.namespace.rstrip("/") + "/" + name


def _number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def endpoints() -> list[str] | None:
    """The routers to connect to as rmw_zenoh finds them: ``connect/endpoints`` of
    ``ZENOH_CONFIG_OVERRIDE``, else of the file ``ZENOH_SESSION_CONFIG_URI`` names; None
    when neither says (zenoh-ros2-sdk's default)."""
    override = os.environ.get("ZENOH_CONFIG_OVERRIDE", "")
    for part in reversed(override.split(";")):
        key, _, value = part.partition("=")
        if key.strip() == "connect/endpoints":
            return list(json.loads(value))
    uri = os.environ.get("ZENOH_SESSION_CONFIG_URI", "").strip()
    if uri:
        import json5

        with open(uri) as f:
            found = json5.load(f).get("connect", {}).get("endpoints")
        return list(found) if found else None
    return None


def router() -> tuple[str, int]:
    """The first router's address (IP, port): what zenoh-ros2-sdk's calls are given."""
    found = endpoints() or ["tcp/127.0.0.1:7447"]
    host, _, port = found[0].split("/", 1)[1].rpartition(":")
    return host.strip("[]"), int(port)


def keep_endpoints() -> None:
    """zenoh-ros2-sdk loads ``ZENOH_SESSION_CONFIG_URI`` and then replaces its endpoints with
    ``tcp/`` of the address it is given; rmw_zenoh keeps the file's. Put them back (first in
    ``ZENOH_CONFIG_OVERRIDE``, which the SDK applies last: the override's own entries win)."""
    found = endpoints()
    if found:
        override = os.environ.get("ZENOH_CONFIG_OVERRIDE", "")
        os.environ["ZENOH_CONFIG_OVERRIDE"] = ";".join(
            filter(None, [f"connect/endpoints={json.dumps(found)}", override]))


# ---- the node ----------------------------------------------------------------------------
class RoverNode:
    def __init__(self, role: str, args: RosArgs) -> None:
        from zenoh_ros2_sdk import ROS2ServiceServer, ZenohSession, get_registry

        from rra_agent.ros2.types import TypeRegistry

        types = TypeRegistry()
        types.register_folder(INTERFACES)
        self.msg_dir = tempfile.TemporaryDirectory(prefix="rover_msgs-")
        types.export(self.msg_dir.name, TYPES)
        get_registry(self.msg_dir.name)
        os.environ["ZENOH_CONFIG_OVERRIDE"] = (
            os.environ.get("ZENOH_CONFIG_OVERRIDE", "") + ";scouting/delay=0"
        ).lstrip(";")
        keep_endpoints()
        ip, port = router()
        self.kw = {"router_ip": ip, "router_port": port, "node_name": args.node,
                   "namespace": args.namespace}
        self.session = ZenohSession.get_instance(ip, port)
        self.store = self.session.store
        self.types = types
        self.role, self.args = role, args
        self.params: dict[str, Any] = dict(args.params)
        self.state = "unconfigured"
        self.mute_until = 0.0
        self.closing = threading.Event()
        self.things: list[Any] = []
        base = f"{args.namespace.rstrip('/')}/{args.node}"
        self.things += [
            ROS2ServiceServer(f"{base}/set_parameters", "rcl_interfaces/srv/SetParameters",
                              self.set_parameters, **self.kw),
            ROS2ServiceServer(f"{base}/get_parameters", "rcl_interfaces/srv/GetParameters",
                              self.get_parameters, **self.kw),
        ]
        if role == "planner":
            self.things.append(ROS2ServiceServer(
                f"{base}/change_state", "lifecycle_msgs/srv/ChangeState", self.change_state,
                **self.kw))
        getattr(self, f"start_{role}")()
        log(f"{role} {base} up ({', '.join(f'{k}={v}' for k, v in self.params.items())})")

    # -- parameters -----------------------------------------------------------------------
    def set_parameters(self, req: Any) -> Any:
        wait = self.mute_until - time.monotonic()
        if wait > 0:
            time.sleep(wait)  # answers nothing in time
        results = []
        for p in req.parameters:
            value = _from_value(p.value)
            ok = p.name in self.params and value is not None
            if ok:
                self.params[p.name] = value
                if p.name == "mute_s":
                    self.mute_until = time.monotonic() + float(value)
            results.append(self.store.types["rcl_interfaces/msg/SetParametersResult"](
                successful=ok, reason="" if ok else f"no parameter {p.name}"))
        return self.things[0].response_msg_class(results=results)

    def get_parameters(self, req: Any) -> Any:
        cls = self.store.types["rcl_interfaces/msg/ParameterValue"]
        values = [_to_value(cls, self.params.get(n)) for n in req.names]
        return self.things[1].response_msg_class(values=values)

    # -- lifecycle ------------------------------------------------------------------------
    def change_state(self, req: Any) -> Any:
        moves = {("unconfigured", 1): "inactive", ("inactive", 3): "active",
                 ("active", 4): "inactive", ("inactive", 2): "unconfigured"}
        target = moves.get((self.state, req.transition.id))
        if target is not None:
            log(f"{self.args.node}: {self.state} -> {target}")
            self.state = target
        return self.things[2].response_msg_class(success=target is not None)

    # -- roles ----------------------------------------------------------------------------
    def start_battery(self) -> None:
        pub = self._publisher("state", "sensor_msgs/msg/BatteryState")

        def loop() -> None:
            while not self.closing.wait(0.1):
                pub.publish(**battery(self.store, float(self.params["level"]) / 100.0))

        self._thread(loop)

    def start_planner(self) -> None:
        pub = self._publisher("cmd", "rover_msgs/msg/Command")

        def loop() -> None:
            while not self.closing.wait(0.05):
                if self.state == "active":
                    pub.publish(planner=self.args.node, speed=float(self.params["speed"]))

        self._thread(loop)

    def start_controller(self) -> None:
        from zenoh_ros2_sdk import ROS2Subscriber

        pub = self._publisher("drive", "rover_msgs/msg/Drive")

        def got(cmd: Any) -> None:
            limit = float(self.params["max_speed"])
            pub.publish(planner=cmd.planner, speed=min(float(cmd.speed), limit), limit=limit)

        self.things.append(ROS2Subscriber(self.args.topic("cmd"), "rover_msgs/msg/Command", got,
                                          **self.kw))

    def start_saboteur(self) -> None:
        from zenoh_ros2_sdk import ROS2Publisher

        wrong = ROS2Publisher("/battery", "std_msgs/msg/String", **self.kw)
        self.things.append(wrong)
        key = "{}/battery/sensor_msgs::msg::dds_::BatteryState_/{}".format(
            os.environ.get("ROS_DOMAIN_ID", "0"),
            self.types.type_hash("sensor_msgs/msg/BatteryState"))
        session = self.session.session
        domain = os.environ.get("ROS_DOMAIN_ID", "0")
        odd = f"@ros2_lv/{domain}/{session.info.zid()}/0/7/XX/%/%/saboteur/odd"

        def loop() -> None:
            token = None
            while not self.closing.wait(0.1):
                mode = self.params.get("mode", "off")
                if mode == "wrong_type":
                    wrong.publish(data="not a battery")
                elif mode == "truncated":
                    session.put(key, b"\x00\x01\x00\x00\x01\x02\x03")
                if mode == "odd_token" and token is None:
                    token = session.liveliness().declare_token(odd)
                elif mode != "odd_token" and token is not None:
                    token.undeclare()
                    token = None
            if token is not None:
                token.undeclare()

        self._thread(loop)

    def _publisher(self, port: str, ros_type: str) -> Any:
        from zenoh_ros2_sdk import ROS2Publisher

        pub = ROS2Publisher(self.args.topic(port), ros_type, **self.kw)
        self.things.append(pub)
        return pub

    def _thread(self, loop: Any) -> None:
        threading.Thread(target=loop, daemon=True).start()

    def close(self) -> None:
        self.closing.set()
        for thing in self.things:
            thing.close()
        self.session.close()
        self.msg_dir.cleanup()


def battery(store: Any, percentage: float) -> dict[str, Any]:
    """Every field of a BatteryState (the SDK wants them all)."""
    import numpy as np

    types = store.types
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="battery")
    zeros = dict.fromkeys(["temperature", "current", "charge", "capacity", "design_capacity"],
                          0.0)
    return dict(header=header, voltage=12.0, percentage=percentage, **zeros,
                power_supply_status=2, power_supply_health=1, power_supply_technology=2,
                present=True, cell_voltage=np.array([3.7, 3.8], dtype=np.float32),
                cell_temperature=np.array([], dtype=np.float32), location="bay",
                serial_number="rover-1")


def _from_value(v: Any) -> Any:
    return {1: v.bool_value, 2: v.integer_value, 3: v.double_value,
            4: v.string_value}.get(v.type)


def _to_value(cls: type, v: Any) -> Any:
    import numpy as np

    empty = {"bool_value": False, "integer_value": 0, "double_value": 0.0, "string_value": "",
             "byte_array_value": np.array([], dtype=np.uint8),
             "bool_array_value": np.array([], dtype=np.bool_),
             "integer_array_value": np.array([], dtype=np.int64),
             "double_array_value": np.array([], dtype=np.float64), "string_array_value": []}
    if isinstance(v, bool):
        return cls(type=1, **{**empty, "bool_value": v})
    if isinstance(v, int):
        return cls(type=2, **{**empty, "integer_value": v})
    if isinstance(v, float):
        return cls(type=3, **{**empty, "double_value": v})
    if isinstance(v, str):
        return cls(type=4, **{**empty, "string_value": v})
    return cls(type=0, **empty)


def main() -> int:
    role = sys.argv[1]
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    node = RoverNode(role, RosArgs(sys.argv[2:]))
    try:
        stop.wait()
    finally:
        node.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
