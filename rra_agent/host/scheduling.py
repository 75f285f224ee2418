"""Apply a component's `Scheduling` (policy, real-time priority, nice, CPU affinity) to a
process, and read back what the kernel actually gave it.

`apply` runs in the node process itself, before the node runs any of its code (the fork
server's child, or the ``preexec_fn`` of an exec'd one), so every thread the node later
starts (Zenoh's included) inherits it; `apply_to_process` also sets the threads already
there (a spare's session opened ahead). `differences` is the host agent's check once the
node is ready: what was asked for and not granted, one line each, for a warning event.
`hold_cpu_latency` is a host agent's request for its host's CPU wake-up latency.
"""

from __future__ import annotations

import os
import struct
import threading

from rra_agent.models.system import Scheduling

POLICIES = {
    "other": os.SCHED_OTHER,
    "batch": os.SCHED_BATCH,
    "idle": os.SCHED_IDLE,
    "fifo": os.SCHED_FIFO,
    "rr": os.SCHED_RR,
}
_NAMES = {v: k for k, v in POLICIES.items()}


def _label(s: Scheduling) -> str:
    return f"SCHED_{s.policy.upper()}" + (f" priority {s.priority}" if s.priority else "")


def apply(s: Scheduling, pid: int = 0, *, reset_on_fork: bool = False) -> list[str]:
    """Apply ``s`` to ``pid`` (0: the calling thread, whose future threads inherit it);
    what the kernel refused, one line each (empty: all applied).

    ``reset_on_fork`` (a host agent scheduling itself): the processes it starts begin as
    normal ones (SCHED_RESET_ON_FORK), and take their own scheduling from the model. A
    node without ``cpus`` may run on every CPU, whatever its host agent is pinned to."""
    problems: list[str] = []
    cpus = s.cpus or (list(range(os.cpu_count() or 1)) if not reset_on_fork else [])
    if cpus and (s.cpus or sorted(os.sched_getaffinity(pid)) != cpus):
        try:
            os.sched_setaffinity(pid, cpus)
        except OSError as e:
            if s.cpus:
                problems.append(f"CPU affinity {s.cpus} refused ({e.strerror})")
    if s.nice:
        try:
            os.setpriority(os.PRIO_PROCESS, pid, s.nice)
        except OSError as e:
            problems.append(f"nice {s.nice} refused ({e.strerror})")
    if s.policy != "other" or reset_on_fork:
        flag = os.SCHED_RESET_ON_FORK if reset_on_fork else 0
        try:
            os.sched_setscheduler(pid, POLICIES[s.policy] | flag, os.sched_param(s.priority))
        except OSError as e:
            problems.append(f"{_label(s)} refused ({e.strerror})")
    return problems


def apply_to_process(s: Scheduling) -> list[str]:
    """`apply` to every thread of this process, the calling one first (its refusals are
    returned): threads started before (a session opened ahead by a spare, whose Zenoh
    threads would otherwise run without it) as well as those started later, which inherit
    it from the thread that starts them."""
    problems = apply(s)
    if s.is_default:
        return problems
    me = threading.get_native_id()
    for tid in _threads():
        if tid != me:
            apply(s, tid)  # what the kernel refuses one thread it refused the first
    return problems


def _threads() -> list[int]:
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return []


def observed(pid: int) -> Scheduling:
    """What the kernel schedules ``pid`` (its main thread) with."""
    policy = _NAMES.get(os.sched_getscheduler(pid) & ~getattr(os, "SCHED_RESET_ON_FORK", 0))
    priority = os.sched_getparam(pid).sched_priority
    cpus = sorted(os.sched_getaffinity(pid))
    return Scheduling(
        policy=policy or "other",  # type: ignore[arg-type]
        priority=priority if policy in ("fifo", "rr") else 0,
        nice=os.getpriority(os.PRIO_PROCESS, pid),
        cpus=cpus,
    )


def differences(wanted: Scheduling, pid: int) -> list[str]:
    """What ``pid`` was asked to run with and does not (empty: as wanted)."""
    try:
        got = observed(pid)
    except OSError:
        return []  # gone already: its exit is reported on its own
    out = []
    if (wanted.policy, wanted.priority) != (got.policy, got.priority):
        out.append(f"asked for {_label(wanted)}, runs with {_label(got)}")
    if wanted.nice != got.nice:
        out.append(f"asked for nice {wanted.nice}, runs with {got.nice}")
    if wanted.cpus and sorted(wanted.cpus) != got.cpus:
        out.append(f"asked for CPUs {wanted.cpus}, runs on {got.cpus}")
    return out


#: Linux's CPU latency PM QoS: a request holds while the file it was written to stays open.
CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"
#: The descriptors of this process's requests (closed by the kernel as the process ends).
_held: list[int] = []


def hold_cpu_latency(us: int, device: str = CPU_LATENCY_DEVICE) -> str | None:
    """Ask the kernel to keep every CPU's wake-up latency within ``us`` microseconds until
    this process ends (the request is the open file: the kernel drops it when its last
    descriptor closes, a kill -9 included; close-on-exec, so no process started from here
    keeps it). What was refused, one line; None once held."""
    fd = -1
    try:
        fd = os.open(device, os.O_WRONLY | os.O_CLOEXEC)
        os.write(fd, struct.pack("=i", us))
    except OSError as e:
        if fd >= 0:
            os.close(fd)
        return f"CPU latency {us} us refused ({device}: {e.strerror})"
    _held.append(fd)
    return None


def holds_cpu_latency() -> bool:
    """Whether this process holds a CPU latency request (`hold_cpu_latency`)."""
    return bool(_held)


def cpu_latency(device: str = CPU_LATENCY_DEVICE) -> int | None:
    """The CPU wake-up latency the kernel currently keeps (us, the strictest request; its
    default is 2000000000: none), or None where it cannot be read."""
    try:
        fd = os.open(device, os.O_RDONLY | os.O_CLOEXEC)
    except OSError:
        return None
    try:
        raw = os.read(fd, 4)
    finally:
        os.close(fd)
    return struct.unpack("=i", raw)[0] if len(raw) == 4 else None
