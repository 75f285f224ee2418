"""Component nodes of the object detection and storing case study (paper Sec. III, Fig. 2).

``scenarios/object_storing/system.yaml`` names these classes as
``rra_agent.nodes.object_storing.<Class>``. Each node uses exactly the port and parameter
names of its component there, treats its inputs as untrusted (a malformed sample is logged
and ignored, never raised on) and steps at 1-10 Hz. The world they simulate (map, racks,
server requests, camera scene) is in `rra_agent.nodes.object_storing.world`.

==========================  =================================================================
class                       component (system.yaml)
==========================  =================================================================
`TaskManager`               task_manager
`RadioSwitch`               radio_switch
`RadioDriver`               radio_driver_a, radio_driver_b (channel A / B)
`MapBasedNavigation`        map_based_navigation
`VfhLocalNavigation`        local_navigation, implementation ``static`` (the default)
`DwaLocalNavigation`        local_navigation, implementation ``dynamic``
`LaserScanner`              laser_scanner
`RobotDriver`               robot_driver
`RgbdCamera`                rgbd_camera
`ObjectDetector`            object_detector
`ObjectStoring`             object_storing
`GraspPlanner`              grasp_planner
`ArmController`             arm_controller
==========================  =================================================================
"""

from rra_agent.nodes.object_storing.manipulation import ArmController, GraspPlanner, ObjectStoring
from rra_agent.nodes.object_storing.navigation import (
    DwaLocalNavigation,
    MapBasedNavigation,
    VfhLocalNavigation,
)
from rra_agent.nodes.object_storing.perception import ObjectDetector
from rra_agent.nodes.object_storing.radio import RadioDriver, RadioSwitch
from rra_agent.nodes.object_storing.sensors import LaserScanner, RgbdCamera, RobotDriver
from rra_agent.nodes.object_storing.task import TaskManager

__all__ = [
    "ArmController",
    "DwaLocalNavigation",
    "GraspPlanner",
    "LaserScanner",
    "MapBasedNavigation",
    "ObjectDetector",
    "ObjectStoring",
    "RadioDriver",
    "RadioSwitch",
    "RgbdCamera",
    "RobotDriver",
    "TaskManager",
    "VfhLocalNavigation",
]
