"""Starting a ROS 2 executable as a component: the command line and environment."""

from __future__ import annotations

import pytest

from rra_agent.ros2.errors import BadName, FieldError
from rra_agent.ros2.launch import Ros2Run, command, param_arg, parse_implementation


def test_ros2_run_with_name_remaps_and_parameters() -> None:
    run = parse_implementation("ros2: demo_nodes_cpp talker")
    assert run == Ros2Run("demo_nodes_cpp", "talker")
    argv, env = command(run, node="talker_a", namespace="/robot",
                        remaps={"chatter": "/cmd_a", "/tf": "/robot/tf"},
                        params={"rate": 10.0, "enabled": True, "name": "x y", "ids": [1, 2]},
                        domain=3, router="tcp/127.0.0.1:7448")
    assert argv == ["ros2", "run", "demo_nodes_cpp", "talker", "--ros-args",
                    "-r", "__node:=talker_a", "-r", "__ns:=/robot",
                    "-r", "chatter:=/cmd_a", "-r", "/tf:=/robot/tf",
                    "-p", "rate:=10.0", "-p", "enabled:=true", "-p", 'name:="x y"',
                    "-p", "ids:=[1,2]"]
    assert env == {"RMW_IMPLEMENTATION": "rmw_zenoh_cpp", "ROS_DOMAIN_ID": "3",
                   "ZENOH_CONFIG_OVERRIDE": 'connect/endpoints=["tcp/127.0.0.1:7448"]'}


def test_a_command_line_gets_the_same_ros_args() -> None:
    argv, _ = command(Ros2Run(argv=("./my_node", "--verbose")), remaps={"in": "/x"})
    assert argv == ["./my_node", "--verbose", "--ros-args", "-r", "in:=/x"]
    assert command(Ros2Run("pkg", "exe"))[0] == ["ros2", "run", "pkg", "exe"]


@pytest.mark.parametrize("bad", ["ros2: pkg", "ros2: pkg exe extra", "ros2: pkg ;rm", "ros2:"])
def test_bad_implementations_are_refused(bad: str) -> None:
    with pytest.raises(BadName, match="expected 'ros2: PACKAGE EXECUTABLE'"):
        parse_implementation(bad)
    assert parse_implementation("python: x") is None


def test_bad_names_and_values_are_refused() -> None:
    run = Ros2Run("pkg", "exe")
    with pytest.raises(BadName):
        command(run, node="bad-name")
    with pytest.raises(BadName):
        command(run, remaps={"in": "/bad name"})
    with pytest.raises(BadName):
        command(run, params={"a b": 1})
    with pytest.raises(BadName):
        command(run, domain=500)
    with pytest.raises(FieldError):
        param_arg({"a": 1})
