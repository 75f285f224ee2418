"""tools/bench_roundtrip.py's plain zenoh-python echoes do what its report says they do: the raw
echo forwards a sample untouched, the floor echo decodes and re-encodes it with a new send-time
stamp and refuses what the SDK refuses (a floor doing less would make the SDK look worse)."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.counters import MAX_PAYLOAD
from rra_agent.bus.data import decode_data, encode_data

TOOLS = Path(__file__).resolve().parents[1] / "tools"
sys.path.insert(0, str(TOOLS))
try:
    import bench_roundtrip as bench
finally:
    sys.path.remove(str(TOOLS))


class Sample:
    def __init__(self, payload: bytes, attachment: bytes | None) -> None:
        self.payload = zenoh.ZBytes(payload)
        self.attachment = None if attachment is None else zenoh.ZBytes(attachment)


class Pub:
    """Records ``put`` calls as (payload, attachment) bytes."""

    def __init__(self) -> None:
        self.puts: list[tuple[bytes, bytes | None]] = []

    def put(self, payload: Any, *, attachment: Any = None) -> None:
        att = None if attachment is None else bytes(attachment)
        self.puts.append((bytes(payload), att))


def test_the_raw_echo_forwards_payload_and_attachment_unchanged():
    pub = Pub()
    payload, stamp = bench.make_payload(7), m.pack_stamp(1.5)
    bench.raw_echo(pub)(Sample(payload, stamp))
    assert pub.puts == [(payload, stamp)]


def test_the_floor_echo_decodes_re_encodes_and_stamps_anew():
    pub = Pub()
    echo = bench.floor_echo(pub)
    before = time.time()
    echo(Sample(bench.make_payload(7), m.pack_stamp(1.5)))
    echo(Sample(bench.make_payload(8), None))
    [(p7, a7), (p8, _)] = pub.puts
    assert decode_data(p7) == decode_data(bench.make_payload(7)) and decode_data(p8)["seq"] == 8
    assert a7 is not None and before <= m.unpack_stamp(a7) <= time.time()


def test_the_floor_echo_refuses_what_the_sdk_refuses():
    pub = Pub()
    echo = bench.floor_echo(pub)
    echo(Sample(b"\xc1", None))  # never valid msgpack
    echo(Sample(encode_data([1, 2]), None))
    echo(Sample(b"\x80" + b"\x00" * MAX_PAYLOAD["data"], None))
    assert pub.puts == []


@pytest.mark.system
def test_the_in_process_timings_run_each_callback_and_the_sdk_relays():
    """The hot-cache table times the three callbacks in this process (the SDK's through
    ZenohTransport and a NodeCore running Relay): each runs, and costs something."""
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    session = zenoh.open(config)
    try:
        timings = bench.in_process(session, "rra_agent.nodes.generic.Relay", n=200)
    finally:
        session.close()
    assert set(timings) == {bench.RAW, bench.FLOOR, bench.SDK}
    assert all(0 < us < 10_000 for us in timings.values()), timings
