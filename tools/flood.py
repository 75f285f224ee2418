"""Publish valid data samples on one key at a fixed rate until Ctrl-C (an overload source).

    python tools/flood.py ENDPOINT KEY [RATE]    e.g. tcp/127.0.0.1:7447 rra/sys/data/noise/out

Each sample is a msgpack map ``{seq, value, relay, count}`` (the generic nodes' Sample), sent
in batches paced to RATE per second (default 10 000). On exit prints the rate achieved.
"""

from __future__ import annotations

import sys
import time

from rra_agent.bus.config import BusConfig
from rra_agent.bus.data import encode_data
from rra_agent.bus.session import open_session


def main(argv: list[str]) -> int:
    endpoint, key = argv[0], argv[1]
    rate = float(argv[2]) if len(argv) > 2 else 10_000.0
    session = open_session(BusConfig(connect=[endpoint], multicast=False, lease_ms=500))
    pub = session.declare_publisher(key)
    sent, t0, batch = 0, time.monotonic(), max(1, int(rate / 1000))
    try:
        while True:
            for _ in range(batch):
                sent += 1
                pub.put(encode_data({"seq": sent, "value": float(sent % 100), "relay": "n",
                                     "count": 0}))  # fmt: skip
            ahead = t0 + sent / rate - time.monotonic()
            if ahead > 0:
                time.sleep(ahead)  # pacing: the flood's own period, not a synchronisation
    except KeyboardInterrupt:
        pass
    finally:
        print(f"{sent / (time.monotonic() - t0):.0f}", flush=True)
        pub.undeclare()
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
