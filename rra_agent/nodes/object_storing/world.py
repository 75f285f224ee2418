"""The simulated world of the object-storing case study (paper Sec. III-A), in one place.

Two rooms joined by a corridor along the x axis, with the robot starting at the origin:

====================  ==================  =============================================
region (label)        x range (m)         contents
====================  ==================  =============================================
``RoomA``             x < 4.0             small racks ``A1``, ``A2`` (static furniture)
``Corridor``          4.0 <= x < 8.0      people and other robots (moving obstacles)
``RoomB``             x >= 8.0            large racks ``B1``, ``B2``
====================  ==================  =============================================

The doors are at (4, 0) and (8, 0); paths between regions go through them. This built-in map
stands for ``maps/two_rooms.yaml`` (the ``map`` parameter of map-based navigation).

The remote server asks for objects ``OBJ-000``, ``OBJ-001``... in a fixed cycle of racks,
target racks and materials (`server_task`). The RGB-D camera sees one synthetic rack
(`camera_scene`): a back panel at 1.1 m with five boxes in front of it.
"""

from __future__ import annotations

import math
import re
from typing import Any

from rra_agent.nodes.object_storing._common import Pose

ROOM_A_END = 4.0
ROOM_B_START = 8.0
REGIONS = ("RoomA", "Corridor", "RoomB")
DOORS = (Pose(ROOM_A_END, 0.0, 0.0), Pose(ROOM_B_START, 0.0, 0.0))
DEFAULT_MAP = "maps/two_rooms.yaml"

#: Rack id -> the pose the robot takes in front of it.
RACKS: dict[str, Pose] = {
    "A1": Pose(1.5, 1.5, math.pi / 2),
    "A2": Pose(2.5, -1.5, -math.pi / 2),
    "B1": Pose(9.5, 1.5, math.pi / 2),
    "B2": Pose(10.5, -1.5, -math.pi / 2),
}


def region_index(x: float) -> int:
    """0 (RoomA), 1 (Corridor) or 2 (RoomB) for a position ``x`` in m."""
    if x < ROOM_A_END:
        return 0
    return 1 if x < ROOM_B_START else 2


def region_label(x: float) -> str:
    return REGIONS[region_index(x)]


def plan_path(start: Pose, goal: Pose) -> list[Pose]:
    """Waypoints from ``start`` to ``goal``: the doors between their regions, then the goal."""
    a, b = region_index(start.x), region_index(goal.x)
    via = list(DOORS[a:b]) if b > a else list(reversed(DOORS[b:a]))
    points = [*via, goal]
    out: list[Pose] = []
    prev = start
    for p in points[:-1]:
        out.append(Pose(p.x, p.y, math.atan2(p.y - prev.y, p.x - prev.x)))
        prev = p
    out.append(goal)
    return out


# ---- the remote server ------------------------------------------------------------------
_RACK_CYCLE = ("A1", "B2", "A2", "B1")
_TARGET = {"A1": "B1", "A2": "B2", "B1": "A1", "B2": "A2"}
_MATERIALS = ("Glass", "Wood", "Metal")
_BARCODE = re.compile(r"^OBJ-(\d+)$")


def barcode_of(n: int) -> str:
    return f"OBJ-{n:03d}"


def barcode_number(barcode: str) -> int | None:
    """``OBJ-012`` -> 12; None for a barcode the server did not hand out."""
    m = _BARCODE.match(barcode)
    return int(m.group(1)) if m else None


def server_task(n: int, task: str) -> dict[str, str]:
    """The server's ``n``-th request (a ``TaskRequest``)."""
    rack = _RACK_CYCLE[n % len(_RACK_CYCLE)]
    return {
        "task": task,
        "rack_id": rack,
        "barcode": barcode_of(n),
        "target_rack": _TARGET[rack],
        "material": _MATERIALS[n % len(_MATERIALS)],
    }


# ---- the camera's view ------------------------------------------------------------------
PANEL_Z = 1.1
OBJECT_FRONT_Z = 0.95
#: Box centres (x, y) in the camera frame (x right, y up, z forward), m.
OBJECTS = ((-0.66, 0.0), (-0.3, 0.05), (-0.05, -0.1), (0.2, 0.05), (0.66, 0.0))
OBJECT_HALF = (0.04, 0.06)  # half width, half height
_GRID = 5  # points per side of an object's front face


def _panel() -> list[list[float]]:
    xs = [round(-0.75 + 0.1 * i, 3) for i in range(16)]
    ys = [round(-0.5 + 0.1 * j, 3) for j in range(11)]
    return [[x, y, PANEL_Z] for y in ys for x in xs]


def _box(cx: float, cy: float) -> list[list[float]]:
    hx, hy = OBJECT_HALF
    step_x, step_y = 2 * hx / (_GRID - 1), 2 * hy / (_GRID - 1)
    return [
        [round(cx - hx + i * step_x, 4), round(cy - hy + j * step_y, 4), OBJECT_FRONT_Z]
        for i in range(_GRID)
        for j in range(_GRID)
    ]


def camera_scene() -> list[list[float]]:
    """The synthetic rack: panel points first, then each box's front face (25 points each)."""
    points = _panel()
    for cx, cy in OBJECTS:
        points.extend(_box(cx, cy))
    return points


# ---- the map in the Rerun viewer (only when the run records one) --------------------------
#: Floor outlines (m): name -> (x_min, y_min, x_max, y_max); the corridor is narrower.
FLOOR = {
    "RoomA": (-1.0, -3.0, ROOM_A_END, 3.0),
    "Corridor": (ROOM_A_END, -1.0, ROOM_B_START, 1.0),
    "RoomB": (ROOM_B_START, -3.0, 12.0, 3.0),
}


def draw_map(log: Any) -> None:
    """The static floor map on a `rra_agent.viz.rerun_log.Logger`: ``/map/rooms`` (labelled
    outlines), ``/map/doors`` and ``/map/racks`` (small racks in room A, large in room B, in
    front of the pose the robot takes to reach them). The 2D view's y axis points down: y is
    drawn negated, as `Logger.robot_pose_2d` does, so that the map's y points up."""
    rr = log.rr
    names = list(FLOOR)
    mins = [(x0, -y1) for x0, _, _, y1 in FLOOR.values()]
    sizes = [(x1 - x0, y1 - y0) for x0, y0, x1, y1 in FLOOR.values()]
    colors = [(70, 110, 200), (200, 140, 40), (50, 150, 80)]
    log.log(
        "/map/rooms",
        rr.Boxes2D(mins=mins, sizes=sizes, labels=names, colors=colors, draw_order=0.0),
        static=True,
    )
    log.log(
        "/map/doors",
        rr.Points2D([(d.x, -d.y) for d in DOORS], radii=0.15, colors=[(120, 80, 40)]),
        static=True,
    )
    centres, halves = [], []
    for rack, p in RACKS.items():
        depth = 0.6  # the rack stands this far ahead of the approach pose
        centres.append((p.x + depth * math.cos(p.theta), -(p.y + depth * math.sin(p.theta))))
        halves.append((0.6, 0.2) if rack.startswith("B") else (0.35, 0.15))
    log.log(
        "/map/racks",
        rr.Boxes2D(centers=centres, half_sizes=halves, labels=list(RACKS), colors=[(150, 100, 60)]),
        static=True,
    )
