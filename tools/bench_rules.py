"""Benchmark of the Adaptation Engine's tick: median and p99 tick time.

Two models:

- the paper's Fig. 5 rules (scenarios/object_storing), measured twice: with a steady context
  (the usual case: the engine ticks far more often than the context changes) and with the
  context switching on every tick through the 24 contexts of the test table (so every tick
  changes the feature selection);
- a generated model of 1000 rules over 200 measurements, with a generated feature model (200
  run-time variation points of 3 variants, 100 optional features, 20 CV attributes with NFRs)
  and measurements model, the rules of each target grouped in a rule set as the paper asks;
  every tick 20 measurements get new samples, drifting (as sensor values do) or jumping to
  random values (the worst case: many conditions and so many features flip every tick).

Each line also gives the tick time without `apply_requests` (rra_agent.core.features), which
turns the fired requests into a valid selection: the rest is this module's own cost. The
lines marked "explained" tick as the Adaptation Engine leader does, with ``explain=True``:
each change of the selection or of a CV value also names the action that made it, what it
read and what it overruled (`TickResult.why`).

``--paired``: what explaining costs, on a busy machine too: a plain and an explaining engine
tick the same samples, interleaved (which goes first alternates), timed in thread CPU time
(preemption by other processes is not counted); median and p99 of each and their ratio.

Run: ``.venv/bin/python tools/bench_rules.py [--ticks N] [--seed S] [--paired]``. Targets on
the 2-core reference machine: Fig. 5 <= 20 us, 1000 rules <= 1 ms.
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import rra_agent.core.adaptation as rules_core  # noqa: E402
from rra_agent.core.adaptation import AdaptationEngine  # noqa: E402
from rra_agent.core.conflicts import check_conflicts  # noqa: E402
from rra_agent.dsl.rules import load_rules, parse_rules  # noqa: E402
from rra_agent.dsl.uvl import load_uvl  # noqa: E402
from rra_agent.models.features import Attribute, Feature, FeatureModel, Group  # noqa: E402
from rra_agent.models.measurements import Measurement, MeasurementsModel  # noqa: E402
from rra_agent.package.yamlload import load_yaml  # noqa: E402

N_VP, N_OPT, N_CV, N_MEAS, N_RULES = 200, 100, 20, 200, 1000
ROOMS = ("RoomA", "RoomB", "Corridor")


def percentiles(samples_ns: list[int]) -> tuple[float, float]:
    """Median and 99th percentile, in microseconds."""
    ordered = sorted(samples_ns)
    p99 = ordered[min(len(ordered) - 1, int(len(ordered) * 0.99))]
    return statistics.median(ordered) / 1000, p99 / 1000


# ---- Fig. 5 -------------------------------------------------------------------------------
def fig5_model() -> tuple[FeatureModel, Any]:
    """The object-storing feature model and rules."""
    pkg = ROOT / "scenarios" / "object_storing"
    fm = load_uvl(pkg / "features.uvl")
    meas = load_yaml(pkg / "measurements.yaml", MeasurementsModel)[0]
    return fm, load_rules(pkg / "adaptation.rra", fm, meas)


def fig5_vectors(ticks: int) -> tuple[list[dict], list[dict]]:
    """Samples of a steady context, and of one that switches every tick."""
    contexts = [
        (loc, batt, dist, mat)
        for loc in ROOMS
        for batt in (20.0, 80.0)
        for dist in (0.3, 3.0)
        for mat in ("Glass", "Wood")
    ]

    def vector(i: int, ctx: tuple) -> dict:
        stamp = i * 0.01
        loc, batt, dist, mat = ctx
        return {
            "SemLoc": (loc, stamp),
            "BattLev": (batt, stamp),
            "ObstDist": (dist, stamp),
            "Material": (mat, stamp),
        }

    steady = [vector(i, contexts[5]) for i in range(ticks)]
    switching = [vector(i, contexts[i % len(contexts)]) for i in range(ticks)]
    return steady, switching


def fig5(ticks: int) -> dict[str, tuple[float, ...]]:
    fm, model = fig5_model()
    steady, switching = fig5_vectors(ticks)
    out = {}
    for explain, tag in ((False, ""), (True, ", explained")):
        engine = AdaptationEngine(fm, {"Manipulation"}, model)
        out[f"Fig. 5, steady context{tag}"] = run_split(engine, steady, explain=explain)
        engine = AdaptationEngine(fm, {"Manipulation"}, model)
        out[f"Fig. 5, context switching every tick{tag}"] = run_split(
            engine, switching, explain=explain
        )
    return out


# ---- generated model ------------------------------------------------------------------------
def _attr(name: str, **value) -> Attribute:
    return Attribute(name=name, value=value)


def generated_feature_model(rng: random.Random) -> FeatureModel:
    runtime = Attribute(name="binding", value="runtime")
    vps = []
    for v in range(N_VP):
        variants = tuple(
            Feature(name=f"V{v}_{k}", attributes=(_attr("Cost", kind="cim", value=cost),))
            for k, cost in enumerate(rng.randint(1, 9) for _ in range(3))
        )
        vps.append(
            Feature(
                name=f"VP{v}",
                attributes=(runtime,),
                groups=(Group(kind="alternative", children=variants),),
            )
        )
    optional = [
        Feature(
            name=f"O{o}",
            attributes=(runtime,)
            + (
                (_attr(f"Lim{o}", kind="nfr", tag="max", value=5.0, constrains=f"CV{o % N_CV}"),)
                if o < N_CV
                else ()
            ),
        )
        for o in range(N_OPT)
    ]
    tuning = Feature(
        name="Tuning",
        attributes=(
            runtime,
            *(_attr(f"CV{c}", kind="cv", lower=0.0, upper=10.0) for c in range(N_CV)),
        ),
    )
    root = Feature(
        name="Bench",
        groups=(
            Group(kind="mandatory", children=(*vps, tuning)),
            Group(kind="optional", children=tuple(optional)),
        ),
    )
    return FeatureModel(root=root, source="<generated>")


def generated_measurements() -> MeasurementsModel:
    types = ["float"] * 140 + ["int"] * 30 + ["str"] * 20 + ["bool"] * 10
    return MeasurementsModel(
        measurements=[
            Measurement(name=f"m{i}", type=t, source=f"c{i}.out", max_age_ms=1000)  # type: ignore[arg-type]
            for i, t in enumerate(types)
        ]
    )


def _cond(rng: random.Random) -> str:
    def atom() -> str:
        i = rng.randrange(N_MEAS)
        if i < 140:
            return f"cdm.m{i} {rng.choice(['<', '>', '<=', '>='])} {rng.uniform(0, 100):.1f}"
        if i < 170:
            return f"cdm.m{i} {rng.choice(['<', '>', '==', '!='])} {rng.randint(0, 5)}"
        if i < 190:
            return f'cdm.m{i} == "{rng.choice(["a", "b", "c"])}"'
        return f"{rng.choice(['', 'NOT '])}cdm.m{i}"

    parts = [atom() for _ in range(rng.choice([1, 1, 2, 3]))]
    return f" {rng.choice(['AND', 'OR'])} ".join(parts)


def _value(rng: random.Random) -> str:
    a, b = rng.randrange(140), rng.randrange(140)
    return rng.choice(
        [
            f"cdm.m{a} / 10",
            f"CV0.min + (CV0.max - CV0.min) * (cdm.m{a} / 100) * [1 - e^(-cdm.m{b} / 50)]",
            f"max(0, min(10, cdm.m{a} - cdm.m{b}))",
            f"abs(cdm.m{a} - 50) / 5",
        ]
    )


def generated_rules(rng: random.Random) -> str:
    """1000 rules written the way the paper asks: the rules acting on one target form a rule
    set, so the model has no conflicts (check_conflicts finds none) and priorities decide."""
    lines = ["import bench.measurements as cdm"]
    n = 0
    for c in range(N_CV):  # 20 sets of 10: a default formula and conditional overrides
        lines.append(f"ruleSet S{c}:")
        for p in range(10, 0, -1):
            head = f"  rule s{c}_{p} priority {p}:"
            if p == 10:
                lines.append(f"{head} set_attribute(CV{c}) with_value({_value(rng)})")
            else:
                lines.append(
                    f"{head} if ({_cond(rng)}) set_attribute(CV{c}) with_value({_value(rng)})"
                )
            n += 1
    periods = ["", " period 0 ms", " period 100 ms"]
    for v in range(N_VP):  # 200 sets of 3: the best variant by default, two overrides
        period = periods[v % 3]
        a, b = rng.sample(range(3), 2)
        lines += [
            f"ruleSet P{v}:",
            f"  rule p{v}_3 priority 3{period}: select_feature_from_variants_of(VP{v}) "
            f"where_attribute {rng.choice(['MIN', 'MAX'])}(Cost)",
            f"  rule p{v}_2 priority 2{period}: if ({_cond(rng)}) activate_feature(V{v}_{a})",
            f"  rule p{v}_1 priority 1{period}: if ({_cond(rng)}) activate_feature(V{v}_{b})",
        ]
        n += 3
    o = 0
    while n < N_RULES:  # sets of 2 for the optional features
        lines += [
            f"ruleSet Q{o}:",
            f"  rule q{o}_2 priority 2: if ({_cond(rng)}) activate_feature(O{o}) "
            f"else deactivate_feature(O{o})",
            f"  rule q{o}_1 priority 1: if ({_cond(rng)}) deactivate_feature(O{o})",
        ]
        n += 2
        o += 1
    return "\n".join(lines) + "\n"


def measurement_value(rng: random.Random, i: int, old: object = None) -> object:
    """A new value for measurement ``i``: a small step from ``old`` if given, else random."""
    if i < 140:
        if isinstance(old, float):
            return min(100.0, max(0.0, old + rng.gauss(0, 1.0)))
        return rng.uniform(0, 100)
    if i < 170:
        if isinstance(old, int) and rng.random() < 0.9:
            return old
        return rng.randint(0, 5)
    if i < 190:
        if isinstance(old, str) and rng.random() < 0.9:
            return old
        return rng.choice(["a", "b", "c"])
    return rng.random() < 0.5 if old is None or rng.random() < 0.1 else old


def measurement_stream(rng: random.Random, ticks: int, drift: bool) -> list[dict]:
    """Per tick, 20 of the 200 measurements get a new sample: a small step (``drift``, as
    sensors do) or a new random value (worst case: many conditions flip every tick)."""
    current = {f"m{i}": (measurement_value(rng, i), 0.0) for i in range(N_MEAS)}
    vectors = []
    for k in range(ticks):
        stamp = (k + 1) * 0.01
        current = dict(current)
        for i in rng.sample(range(N_MEAS), 20):
            old = current[f"m{i}"][0] if drift else None
            current[f"m{i}"] = (measurement_value(rng, i, old), stamp)
        for i in range(N_MEAS):  # keep every sample fresh (max_age 1000 ms)
            value, then = current[f"m{i}"]
            if stamp - then > 0.5:
                current[f"m{i}"] = (value, stamp)
        vectors.append(current)
    return vectors


class _Timed:
    """Wraps `apply_requests` to measure the share of a tick spent in it."""

    def __init__(self) -> None:
        self.spent = 0
        self.inner = rules_core.apply_requests

    def __call__(self, *args, **kwargs):
        t0 = time.perf_counter_ns()
        try:
            return self.inner(*args, **kwargs)
        finally:
            self.spent += time.perf_counter_ns() - t0


def run_split(
    engine: AdaptationEngine, vectors: list[dict], warmup: int = 100, *, explain: bool = False
) -> tuple[float, ...]:
    """Median and p99 of the tick, and median of the tick without apply_requests."""
    timer = _Timed()
    rules_core.apply_requests = timer  # type: ignore[assignment]
    try:
        total, own = [], []
        now = 0.0
        for i, vector in enumerate(vectors):
            now += 0.01
            timer.spent = 0
            t0 = time.perf_counter_ns()
            engine.tick(now, vector, explain=explain)
            dt = time.perf_counter_ns() - t0
            if i >= warmup:
                total.append(dt)
                own.append(dt - timer.spent)
    finally:
        rules_core.apply_requests = timer.inner  # type: ignore[assignment]
    median, p99 = percentiles(total)
    own_median, own_p99 = percentiles(own)
    return median, p99, own_median, own_p99


def generated(ticks: int, seed: int) -> dict[str, tuple[float, ...]]:
    rng = random.Random(seed)
    fm = generated_feature_model(rng)
    meas = generated_measurements()
    text = generated_rules(rng)
    t0 = time.perf_counter()
    model = parse_rules(text, "<generated>.rra", fm, meas)
    t1 = time.perf_counter()
    AdaptationEngine(fm, (), model)
    t2 = time.perf_counter()
    found = check_conflicts(model, fm)
    t3 = time.perf_counter()
    print(
        f"generated model: {sum(1 for _ in model.rules())} rules, {N_MEAS} measurements, "
        f"{len(fm.features)} features; parse {1000 * (t1 - t0):.0f} ms, "
        f"compile {1000 * (t2 - t1):.0f} ms, check_conflicts {1000 * (t3 - t2):.0f} ms "
        f"({len(found)} conflicts)"
    )
    out = {}
    for explain, tag in ((False, ""), (True, ", explained")):
        for drift, label in ((True, "drifting values"), (False, "random jumps")):
            vectors = measurement_stream(random.Random(seed + 1), ticks, drift)
            name = f"{N_RULES} rules, 20/{N_MEAS} measurements new per tick, {label}{tag}"
            out[name] = run_split(AdaptationEngine(fm, (), model), vectors, explain=explain)
    return out


def paired_run(
    make: Callable[[], AdaptationEngine], vectors: list[dict], warmup: int = 100
) -> tuple[list[float], list[float]]:
    """Thread CPU time (us) of each tick of a plain and an explaining engine on ``vectors``."""
    engines = (make(), make())
    times: tuple[list[float], list[float]] = ([], [])
    now = 0.0
    for i, vector in enumerate(vectors):
        now += 0.01
        for explain in (0, 1) if i % 2 else (1, 0):
            t0 = time.thread_time_ns()
            engines[explain].tick(now, vector, explain=bool(explain))
            if i >= warmup:
                times[explain].append((time.thread_time_ns() - t0) / 1000)
    return times


def paired(ticks: int, seed: int) -> None:
    """Plain against explained, interleaved, in thread CPU time."""
    fm, model = fig5_model()
    steady, switching = fig5_vectors(ticks)
    rng = random.Random(seed)
    gfm = generated_feature_model(rng)
    gmodel = parse_rules(generated_rules(rng), "<generated>.rra", gfm, generated_measurements())

    def fig5_engine() -> AdaptationEngine:
        return AdaptationEngine(fm, {"Manipulation"}, model)

    cases: list[tuple[str, Callable[[], AdaptationEngine], list[dict]]] = [
        ("Fig. 5, steady context", fig5_engine, steady),
        ("Fig. 5, context switching every tick", fig5_engine, switching),
    ]
    for drift, label in ((True, "drifting values"), (False, "random jumps")):
        vectors = measurement_stream(random.Random(seed + 1), max(ticks // 5, 500), drift)
        cases.append((f"{N_RULES} rules, {label}", lambda: AdaptationEngine(gfm, (), gmodel),
                      vectors))  # fmt: skip
    print(f"{'thread CPU time, us':<40} {'plain':>17} {'explained':>17}  ratio of medians")
    for name, make, vectors in cases:
        plain, explained = (sorted(t) for t in paired_run(make, vectors))
        p, e = statistics.median(plain), statistics.median(explained)
        print(f"{name:<40} {p:8.1f} / {plain[int(len(plain) * 0.99)]:6.1f} "
              f"{e:8.1f} / {explained[int(len(explained) * 0.99)]:6.1f}  {e / p:.3f}")  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n", 1)[0])
    parser.add_argument("--ticks", type=int, default=5000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--paired", action="store_true", help="plain against explained")
    args = parser.parse_args(argv)
    if args.paired:
        paired(args.ticks, args.seed)
        return 0
    results: dict[str, tuple[float, ...]] = dict(fig5(args.ticks))
    results.update(generated(max(args.ticks // 5, 500), args.seed))
    width = max(len(k) for k in results)
    head = f"{'tick time':<{width}}  {'median':>10}  {'p99':>10}"
    print(f"{head}   (without apply_requests: median, p99)")
    for name, times in results.items():
        line = f"{name:<{width}}  {times[0]:>8.1f}us  {times[1]:>8.1f}us"
        if len(times) == 4:
            line += f"   ({times[2]:.1f}us, {times[3]:.1f}us)"
        print(line)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
