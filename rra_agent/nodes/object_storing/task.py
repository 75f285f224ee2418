"""The Task Manager (paper Fig. 2): coordinates one server request at a time.

A ``detect`` request: navigate to the rack, ask the object detector for the barcode, reply
with the object's position. A ``store`` request (Manipulation) goes on: the object storing
component picks the object and stores it on the robot, the robot drives to the target rack,
and object storing places it there; then the reply.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from rra_agent.nodes.object_storing._common import SafeNode, numbers, text
from rra_agent.nodes.object_storing.radio import parse_request

DETECT_TIMEOUT = 5.0  # s for the detector's answer (one attempt)
STORE_TIMEOUT = 120.0  # s for object storing to report stored / placed
RESULTS_KEPT = 64
TASKS = {"detect": "detect", "detection": "detect", "store": "store", "manipulation": "store"}


@dataclass
class Job:
    """The request in progress and where it stands."""

    task: str  # detect | store
    rack_id: str
    barcode: str
    target_rack: str
    material: str
    phase: str = "to_rack"  # to_rack, detect, pick, to_target, place
    attempts: int = 1
    since: float = 0.0
    position: list[float] = field(default_factory=list)


class TaskManager(SafeNode):
    """Runs the task loop over its ports (names as in system.yaml).

    - ``request`` (TaskRequest, from the radio switch) starts a job; ``task`` is ``detect``
      or ``store`` (``detection`` / ``manipulation`` are accepted). While busy, other
      requests are ignored (the server asks again); a request already done is answered
      again from the results kept.
    - ``nav_goal`` (NavigationGoal with the rack id) <- ``nav_status`` (NavigationStatus):
      ``reached`` moves on, ``failed`` retries.
    - ``detect`` (DetectionRequest) <- ``detected_objects`` (DetectedObjects): the object
      whose barcode was read gives the position; none, or no answer within 5 s, retries.
    - ``store`` (StoreRequest) <- ``store_status`` (StoreStatus): ``stored`` then ``placed``.
    - ``reply`` (TaskReply): the result; when idle, a ``ready`` reply (empty barcode) asks
      the server for work every ``server_timeout`` s.

    Parameters: ``server_timeout`` (s); ``retry_limit``: retries after the first attempt of
    a navigation or detection step, then the job fails.
    """

    rate_hz = 2.0
    inputs = {
        "request": "_on_request",
        "nav_status": "_on_nav_status",
        "detected_objects": "_on_objects",
        "store_status": "_on_store_status",
    }
    outputs = ("reply", "nav_goal", "detect", "store")

    def on_start(self) -> None:
        self.job: Job | None = None
        self.results: dict[str, dict[str, Any]] = {}
        self.last_contact = self.ctx.now()

    # -- inputs ---------------------------------------------------------------------------
    def _on_request(self, data: dict[str, Any]) -> bool:
        request = parse_request(data)
        task = TASKS.get(request["task"].lower()) if request else None
        if request is None or task is None or not request["rack_id"] or not request["barcode"]:
            return False
        self.last_contact = self.ctx.now()
        barcode = request["barcode"]
        if self.job is not None:
            if self.job.barcode != barcode:
                self.warn("busy", f"busy with {self.job.barcode}: request {barcode} ignored")
        elif barcode in self.results:
            self.emit("reply", self.results[barcode])
        else:
            self.job = Job(
                task, request["rack_id"], barcode, request["target_rack"], request["material"]
            )
            self._enter("to_rack")
        return True

    def _on_nav_status(self, data: dict[str, Any]) -> bool:
        rack_id, state = text(data.get("rack_id")), text(data.get("state"))
        if rack_id is None or state is None:
            return False
        job = self.job
        if (
            job is None
            or job.phase not in ("to_rack", "to_target")
            or rack_id != self._nav_target()
        ):
            return True
        if state == "reached":
            self._enter("detect" if job.phase == "to_rack" else "place")
        elif state == "failed":
            self._retry(f"navigation to {rack_id} failed")
        return True

    def _on_objects(self, data: dict[str, Any]) -> bool:
        rack_id, objects = text(data.get("rack_id")), data.get("objects")
        if rack_id is None or not isinstance(objects, list):
            return False
        job = self.job
        if job is None or job.phase != "detect" or rack_id != job.rack_id:
            return True
        position = self._find(objects, job.barcode)
        if position is None:
            self._retry(f"{job.barcode} not found on rack {rack_id}")
        elif job.task == "detect":
            job.position = position
            self._finish(True, "detected")
        else:
            job.position = position
            self._enter("pick")
        return True

    def _on_store_status(self, data: dict[str, Any]) -> bool:
        barcode, state = text(data.get("barcode")), text(data.get("state"))
        if barcode is None or state is None:
            return False
        job = self.job
        if job is None or job.phase not in ("pick", "place") or barcode != job.barcode:
            return True
        if state == "stored" and job.phase == "pick":
            self._enter("to_target")
        elif state == "placed" and job.phase == "place":
            self._finish(True, f"stored on rack {job.target_rack}")
        elif state in ("failed", "full", "rejected"):
            self._finish(False, f"object storing: {state}")
        return True

    # -- periodic -------------------------------------------------------------------------
    def step(self, now: float) -> None:
        job = self.job
        if job is None:
            if now - self.last_contact >= self.fparam("server_timeout", 5.0, 0.1):
                self.last_contact = now
                self.emit(
                    "reply", {"barcode": "", "success": False, "position": [], "message": "ready"}
                )
        elif job.phase == "detect" and now - job.since >= DETECT_TIMEOUT:
            self._retry(f"no detection answer for rack {job.rack_id}")
        elif job.phase in ("pick", "place") and now - job.since >= STORE_TIMEOUT:
            self._finish(False, f"object storing timed out ({job.phase})")

    # -- the job --------------------------------------------------------------------------
    def _nav_target(self) -> str:
        assert self.job is not None
        return self.job.rack_id if self.job.phase == "to_rack" else self.job.target_rack

    def _enter(self, phase: str, attempts: int = 1) -> None:
        job = self.job
        assert job is not None
        job.phase, job.attempts, job.since = phase, attempts, self.ctx.now()
        if phase in ("to_rack", "to_target"):
            if not self._nav_target():
                self._finish(False, "no target rack")
                return
            self.emit("nav_goal", {"rack_id": self._nav_target(), "x": 0.0, "y": 0.0, "theta": 0.0})
        elif phase == "detect":
            self.emit("detect", {"rack_id": job.rack_id, "barcode": job.barcode})
        else:  # pick / place: the same request; object storing knows what is on board
            self.emit(
                "store",
                {"barcode": job.barcode, "target_rack": job.target_rack, "material": job.material},
            )

    def _retry(self, why: str) -> None:
        job = self.job
        assert job is not None
        if job.attempts > self.iparam("retry_limit", 3, 0, 1000):
            self._finish(False, why)
        else:
            self.ctx.log(f"{why}: attempt {job.attempts + 1}")
            self._enter(job.phase, job.attempts + 1)

    def _finish(self, success: bool, message: str) -> None:
        job = self.job
        assert job is not None
        reply = {
            "barcode": job.barcode,
            "success": success,
            "position": job.position,
            "message": message,
        }
        self.results[job.barcode] = reply
        while len(self.results) > RESULTS_KEPT:
            del self.results[next(iter(self.results))]
        self.job = None
        self.last_contact = self.ctx.now()
        self.emit("reply", reply)

    @staticmethod
    def _find(objects: list[Any], barcode: str) -> list[float] | None:
        for obj in objects:
            if isinstance(obj, dict) and obj.get("barcode") == barcode:
                position = numbers(obj.get("position"), 3)
                if position is not None:
                    return position
        return None
