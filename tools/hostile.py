"""A hostile client on a system's bus: everything it sends must be refused, dropped or ignored.

    python tools/hostile.py ENDPOINT SYSTEM [--rate 200] [--seconds S]

At ``--rate`` messages per second (until Ctrl-C, or for ``--seconds``) it cycles through:
junk bytes and payloads over the size limit on every data, ctx, selection, events and
inject key it has seen; data samples that are ill-typed (a field missing or of the wrong
type), truncated msgpack, arrays, or that carry NaN and infinities, on every data key it
has seen; payloads over their key family's limit on every family (data, ctx, selection,
events, state, injections) and queries over it to every node, host and engine control
endpoint (at most one every 2 s: the routers drop them, the network still carries them);
selections forged with a fence no live leader holds, naming unknown
features and CV values of 1e6; operators' measurement overrides forged on every ctx key it
has seen (an override without the monitor leader's fence, or with one no leader holds) and
override requests to the monitor that it refuses (an unknown measurement, a duration out of
range); node requests with parameters out of their bounds, of the
wrong type or unknown; malformed queries to every node, host and engine control endpoint;
host requests the model does not allow (an undeclared command, a declared-looking one with
injected ``PYTHONWARNINGS``/``BROWSER`` variables, a node name escaping the log folder, a
spec update smuggling a command in).
It never sends a valid unauthenticated command (that is access control's business), nor a
well-typed plausible data sample: a runtime that is disturbed by it (a restart, a FATAL node,
a value out of bounds, a lost adaptation, a measurement from a forged sample) has a bug. (A
NaN in an otherwise well-typed sample is refused unless a measurement reading it says
``finite: false``.) Used by the tests with ``pytest --hostile`` and by hand.
On exit prints how many messages it sent.
"""

from __future__ import annotations

import argparse
import itertools
import random
import sys
import threading
import time
from typing import Any

import msgspec
import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.counters import MAX_PAYLOAD
from rra_agent.bus.keys import Keys
from rra_agent.bus.session import open_session
from rra_agent.models.system import Command

JUNK = [b"", b"\x00", b"\xc1\xff", b"\x81\xa1t\xa3zzz", bytes(range(256)), b"\x92\xa3sel\xc0"]
_NAN, _INF = float("nan"), float("inf")
#: Data samples a typed reader refuses: ill-typed, truncated, not a map, non-finite.
FORGED_DATA = [
    msgspec.msgpack.encode(x)
    for x in (
        {"value": 9.0},  # most fields missing
        {"seq": "1", "value": 9.0, "level": "9"},  # strings for numbers
        {"seq": True, "value": True, "level": True},  # booleans for numbers
        {"seq": 1, "value": _NAN, "level": _NAN},
        {"seq": 1, "value": _INF, "level": -_INF},
        [1, 9.0],
    )
]
FORGED_DATA.append(msgspec.msgpack.encode({"seq": 1, "value": 9.0, "level": 9.0})[:-5])
#: Seconds between two payloads over a family's limit.
OVERSIZED_EVERY = 2.0
_SEL = m.Codec[m.SelectionMessage](m.SelectionMessage)
_CTX = m.Codec[m.CtxMessage](m.CtxMessage)
#: Families whose keys are asked (queries), not put to.
QUERIED = ("node_ctl", "host_ctl", "engine_ctl")
_ANY = m.Codec[Any](Any)


class Hostile:
    def __init__(self, session: zenoh.Session, keys: Keys, seed: int = 1) -> None:
        self.session, self.keys = session, keys
        self.rng = random.Random(seed)
        self.lock = threading.Lock()
        self.topics: set[str] = {keys.selection, keys.events, keys.inject("motor/2")}
        self.nodes: set[str] = set()
        self.hosts: set[str] = set()
        self.sent = 0
        self.oversized_sent = 0
        self._next_oversized = 0.0
        self._families = itertools.cycle(
            ["data", "ctx", "selection", "events", "state", "inject", *QUERIED]
        )
        self.sub = session.declare_subscriber(keys.everything, self._learn)

    def _learn(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        if "/data/" in key or "/ctx/" in key:
            with self.lock:
                self.topics.add(key)

    def discover(self) -> None:
        for reply in self.session.liveliness().get(self.keys.alive_all, timeout=0.5):
            if reply.ok is not None:
                parsed = self.keys.parse_alive(str(reply.ok.key_expr))
                if parsed:
                    self.nodes.add(parsed[1])
        for reply in self.session.liveliness().get(self.keys.host_alive_all, timeout=0.5):
            if reply.ok is not None:
                self.hosts.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])

    # ---- what it sends ------------------------------------------------------------------
    def junk(self) -> None:
        with self.lock:
            key = self.rng.choice(sorted(self.topics))
        family = key.removeprefix(self.keys.prefix + "/").split("/")[0]
        payloads = list(JUNK)
        if family in ("ctx", "selection", "inject"):  # over the limit (data's is 16 MiB: no)
            payloads.append(b"\x00" * (MAX_PAYLOAD[family] + 1))
        self.session.put(key, self.rng.choice(payloads))

    def forged_data(self) -> None:
        with self.lock:
            data = sorted(k for k in self.topics if "/data/" in k)
        if data:
            self.session.put(self.rng.choice(data), self.rng.choice(FORGED_DATA))

    def oversized(self) -> None:
        """A payload 1 KiB over its family's limit on the next family, every few seconds."""
        now = time.monotonic()
        if now < self._next_oversized:
            return
        self._next_oversized = now + OVERSIZED_EVERY
        family = next(self._families)
        payload = b"\x00" * (MAX_PAYLOAD[family] + 1024)
        with self.lock:
            data = sorted(k for k in self.topics if "/data/" in k) or [self.keys.data("x")]
        keys = {
            "data": self.rng.choice(data),
            "ctx": self.keys.ctx("Level"),
            "selection": self.keys.selection,
            "events": self.keys.events,
            "state": self.keys.state("resolution"),
            "inject": self.keys.inject("motor/2"),
            "node_ctl": self.keys.node_ctl(self.rng.choice(sorted(self.nodes) or ["sink"])),
            "host_ctl": self.keys.host_ctl(self.rng.choice(sorted(self.hosts) or ["local"])),
            "engine_ctl": self.keys.engine_ctl("resolution"),
        }
        if family in QUERIED:
            self.query(keys[family], payload)
        else:
            self.session.put(keys[family], payload)
        self.oversized_sent += 1

    def forged_selection(self) -> None:
        fence = self.rng.choice([None, m.Fence(epoch=10**9, leader="mallory")])
        features = self.rng.choice([["Teleport"], ["Direct", "Filtered"], []])
        msg = m.Selection(
            seq=self.rng.randrange(1, 10**6), stamp=time.time(), deployment=[],
            features=features, cv={"Gain": 1e6, "MaxVel": 1e6}, changed=True, fence=fence,
        )  # fmt: skip
        self.session.put(self.keys.selection, _SEL.encode(msg))

    def forged_override(self) -> None:
        """A plausible value of a measurement it has seen, marked as an operator's override
        but without the live monitor leader's fence."""
        with self.lock:
            ctx = sorted(k for k in self.topics if "/ctx/" in k)
        if not ctx:
            return
        key = self.rng.choice(ctx)
        fence = self.rng.choice([None, m.Fence(epoch=10**9, leader="monitor-a")])
        msg = m.Measurement(name=key.rsplit("/", 1)[-1], value=9.0, stamp=time.time(),
                            override="mallory", until=time.time() + 60, fence=fence)  # fmt: skip
        self.session.put(key, _CTX.encode(msg))

    def bad_override(self) -> None:
        """Override requests the monitor refuses: an unknown name, a duration out of range."""
        bad = {"t": "override_measurement", "name": "Level", "value": 9}
        request = self.rng.choice([
            _ANY.encode(m.OverrideMeasurement(name="NoSuchMeasurement", value=1, duration=5)),
            _ANY.encode({**bad, "duration": -1}),
            _ANY.encode({**bad, "duration": 1e9}),
        ])  # fmt: skip
        self.query(self.keys.engine_ctl("monitor"), request)

    def bad_params(self) -> None:
        if not self.nodes:
            return
        node = self.rng.choice(sorted(self.nodes))
        # Wrong types and unknown names: refused whatever the declared bounds.
        params = self.rng.choice(
            [{"rate_hz": "fast"}, {"offset": "x"}, {"no_such_parameter": 1}, {"value": [1e6]}]
        )
        self.query(self.keys.node_ctl(node), _ANY.encode(m.SetParams(params=params)))

    def bad_host_requests(self) -> None:
        if not self.hosts:
            return
        host = self.rng.choice(sorted(self.hosts))
        node = self.rng.choice(sorted(self.nodes) or ["sink"])
        cmd = Command(
            command=[sys.executable, "-m", "rra_agent.engines.resolution"],
            env={"PYTHONWARNINGS": "ignore::0:os.system('id'):0", "BROWSER": "sh -c id"},
        )
        spec = m.NodeSpec(system=self.keys.system, name=node, host=host, implementation=cmd)
        request = self.rng.choice([
            m.StartNode(spec=spec),
            m.StartNode(spec=msgspec.structs.replace(spec, name="../../../../tmp/mallory")),
            m.StartNode(spec=msgspec.structs.replace(spec, name="mallory")),
            m.UpdateSpec(specs=[spec]),
        ])  # fmt: skip
        self.query(self.keys.host_ctl(host), _ANY.encode(request))

    def bad_queries(self) -> None:
        targets = [self.keys.node_ctl(n) for n in self.nodes]
        targets += [self.keys.host_ctl(h) for h in self.hosts]
        targets += [self.keys.engine_ctl(e) for e in ("resolution", "adaptation", "monitor")]
        self.query(self.rng.choice(targets), self.rng.choice(JUNK))

    def query(self, key: str, payload: bytes) -> None:
        self.session.get(
            key, zenoh.handlers.Callback(lambda _r: None), payload=payload, timeout=1.0
        )

    def run(self, rate: float, seconds: float | None, stop: threading.Event) -> None:
        actions = itertools.cycle(
            [
                self.junk,
                self.forged_selection,
                self.forged_data,
                self.junk,
                self.bad_params,
                self.bad_queries,
                self.forged_data,
                self.bad_host_requests,
                self.oversized,
                self.forged_override,
                self.bad_override,
            ]
        )
        t0 = time.monotonic()
        next_discovery = t0
        while not stop.is_set() and (seconds is None or time.monotonic() - t0 < seconds):
            if time.monotonic() >= next_discovery:
                self.discover()
                next_discovery = time.monotonic() + 1.0
            next(actions)()
            self.sent += 1
            stop.wait(max(0.0, t0 + self.sent / rate - time.monotonic()))  # pacing


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("endpoint")
    ap.add_argument("system")
    ap.add_argument("--rate", type=float, default=200.0, help="messages per second")
    ap.add_argument("--seconds", type=float, help="stop after this long (default: Ctrl-C)")
    args = ap.parse_args(argv)
    session = open_session(BusConfig(connect=[args.endpoint], multicast=False, lease_ms=500))
    hostile = Hostile(session, Keys(args.system))
    stop = threading.Event()
    try:
        hostile.run(args.rate, args.seconds, stop)
    except KeyboardInterrupt:
        pass
    finally:
        print(f"hostile: sent {hostile.sent} ({hostile.oversized_sent} oversized)", flush=True)
        hostile.sub.undeclare()
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
