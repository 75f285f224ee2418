"""The far side of tests/test_ros2_interop.py: zenoh-ros2-sdk (an independent Python
implementation of rmw_zenoh) in a process of its own.

    python sdk_peer.py ROUTER_PORT MSG_DIR ROLE [ARGS...]

Each line it prints on stdout is one JSON object; ``{"ready": ...}`` once its endpoints
are declared. It runs until its stdin closes (the test closes it), then exits cleanly.
Roles:
  pub_battery [P [T]]  publish sensor_msgs/BatteryState on topic T (/battery) every P s
                   (0.02; i/100 %)
  pub_string       publish std_msgs/String on /battery (a wrong type on that topic)
  sub_battery [T]  print every BatteryState received on topic T (/battery)
  serve            node /sdk_node: set_parameters, get_parameters and change_state servers
  call NODE        call NODE's set_parameters, get_parameters and change_state, print replies
  topic_info NAME  print what its graph knows of topic NAME and of NODE services
  sub TOPIC TYPE   print the scalar fields of every message received on TOPIC
"""

from __future__ import annotations

import json
import sys
import threading
import time


def out(**obj: object) -> None:
    print(json.dumps(obj, default=str), flush=True)


def main() -> None:
    port, msg_dir, role, *args = sys.argv[1:]
    from zenoh_ros2_sdk import (
        ROS2Publisher,
        ROS2ServiceClient,
        ROS2ServiceServer,
        ROS2Subscriber,
        ZenohSession,
        get_registry,
    )

    get_registry(msg_dir)
    kw = {"router_ip": "127.0.0.1", "router_port": int(port)}
    closing = threading.Event()
    things: list = []
    try:
        if role in ("pub_battery", "pub_string"):
            string = role == "pub_string"
            pub = ROS2Publisher(
                args[1] if len(args) > 1 else "/battery",
                "std_msgs/msg/String" if string else "sensor_msgs/msg/BatteryState",
                node_name="battery_node", **kw,
            )
            things.append(pub)
            out(ready=pub.keyexpr)

            period = float(args[0]) if args else 0.02

            def loop() -> None:
                i = 0
                while not closing.wait(period):
                    i += 1
                    if string:
                        pub.publish(data=f"not a battery {i}")
                    else:
                        pub.publish(**battery(pub.session_mgr.store, i / 100.0))

            threading.Thread(target=loop, daemon=True).start()
        elif role == "sub_battery":
            def got(msg: object) -> None:
                out(percentage=float(msg.percentage), voltage=float(msg.voltage),
                    frame=msg.header.frame_id, cells=[float(x) for x in msg.cell_voltage])

            sub = ROS2Subscriber(args[0] if args else "/battery",
                                 "sensor_msgs/msg/BatteryState", got,
                                 node_name="battery_listener", **kw)
            things.append(sub)
            out(ready=sub.keyexpr)
        elif role == "sub":
            def echo(msg: object) -> None:
                fields = getattr(msg, "__dataclass_fields__", {})
                values = {k: getattr(msg, k) for k in fields}
                out(topic=args[0], msg={k: v for k, v in values.items()
                                        if isinstance(v, (bool, int, float, str))})

            sub = ROS2Subscriber(args[0], args[1], echo, node_name="sdk_echo", **kw)
            things.append(sub)
            out(ready=sub.keyexpr)
        elif role == "serve":
            serve(things, kw, ROS2ServiceServer)
        elif role == "call":
            call(args[0], kw, ROS2ServiceClient, things)
        elif role == "topic_info":
            topic_info(args, kw)
        else:
            raise SystemExit(f"unknown role {role}")
        sys.stdin.read()  # until the test closes our stdin
    finally:
        closing.set()
        for thing in things:
            thing.close()
        ZenohSession.get_instance(**kw).close()


def battery(store: object, percentage: float) -> dict:
    """Every field of a BatteryState (the SDK wants them all)."""
    import numpy as np

    types = store.types  # type: ignore[attr-defined]
    stamp = types["builtin_interfaces/msg/Time"](sec=1, nanosec=2)
    header = types["std_msgs/msg/Header"](stamp=stamp, frame_id="sdk")
    zeros = dict.fromkeys(
        ["temperature", "current", "charge", "capacity", "design_capacity"], 0.0)
    return dict(header=header, voltage=12.0, percentage=percentage, **zeros,
                power_supply_status=2, power_supply_health=1, power_supply_technology=2,
                present=True, cell_voltage=np.array([3.7, 3.8], dtype=np.float32),
                cell_temperature=np.array([], dtype=np.float32), location="bay",
                serial_number="sn1")


def serve(things: list, kw: dict, server: type) -> None:
    params: dict[str, object] = {"speed": 1.0}
    state = {"label": "inactive"}

    def set_params(req):
        cls = type(req.parameters[0]) if req.parameters else None
        results = []
        for p in req.parameters:
            params[p.name] = p.value.double_value if p.value.type == 3 else p.value.integer_value
            results.append(res_cls(successful=p.name != "forbidden", reason="no" if p.name ==
                                   "forbidden" else ""))
        del cls
        return set_srv.response_msg_class(results=results)

    def get_params(req):
        pv = get_srv.response_msg_class.__dataclass_fields__  # noqa: F841
        from_store = set_srv.session_mgr.store.types["rcl_interfaces/msg/ParameterValue"]
        values = []
        for name in req.names:
            v = params.get(name)
            values.append(_value(from_store, v))
        return get_srv.response_msg_class(values=values)

    def change(req):
        ok = (state["label"], req.transition.id) in (("inactive", 3), ("active", 4))
        if ok:
            state["label"] = "active" if req.transition.id == 3 else "inactive"
        out(transition=req.transition.id, success=ok)
        return change_srv.response_msg_class(success=ok)

    set_srv = server("/sdk_node/set_parameters", "rcl_interfaces/srv/SetParameters",
                     set_params, node_name="sdk_node", **kw)
    res_cls = set_srv.session_mgr.store.types["rcl_interfaces/msg/SetParametersResult"]
    get_srv = server("/sdk_node/get_parameters", "rcl_interfaces/srv/GetParameters",
                     get_params, node_name="sdk_node", **kw)
    change_srv = server("/sdk_node/change_state", "lifecycle_msgs/srv/ChangeState", change,
                        node_name="sdk_node", **kw)
    things += [set_srv, get_srv, change_srv]
    out(ready=[set_srv.keyexpr, get_srv.keyexpr, change_srv.keyexpr])


def _value(cls: type, v: object) -> object:
    import numpy as np

    empty = {"bool_value": False, "integer_value": 0, "double_value": 0.0, "string_value": "",
             "byte_array_value": np.array([], dtype=np.uint8),
             "bool_array_value": np.array([], dtype=np.bool_),
             "integer_array_value": np.array([], dtype=np.int64),
             "double_array_value": np.array([], dtype=np.float64), "string_array_value": []}
    if isinstance(v, float):
        return cls(type=3, **{**empty, "double_value": v})
    if isinstance(v, int):
        return cls(type=2, **{**empty, "integer_value": v})
    return cls(type=0, **empty)


def call(node: str, kw: dict, client: type, things: list) -> None:
    import numpy as np

    set_cli = client(f"{node}/set_parameters", "rcl_interfaces/srv/SetParameters",
                     node_name="sdk_caller", timeout=5.0, **kw)
    get_cli = client(f"{node}/get_parameters", "rcl_interfaces/srv/GetParameters",
                     node_name="sdk_caller", timeout=5.0, **kw)
    change_cli = client(f"{node}/change_state", "lifecycle_msgs/srv/ChangeState",
                        node_name="sdk_caller", timeout=5.0, **kw)
    things += [set_cli, get_cli, change_cli]
    store = set_cli.session_mgr.store
    PV = store.types["rcl_interfaces/msg/ParameterValue"]
    P = store.types["rcl_interfaces/msg/Parameter"]
    T = store.types["lifecycle_msgs/msg/Transition"]
    pv = PV(type=3, bool_value=False, integer_value=0, double_value=0.25, string_value="",
            byte_array_value=np.array([], dtype=np.uint8),
            bool_array_value=np.array([], dtype=np.bool_),
            integer_array_value=np.array([], dtype=np.int64),
            double_array_value=np.array([], dtype=np.float64), string_array_value=[])
    out(ready=True)
    deadline = time.monotonic() + 10
    reply = None
    while reply is None and time.monotonic() < deadline:  # until the server is up
        reply = set_cli.call(parameters=[P(name="gain", value=pv)])
    out(set=[[r.successful, r.reason] for r in reply.results] if reply else None)
    got = get_cli.call(names=["gain"])
    out(get=[[v.type, v.double_value] for v in got.values] if got else None)
    changed = change_cli.call(transition=T(id=3, label="activate"))
    out(change=changed.success if changed else None)


def topic_info(args: list[str], kw: dict) -> None:
    from zenoh_ros2_sdk import get_service_names_and_types, get_topic_info

    deadline = time.monotonic() + 10
    info = None
    # its session may still be joining, its graph still filling: until it has an endpoint
    while time.monotonic() < deadline and (info is None or not info.publishers):
        info = get_topic_info(args[0], verbose=True, timeout=0.5, **kw)
    pubs = [p.node_name for p in info.publishers] if info else []
    subs = [s.node_name for s in info.subscribers] if info else []
    services = get_service_names_and_types(timeout=1.0, **kw)
    out(types=info.topic_types if info else [], publishers=pubs, subscribers=subs,
        services=[[n, t] for n, t in services])


if __name__ == "__main__":
    main()
