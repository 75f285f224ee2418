"""Who leads *another* engine role: whose selections, states and events an engine trusts.

An engine acts on what the leader of another role publishes: the Run-time Resolution Engine
on the Adaptation Engine leader's selections, the Adaptation Engine and the Context Monitor
on the Resolution Engine leader's state (what is in effect, what is unavailable). A
`LeaderWatch` follows that role's member and claim liveliness tokens (as its own replicas'
election does, `rra_agent.engines.election`) and says whether a fence is the term of a live
leader. Callbacks run on Zenoh's thread; `is_leader` may be asked from any thread.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import Any

import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.core.election import Term, parse_claim


class LeaderWatch:
    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        role: str,
        on_change: Callable[[], None] | None = None,
    ) -> None:
        self.role = role
        self.on_change = on_change
        self._lock = threading.Lock()
        #: Live claims ((replica, instance) -> epoch) and live members (names) of the role.
        self.claims: dict[tuple[str, str], int] = {}
        self.members: set[str] = set()
        lv = session.liveliness()
        self._entities: list[Any] = [
            lv.declare_subscriber(f"{keys.lead(role)}/**", self._on_claim, history=True),
            lv.declare_subscriber(keys.member(role, "*"), self._on_member, history=True),
        ]

    def undeclare(self) -> None:
        """Stop following (as a Zenoh entity is undeclared: it may sit in an entity list)."""
        for entity in self._entities:
            with contextlib.suppress(Exception):
                entity.undeclare()
        self._entities = []

    def is_leader(self, fence: m.Fence | Term | None) -> bool:
        """The term of a live claim of the role, or of a live member claiming above every
        claim seen (its claim token may still be on its way)."""
        if fence is None:
            return False
        epoch, leader, instance = fence.term if isinstance(fence, m.Fence) else fence
        with self._lock:
            if self.claims.get((leader, instance)) == epoch:
                return True
            newest = max(self.claims.values(), default=0)
            return leader in self.members and epoch > newest

    def holds(self, fence: m.Fence | None) -> bool:
        """Strictly: the term of a live claim of the role (a claim on its way is not yet;
        for what only a settled leader sends, e.g. an operator's override)."""
        if fence is None:
            return False
        with self._lock:
            return self.claims.get((fence.leader, fence.instance)) == fence.epoch

    def _on_claim(self, sample: zenoh.Sample) -> None:
        term = parse_claim(str(sample.key_expr).split("/")[-3:])
        if term is None:
            return
        epoch, who = term[0], term[1:]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.claims[who] = epoch
            elif self.claims.get(who) == epoch:
                del self.claims[who]
        self._changed()

    def _on_member(self, sample: zenoh.Sample) -> None:
        replica = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self.members.add(replica)
            else:
                self.members.discard(replica)
        self._changed()

    def _changed(self) -> None:
        if self.on_change is not None:
            self.on_change()
