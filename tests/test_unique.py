"""How a starting host agent names the host of a system already on the bus
(`rra_agent.host.unique`), against a bus whose tokens come in batches."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from rra_agent.bus import messages as m
from rra_agent.bus.keys import Keys
from rra_agent.host import unique

KEYS = Keys("relay_system")
MEMBERS = [f"{KEYS.prefix}/member/monitor/monitor-a"]
ALIVE = [KEYS.alive("local", "monitor-a"), KEYS.alive("local", "source")]


class Bus:
    """Answers liveliness queries from the tokens it holds; the host's tokens arrive only
    after ``alive_after`` queries (the linked router's second batch)."""

    def __init__(self, alive_after: int | None) -> None:
        self.queries = 0
        self.alive_after = alive_after

    def liveliness(self) -> Bus:
        return self

    def get(self, key: str, timeout: float) -> list[SimpleNamespace]:
        self.queries += 1
        if "/member/" in key:
            held = MEMBERS
        elif self.alive_after is not None and self.queries > self.alive_after:
            held = ALIVE
        else:
            held = []
        return [SimpleNamespace(ok=SimpleNamespace(key_expr=k)) for k in held]


def test_the_engines_host_is_found_when_its_tokens_come_after_the_members() -> None:
    bus = Bus(alive_after=4)
    assert unique.engines_host(bus, KEYS, patience=5.0) == "local"  # type: ignore[arg-type]
    assert bus.queries > 4


def test_a_host_never_named_is_unknown_once_the_patience_is_spent() -> None:
    assert unique.engines_host(Bus(alive_after=None), KEYS, patience=0.1) == "?"  # type: ignore[arg-type]


def test_no_engine_replica_means_no_other_system() -> None:
    bus = Bus(alive_after=0)
    bus.get = lambda key, timeout: []  # type: ignore[method-assign]
    assert unique.engines_host(bus, KEYS, patience=5.0) is None  # type: ignore[arg-type]


class Agent:
    """The running agent's control queryable, reachable only from the ``routed_after``-th
    get on (a just linked router knows its tokens before its queryable)."""

    def __init__(self, routed_after: int) -> None:
        self.gets = 0
        self.routed_after = routed_after

    def get(self, key: str, payload: bytes, timeout: float) -> list[SimpleNamespace]:
        self.gets += 1
        if self.gets < self.routed_after:
            return []
        answer = m.Codec[Any](Any).encode(m.Ok(result={"pid": 4242, "listen": ["tcp/x:1"]}))
        return [
            SimpleNamespace(ok=SimpleNamespace(payload=SimpleNamespace(to_bytes=lambda: answer)))
        ]


def test_the_refusal_names_an_agent_whose_queryable_is_routed_after_its_tokens() -> None:
    agent = Agent(routed_after=3)
    assert unique.where(agent, KEYS, "local") == "host local (agent pid 4242, router tcp/x:1)"  # type: ignore[arg-type]
    assert agent.gets == 3


class LateEngines(Agent):
    """A running system whose agent's token is in but whose engine replicas' member tokens
    come only from the ``members_after``-th liveliness query on."""

    def __init__(self, members_after: int) -> None:
        super().__init__(routed_after=1)
        self.queries = 0
        self.members_after = members_after

    def liveliness(self) -> LateEngines:
        return self

    def get(self, key: str, *args: Any, **kw: Any) -> list[SimpleNamespace]:  # type: ignore[override]
        if "payload" in kw:  # the agent's Ping
            return super().get(key, kw["payload"], kw["timeout"])
        self.queries += 1
        if "/hostagent/" in key:
            held = [KEYS.host_alive("local")]
        elif "/member/" in key:
            held = MEMBERS if self.queries >= self.members_after else []
        else:
            held = ALIVE
        return [SimpleNamespace(ok=SimpleNamespace(key_expr=k)) for k in held]


def test_a_system_whose_engines_come_after_its_agent_is_named_as_a_system() -> None:
    bus = LateEngines(members_after=5)
    why = unique.already_running(bus, KEYS, "local", engines=True, who="rra up")  # type: ignore[arg-type]
    assert why is not None and why.startswith(
        "system 'relay_system' already runs on this bus, its engines on host local (agent pid 4242"
    ), why
