"""The election's decisions (`rra_agent.engines.election.Election`) on a liveliness view and a
clock the test sets: the races of a takeover, played in the order that loses them. (The
same elections on real Zenoh sessions and processes: tests/test_one_system.py,
tests/test_failures.py.)"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from rra_agent.bus.keys import Keys
from rra_agent.bus.loop import MainLoop
from rra_agent.engines.election import Election

K = Keys("sys")


@dataclass
class Clock:
    now: float = 100.0

    def __call__(self) -> float:
        return self.now


@dataclass
class Reply:
    ok: Any


@dataclass
class Sample:
    key_expr: str


@dataclass
class Entity:
    def undeclare(self) -> None:
        pass


@dataclass
class Liveliness:
    """The tokens a replica's session sees (a `get` answers them; nothing is pushed)."""

    tokens: set[str] = field(default_factory=set)
    declared: list[str] = field(default_factory=list)

    def declare_token(self, key: str) -> Entity:
        self.declared.append(key)
        return Entity()

    def declare_subscriber(self, key: str, cb: Callable[..., None], history: bool) -> Entity:
        return Entity()

    def get(self, key: str, timeout: float) -> list[Reply]:
        prefix = key.removesuffix("**").removesuffix("*")
        return [Reply(Sample(t)) for t in sorted(self.tokens) if t.startswith(prefix)]


@dataclass
class Session:
    instance: str
    view: Liveliness

    def zid(self) -> str:
        return self.instance

    def liveliness(self) -> Liveliness:
        return self.view


def replica(name: str, instance: str, tokens: set[str], clock: Clock, epoch: int = 0) -> Election:
    election = Election(Session(instance, Liveliness(tokens)), K, "resolution", name,  # type: ignore[arg-type]
                        MainLoop(), lambda: None, tick_period=0.1, clock=clock)  # fmt: skip
    election.max_epoch = epoch  # `EngineProcess.epoch_floor`: the saved state's
    return election


def member(name: str) -> str:
    return K.member("resolution", name)


def claim(epoch: int, name: str, instance: str) -> str:
    return f"{K.lead('resolution')}/{epoch:010d}/{name}/{instance}"


def test_a_replica_restarted_at_once_leaves_the_lead_to_the_standby() -> None:
    """The leader resolution-a is killed and its fork server starts it again within
    milliseconds. The standby resolution-b saw the claim go but, its ticks late, not
    a's member token go (it came back at once): a is still first by name, so b waits
    `claim_after` for a claim. The restarted a, first by name, finds the role leaderless:
    it waited as long, and the first to tick took the lead (a new term of resolution-a,
    after a second without a leader, and the standby's hot mirror unused). Now the
    restarted one waits for the standby's claim."""
    clock = Clock()
    b = replica("resolution-b", "bb", {member("resolution-a"), member("resolution-b"),
                                       claim(1, "resolution-a", "a1")}, clock)  # fmt: skip
    b.start()
    assert not b.leading and b.leader == (1, "resolution-a", "a1")
    # a is killed: its claim goes (b's ticks came late: a's member token, back at once
    # with the restarted process, never went away in b's view).
    b._claim_seen(claim(1, "resolution-a", "a1"), False)
    b.decide()
    assert not b.leading  # a is first by name
    clock.now += 0.05  # the restarted a starts: the state it resumes from says epoch 1
    a = replica("resolution-a", "a2", {member("resolution-a"), member("resolution-b")},
                clock, epoch=1)  # fmt: skip
    a.start()
    assert not a.leading
    clock.now += b.claim_after  # both have waited `claim_after`; a ticks first
    a.tick()
    assert not a.leading, "the restarted replica took the lead from the standby"
    b.tick()
    assert b.leading and b.term is not None and b.term[:2] == (2, "resolution-b")
    a._claim_seen(claim(*b.term), True)
    clock.now += 2 * a.claim_after
    a.tick()
    assert not a.leading and a.leader == b.term


def test_a_replica_restarted_alone_takes_the_lead_after_claim_after() -> None:
    """No standby: a restarted replica waits `claim_after` (a claim may be on its way), then
    leads, above the epoch it resumed from."""
    clock = Clock()
    a = replica("resolution-a", "a2", {member("resolution-a")}, clock, epoch=4)
    a.start()
    assert not a.leading
    clock.now += a.claim_after
    a.tick()
    assert a.leading and a.term == (5, "resolution-a", "a2")


def test_a_restarted_replica_leads_when_the_standby_never_claims() -> None:
    """The standby is up but does not claim (frozen): the restarted replica leads once it
    has left it twice `claim_after`."""
    clock = Clock()
    a = replica("resolution-a", "a2", {member("resolution-a"), member("resolution-b")},
                clock, epoch=1)  # fmt: skip
    a.start()
    clock.now += 1.5 * a.claim_after
    a.tick()
    assert not a.leading
    clock.now += a.claim_after
    a.tick()
    assert a.leading and a.term is not None and a.term[0] == 2
