"""Object detection on the RGB-D point cloud (paper Sec. III, variation point (d): rack size).

The detector keeps one point in ``subsampling`` of the latest cloud, crops it to the region
of interest, takes the farthest depth as the rack's back panel and clusters the points in
front of it along x. Small racks (objects close together) need the full cloud and a narrow
region; large racks tolerate a coarser cloud over a wider one (runtime.yaml, Small / Large).
"""

from __future__ import annotations

from typing import Any

from rra_agent.nodes.object_storing._common import SafeNode, numbers, text

DEFAULT_ROI = (-0.6, -0.5, 0.3, 0.6, 0.5, 1.8)
FOREGROUND = 0.05  # m in front of the back panel
CLUSTER_GAP = 0.06  # m along x between two objects
MIN_POINTS = 4  # fewer points is noise, not an object
MAX_POINTS = 20000  # larger clouds are truncated

Point = tuple[float, float, float]


def parse_cloud(data: dict[str, Any]) -> list[Point] | None:
    """The points of a PointCloud map (bad points skipped); None if there is no point list."""
    raw = data.get("points")
    if not isinstance(raw, list):
        return None
    points: list[Point] = []
    for item in raw[:MAX_POINTS]:
        xyz = numbers(item[:3] if isinstance(item, list) else None, 3)
        if xyz is not None:
            points.append((xyz[0], xyz[1], xyz[2]))
    return points


def _cluster(points: list[Point]) -> list[list[Point]]:
    clusters: list[list[Point]] = []
    for p in sorted(points):
        if clusters and p[0] - clusters[-1][-1][0] <= CLUSTER_GAP:
            clusters[-1].append(p)
        else:
            clusters.append([p])
    return [c for c in clusters if len(c) >= MIN_POINTS]


def _describe(cluster: list[Point], back: float) -> dict[str, Any]:
    xs, ys, zs = zip(*cluster, strict=True)
    front = min(zs)
    depth = max(back - front, 0.01)
    return {
        "barcode": "",
        "position": [
            round(sum(xs) / len(xs), 4),
            round(sum(ys) / len(ys), 4),
            round(front + depth / 2, 4),
        ],
        "size": [
            round(max(xs) - min(xs), 4),
            round(max(ys) - min(ys), 4),
            round(depth, 4),
        ],
    }


def detect(
    points: list[Point], subsampling: int, roi: tuple[float, ...], barcode: str
) -> list[dict[str, Any]]:
    """The ``DetectedObject`` maps found in ``points``, ordered by x.

    The barcode reader is simulated: the requested ``barcode`` is read on object number
    ``sum(bytes) % count`` (deterministic), the others stay unread ("").
    """
    lo, hi = roi[:3], roi[3:]
    kept = [
        p for p in points[:: max(1, subsampling)] if all(lo[i] <= p[i] <= hi[i] for i in range(3))
    ]
    if not kept:
        return []
    back = max(p[2] for p in kept)
    objects = [_describe(c, back) for c in _cluster([p for p in kept if p[2] < back - FOREGROUND])]
    if objects and barcode:
        objects[sum(barcode.encode()) % len(objects)]["barcode"] = barcode
    return objects


class ObjectDetector(SafeNode):
    """Answers each ``request`` (DetectionRequest) with ``objects`` (DetectedObjects) found in
    the latest ``point_cloud`` (PointCloud); a request before any cloud is answered when the
    first cloud arrives. Event-driven (no periodic step).

    Parameters: ``subsampling`` (int >= 1: keep one point in N) and ``roi`` (x_min, y_min,
    z_min, x_max, y_max, z_max in the camera frame, m; an invalid value falls back to the
    default region, logged), both read at each detection.
    """

    inputs = {"request": "_on_request", "point_cloud": "_on_cloud"}
    outputs = ("objects",)

    def on_start(self) -> None:
        self.points: list[Point] | None = None
        self.pending: tuple[str, str] | None = None

    def _on_cloud(self, data: dict[str, Any]) -> bool:
        points = parse_cloud(data)
        if points is None:
            return False
        self.points = points
        if self.pending is not None:
            self._answer(*self.pending)
            self.pending = None
        return True

    def _on_request(self, data: dict[str, Any]) -> bool:
        rack_id, barcode = text(data.get("rack_id", "")), text(data.get("barcode", ""))
        if rack_id is None or barcode is None:
            return False
        if self.points is None:
            self.pending = (rack_id, barcode)
        else:
            self._answer(rack_id, barcode)
        return True

    def _answer(self, rack_id: str, barcode: str) -> None:
        subsampling = self.iparam("subsampling", 2, 1, 1000)
        objects = detect(self.points or [], subsampling, self.roi(), barcode)
        self.emit("objects", {"rack_id": rack_id, "objects": objects})

    def roi(self) -> tuple[float, ...]:
        value = numbers(self.ctx.param("roi"), 6)
        if value is None or any(value[i] > value[i + 3] for i in range(3)):
            self.warn("roi", f"invalid roi {self.ctx.param('roi')!r}: using {DEFAULT_ROI}")
            return DEFAULT_ROI
        return tuple(value)
