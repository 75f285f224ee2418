"""Leader election and fencing rules (rra_agent.core.election), pure."""

from __future__ import annotations

import itertools

from hypothesis import given
from hypothesis import strategies as st

from rra_agent.core.election import leader_of, newer, next_epoch, parse_claim, should_claim

terms = st.tuples(
    st.integers(0, 5), st.sampled_from(["a", "b", "c", "ab"]), st.sampled_from(["1f", "2e"])
)


def test_newer_orders_by_epoch_then_smaller_name() -> None:
    assert newer((2, "b", "9"), (1, "a", "1"))
    assert not newer((1, "a", "1"), (2, "b", "9"))
    assert newer((2, "a", "9"), (2, "b", "1"))
    assert not newer((2, "b", "1"), (2, "a", "9"))
    assert newer((2, "b", "5"), (2, "b", "5"))  # the same leader again
    assert newer((0, "z", "1"), None)


def test_two_processes_of_one_replica_name_are_two_terms() -> None:
    """A replica name running twice (a second system on the bus, the sides of a partition):
    the same epoch and name, another instance. A receiver that has accepted one refuses
    the other, and the election elects one of them."""
    first, second = (1, "resolution-a", "1f3c"), (1, "resolution-a", "7a02")
    assert newer(first, second) != newer(second, first)
    assert not newer(second, first)  # accepted ``first``: ``second`` is refused
    assert leader_of([second, first]) == first == leader_of([first, second])


@given(st.lists(terms, min_size=1))
def test_leader_is_the_claim_every_receiver_accepts_last(claims: list) -> None:
    """The elected term is one no other claim supersedes: a receiver that accepted it
    refuses every other live claim."""
    best = leader_of(claims)
    assert best in claims
    for other in claims:
        if other != best:
            assert not newer(other, best)
            assert newer(best, other)


@given(st.lists(terms, min_size=2, max_size=8))
def test_fencing_never_lets_an_older_leader_act_after_a_newer_one(sequence: list) -> None:
    """Whatever order requests of several terms arrive in, the accepted ones are
    non-decreasing in the fence order."""
    accepted, highest = [], None
    for term in sequence:
        if newer(term, highest):
            accepted.append(term)
            highest = term
    for earlier, later in itertools.pairwise(accepted):
        assert newer(later, earlier)


def test_first_member_claims_only_when_nobody_leads() -> None:
    assert should_claim("a", {"a", "b"}, [])
    assert not should_claim("b", {"a", "b"}, [])
    assert should_claim("b", {"b"}, [])  # a is gone
    assert not should_claim("a", {"a", "b"}, [(3, "b", "1")])
    assert should_claim("b", set(), [])  # its own token not seen yet: still a member


def test_next_epoch_and_claim_keys() -> None:
    assert next_epoch([], []) == 1
    assert next_epoch([3, 1], [7]) == 8
    assert parse_claim(["12", "resolution-b", "7a02"]) == (12, "resolution-b", "7a02")
    assert parse_claim(["12", "resolution-b"]) is None  # no instance
    assert parse_claim(["x", "a", "1"]) is None
    assert parse_claim(["1"]) is None
