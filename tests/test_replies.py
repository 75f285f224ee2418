"""Reading the answers of a Zenoh get (`rra_agent.bus.client.oks`, `decoded`): what a forged
or broken answer does to the reader: nothing."""

from __future__ import annotations

from types import SimpleNamespace

from rra_agent.bus import messages as m
from rra_agent.bus.client import oks


def test_the_answers_of_a_get_skip_error_replies_malformed_answers_and_errs():
    """`oks` (every tool and engine reading a get's answers): a forged queryable's bytes or an
    error reply is skipped, never raised (a host agent's start once raised on one)."""
    codec = m.Codec[m.Reply](m.Reply)

    def reply(payload: bytes | None) -> SimpleNamespace:
        ok = None if payload is None else SimpleNamespace(payload=SimpleNamespace(
            to_bytes=lambda: payload))  # fmt: skip
        return SimpleNamespace(ok=ok)

    replies = [
        reply(None),  # an error reply
        reply(b"\xc1 not msgpack"),
        reply(codec.encode(m.Err(message="no", code="denied"))),
        reply(codec.encode(m.Ok(result={"a": 1}))),
    ]
    assert [a.result for a in oks(replies)] == [{"a": 1}]  # type: ignore[arg-type]
