"""dora-rs nodes of ``tools/bench_peer.py``: the counterparts of ``tools/peer_nodes.py``, on
dora's Python node API (``dora.Node``), one process each, started by ``dora run``.

    python tools/peer_dora.py pinger OUT N WARM   # ping on ``ping``, echo back on ``pong``
    python tools/peer_dora.py echo                # ``in`` -> ``out``, the received array as is
    python tools/peer_dora.py source              # on each ``tick``: (pid, seq) on ``out``
    python tools/peer_dora.py relay               # ``in`` -> ``out``
    python tools/peer_dora.py recorder OUT        # ``<wall time> <pid>`` per sample on ``in``

The pinger sends the same 93 bytes as the rra-agent pinger (the msgpack encoding of
``peer_nodes.payload``, made here without msgspec) and times from just before
``send_output`` to the return of ``next()`` with the echo, one round trip at a time.
"""

from __future__ import annotations

import os
import struct
import sys
import time

PID_SEQ = struct.Struct("<qq")


def payload(seq: int) -> bytes:
    """``peer_nodes.payload(seq)`` as msgpack: the same 93 bytes."""
    seq %= 100
    return (
        b"\x86\xa3seq" + bytes([seq]) + b"\xa5stamp\xcb" + struct.pack(">d", 1.7e9 + seq * 1e-3)
        + b"\xa5frame\xa9base_link\xa8position\x93\xcb" + struct.pack(">d", 0.125)
        + b"\xcb" + struct.pack(">d", -1.5) + b"\xcb" + struct.pack(">d", 2.75)
        + b"\xa5value\xcb" + struct.pack(">d", 41.5) + b"\xa2ok\xc3"
    )  # fmt: skip


def _node():  # -> dora.Node (imported here: payload() needs no dora)
    from dora import Node

    return Node()


def pinger(out: str, n: int, warm: int) -> None:
    node = _node()
    samples: list[float] = []
    seq, expected = 1, payload(1)
    sent = time.perf_counter()
    node.send_output("ping", expected)
    for event in node:
        if event["type"] != "INPUT":
            if event["type"] == "STOP":
                break
            continue
        if event["id"] == "tick":
            if time.perf_counter() - sent > 1.0:  # lost (the echo was not there yet)
                sent = time.perf_counter()
                node.send_output("ping", expected)
            continue
        arrived = time.perf_counter()
        if event["value"].to_numpy().tobytes() != expected:
            continue
        if seq > warm:
            samples.append((arrived - sent) * 1e6)
        if len(samples) >= n:
            break
        seq += 1
        expected = payload(seq)
        sent = time.perf_counter()
        node.send_output("ping", expected)
    with open(f"{out}.tmp", "w") as f:
        f.write("".join(f"{s:.1f}\n" for s in samples))
    os.replace(f"{out}.tmp", out)


def echo() -> None:
    node = _node()
    for event in node:
        if event["type"] == "INPUT":
            node.send_output("out", event["value"])


def source() -> None:
    node = _node()
    pid, seq = os.getpid(), 0
    for event in node:
        if event["type"] == "INPUT":
            seq += 1
            node.send_output("out", PID_SEQ.pack(pid, seq))


def relay() -> None:
    echo()


def recorder(out: str) -> None:
    node = _node()
    with open(out, "a", buffering=1) as f:
        for event in node:
            if event["type"] == "INPUT":
                pid, _ = PID_SEQ.unpack(event["value"].to_numpy().tobytes()[: PID_SEQ.size])
                f.write(f"{time.time():.6f} {pid}\n")


def main(argv: list[str]) -> None:
    kind, args = argv[0], argv[1:]
    if kind == "pinger":
        pinger(args[0], int(args[1]), int(args[2]))
    elif kind == "recorder":
        recorder(args[0])
    else:
        {"echo": echo, "source": source, "relay": relay}[kind]()


if __name__ == "__main__":
    main(sys.argv[1:])
