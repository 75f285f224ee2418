"""The attachment rmw_zenoh puts on every sample, service request and reply (33 bytes).

Zenoh's own serialization of (int64 sequence number, int64 source timestamp in ns since
the UNIX epoch, array of 16 bytes GID): two little-endian int64 and the GID as a sequence,
its length (16) as one LEB128 byte first. A publisher numbers its samples and puts its GID;
a client numbers its requests and puts its GID; a server's reply carries the request's
sequence number and the client's GID with the server's own timestamp.
"""

from __future__ import annotations

import hashlib
import struct
import time
from dataclasses import dataclass

from rra_agent.ros2.errors import BadAttachment

GID_SIZE = 16
SIZE = 8 + 8 + 1 + GID_SIZE
_HEAD = struct.Struct("<qqB")


@dataclass(frozen=True, slots=True)
class Attachment:
    seq: int
    timestamp_ns: int
    gid: bytes

    def pack(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise BadAttachment(f"a GID has {GID_SIZE} bytes, not {len(self.gid)}")
        try:
            return _HEAD.pack(self.seq, self.timestamp_ns, GID_SIZE) + bytes(self.gid)
        except struct.error as e:
            raise BadAttachment(f"attachment field out of range: {e}") from None


def unpack(data: bytes | None) -> Attachment:
    """The `Attachment` in ``data``; `BadAttachment` if it is missing or not one."""
    if data is None:
        raise BadAttachment("no attachment (rmw_zenoh puts one on every sample and call)")
    if len(data) != SIZE:
        raise BadAttachment(f"attachment of {len(data)} bytes, expected {SIZE}")
    seq, ts, n = _HEAD.unpack_from(data)
    if n != GID_SIZE:
        raise BadAttachment(f"attachment GID length {n}, expected {GID_SIZE}")
    return Attachment(seq, ts, bytes(data[_HEAD.size :]))


def make(seq: int, gid: bytes, now_ns: int | None = None) -> bytes:
    """The packed attachment of sample or request ``seq`` from ``gid``, stamped now."""
    return Attachment(seq, time.time_ns() if now_ns is None else now_ns, gid).pack()


def gid_of(token_key: str) -> bytes:
    """A 16-byte GID derived from an entity's liveliness token (rmw_zenoh hashes the token
    too, with XXH3-128; a GID only has to be unique and stable for the entity)."""
    return hashlib.sha256(token_key.encode()).digest()[:GID_SIZE]
