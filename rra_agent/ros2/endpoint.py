"""ROS 2 nodes, publishers, subscriptions, service servers and clients on a Zenoh session,
speaking rmw_zenoh: its key expressions, liveliness tokens, CDR payloads and attachments.

A `Ros2Context` is one Zenoh session seen as a ROS 2 context (its Zenoh id in every token,
node and entity ids from one counter); `Ros2Context.node` declares a node (its NN token),
whose methods make its endpoints, each declaring its own token. Nothing here raises in a
Zenoh callback: a sample of a wrong type, with a bad hash or undecodable bytes is counted
in `Subscription.dropped` (and reported to ``on_drop``); a request that cannot be decoded
or handled gets an error reply and is counted in `Service.dropped`. A `Client.call` has a
deadline and raises `ServiceTimeout` or `ServiceFailed`, one-line errors.

Close every endpoint (or the node, or the context) before the session: a process with a
callback subscriber or queryable still declared at exit hangs.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import zenoh

from rra_agent.ros2 import attachment
from rra_agent.ros2.attachment import Attachment
from rra_agent.ros2.errors import (
    BadAttachment,
    BadToken,
    DecodeError,
    FieldError,
    NoServer,
    Ros2Error,
    ServiceFailed,
    ServiceTimeout,
)
from rra_agent.ros2.names import (
    NO_TYPE_HASH,
    DataKey,
    check_domain,
    data_key,
    parse_data_key,
    qualify,
)
from rra_agent.ros2.tokens import Kind, Qos, Token, node_token

if TYPE_CHECKING:  # a registry is built by its user; importing it imports numpy and rosbags
    from rra_agent.ros2.types import TypeRegistry

Message = dict[str, Any]


class Ros2Context:
    """One Zenoh session as a ROS 2 context of domain ``domain``."""

    def __init__(self, session: zenoh.Session, types: TypeRegistry, domain: int = 0) -> None:
        self.session = session
        self.types = types
        self.domain = check_domain(domain)
        self.zid = str(session.info.zid())
        self._ids = 0
        self._lock = threading.Lock()
        self._nodes: list[Ros2Node] = []

    def next_id(self) -> int:
        with self._lock:
            self._ids += 1
            return self._ids - 1

    def node(self, name: str, namespace: str = "/") -> Ros2Node:
        node = Ros2Node(self, name, namespace)
        self._nodes.append(node)
        return node

    def close(self) -> None:
        for node in self._nodes:
            node.close()
        self._nodes.clear()


class _Entity:
    """What every endpoint has: its token (declared last, undeclared first) and GID."""

    kind: Kind
    token: Token
    gid: bytes
    _lv: Any = None

    def _announce(self, node: Ros2Node, key: DataKey, qos: Qos) -> None:
        self.token = Token(
            node.ctx.domain, node.ctx.zid, node.token.node_id, node.ctx.next_id(), self.kind,
            node.token.node, node.token.namespace, name=key.name, ros_type=key.ros_type,
            type_hash=key.type_hash, qos=qos,
        )
        self.gid = attachment.gid_of(self.token.key)
        self._lv = node.ctx.session.liveliness().declare_token(self.token.key)
        node._entities.append(self)

    def close(self) -> None:
        """Undeclare the token, then the endpoint (again: nothing)."""
        if self._lv is None:
            return
        self._lv.undeclare()
        self._lv = None
        self._undeclare()

    def _undeclare(self) -> None:  # pragma: no cover - each endpoint has its own
        pass


class Ros2Node:
    """A ROS 2 node: its NN token and the endpoints made through it."""

    def __init__(self, ctx: Ros2Context, name: str, namespace: str = "/") -> None:
        self.ctx = ctx
        self.token = node_token(ctx.domain, ctx.zid, ctx.next_id(), name, namespace)
        self._entities: list[_Entity] = []
        self._lv: Any = ctx.session.liveliness().declare_token(self.token.key)

    @property
    def fq_name(self) -> str:
        return self.token.fq_node

    def _key(self, name: str, ros_type: str) -> DataKey:
        """A name's data key: absolute, relative (to the namespace) or private (``~/x``)."""
        full = f"{self.fq_name}/{name[2:]}" if name.startswith("~/") else name
        full = qualify(full, self.token.namespace)
        return data_key(self.ctx.domain, full, ros_type, self.ctx.types.type_hash(ros_type))

    def publisher(self, topic: str, ros_type: str, qos: Qos | None = None) -> Publisher:
        return Publisher(self, self._key(topic, ros_type), qos or Qos())

    def subscription(
        self,
        topic: str,
        ros_type: str,
        callback: Callable[[Received], None],
        *,
        qos: Qos | None = None,
        decode: bool = True,
        on_drop: Callable[[str, str], None] | None = None,
    ) -> Subscription:
        key = self._key(topic, ros_type)
        return Subscription(self, key, callback, qos or Qos(), decode, on_drop)

    def service(
        self,
        name: str,
        srv_type: str,
        handler: Callable[[Message], Mapping[str, Any]],
        qos: Qos | None = None,
    ) -> Service:
        self.ctx.types.require_service(srv_type)
        return Service(self, self._key(name, srv_type), handler, qos or Qos())

    def client(self, name: str, srv_type: str, qos: Qos | None = None) -> Client:
        self.ctx.types.require_service(srv_type)
        return Client(self, self._key(name, srv_type), qos or Qos())

    def close(self) -> None:
        for entity in reversed(self._entities):
            entity.close()
        self._entities.clear()
        if self._lv is not None:
            self._lv.undeclare()
            self._lv = None


class Publisher(_Entity):
    """Publishes CDR samples with rmw_zenoh's attachment; `publish` takes a dict or bytes."""

    kind = Kind.PUBLISHER

    def __init__(self, node: Ros2Node, key: DataKey, qos: Qos) -> None:
        self.key = key
        self.types = node.ctx.types
        self.seq = 0
        self._lock = threading.Lock()
        reliable = qos.reliability in (0, 1)
        self._pub = node.ctx.session.declare_publisher(
            key.key,
            congestion_control=(
                zenoh.CongestionControl.BLOCK if reliable else zenoh.CongestionControl.DROP
            ),
        )
        self._announce(node, key, qos)

    def publish(self, message: Mapping[str, Any] | bytes) -> int:
        """Send one sample (a dict is encoded; bytes are sent as they are, CDR already);
        returns its sequence number."""
        data = message if isinstance(message, bytes) else self.types.encode(
            self.key.ros_type, message
        )
        with self._lock:
            self.seq += 1
            seq = self.seq
        self._pub.put(data, attachment=attachment.make(seq, self.gid))
        return seq

    def matched(self) -> bool:
        """Whether a subscriber matches now (the status object itself is always truthy)."""
        return _matching(self._pub.matching_status)

    def _undeclare(self) -> None:
        self._pub.undeclare()


@dataclass(frozen=True, slots=True)
class Received:
    """One sample that passed the checks: its message (None when not decoded), bytes,
    attachment (None when the sender put none or an invalid one) and when it arrived."""

    message: Message | None
    payload: bytes
    key: str
    attachment: Attachment | None
    received_ns: int


class Subscription(_Entity):
    """Receives a topic's samples; samples of another type or hash are refused and counted.

    It listens on the topic with any type and hash, so a publisher of a wrong type on the
    same topic is seen (counted as ``wrong_type``) rather than silently never matched.
    """

    kind = Kind.SUBSCRIPTION

    def __init__(
        self,
        node: Ros2Node,
        key: DataKey,
        callback: Callable[[Received], None],
        qos: Qos,
        decode: bool,
        on_drop: Callable[[str, str], None] | None,
    ) -> None:
        self.key = key
        self.types = node.ctx.types
        self.callback = callback
        self.decode = decode
        self.on_drop = on_drop
        self.received = 0
        self.dropped: Counter[str] = Counter()
        self.last_drop: str | None = None
        self._sub = node.ctx.session.declare_subscriber(key.any_type, self._on_sample)
        self._announce(node, key, qos)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        now = time.time_ns()
        key = str(sample.key_expr)
        try:
            self._check(parse_data_key(key))
            payload = sample.payload.to_bytes()
            message = self.types.decode(self.key.ros_type, payload) if self.decode else None
        except (BadToken, DecodeError) as e:
            reason = "decode" if isinstance(e, DecodeError) else getattr(e, "reason", "bad_key")
            self._drop(reason, f"{self.key.name}: {e}")
            return
        att = sample.attachment
        try:
            meta = attachment.unpack(att.to_bytes()) if att is not None else None
        except BadAttachment:
            meta = None
        self.received += 1
        try:
            self.callback(Received(message, payload, key, meta, now))
        except Exception as e:
            self._drop("callback", f"{self.key.name}: callback failed: {e}")

    def _check(self, got: DataKey) -> None:
        want = self.key
        if got.ros_type != want.ros_type:
            raise _Refused(
                "wrong_type", f"a {got.ros_type} sample, expected {want.ros_type}"
            )
        if NO_TYPE_HASH not in (got.type_hash, want.type_hash) and got.type_hash != want.type_hash:
            raise _Refused(
                "type_hash",
                f"a {got.ros_type} of another definition ({got.type_hash[:15]}..., expected "
                f"{want.type_hash[:15]}...)",
            )

    def _drop(self, reason: str, detail: str) -> None:
        self.dropped[reason] += 1
        self.last_drop = detail
        if self.on_drop is not None:
            with contextlib.suppress(Exception):  # a listener's bug must not stop the topic
                self.on_drop(reason, detail)

    def _undeclare(self) -> None:
        self._sub.undeclare()


class _Refused(BadToken):
    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class Service(_Entity):
    """A service server: ``handler(request) -> response`` (dicts), on a complete queryable.

    A request without a valid attachment, that does not decode, whose handler raises or
    whose response does not fit the type gets an error reply and is counted in `dropped`.
    """

    kind = Kind.SERVICE

    def __init__(
        self,
        node: Ros2Node,
        key: DataKey,
        handler: Callable[[Message], Mapping[str, Any]],
        qos: Qos,
    ) -> None:
        self.key = key
        self.types = node.ctx.types
        self.handler = handler
        self.served = 0
        self.dropped: Counter[str] = Counter()
        self.last_drop: str | None = None
        self._q = node.ctx.session.declare_queryable(key.key, self._on_query, complete=True)
        self._announce(node, key, qos)

    def _on_query(self, query: zenoh.Query) -> None:
        srv = self.key.ros_type
        try:
            att = query.attachment
            meta = attachment.unpack(att.to_bytes() if att is not None else None)
            payload = query.payload
            request = self.types.decode(
                f"{srv}_Request", payload.to_bytes() if payload is not None else b""
            )
        except (BadAttachment, DecodeError) as e:
            self._refuse(query, "bad_request", f"{self.key.name}: {e}")
            return
        try:
            response = self.types.encode(f"{srv}_Response", self.handler(request))
        except FieldError as e:
            self._refuse(query, "bad_response", f"{self.key.name}: handler's response: {e}")
            return
        except Exception as e:
            self._refuse(query, "handler", f"{self.key.name}: handler failed: {e}")
            return
        query.reply(self.key.key, response, attachment=attachment.make(meta.seq, meta.gid))
        self.served += 1

    def _refuse(self, query: zenoh.Query, reason: str, detail: str) -> None:
        self.dropped[reason] += 1
        self.last_drop = detail
        query.reply_err(detail.encode())

    def _undeclare(self) -> None:
        self._q.undeclare()


class Client(_Entity):
    """A service client whose every `call` has a deadline."""

    kind = Kind.CLIENT

    def __init__(self, node: Ros2Node, key: DataKey, qos: Qos) -> None:
        self.key = key
        self.types = node.ctx.types
        self.session = node.ctx.session
        self.seq = 0
        self._lock = threading.Lock()
        # only for its matching status: whether a server is there right now
        self._querier = node.ctx.session.declare_querier(
            key.key, target=zenoh.QueryTarget.ALL_COMPLETE
        )
        self._announce(node, key, qos)

    def available(self) -> bool:
        """Whether a server of this service is reachable now."""
        return _matching(self._querier.matching_status)

    def call(self, request: Mapping[str, Any], timeout: float = 2.0) -> Message:
        """The response to ``request``; `ServiceTimeout` when no reply came within
        ``timeout`` s, `ServiceFailed` for an error reply, no server or a bad response."""
        srv, name = self.key.ros_type, self.key.name
        data = self.types.encode(f"{srv}_Request", request)
        with self._lock:
            self.seq += 1
            seq = self.seq
        start = time.monotonic()
        replies = self.session.get(
            self.key.key,
            payload=data,
            attachment=attachment.make(seq, self.gid),
            target=zenoh.QueryTarget.ALL_COMPLETE,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout,
        )
        for reply in replies:
            if reply.ok is None:
                err = reply.err.payload.to_bytes().decode(errors="replace") if reply.err else ""
                if time.monotonic() - start >= timeout * 0.95 and "imeout" in err:
                    break
                raise ServiceFailed(f"service {name} ({srv}) answered with an error: {err}")
            try:
                return self.types.decode(f"{srv}_Response", reply.ok.payload.to_bytes())
            except DecodeError as e:
                raise ServiceFailed(f"service {name}: bad response: {e}") from None
        if time.monotonic() - start < timeout * 0.95:  # the call ended before its deadline
            if not self.available():
                raise NoServer(f"no server for service {name} ({srv}) in domain "
                               f"{self.key.domain}")
            raise NoServer(f"service {name} ({srv}) ended the call without a reply")
        raise ServiceTimeout(f"service {name} ({srv}) did not answer within {timeout:g} s")

    def _undeclare(self) -> None:
        self._querier.undeclare()


def _matching(status: Any) -> bool:
    """A matching status: an object with ``matching`` (whose own truth is always true) or,
    in some zenoh-python versions, a bool."""
    return bool(getattr(status, "matching", status))


__all__ = [
    "Client",
    "Publisher",
    "Received",
    "Ros2Context",
    "Ros2Error",
    "Ros2Node",
    "Service",
    "Subscription",
]
