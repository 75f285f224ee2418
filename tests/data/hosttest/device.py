"""A node that holds a device, as a driver does: what a swap must not start twice at once."""

from __future__ import annotations

import fcntl
import os
import time

from rra_agent.node import Node, NodeContext


class Holder(Node):
    """Takes the exclusive lock of the file ``device`` in its constructor (its code fails if
    another process holds it; the kernel releases it as the process ends) and writes what it
    does, with the time (CLOCK_MONOTONIC, one clock for every process of the machine), to the
    file ``witness``. Its ``on_stop`` takes ``stop_seconds``."""

    def __init__(self, ctx: NodeContext) -> None:
        super().__init__(ctx)
        self._note("constructed")
        self.device = os.open(str(ctx.param("device")), os.O_RDWR)
        fcntl.flock(self.device, fcntl.LOCK_EX | fcntl.LOCK_NB)  # BlockingIOError: held
        self._note("holds the device")

    @classmethod
    def rehearse(cls) -> None:
        """Notes ``rehearsal <pid>`` in the file ``$HOSTTEST_WITNESS`` (it has no spec yet)."""
        path = os.environ.get("HOSTTEST_WITNESS")
        if path:
            with open(path, "a") as f:
                f.write(f"{time.monotonic():.6f} rehearsal {os.getpid()}\n")

    def export_state(self) -> dict[str, str]:
        """Its state for a replacement (``export_fails``: it cannot give it)."""
        if self.ctx.param("export_fails", False):
            raise RuntimeError("the device is mid-transfer")
        self._note("exported")
        return {"from": self.ctx.name}

    def import_state(self, state: dict[str, str]) -> None:
        self._note(f"imported {state['from']}")

    def on_stop(self) -> None:
        time.sleep(float(self.ctx.param("stop_seconds", 0.0)))
        self._note("stopped")

    def _note(self, what: str) -> None:
        with open(str(self.ctx.param("witness")), "a") as f:
            f.write(f"{time.monotonic():.6f} {self.ctx.name} {what}\n")
