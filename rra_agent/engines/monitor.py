"""The Context Monitor process (paper Sec. III-C), configured from ``measurements.yaml``.

The paper generated a monitor per system by model-to-text transformation; this process
interprets the model instead: it subscribes to every source interface the measurements name
(the publisher's topic in the Deployment-time Configured System Model), feeds the samples to
`rra_agent.core.context.ContextMonitor`, and publishes each Context Dependent Measurement on
``rra/<system>/ctx/<name>`` with its computation time and the send times of its sources.
Malformed samples are dropped and counted.
"""

from __future__ import annotations

import importlib
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.bus.keys import Keys
from rra_agent.bus.loop import MainLoop
from rra_agent.bus.runtime import open_session
from rra_agent.core.context import ContextMonitor
from rra_agent.core.resolution import topic_of
from rra_agent.deployment import Deployment
from rra_agent.errors import RraError
from rra_agent.models.system import parse_endpoint
from rra_agent.node import decode_data
from rra_agent.viz.rerun_log import Logger, open_logger

NAME = "monitor"
_CTX = m.Codec[m.CtxMessage](m.CtxMessage)


def import_dotted(dotted: str) -> Any:
    """``pkg.module.attr`` -> the object (the longest importable module prefix is used)."""
    parts = dotted.split(".")
    for i in range(len(parts) - 1, 0, -1):
        try:
            obj: Any = importlib.import_module(".".join(parts[:i]))
        except ModuleNotFoundError:
            continue
        for attr in parts[i:]:
            obj = getattr(obj, attr)
        return obj
    raise RraError(f"cannot import {dotted!r}")


def measurement_functions(dep: Deployment) -> dict[str, Callable[..., Any]]:
    """Measurement name -> its function: a function of the source data type, or a dotted path.

    The package folder is put on ``sys.path`` so a package may ship its own functions.
    """
    pkg = dep.package
    if str(pkg.root) not in sys.path:
        sys.path.insert(0, str(pkg.root))
    out = {}
    for meas in pkg.measurements.measurements:
        if meas.function is None:
            continue
        dotted = meas.function
        if "." not in dotted:
            for src in meas.inputs:
                ep = parse_endpoint(src)
                comp = pkg.system.component(ep.component)
                port = comp.port(ep.port) if comp else None
                dt = pkg.measurements.data_type(port.type) if port else None
                if dt is not None and dotted in dt.functions:
                    dotted = dt.functions[dotted]
                    break
        fn = import_dotted(dotted)
        if not callable(fn):
            raise RraError(f"function {dotted!r} of measurement {meas.name} is not callable")
        out[meas.name] = fn
    return out


class MonitorProcess:
    def __init__(self, dep: Deployment, bus: BusConfig, *, host: str = "local", name: str = NAME):
        self.dep = dep
        self.bus = bus
        self.host = host
        self.name = name
        self.keys = Keys(dep.system)
        self.core = ContextMonitor(dep.package.measurements, measurement_functions(dep))
        self.loop = MainLoop()
        self.lock = threading.Lock()
        self.dropped = 0
        self.published = 0
        self.publishers: dict[str, zenoh.Publisher] = {}
        self.viz: Logger | None = None  # Rerun, when RRA_RERUN says so

    def source_key(self, source: str) -> str:
        ep = parse_endpoint(source)
        return self.keys.data(topic_of(self.dep.package.system, ep.component, ep.port))

    def _on_sample(self, source: str) -> Callable[[zenoh.Sample], None]:
        def callback(sample: zenoh.Sample) -> None:
            try:
                data = decode_data(sample.payload.to_bytes())
            except ValueError:
                with self.lock:
                    self.dropped += 1
                return
            att = sample.attachment
            stamp = m.unpack_stamp(att.to_bytes() if att else None) or time.time()
            with self.lock:
                computed = self.core.on_sample(source, data, stamp)
                for c in computed:
                    msg = m.Measurement(
                        name=c.name, value=c.value, stamp=time.time(), sources=c.sources
                    )
                    self.publishers[c.name].put(_CTX.encode(msg))
                    self.published += 1
                    if self.viz:
                        self.viz.measurement(c.name, c.value, msg.stamp)

        return callback

    def run(self, *, install_signals: bool = True) -> int:
        if install_signals:
            self.loop.install_signals()
        self.viz = open_logger(self.name)
        session = open_session(self.bus)
        try:
            for meas in self.dep.package.measurements.measurements:
                self.publishers[meas.name] = session.declare_publisher(
                    self.keys.ctx(meas.name),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                    express=True,
                )
            entities = [
                session.declare_subscriber(self.source_key(src), self._on_sample(src))
                for src in self.core.sources
            ]
            entities.append(
                session.liveliness().declare_token(self.keys.alive(self.host, self.name))
            )
            self.loop.run()
            del entities
            return 0
        finally:
            session.close()
            if self.viz:
                self.viz.close()


def main(argv: list[str] | None = None) -> int:
    """``python -m rra_agent.engines.monitor --package PKG --select F,...``."""
    from rra_agent.engines.launch import engine_arguments, engine_setup

    args = engine_arguments("rra monitor", __doc__).parse_args(argv)
    setup = engine_setup(args, NAME)
    if setup is None:
        return 2
    dep, bus, host, name = setup
    try:
        proc = MonitorProcess(dep, bus, host=host, name=name)
    except (RraError, ImportError, AttributeError, ValueError) as e:
        print(f"rra monitor: {e}", file=sys.stderr)
        return 2
    return proc.run()


if __name__ == "__main__":
    sys.exit(main())
