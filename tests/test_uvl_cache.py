"""The on-disk cache of built lark parsers (`rra_agent.dsl.parser_cache`)."""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from lark import Lark

from rra_agent.dsl import parser_cache, rules, uvl
from rra_agent.dsl.parser_cache import cache_dir, cached_lark

ROOT = Path(__file__).resolve().parents[1]
GRAMMAR = 'start: WORD+\nWORD: /[a-z]+/\n%ignore " "\n'
OPTIONS = {"parser": "lalr", "strict": True}


@pytest.fixture
def builds(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[list[str]]:
    """Points the cache at a fresh folder and records every grammar lark builds."""
    monkeypatch.setenv("RRA_CACHE_DIR", str(tmp_path / "cache"))
    built: list[str] = []
    real_init = Lark.__init__

    def counting_init(self: Lark, grammar: str, **options: object) -> None:
        built.append(grammar)
        real_init(self, grammar, **options)

    monkeypatch.setattr(Lark, "__init__", counting_init)
    uvl._parser.cache_clear()
    rules._parser.cache_clear()
    yield built
    uvl._parser.cache_clear()
    rules._parser.cache_clear()


def test_parser_is_built_once_then_loaded(builds: list[str]) -> None:
    first = cached_lark("t", GRAMMAR, **OPTIONS)
    assert len(builds) == 1
    files = list(cache_dir().iterdir())
    assert [f.suffix for f in files] == [".lark"]  # no temporary file left behind
    second = cached_lark("t", GRAMMAR, **OPTIONS)
    assert len(builds) == 1  # loaded, not built
    assert second.parse("ab cd") == first.parse("ab cd")


def test_changed_grammar_gets_a_new_cache_file(builds: list[str]) -> None:
    cached_lark("t", GRAMMAR, **OPTIONS)
    changed = GRAMMAR.replace("[a-z]", "[a-z0-9]")
    parser = cached_lark("t", changed, **OPTIONS)
    assert len(builds) == 2
    assert len(list(cache_dir().iterdir())) == 2
    assert parser.parse("a1 b2").children[0] == "a1"  # the new grammar, not the cached old one
    cached_lark("t", changed, **OPTIONS)
    assert len(builds) == 2


def test_lark_version_is_part_of_the_key(
    builds: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    cached_lark("t", GRAMMAR, **OPTIONS)
    monkeypatch.setattr(parser_cache.lark, "__version__", "0.0.0-other")
    cached_lark("t", GRAMMAR, **OPTIONS)
    assert len(builds) == 2


def test_damaged_cache_file_is_rebuilt_and_replaced(builds: list[str]) -> None:
    cached_lark("t", GRAMMAR, **OPTIONS)
    (path,) = cache_dir().iterdir()
    path.write_bytes(b"not a pickle")
    parser = cached_lark("t", GRAMMAR, **OPTIONS)
    assert len(builds) == 2
    assert parser.parse("ok").children == ["ok"]
    cached_lark("t", GRAMMAR, **OPTIONS)
    assert len(builds) == 2  # the rebuilt file replaced the damaged one


def test_cache_file_others_may_write_is_not_loaded(builds: list[str]) -> None:
    """Unpickling runs code: a cache file writable by other users is rebuilt, not loaded."""
    cached_lark("t", GRAMMAR, **OPTIONS)
    (path,) = cache_dir().iterdir()
    path.chmod(0o666)
    cached_lark("t", GRAMMAR, **OPTIONS)
    assert len(builds) == 2
    (path,) = cache_dir().iterdir()
    assert path.stat().st_mode & 0o022 == 0  # replaced by a private file
    cached_lark("t", GRAMMAR, **OPTIONS)
    assert len(builds) == 2


def test_unwritable_cache_still_gives_a_parser(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("a file where the cache folder should be")
    monkeypatch.setenv("RRA_CACHE_DIR", str(blocker / "cache"))
    assert cached_lark("t", GRAMMAR, **OPTIONS).parse("x").children == ["x"]


def test_no_home_folder_still_gives_a_parser(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_home() -> Path:
        raise RuntimeError("Could not determine home directory.")

    for var in ("RRA_CACHE_DIR", "XDG_CACHE_HOME"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(Path, "home", staticmethod(no_home))
    assert cached_lark("t", GRAMMAR, **OPTIONS).parse("x").children == ["x"]


def test_cache_folder_follows_xdg(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("RRA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert cache_dir() == tmp_path / "rra-agent"
    monkeypatch.setenv("XDG_CACHE_HOME", "relative/ignored")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert cache_dir() == tmp_path / "home/.cache/rra-agent"


def test_uvl_and_rules_parsers_come_from_the_cache(builds: list[str]) -> None:
    """The UVL parser (with its Indenter postlexer) and the rules parser, loaded from disk,
    parse exactly like freshly built ones."""
    text = (ROOT / "scenarios/object_storing/features.uvl").read_text(encoding="utf-8")
    fresh = uvl.parse_uvl(text)
    rules._parser()
    assert len(builds) == 2
    uvl._parser.cache_clear()
    rules._parser.cache_clear()
    loaded = uvl.parse_uvl(text)
    rules._parser()
    assert len(builds) == 2  # both loaded
    assert uvl.strip_spans(loaded) == uvl.strip_spans(fresh)
    assert uvl.to_uvl(loaded) == uvl.to_uvl(fresh)
    with pytest.raises(uvl.DslSyntaxError, match="inconsistent dedent"):
        uvl.parse_uvl("features\n    A\n        optional\n            B\n      C\n")


@pytest.mark.system
def test_processes_starting_together_share_the_cache(tmp_path: Path) -> None:
    """Several processes building at once: each gets a working parser, and the folder ends up
    holding one whole cache file (written under a temporary name, then renamed into place)."""
    env = {**os.environ, "RRA_CACHE_DIR": str(tmp_path), "PYTHONPATH": str(ROOT)}
    code = (
        "from rra_agent.dsl.uvl import parse_uvl\n"
        "assert parse_uvl('features\\n    A\\n        optional\\n            B\\n')"
        ".features.keys() == {'A', 'B'}\n"
    )
    procs = [subprocess.Popen([sys.executable, "-c", code], env=env) for _ in range(2)]
    assert [p.wait(timeout=120) for p in procs] == [0, 0]
    assert [p.suffix for p in tmp_path.iterdir()] == [".lark"]


@pytest.mark.system
def test_validate_imports_neither_zenoh_nor_cryptography(tmp_path: Path) -> None:
    """``rra validate`` configures only its own arguments: the modules of the other commands
    (zenoh, cryptography, the simulator) stay unimported, which keeps its start quick."""
    code = (
        "import sys\n"
        "from rra_agent.cli.commands import main\n"
        f"assert main(['validate', {str(ROOT / 'scenarios/quadcopter')!r}]) == 0\n"
        "heavy = sorted(m for m in ('zenoh', 'cryptography', 'mujoco', 'rerun') "
        "if m in sys.modules)\n"
        "assert not heavy, heavy\n"
    )
    env = {**os.environ, "RRA_CACHE_DIR": str(tmp_path), "PYTHONPATH": str(ROOT)}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


def test_parsing_pauses_the_cyclic_collector_and_restores_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Full collections during a parse made its time grow faster than the model; the parse
    runs with the collector off and leaves it as it found it, also after an error."""
    import gc

    seen: list[bool] = []
    real = uvl._parse_tree

    def spy(text: str, file: str) -> object:
        seen.append(gc.isenabled())
        return real(text, file)

    monkeypatch.setattr(uvl, "_parse_tree", spy)
    assert gc.isenabled()
    uvl.parse_uvl("features\n    A\n")
    with pytest.raises(uvl.RraError):
        uvl.parse_uvl("features\n    A {\n")
    assert seen == [False, False]
    assert gc.isenabled()
    gc.disable()
    try:
        uvl.parse_uvl("features\n    A\n")
        assert not gc.isenabled()  # left off when it was off
    finally:
        gc.enable()
