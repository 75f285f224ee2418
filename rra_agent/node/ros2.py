"""A ROS 2 executable as a component (``ros2: PACKAGE EXECUTABLE``, or a command of a
component with a ``ros2:`` section): the host agent runs this node (`run_ros2_executable`),
which starts the executable with ``--ros-args`` (its node name, a remapping per port, its
parameters; ``RMW_IMPLEMENTATION=rmw_zenoh_cpp``, the ROS domain, the host router's
endpoint, and on a bus with certificates ``ZENOH_SESSION_CONFIG_URI``, the session
configuration its host agent wrote for it), waits for its ROS 2 node (its liveliness token,
and its parameter and lifecycle services) and speaks for it on the bus: the engines see a
node like any other and its control requests become ROS 2 calls:

- ``SetParams``: ``set_parameters``; what the node refuses is not set, and the reply says
  why; ``Describe`` reads the values back with ``get_parameters``;
- ``Activate`` / ``Deactivate``: ``change_state`` (activate, deactivate) of a managed
  (lifecycle) node, configured at start and activated if the spec says so; a node that is
  not managed is always active;
- ``Rewire`` of a subscriber port: with ``rewire: relay`` (the default) the port is
  remapped at start to a topic of its own (``/_rra/<node>/<port>``) that a relay here
  feeds from the publishers it is wired to, and a rewire switches the relay (make before
  break); with ``rewire: restart`` the port is remapped to its publisher's topic and a
  rewire restarts the executable with the new ``-r`` remapping, its parameters and its
  lifecycle state, and answers once the node is back (within 1.5 s, else an error and the
  plan's unit is undone);
- every ROS 2 call has the component's deadline (``ros2: {timeout}``, 1 s): a service that
  does not answer is an error reply saying which service of which node
  (``ros2_timeout``), one that answers with an error or not at all ``ros2_failed``; the
  executor fails the action's unit with that message, nothing waits longer.

The executable's exit ends this node with a failure report (its status), so its host agent
restarts it like any node. It is this process's child, in a process group of its own
(``ros2 run`` starts the node as its own child: the group is stopped whole), killed with
this process (``PR_SET_PDEATHSIG``).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import zenoh

from rra_agent.bus import failure
from rra_agent.bus import messages as m
from rra_agent.bus.config import BusConfig
from rra_agent.node.api import Node, NodeError
from rra_agent.node.core import NodeCore
from rra_agent.node.ros2mirror import Ros2Side, ros2_token, ros2_topic
from rra_agent.node.runtime import NodeRuntime
from rra_agent.ros2 import launch
from rra_agent.ros2.errors import NoServer, Ros2Error, ServiceFailed, ServiceTimeout
from rra_agent.ros2.names import mangle
from rra_agent.ros2.params import LifecycleClient, ParameterClient
from rra_agent.ros2.relay import Relay
from rra_agent.ros2.tokens import ADMIN_SPACE

#: How long a restart for a rewire may take until the node is back (the engine's request
#: waits 2 s for the reply).
RESTART_DEADLINE = 1.5
#: How long a ``Describe`` waits for ``get_parameters`` (then it shows the values it set).
READBACK_TIMEOUT = 0.5
#: How long a started node's first call is tried again while it reaches no server, s.
FIRST_CALL_GRACE = 1.0
#: Grace of a stopping executable after SIGINT, then SIGKILL (its whole process group).
STOP_GRACE = 1.5

# ---- a ROS 2 executable -------------------------------------------------------------------
class NotApplied(NodeError):
    """The node refused some of the parameters: ``applied`` were set."""

    def __init__(self, message: str, applied: dict[str, Any]) -> None:
        super().__init__(message)
        self.applied = applied


def resolve_run(impl: m.Implementation) -> tuple[launch.Ros2Run, dict[str, str], str | None]:
    """What to start for an implementation: (the run, its own environment, its folder).
    ``ros2: PACKAGE EXECUTABLE`` is the executable in ``<prefix>/lib/<package>/`` of the
    first ``AMENT_PREFIX_PATH`` prefix that has it (what ``ros2 run`` runs, without ``ros2
    run`` between: its child would outlive a kill of this process), else ``ros2 run``."""
    if isinstance(impl, str):
        run = launch.parse_implementation(impl)
        if run is None:
            raise NodeError(f"{impl!r} is not a ROS 2 executable ('ros2: PACKAGE EXECUTABLE')")
        for prefix in filter(None, os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep)):
            path = Path(prefix) / "lib" / str(run.package) / str(run.executable)
            if path.is_file() and os.access(path, os.X_OK):
                return launch.Ros2Run(argv=(str(path),)), {}, None
        return run, {}, None
    return launch.Ros2Run(argv=tuple(impl.command)), dict(impl.env), impl.cwd


def _child_setup() -> None:
    """In the executable's process, before its exec: a process group of its own, and
    SIGKILL when this node dies."""
    with contextlib.suppress(Exception):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    os.setpgid(0, 0)


class Executable:
    """One ROS 2 executable, its node, and the calls made to it (see the module doc)."""

    def __init__(
        self,
        spec: m.NodeSpec,
        side: Ros2Side,
        router: str,
        on_exit: Callable[[int], None],
        log: Callable[[str], None],
    ) -> None:
        assert spec.ros2 is not None
        self.spec = spec
        self.ros = ros = spec.ros2
        self.run, self.env, cwd = resolve_run(spec.implementation)
        #: Where it runs: the package folder (its command's ``cwd`` is relative to it).
        self.cwd = str(Path(ros.folder or ".") / cwd) if cwd else ros.folder
        #: rra-agent's interpreter, for stand-ins written in Python (the example's).
        self.env.setdefault("RRA_PYTHON", sys.executable)
        self.target = ros.namespace.rstrip("/") + "/" + ros.node
        self.side = side
        self.router = router
        self.on_exit = on_exit
        self.log = log
        self.params = ParameterClient(side.node, self.target)
        self.lifecycle = LifecycleClient(side.node, self.target) if ros.lifecycle else None
        #: lifecycle state as this node made it (a node that is not managed: active)
        self.state = "unconfigured" if ros.lifecycle else "active"
        self.outputs: dict[str, str] = {}
        self.inputs: dict[str, tuple[str, ...]] = {}
        self.relays: dict[str, Relay] = {}
        self.proc: subprocess.Popen[bytes] | None = None
        #: The executable's exit status when it ended on its own.
        self.exited: int | None = None
        self.restarts = 0
        #: The parameters a restart starts it with (the runtime's: the node's current ones).
        self.current_params: Callable[[], Mapping[str, Any]] = lambda: {}
        self._lock = threading.Lock()
        self._stopping = False
        self._cancel = threading.Event()
        self._seen = threading.Condition()
        self._alive: set[str] = set()
        pattern = f"{ADMIN_SPACE}/{ros.domain}/*/*/*/NN/*/{mangle(ros.namespace)}/{ros.node}"
        self._tokens = side.ctx.session.liveliness().declare_subscriber(
            pattern, self._on_token, history=True
        )

    # -- wiring (recorded before the start; live afterwards) -------------------------------
    def relay_topic(self, port: str) -> str:
        ns = "" if self.ros.namespace == "/" else self.ros.namespace
        return f"/_rra{ns}/{self.ros.node}/{ros2_token(port)}"

    def remaps(self) -> dict[str, str]:
        out = dict(self.outputs)
        for port, topics in self.inputs.items():
            relayed = self.ros.rewire == "relay" or not topics
            out[port] = self.relay_topic(port) if relayed else topics[0]
        return out

    def wire(self, port: str, direction: str, topics: list[str]) -> None:
        """Port ``port`` now publishes on (is fed from) ``topics``."""
        if direction == "publish":
            if len(topics) != 1:
                raise NodeError(f"output port {port!r} publishes on exactly one topic")
            changed = self.outputs.get(port) != topics[0]
            self.outputs[port] = topics[0]
            if changed and self.proc is not None:
                self.restart(f"output {port} moved to {topics[0]}")
            return
        wanted = tuple(topics)
        if self.ros.rewire == "restart" and len(wanted) > 1:
            raise NodeError(
                f"port {port} of ROS 2 node {self.target} is rewired by restart: one publisher "
                f"at a time, not {len(wanted)} (use `rewire: relay`)"
            )
        old, self.inputs[port] = self.inputs.get(port), wanted
        if self.ros.rewire == "relay":
            relay = self.relays.get(port)
            if relay is not None:
                relay.switch(wanted)
        elif self.proc is not None and old != wanted:
            self.restart(f"input {port} rewired to {', '.join(wanted) or 'nothing'}")

    # -- the process ----------------------------------------------------------------------
    def start(self, params: Mapping[str, Any], active: bool, timeout: float) -> None:
        """Relays, the executable, its node; configured (and activated) if managed."""
        if self.ros.rewire == "relay":
            for port, topics in self.inputs.items():
                self.relays[port] = Relay(
                    self.side.node, self.relay_topic(port), self.ros.ports[port], topics
                )
        self._spawn(params)
        self._wait_ready(timeout)
        self._bring_up(active, FIRST_CALL_GRACE)

    def _bring_up(self, active: bool, grace: float = 0.0) -> None:
        if self.lifecycle is None:
            if not active:
                self.log(f"ROS 2 node {self.target} is not managed: it runs active")
            return
        self._first_call(lambda: self.change("configure"), grace)
        if active:
            self.change("activate")

    def _first_call(self, call: Callable[[], None], grace: float) -> None:
        """The first call to a node that has just come up: its services were seen, but a
        call may reach no server for a moment yet (routing catching up; seen under load):
        tried again until ``grace`` s have passed, then the error stands."""
        deadline = time.monotonic() + grace
        while True:
            try:
                return call()
            except NoServer:
                if time.monotonic() >= deadline or self._cancel.wait(0.05):
                    raise

    def _spawn(self, params: Mapping[str, Any]) -> None:
        argv, env = launch.command(
            self.run,
            node=self.ros.node,
            namespace=self.ros.namespace,
            remaps=self.remaps(),
            params={k: v for k, v in params.items() if v is not None},
            domain=self.ros.domain,
            router=self.router,
            session_config=os.environ.get(launch.SESSION_CONFIG_ENV) or None,
        )
        self.state = "unconfigured" if self.lifecycle is not None else "active"
        self.exited = None
        with self._seen:
            self._alive.clear()  # a token of an earlier process is not this one's
        try:
            proc = subprocess.Popen(
                argv,
                env={**os.environ, **self.env, **env},
                cwd=self.cwd,
                stdin=subprocess.DEVNULL,
                preexec_fn=_child_setup,
            )
        except OSError as e:
            raise NodeError(f"cannot start ROS 2 executable {argv[0]}: {e}") from None
        with self._lock:
            self.proc = proc
        self.log(f"started ROS 2 executable (pid {proc.pid}): {' '.join(argv)}")
        threading.Thread(target=self._watch, args=(proc,), daemon=True).start()

    def _watch(self, proc: subprocess.Popen[bytes]) -> None:
        code = proc.wait()
        with self._seen:
            self._seen.notify_all()
        with self._lock:
            if proc is not self.proc or self._stopping:
                return
            self.exited = code
        self.on_exit(code)

    def _on_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with self._seen:
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(key)
            else:
                self._alive.discard(key)
            self._seen.notify_all()

    def _ready(self) -> bool:
        if not self._alive:
            return False
        if self.lifecycle is not None and not self.lifecycle.available():
            return False
        return not self.spec.params or self.params.available()

    def _wait_ready(self, timeout: float) -> None:
        """Until the node's token and its services are here; `NodeError` if the executable
        exits first or the deadline passes."""
        deadline = time.monotonic() + timeout
        proc = self.proc
        assert proc is not None
        with self._seen:
            while not self._ready():
                code = proc.poll()
                if code is not None:
                    raise NodeError(f"ROS 2 executable {self.run.base[0]} exited with status "
                                    f"{code} before its node {self.target} was ready")
                left = deadline - time.monotonic()
                if left <= 0 or self._cancel.is_set():
                    what = "node" if not self._alive else "parameter and lifecycle services"
                    raise NodeError(f"ROS 2 node {self.target}: its {what} did not appear "
                                    f"within {timeout:g} s")
                self._seen.wait(min(left, 0.02))  # services: polled (no event for them)

    def restart(self, why: str) -> None:
        """Stop the executable and start it again (its remappings changed), with the
        parameters and lifecycle state it had; until its node is back."""
        active = self.state == "active"
        self._terminate()
        self.restarts += 1
        self.log(f"restarting ROS 2 node {self.target}: {why}")
        params = self.current_params()
        self._spawn(params)
        self._wait_ready(RESTART_DEADLINE)
        self._bring_up(active)

    def _terminate(self) -> None:
        with self._lock:
            proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGINT)
        try:
            proc.wait(STOP_GRACE)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)  # what it left behind in its group

    def cancel(self) -> None:
        """Stop waiting for the node (this process is asked to stop)."""
        self._cancel.set()

    def stop(self) -> None:
        self._stopping = True
        self._cancel.set()
        self._terminate()

    def close(self) -> None:
        self.stop()
        for relay in self.relays.values():
            relay.close()
        self._tokens.undeclare()

    # -- calls ----------------------------------------------------------------------------
    def change(self, transition: str) -> None:
        """A lifecycle transition; `ServiceFailed` if the node refuses it."""
        assert self.lifecycle is not None
        try:
            ok = self.lifecycle.change(transition, self.ros.timeout, current=self.state)
        except Ros2Error as e:
            raise type(e)(f"ROS 2 node {self.target}: {transition}: {e}") from None
        if not ok:
            raise ServiceFailed(
                f"ROS 2 node {self.target} refused the lifecycle transition {transition} "
                f"(it was {self.state})"
            )
        self.state = {"configure": "inactive", "activate": "active", "deactivate": "inactive",
                      "cleanup": "unconfigured", "shutdown": "finalized"}[transition]

    def activate(self, active: bool) -> None:
        if self.lifecycle is None:
            if not active:
                raise NodeError(
                    f"ROS 2 node {self.target} is not managed (no lifecycle): it cannot be "
                    "deactivated; give its component `ros2: {lifecycle: true}`"
                )
            return
        if (self.state == "active") != active:
            self.change("activate" if active else "deactivate")

    def set_params(self, values: Mapping[str, Any]) -> None:
        """Set parameters through ``set_parameters``; `NotApplied` naming what the node
        refused (with what it set)."""
        try:
            result = self.params.set(dict(values), self.ros.timeout)
        except Ros2Error as e:
            raise type(e)(f"ROS 2 node {self.target}: {e}") from None
        refused = {n: why for n, why in result.items() if why is not None}
        if refused:
            applied = {n: v for n, v in values.items() if result.get(n) is None}
            reasons = "; ".join(f"{n} = {values[n]!r}: {why}" for n, why in refused.items())
            raise NotApplied(f"ROS 2 node {self.target} refused {reasons}", applied)

    def read_params(self, names: list[str]) -> dict[str, Any]:
        """The values the node reports (best effort: {} when it does not answer in time)."""
        if not names or self.proc is None:
            return {}
        try:
            got = self.params.get(names, READBACK_TIMEOUT)
        except Ros2Error:
            return {}
        return {n: v for n, v in got.items() if v is not None}


class Ros2Transport:
    """`rra_agent.node.core.Transport` of a ROS 2 executable: ports are its remappings."""

    def __init__(self, exe: Executable) -> None:
        self.exe = exe
        self.core: NodeCore | None = None

    def publish(self, port: str, payload: bytes, stamp: float) -> None:
        raise NodeError("a ROS 2 executable publishes by itself")

    def rebind(
        self, port: str, direction: str, keys: list[str], standby: list[str] | None = None
    ) -> None:
        self.exe.wire(port, direction, [ros2_topic(k) for k in keys])

    def subscribe(self, key_expr: str, callback: Any) -> None:
        raise NodeError("a ROS 2 executable has no raw subscriptions")

    def start_delivery(self, core: NodeCore) -> None:
        """Nothing is delivered through here: the executable takes its topics itself."""
        self.core = core


class _Speaker(Node):
    """What the node core runs for a ROS 2 executable: its hooks call `Executable`."""

    exe: Executable
    start_timeout: float = 10.0

    def on_start(self) -> None:
        self.exe.start(self.ctx.params, self.ctx.active, self.start_timeout)

    def on_params(self, changed: dict[str, Any]) -> None:
        self.exe.set_params(changed)

    def on_stop(self) -> None:
        self.exe.stop()


class Ros2Core(NodeCore):
    """A node core whose parameters, activation and description are the ROS 2 node's:
    a change is made on the ROS 2 node first, and only what it took is recorded."""

    exe: Executable

    def handle(self, request: m.NodeRequest) -> m.Reply:
        with self.lock:
            try:
                return self._handle(request)
            except NodeError as e:
                return m.Err(message=str(e), code="refused")
            except ServiceTimeout as e:
                self.counters.bump("ros2_timeouts")
                self.log(str(e))
                return m.Err(message=str(e), code="ros2_timeout")
            except Ros2Error as e:
                self.counters.bump("ros2_failures")
                self.log(str(e))
                return m.Err(message=str(e), code="ros2_failed")
            except self._catch as e:
                f = self._error(str(request.__struct_config__.tag), e)
                return m.Err(message=f"{type(e).__name__}: {e}", code="node_error", failure=f)

    def _set_params(self, params: dict[str, Any]) -> None:
        before = dict(self.params)
        try:
            super()._set_params(params)
        except NotApplied as e:
            self.params = {**before, **e.applied}
            raise
        except Ros2Error:
            self.params = before
            raise

    def _set_active(self, active: bool) -> None:
        if active != self.active:
            self.exe.activate(active)
            self.active = active

    def describe(self) -> m.NodeInfo:
        self.params.update(self.exe.read_params(sorted(self.params)))
        return super().describe()

    def stats(self) -> m.ProcessStats:
        self.counters.extra["ros2_restarts"] = self.exe.restarts
        return super().stats()


class Ros2ExecutableRuntime(NodeRuntime):
    """The process of a ROS 2 executable's component (see the module doc)."""

    def __init__(self, spec: m.NodeSpec, bus: BusConfig) -> None:
        super().__init__(spec, _Speaker, bus)
        self.side: Ros2Side | None = None
        self.exe: Executable | None = None

    def _on_signal(self, signum: int, frame: Any) -> None:
        super()._on_signal(signum, frame)
        if self.exe is not None:
            self.exe.cancel()

    def _child_exited(self, code: int) -> None:
        core = self.core
        if core is not None:
            core.stop_requested.set()
        self.wake()

    def make_transport(self, session: zenoh.Session) -> Any:
        ros = self.spec.ros2
        assert ros is not None
        ns = "/rra" + ("" if ros.namespace == "/" else ros.namespace)
        self.side = Ros2Side(session, ros, ros.node, ns)
        log = lambda s: print(f"[{self.spec.name}] {s}", file=sys.stderr, flush=True)  # noqa: E731
        if not self.bus.hub.startswith("tcp/") and not os.environ.get(launch.SESSION_CONFIG_ENV):
            log(f"warning: the ROS 2 executable connects to {self.bus.hub}: it needs that "
                f"transport's configuration ({launch.SESSION_CONFIG_ENV})")
        self.exe = Executable(self.spec, self.side, self.bus.hub, self._child_exited, log)
        return Ros2Transport(self.exe)

    def make_core(self, transport: Any) -> NodeCore:
        assert self.exe is not None
        node_cls = type("Ros2Executable", (_Speaker,), {
            "exe": self.exe,
            "start_timeout": max(1.0, self.spec.supervision.start_timeout - 1.0),
        })
        core = Ros2Core(
            self.spec,
            node_cls,
            transport,
            logger=lambda s: print(s, file=sys.stderr, flush=True),
            pid=os.getpid(),
            max_data=self.bus.max_data_bytes,
        )
        core.exe = self.exe
        self.exe.current_params = lambda: dict(core.params)
        if self.exe.lifecycle is None:
            core.active = True  # what it is: a node that is not managed always runs
        return core

    def release(self) -> None:
        if self.exe is not None:
            self.exe.close()
        if self.side is not None:
            self.side.close()

    def run(self) -> int:
        code = super().run()
        exe = self.exe
        if exe is not None and exe.exited is not None:
            f = m.Failure(
                message=f"ROS 2 executable {exe.run.base[0]} (node {exe.target}) exited "
                f"with status {exe.exited}",
                during="run",
                stamp=time.time(),
            )
            print(f"rra node {self.spec.name}: {f.message}", file=sys.stderr, flush=True)
            failure.write_report(f)
            return 1
        return code


def run_ros2_executable(spec: m.NodeSpec, bus: BusConfig) -> int:
    """Run the node of a ROS 2 executable's component until it is told to stop, or the
    executable ends (exit status 1, with a failure report)."""
    return Ros2ExecutableRuntime(spec, bus).run()
