"""ROS 2 over Zenoh, without ROS installed: rmw_zenoh's wire format, done small and in Python.

ROS 2 nodes running on ``rmw_zenoh_cpp`` put every topic sample, service call and graph
announcement on Zenoh. This package speaks that mapping so rra-agent can see a ROS 2 graph,
read its topics, call its services and be seen from it:

- `names`: ROS 2 names, type names and the data key expressions;
- `tokens`: the graph's liveliness tokens (nodes, publishers, subscriptions, services,
  clients) and their QoS field;
- `attachment`: the 33-byte attachment of every sample, request and reply;
- `types`: message and service definitions (rosbags' offline type stores), CDR to and from
  plain dicts, dotted field paths, RIHS01 type hashes;
- `graph`: the live ROS 2 graph fed by liveliness tokens;
- `endpoint`: nodes, publishers, subscriptions, service servers and clients on a session;
- `params`: parameter and lifecycle services (rcl_interfaces, lifecycle_msgs);
- `bridge`: ROS 2 topic fields as measurement values, adaptation events as a ROS 2 topic;
- `launch`: the command line and environment of a ``ros2: PACKAGE EXECUTABLE`` component;
- `relay`: rewiring a ROS 2 subscriber through a relay instead of a restart.

The wire format followed is documented in docs/ros2.md (`RMW_ZENOH` below).
"""

from __future__ import annotations

#: The rmw_zenoh wire format this package follows (docs/ros2.md).
RMW_ZENOH = "rmw_zenoh design.md at commit 99a6a2bd (binary attachment of rmw_zenoh PR #601)"
