"""The link to the remote server: `RadioSwitch` on the robot and the `RadioDriver` channels.

A ``RadioFrame`` carries a msgpack map in its ``payload``: ``{"kind": "request", ...}`` (a
``TaskRequest``, server to robot), ``{"kind": "reply", ...}`` (a ``TaskReply``, robot to
server) or ``{"kind": "beacon"}`` (link keep-alive, each second). Only one driver runs at a
time (paper Fig. 2, run-time variation point (c)); the switch answers on whichever channel
it last heard from.

The remote server itself is simulated inside the driver (`_Server`): it asks for objects
``OBJ-000``, ``OBJ-001``... (`world.server_task`), asks again every ``request_period`` until
the robot replies, and moves on to the object after the one a reply names. Its position in
the sequence is therefore recovered from the robot's replies after a channel switch.
"""

from __future__ import annotations

from collections import deque
from typing import Any

import msgspec

from rra_agent.nodes.object_storing import world
from rra_agent.nodes.object_storing._common import Every, SafeNode, numbers, text

_ENC = msgspec.msgpack.Encoder()
_DEC = msgspec.msgpack.Decoder()

REQUEST_FIELDS = ("task", "rack_id", "barcode", "target_rack", "material")
MATERIAL_PERIOD = 5.0  # s between ObjectMaterial repeats
OUTBOX_SIZE = 16  # replies kept while the link is down
BEACON_PERIOD = 1.0  # s
DEFAULT_LATENCY_MS = {"A": 300.0, "B": 30.0}


def pack(kind: str, body: dict[str, Any] | None = None) -> bytes:
    return _ENC.encode({"kind": kind, **(body or {})})


def unpack(payload: Any) -> dict[str, Any] | None:
    """The map inside a frame's payload, or None if it is not one."""
    if not isinstance(payload, bytes | bytearray):
        return None
    try:
        value = _DEC.decode(payload)
    except msgspec.DecodeError:
        return None
    return value if isinstance(value, dict) and isinstance(value.get("kind"), str) else None


def parse_request(data: dict[str, Any]) -> dict[str, str] | None:
    """A ``TaskRequest`` with every field a string (``target_rack``, ``material`` may be
    missing: ""), or None."""
    out = {
        f: text(data.get(f, "" if f in ("target_rack", "material") else None))
        for f in REQUEST_FIELDS
    }
    return None if any(v is None for v in out.values()) else out  # type: ignore[return-value]


def parse_reply(data: dict[str, Any]) -> dict[str, Any] | None:
    barcode, message = text(data.get("barcode")), text(data.get("message", ""))
    success, position = data.get("success"), numbers(data.get("position", []))
    if barcode is None or message is None or not isinstance(success, bool) or position is None:
        return None
    return {"barcode": barcode, "success": success, "position": position, "message": message}


class RadioSwitch(SafeNode):
    """Bridges the task manager and the connected radio driver.

    - ``radio_in`` (RadioFrame from a driver): a request frame is published on ``request``
      (TaskRequest) and its material on ``object_material`` (ObjectMaterial; repeated every
      5 s for the Context Monitor's Material measurement, 60 s max age).
    - ``reply`` (TaskReply from the task manager) goes out on ``radio_out`` (RadioFrame,
      the channel last heard from). While the link is down (no frame for ``link_timeout``
      s) replies wait in a 16-frame outbox (one ``ready`` ask at most), sent when a frame
      arrives again.

    Parameters: ``link_timeout`` (s); ``material`` (str, default empty): when not empty,
    the published material whatever the request says (tests and scenarios set the context).
    """

    rate_hz = 2.0
    inputs = {"radio_in": "_on_radio_in", "reply": "_on_reply"}
    outputs = ("radio_out", "request", "object_material")

    def on_start(self) -> None:
        self.channel = ""
        self.last_rx: float | None = None
        self.seq = 0
        self.outbox: deque[dict[str, Any]] = deque(maxlen=OUTBOX_SIZE)
        self.barcode = ""
        self.material = ""
        self.material_timer = Every()

    def link_up(self, now: float) -> bool:
        timeout = self.fparam("link_timeout", 2.0, 0.0)
        return self.last_rx is not None and now - self.last_rx <= timeout

    def _on_radio_in(self, data: dict[str, Any]) -> bool:
        channel, body = text(data.get("channel", "")), unpack(data.get("payload"))
        if channel is None or body is None:
            return False
        self.channel, self.last_rx = channel, self.ctx.now()
        self._flush()
        if body["kind"] != "request":
            return True
        request = parse_request(body)
        if request is None:
            return False
        self.barcode, self.material = request["barcode"], request["material"]
        self.emit("request", request)
        self._publish_material()
        return True

    def _on_reply(self, data: dict[str, Any]) -> bool:
        reply = parse_reply(data)
        if reply is None:
            return False
        if not reply["barcode"]:  # a "ready" ask: the latest one is enough
            self.outbox = deque((r for r in self.outbox if r["barcode"]), maxlen=OUTBOX_SIZE)
        self.outbox.append(reply)
        if self.link_up(self.ctx.now()):
            self._flush()
        return True

    def step(self, now: float) -> None:
        if self.link_up(now):
            self._flush()
        if self.material_timer.due(now, MATERIAL_PERIOD):
            self._publish_material()

    def on_params(self, changed: dict[str, Any]) -> None:
        if "material" in changed:
            self._publish_material()

    def _flush(self) -> None:
        while self.outbox:
            frame = {
                "channel": self.channel,
                "seq": self.seq + 1,
                "payload": pack("reply", self.outbox[0]),
            }
            if not self.emit("radio_out", frame):
                break
            self.seq += 1
            self.outbox.popleft()

    def _publish_material(self) -> None:
        material = self.sparam("material", "") or self.material
        if material:
            self.emit("object_material", {"barcode": self.barcode, "material": material})


class _Server:
    """The simulated remote server behind a radio driver."""

    def __init__(self, task: str) -> None:
        self.task = task
        self.next_n = 0
        self.due_at: float | None = None  # when to (re)send the current request
        self.replies: list[dict[str, Any]] = []

    def poll(self, now: float, period: float) -> dict[str, Any] | None:
        """The request to send now, if any."""
        if self.due_at is None or now < self.due_at:
            return None
        self.due_at = now + period
        return world.server_task(self.next_n, self.task)

    def receive(self, body: dict[str, Any], now: float) -> None:
        reply = parse_reply(body)
        if reply is None:
            return
        self.replies.append(reply)
        n = world.barcode_number(reply["barcode"])
        if n is not None and n >= self.next_n:
            self.next_n = n + 1
        self.due_at = now  # answered (or the robot is asking): next request right away


class RadioDriver(SafeNode):
    """One radio channel with the remote server behind it.

    ``tx`` (RadioFrame from the switch) reaches the server, and the server's frames go out
    on ``rx`` (RadioFrame), each after ``latency_ms`` plus the frame's transmission time at
    ``bitrate_kbps``. The driver sends a beacon each second and the server's current
    request every ``request_period`` s until answered (first one 1 s after start).

    Parameters: ``channel`` (stamped on frames), ``bitrate_kbps``, ``latency_ms`` (default
    300 for channel A, 30 for B, 100 otherwise), ``request_period`` (s, default 20),
    ``task`` (what the server asks: ``detect``, the default, or ``store``).
    """

    rate_hz = 5.0
    inputs = {"tx": "_on_tx"}
    outputs = ("rx",)

    def on_start(self) -> None:
        self.server = _Server(self.sparam("task", "detect"))
        self.server.due_at = self.ctx.now() + 1.0
        self.seq = 0
        self.queue: list[tuple[float, str, dict[str, Any]]] = []  # (due, direction, body)
        self.beacon_timer = Every()

    def _on_tx(self, data: dict[str, Any]) -> bool:
        body = unpack(data.get("payload"))
        if body is None:
            return False
        self._delay("up", body, len(data["payload"]))
        return True

    def step(self, now: float) -> None:
        self.server.task = self.sparam("task", "detect")
        request = self.server.poll(now, self.fparam("request_period", 20.0, 0.5))
        if request is not None:
            self._delay("down", {"kind": "request", **request})
        if self.beacon_timer.due(now, BEACON_PERIOD):
            self._send({"kind": "beacon"})
        due = [item for item in self.queue if item[0] <= now]
        self.queue = [item for item in self.queue if item[0] > now]
        for _, direction, body in due:
            if direction == "up":
                self.server.receive(body, now)
            else:
                self._send(body)

    def _delay(self, direction: str, body: dict[str, Any], size: int | None = None) -> None:
        channel = self.sparam("channel", "")
        latency = self.fparam("latency_ms", DEFAULT_LATENCY_MS.get(channel, 100.0), 0.0)
        bits = 8 * (size if size is not None else len(pack("x", body)))
        airtime = bits / (1000 * self.fparam("bitrate_kbps", 250.0, 1.0))
        self.queue.append((self.ctx.now() + latency / 1000 + airtime, direction, body))

    def _send(self, body: dict[str, Any]) -> None:
        self.seq += 1
        frame = {
            "channel": self.sparam("channel", ""),
            "seq": self.seq,
            "payload": pack(body["kind"], body),
        }
        self.emit("rx", frame)
