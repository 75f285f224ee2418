"""Leader election among the replicas of an engine, on Zenoh liveliness (the shell around
`rra_agent.core.election`).

Every replica declares ``rra/<system>/member/<role>/<replica>``; the leader also declares
``rra/<system>/lead/<role>/<epoch>/<replica>/<instance>``, where the instance is its
session's Zenoh id (so two processes of one replica name are two claims, see
`rra_agent.core.election`). Each replica follows both with liveliness subscribers and
decides on its main loop:

- no live claim and it is the first live member by name (or nobody has claimed for
  ``claim_after`` seconds): claim, with an epoch above every epoch seen; a replica that
  found itself stalled does not claim as the first member for ``claim_after``, and one that
  started into a role that has had a leader claims nothing for twice that while another
  member is up (a restarted replica leaves the lead to the standby);
- a live claim beats its own: step down (undeclare its claim);
- a receiver reports a newer epoch than its own (`observe_epoch`): step down and claim again
  above it.

A leader that dies (kill -9) loses its tokens when its link to the router closes, so the
next replica claims within milliseconds; a frozen one loses them at the transport lease
(`rra_agent.bus.config`: a silence shorter than the failure-detection budget, a stall of
the router included, loses nothing).
When the frozen one resumes, its session re-declares its old claim, which a newer epoch
beats: it steps down. The fence (`fence`) it put on its requests is refused by every
receiver that has seen its successor's.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from typing import Any

import zenoh

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.bus.loop import MainLoop
from rra_agent.core.election import Term, leader_of, next_epoch, parse_claim, should_claim


class Election:
    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        role: str,
        replica: str,
        loop: MainLoop,
        on_change: Callable[[], None],
        *,
        claim_after: float = 1.0,
        tick_period: float = 0.1,
        on_stall: Callable[[], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.session = session
        self.keys = keys
        self.role = role
        self.me = replica
        self.loop = loop
        self.on_change = on_change
        self.claim_after = claim_after
        self.clock = clock
        #: This process: its session's Zenoh id (a replica name may run twice on the bus).
        self.instance = str(session.zid())
        self.members: set[str] = set()
        #: Live claims: (replica, instance) -> epoch.
        self.claims: dict[tuple[str, str], int] = {}
        self.max_epoch = 0
        self.term: Term | None = None
        self._claim: Any = None
        self._entities: list[Any] = []
        self._leaderless_since: float | None = None
        self._defer_until = 0.0
        #: Started into a role that has had a leader: no claim of any kind before this.
        self._yield_until = 0.0
        #: A gap this long between ticks means this replica itself stalled (frozen,
        #: starved): its view of the tokens is being rebuilt, so it defers any claim.
        self._stall = max(0.5, 3 * tick_period)
        self._last_tick: float | None = None
        #: Called when this replica finds it has stalled (to re-sync what it mirrors).
        self.on_stall = on_stall
        self.changes = 0
        #: No decision before `start` has read the claims: a membership or claim change
        #: arriving while it waits must not make it claim on half a picture (a restarted
        #: replica took the lead back from the standby that had just replaced it).
        self._started = False

    # ---- queries -----------------------------------------------------------------------
    @property
    def leading(self) -> bool:
        return self.term is not None

    @property
    def fence(self) -> m.Fence | None:
        return None if self.term is None else m.Fence.of(self.term)

    @property
    def leader(self) -> Term | None:
        return leader_of((e, *who) for who, e in self.claims.items())

    @property
    def _mine(self) -> tuple[str, str]:
        return (self.me, self.instance)

    # ---- lifecycle ---------------------------------------------------------------------
    def start(self, timeout: float = 5.0) -> None:
        """Declare membership, learn who leads now, and decide once.

        The view of the others is only trusted once this replica's own membership has come
        back through the router (so the router has told it what it knows)."""
        lv = self.session.liveliness()
        self._entities = [
            lv.declare_token(self.keys.member(self.role, self.me)),
            lv.declare_subscriber(self.keys.member(self.role, "*"), self._on_member, history=True),
            lv.declare_subscriber(f"{self.keys.lead(self.role)}/**", self._on_claim, history=True),
        ]
        deadline = self.clock() + timeout
        while self.me not in self.members and self.clock() < deadline:
            for reply in lv.get(self.keys.member(self.role, "*"), timeout=1.0):
                if reply.ok is not None:
                    self.members.add(str(reply.ok.key_expr).rsplit("/", 1)[-1])
            if self.me not in self.members:
                self.loop.cycle(0.02)
        for reply in lv.get(f"{self.keys.lead(self.role)}/**", timeout=1.0):
            if reply.ok is not None:
                self._claim_seen(str(reply.ok.key_expr), True)
        if self.max_epoch > 0 and not self.claims:
            # The role has had a leader (an epoch is known) but no claim is visible: this
            # replica restarted while its predecessor's standby takes over (or the claim is
            # on its way). It leaves the lead to that standby, which claims at the latest
            # `claim_after` after it saw the role leaderless, even when this replica's
            # member token, first by name, came back first (a restart by the fork server
            # takes milliseconds): twice that before it claims itself (alone, once that).
            standby = bool(self.members - {self.me})
            self._yield_until = self.clock() + (2 if standby else 1) * self.claim_after
        self._started = True
        self.decide()

    def close(self) -> None:
        self._withdraw()
        for entity in self._entities:
            with contextlib.suppress(Exception):
                entity.undeclare()
        self._entities = []

    # ---- observations (Zenoh thread: post to the main loop) -----------------------------
    def _on_member(self, sample: zenoh.Sample) -> None:
        name = str(sample.key_expr).rsplit("/", 1)[-1]
        alive = sample.kind == zenoh.SampleKind.PUT

        def update() -> None:
            (self.members.add if alive else self.members.discard)(name)
            self.decide()

        self.loop.post(update)

    def _on_claim(self, sample: zenoh.Sample) -> None:
        key, alive = str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT

        def update() -> None:
            self._claim_seen(key, alive)
            self.decide()

        self.loop.post(update)

    def _claim_seen(self, key: str, alive: bool) -> None:
        term = parse_claim(key.removeprefix(self.keys.lead(self.role) + "/").split("/"))
        if term is None:
            return
        epoch, who = term[0], term[1:]
        self.max_epoch = max(self.max_epoch, epoch)
        if alive:
            self.claims[who] = max(epoch, self.claims.get(who, 0))
        elif self.claims.get(who) == epoch:
            del self.claims[who]

    def step_down(self) -> None:
        """A receiver refused this leader's request (another leader acted first): give up
        the claim and decide again, as after losing to a claim seen on the bus."""
        if self.term is None:
            return
        self._withdraw()
        self.decide()  # may claim again, above every epoch seen (and say so)
        if self.term is None:
            self.changes += 1
            self.on_change()

    def observe_epoch(self, epoch: int) -> None:
        """An epoch seen elsewhere (a receiver's reply, a published state): if it is newer
        than this leader's, this leader is out of date: it claims again above it."""
        self.max_epoch = max(self.max_epoch, epoch)
        if self.term is not None and epoch > self.term[0]:
            self._withdraw()
            self.decide()

    # ---- the decision (main thread) -----------------------------------------------------
    def _check_stall(self) -> None:
        now = self.clock()
        if self._last_tick is not None and now - self._last_tick > self._stall:
            self._defer_until = max(self._defer_until, now + self.claim_after)
            if self.on_stall is not None:
                self.on_stall()
        self._last_tick = now

    def decide(self) -> None:
        if not self._started:
            return
        self._check_stall()
        before = self.term
        others = {(e, *who) for who, e in self.claims.items() if who != self._mine}
        if self.term is not None:
            best = leader_of([*others, self.term])
            if best != self.term:
                self._withdraw()  # a newer claim beats ours
        if self.term is None:
            mine = self._mine
            claims = others | ({(self.claims[mine], *mine)} if mine in self.claims else set())
            if claims:
                self._leaderless_since = None
            elif self._leaderless_since is None:
                self._leaderless_since = self.clock()
            waited = self._leaderless_since is not None and (
                self.clock() - self._leaderless_since >= self.claim_after
            )
            stale_own = {t for t in claims if t[1:] == mine}  # ours, re-declared
            deferred = self.clock() < self._defer_until
            yielding = self.clock() < self._yield_until  # restarted: the standby first
            first = not deferred and should_claim(self.me, self.members, claims - stale_own)
            if not yielding and (first or (waited and not (claims - stale_own))):
                self._claim_lead()
        if self.term != before:
            self.changes += 1
            self.on_change()

    def tick(self) -> None:
        """Called periodically: claims a lead nobody else took within ``claim_after``."""
        self._check_stall()
        if self.term is None and not (set(self.claims) - {self._mine}):
            self.decide()

    def _claim_lead(self) -> None:
        epoch = next_epoch([self.max_epoch], self.claims.values())
        self.max_epoch = epoch
        self.term = (epoch, self.me, self.instance)
        self._claim = self.session.liveliness().declare_token(
            f"{self.keys.lead(self.role)}/{epoch:010d}/{self.me}/{self.instance}"
        )
        self.claims[self._mine] = epoch

    def _withdraw(self) -> None:
        if self._claim is not None:
            with contextlib.suppress(Exception):
                self._claim.undeclare()
            self._claim = None
        if self.term is not None and self.claims.get(self._mine) == self.term[0]:
            del self.claims[self._mine]
        self.term = None
