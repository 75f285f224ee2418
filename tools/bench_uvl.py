"""Benchmark of the UVL parser: rra-agent's `parse_uvl` against the reference parser
``uvlparser`` (the UVL project's ANTLR parser, from the ``test`` extra) on generated models.

Each model is generated from a seed, like the real-world models of the UVL corpus: a tree
about 8 levels deep whose features have up to 5 children in mandatory, optional, alternative,
or and cardinality groups, a fifth of the features with attributes, some typed features, and
half as many cross-tree constraints as features (propositional ones, and a tenth with
comparisons, arithmetic and aggregate functions). For each size the table gives both parsers'
CPU time (the best of ``--repeat`` runs; CPU rather than wall time, so that other processes on
the machine do not distort the figures), the time per feature (flat when parsing is linear in
model size) and the ratio. rra-agent's time is a complete `parse_uvl`: parse, build the
model and run every semantic check; the reference's is its parse tree only.

Run: ``.venv/bin/python tools/bench_uvl.py [--sizes 1000 10000 20000] [--repeat N]
[--no-reference]`` (the reference needs minutes for the largest model).
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from rra_agent.dsl.uvl import parse_uvl  # noqa: E402

GROUPS = ("mandatory", "optional", "alternative", "or", "[1..2]", "[0..*]")
TYPES = ("Integer", "Real", "String")


def generate(n: int, seed: int = 1) -> str:
    """UVL text of a model of ``n`` features (see the module docstring)."""
    rng = random.Random(seed)
    lines = ["namespace Bench", "", "features"]
    typed: list[str] = []
    count = 1

    def feature(name: str, depth: int, indent: str, budget: int) -> None:
        nonlocal count
        head = name
        if depth > 0 and rng.random() < 0.05:
            ftype = rng.choice(TYPES)
            head = f"{ftype} {name}"
            typed.append(name)
        if rng.random() < 0.2:
            head += f" {{cost {rng.randint(1, 99)}, label 'f{count}', weight {rng.random():.3f}}}"
        lines.append(indent + head)
        if budget <= 0 or depth >= 8:
            return
        n_children = min(budget, rng.randint(1, 5) if depth < 7 else budget)
        share = (budget - n_children) // n_children
        extra = (budget - n_children) % n_children
        kids = []
        for i in range(n_children):
            kids.append((f"F{count}", share + (1 if i < extra else 0)))
            count += 1
        while kids:
            size = min(len(kids), rng.randint(1, 4))
            lines.append(indent + "    " + rng.choice(GROUPS))
            for kid, kid_budget in kids[:size]:
                feature(kid, depth + 1, indent + "        ", kid_budget)
            kids = kids[size:]

    feature("F0", 0, "    ", n - 1)
    names = [f"F{i}" for i in range(count)]
    lines += ["", "constraints"]
    for _ in range(n // 2):
        a, b, c = rng.sample(names, 3)
        r = rng.random()
        if r < 0.1 and typed:
            t = rng.choice(typed)
            lines.append(
                f"    {a} => {t} > {rng.randint(0, 9)} | sum(cost) < {rng.randint(100, 999)}"
            )
        elif r < 0.5:
            lines.append(f"    {a} => {b}")
        elif r < 0.8:
            lines.append(f"    !({a} & {b}) | {c}")
        else:
            lines.append(f"    ({a} | {b}) <=> !{c}")
    return "\n".join(lines) + "\n"


def _reference_parse(text: str) -> None:
    from antlr4 import CommonTokenStream, InputStream
    from uvl.UVLCustomLexer import UVLCustomLexer
    from uvl.UVLPythonParser import UVLPythonParser

    parser = UVLPythonParser(CommonTokenStream(UVLCustomLexer(InputStream(text))))
    parser.featureModel()
    if parser.getNumberOfSyntaxErrors():
        raise SystemExit("the reference parser refused a generated model")


def _best(fn: Callable[[str], object], text: str, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        start = time.process_time()
        fn(text)
        best = min(best, time.process_time() - start)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 20000])
    ap.add_argument("--repeat", type=int, default=3, help="runs of rra-agent's parser per size")
    ap.add_argument("--no-reference", action="store_true", help="time rra-agent only")
    args = ap.parse_args()

    have_reference = not args.no_reference
    if have_reference:
        try:
            import uvl.UVLPythonParser  # noqa: F401
        except ImportError:
            print("uvlparser is not installed (pip install -e '.[test]'): rra-agent only")
            have_reference = False
    parse_uvl(generate(50))  # load the cached parser before timing

    print(f"{'features':>8} {'lines':>7} {'rra-agent':>10} {'us/feat':>8} "
          f"{'uvlparser':>10} {'us/feat':>8} {'ratio':>7}")  # fmt: skip
    for n in args.sizes:
        text = generate(n)
        fm = parse_uvl(text)
        assert len(fm.features) == n, (len(fm.features), n)
        ours = _best(parse_uvl, text, args.repeat)
        row = f"{n:>8} {text.count(chr(10)):>7} {ours:>9.3f}s {ours / n * 1e6:>8.1f}"
        if have_reference:
            ref = _best(_reference_parse, text, 1)
            row += f" {ref:>9.3f}s {ref / n * 1e6:>8.1f} {ref / ours:>6.1f}x"
        print(row, flush=True)


if __name__ == "__main__":
    main()
