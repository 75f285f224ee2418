"""Leader election and fencing among the replicas of an engine, as pure functions.

Each engine role (monitor, adaptation, resolution) may run as several replicas: one leader
acts, the others follow hot and take over when it goes. The shell
(`rra_agent.engines.election`) feeds these functions with the Zenoh liveliness tokens it
sees: ``member/<role>/<replica>`` for every replica that is up, and
``lead/<role>/<epoch>/<replica>/<instance>`` for a replica that has claimed the lead.

- A replica is its name *and* its instance: the Zenoh session id of its process, new with
  every process. Two processes with one name (a second system started on the bus, the two
  sides of a partition, a restarted replica and its frozen predecessor) are two replicas,
  whose terms differ, so no receiver takes one for the other.
- The leader is the claim with the highest epoch; at equal epochs the smaller replica name
  wins, then the smaller instance (`leader_of`). A replica that sees a claim beating its
  own steps down.
- When no claim is alive, the first live member by name claims, with an epoch above every
  epoch seen so far (`should_claim`), so the terms of successive leaders only grow.
- A *fence* is the term (epoch, leader, instance) a leader puts on every request that changes the
  system. Receivers keep the newest fence they accepted and refuse older ones (`newer`): a
  leader frozen and resumed after its successor acted can no longer act. Two leaders may
  briefly both believe they lead (their views of the tokens differ); fencing makes sure
  that, at every receiver, once a newer leader has acted an older one never acts again.
"""

from __future__ import annotations

from collections.abc import Iterable

#: A leader's term: (epoch, replica name, instance).
Term = tuple[int, str, str]


def newer(candidate: Term, current: Term | None) -> bool:
    """Whether a receiver that has accepted ``current`` may accept ``candidate`` (the same
    term again, or a newer one: higher epoch, or the same epoch and a smaller name, or the
    same name and a smaller instance). A total order: of two terms, exactly one is newer
    unless they are the same."""
    if current is None:
        return True
    if candidate[0] != current[0]:
        return candidate[0] > current[0]
    return candidate[1:] <= current[1:]


def leader_of(claims: Iterable[Term]) -> Term | None:
    """The winning claim among the live ones: highest epoch, then smallest name, then
    smallest instance."""
    return min(claims, key=lambda term: (-term[0], *term[1:]), default=None)


def should_claim(me: str, members: Iterable[str], claims: Iterable[Term]) -> bool:
    """No live claim and ``me`` is the first live member by name (``me`` is always a
    member of its own view)."""
    if any(True for _ in claims):
        return False
    return me == min({*members, me})


def next_epoch(*seen: Iterable[int]) -> int:
    """An epoch above every epoch seen (from tokens, states, receivers' replies)."""
    return 1 + max((e for group in seen for e in group), default=0)


def parse_claim(chunks: list[str]) -> Term | None:
    """``[<epoch>, <replica>, <instance>]`` (the tail of a lead token's key) -> a term, else
    None."""
    if len(chunks) != 3 or not chunks[0].isdigit() or not chunks[1] or not chunks[2]:
        return None
    return int(chunks[0]), chunks[1], chunks[2]
