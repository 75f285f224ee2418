"""Scenario files (``*.scenario.yaml``): the Structs, and loading them into runnable cases.

A scenario names a system package, the deployment-time selection, optional replacement
strategy overrides, a duration, a timeline of injections and a list of expectations (the
textual forms of `rra_agent.scenario.expectations`). A file may hold several ``cases``
(e.g. the adaptive run and its control run with adaptation disabled): each case overrides
the scenario's settings and adds its own timeline steps and expectations.

`load_scenario` reads a file with `rra_agent.package.yamlload` (every problem located as
``file:line:col``), loads the package, parses every expectation and checks every name it and
the timeline refer to (features, nodes, ports, parameters, measurements, CV attributes,
injections, links) against the package, so a typo fails at load (pytest: at collection), not
after a run. The JSON Schema of `Scenario` is ``schemas/scenario.schema.json``.

Several hosts: ``host`` is the first (``rra up --host``: the engines, its router the one the
others join); every other host of the system model (or those ``hosts`` lists) gets an
``rra agent`` joining it through a link the timeline can cut and restore (``cut_link``,
``restore_link``: a partition on one machine, `rra_agent.scenario.link`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

import msgspec
from yaml.nodes import ScalarNode

from rra_agent.bus.keys import check_topic
from rra_agent.core.conflicts import conflict_targets
from rra_agent.core.features import complete_deployment, default_runtime_selection
from rra_agent.core.plan import peers_of, topic_of
from rra_agent.core.resolution import resolve_deployment
from rra_agent.deployment import Deployment
from rra_agent.errors import ErrorGroup, Location, ModelError, RraError
from rra_agent.models.base import FrozenModel
from rra_agent.models.resolution import Replacement
from rra_agent.models.system import parse_endpoint
from rra_agent.package.loader import load_package
from rra_agent.package.yamlload import YamlDoc, load_yaml, unknown_name
from rra_agent.scenario import expectations as x

Name = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_.\-]+$")]
Seconds = Annotated[float, msgspec.Meta(ge=0.0)]
Duration = Annotated[float, msgspec.Meta(gt=0.0, le=600.0)]
Period = Annotated[float, msgspec.Meta(gt=0.0)]
ENGINES = ("monitor", "adaptation", "resolution")  # as rra_agent.cli.up.ENGINES
ACTIONS = (
    "set_params",
    "publish",
    "malformed",
    "kill",
    "freeze",
    "resume",
    "inject",
    "cut_link",
    "restore_link",
)
#: Timeline actions naming a host (one of the case's agent hosts) rather than a node.
LINK_ACTIONS = ("cut_link", "restore_link")


# ---- timeline steps --------------------------------------------------------------------------
class SetParamsStep(FrozenModel, frozen=True, kw_only=True):
    """Set parameters of a running node (a ``SetParams`` control request)."""

    node: str
    params: dict[str, Any]


class PublishStep(FrozenModel, frozen=True, kw_only=True):
    """Publish a data sample on a publisher port's topic, as if its component had."""

    #: ``component.port`` (a publisher port of the package's system model).
    port: str
    data: dict[str, Any]
    #: Publish again every ``every`` seconds ...
    every: Period | None = None
    #: ... until this time (seconds after deployment; default: the end of the run).
    until: Seconds | None = None


class MalformedStep(FrozenModel, frozen=True, kw_only=True):
    """Publish bytes that are not a valid sample: on a port's topic or on any key of the
    system (``key`` relative to ``rra/<system>/``, e.g. ``ctx/BattLev`` or ``selection``)."""

    port: str | None = None
    key: str | None = None
    #: The payload as hex digits (default ``c1``: a byte msgpack never uses).
    hex: str = "c1"

    def __post_init__(self) -> None:
        if (self.port is None) == (self.key is None):
            raise ValueError("give exactly one of 'port' and 'key'")
        try:
            bytes.fromhex(self.hex)
        except ValueError:
            raise ValueError(f"'hex' is not hex digits: {self.hex!r}") from None


class InjectStep(FrozenModel, frozen=True, kw_only=True):
    """A fault for a simulator (an ``Inject`` message on ``rra/<system>/inject/<kind>``)."""

    kind: Name
    target: str = ""
    args: dict[str, Any] = {}


class Step(FrozenModel, frozen=True, kw_only=True):
    """One timeline entry: at ``at`` seconds after deployment, exactly one action."""

    at: Seconds
    #: The name expectations use for it (``within 1 s after low_battery``).
    name: Name | None = None
    set_params: SetParamsStep | None = None
    publish: PublishStep | None = None
    malformed: MalformedStep | None = None
    #: SIGKILL the node's process (its host agent restarts it per its restart policy).
    kill: str | None = None
    #: SIGSTOP the node's process (it loses its liveliness at the lease, and is restarted).
    freeze: str | None = None
    #: SIGCONT a frozen node's process.
    resume: str | None = None
    inject: InjectStep | None = None
    #: Pull the cable of a host's link to the first host: nothing passes either way, neither
    #: end is told (each finds out at its own lease); the host's agent runs on, cut off.
    cut_link: str | None = None
    #: Plug it back: the host's router reconnects, its agent is reachable again.
    restore_link: str | None = None

    def __post_init__(self) -> None:
        given = [a for a in ACTIONS if getattr(self, a) is not None]
        if len(given) != 1:
            found = ", ".join(given) if given else "none"
            raise ValueError(
                f"a timeline step needs exactly one action of {', '.join(ACTIONS)} (found: {found})"
            )

    @property
    def action(self) -> str:
        return next(a for a in ACTIONS if getattr(self, a) is not None)

    @property
    def label(self) -> str:
        return self.name or f"{self.action}@{self.at:g}s"


# ---- the scenario ---------------------------------------------------------------------------
class Case(FrozenModel, frozen=True, kw_only=True):
    """A variant of the scenario: overrides its settings, adds steps and expectations."""

    name: Name
    description: str = ""
    select: list[str] | None = None
    adaptation: bool | None = None
    replacement: Replacement | None = None
    duration: Duration | None = None
    slow: bool | None = None
    timeline: list[Step] = []
    expect: list[str] = []


class Scenario(FrozenModel, frozen=True, kw_only=True):
    """A ``*.scenario.yaml`` file."""

    name: Name
    description: str = ""
    #: The system package folder, relative to this file.
    package: str = "."
    #: Deployment-time features (default: the package manifest's ``default_selection``).
    select: list[str] = []
    #: False runs the system without its Adaptation Engine (a control case).
    adaptation: bool = True
    #: Replaces the ``replacement`` section of the package's Run-time Resolution Model.
    replacement: Replacement | None = None
    #: The first host: ``rra up --host`` runs the engines and the components placed on it (or
    #: on no host), and is the router the other hosts join.
    host: Name = "local"
    #: The other hosts: one ``rra agent`` each, joining the first host's router through a link
    #: the timeline may cut (``cut_link``). Default: every host of the system model but ``host``.
    hosts: list[Name] | None = None
    #: Seconds the run lasts after deployment.
    duration: Duration
    #: Marked ``slow`` in pytest (deselect with ``-m "not slow"``).
    slow: bool = False
    #: Names for quantities used in expectations: ``altitude: vehicle_simulator.state.position[2]``.
    quantities: dict[str, str] = {}
    #: How often node parameters named by expectations (``param node.p``) are sampled.
    sample_period: Period = 0.25
    timeline: list[Step] = []
    expect: list[str] = []
    cases: list[Case] = []

    def __post_init__(self) -> None:
        names = [c.name for c in self.cases]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicate case name(s) {', '.join(dup)}")


# ---- loaded, runnable cases -------------------------------------------------------------------
@dataclass(frozen=True)
class TimedStep:
    step: Step
    name: str
    location: Location
    #: For ``publish``/``malformed``: the key below ``rra/<system>/`` to put on.
    key: str = ""


@dataclass(frozen=True)
class ScenarioCase:
    """One runnable case: everything the runner and the evaluation need."""

    file: Path
    scenario: str
    case: str | None
    description: str
    location: Location
    package: Path
    system: str
    #: The deployment-time features as written (passed to ``rra up --select``).
    select: tuple[str, ...]
    deployment: frozenset[str]
    initial_features: frozenset[str]
    initial_cv: Mapping[str, float]
    swap_pairs: tuple[tuple[str, str], ...]
    adaptation: bool
    replacement: Replacement | None
    #: The Run-time Resolution Model's file name in the package (for ``replacement``).
    runtime_file: str
    duration: float
    slow: bool
    sample_period: float
    timeline: tuple[TimedStep, ...]
    expectations: tuple[x.Expectation, ...]
    #: Further data topics to record (tools such as ``rra demo`` read them).
    record_topics: frozenset[str] = frozenset()
    #: Further arguments for ``rra up`` (e.g. ``--rerun save PATH``).
    up_args: tuple[str, ...] = ()
    #: The first host (``rra up --host``).
    host: str = "local"
    #: The other hosts, each an ``rra agent`` behind a cuttable link.
    hosts: tuple[str, ...] = ()

    @property
    def id(self) -> str:
        return f"{self.scenario}::{self.case}" if self.case else self.scenario

    def data_topics(self) -> set[str]:
        """Topics the expectations read, and `record_topics` (the runner records these only)."""
        return {
            e.quantity.topic
            for e in self.expectations
            if isinstance(e, x.ValueExpectation) and e.quantity.kind == "data"
        } | set(self.record_topics)

    def param_nodes(self) -> set[str]:
        """Nodes whose parameters the expectations read (sampled during the run)."""
        return {
            e.quantity.name.split(".", 1)[0]
            for e in self.expectations
            if isinstance(e, x.ValueExpectation) and e.quantity.kind == "param"
        }


@dataclass(frozen=True)
class ScenarioFile:
    path: Path
    scenario: Scenario
    doc: YamlDoc
    cases: tuple[ScenarioCase, ...]


def load_scenario(path: str | Path) -> ScenarioFile:
    """Load, parse and check a scenario file; every problem is a located `ModelError`
    (several come as an `ErrorGroup`)."""
    scenario, doc = load_yaml(path, Scenario)
    return _Loader(Path(path), scenario, doc).load()


# ---- the loader -----------------------------------------------------------------------------
PathItem = str | int


class _Loader:
    def __init__(self, path: Path, scenario: Scenario, doc: YamlDoc) -> None:
        self.path = path
        self.scenario = scenario
        self.doc = doc
        self.errors: list[RraError] = []

    def err(self, message: str, loc: Location) -> None:
        error = self.doc.error(message, loc)
        if all(str(e) != str(error) for e in self.errors):  # shared by several cases: once
            self.errors.append(error)

    def load(self) -> ScenarioFile:
        sc = self.scenario
        root = (self.path.parent / sc.package).resolve()
        try:
            pkg = load_package(root)
        except ModelError:
            raise
        except RraError as e:
            raise self.doc.error(f"package {sc.package!r}: {e}", self.doc.loc("package")) from None
        self.pkg = pkg
        self.hosts = self.agent_hosts()
        variants: list[tuple[Case | None, tuple[PathItem, ...]]] = (
            [(c, ("cases", i)) for i, c in enumerate(sc.cases)] if sc.cases else [(None, ())]
        )
        cases = [self.case(c, at) for c, at in variants]
        ErrorGroup.raise_if_any(self.errors)
        return ScenarioFile(self.path, sc, self.doc, tuple(c for c in cases if c is not None))

    def case(self, c: Case | None, at: tuple[PathItem, ...]) -> ScenarioCase | None:
        sc, pkg = self.scenario, self.pkg

        def pick(name: str) -> Any:  # the case's setting, else the scenario's
            own = getattr(c, name) if c is not None else None
            return own if own is not None else getattr(sc, name)

        select = pick("select")
        select_at = (*at, "select") if c is not None and c.select is not None else ("select",)
        try:
            deployment = complete_deployment(
                pkg.features, list(select) or pkg.manifest.default_selection
            )
            configured = resolve_deployment(pkg.system, pkg.deployment, pkg.features, deployment)
            initial = default_runtime_selection(pkg.features, deployment)
        except RraError as e:
            self.err(f"deployment-time selection: {e}", self.doc.loc(*select_at))
            return None
        initial_cv = Deployment(pkg, deployment, configured).initial_cv()
        duration = pick("duration")
        timeline = self.timeline(c, at, duration)
        names = {t.step.name for t in timeline if t.step.name}
        expectations: list[x.Expectation] = []
        texts: list[tuple[str, tuple[PathItem, ...]]] = [
            (text, ("expect", i)) for i, text in enumerate(sc.expect)
        ]
        if c is not None:
            texts += [(text, (*at, "expect", i)) for i, text in enumerate(c.expect)]
        for text, where in texts:
            exp = self.expectation(text, where, names)
            if exp is not None:
                expectations.append(exp)
        return ScenarioCase(
            file=self.path,
            scenario=sc.name,
            case=c.name if c is not None else None,
            description=(c.description if c is not None and c.description else sc.description),
            location=self.doc.loc(*at, "name") if c is not None else self.doc.loc("name"),
            package=pkg.root,
            system=pkg.system.system,
            select=tuple(select),
            deployment=deployment,
            initial_features=initial,
            initial_cv=initial_cv,
            swap_pairs=swap_pairs(configured),
            adaptation=pick("adaptation"),
            replacement=pick("replacement"),
            runtime_file=pkg.manifest.runtime,
            duration=duration,
            slow=pick("slow"),
            sample_period=sc.sample_period,
            timeline=tuple(timeline),
            expectations=tuple(expectations),
            host=sc.host,
            hosts=self.hosts,
        )

    def agent_hosts(self) -> tuple[str, ...]:
        """The hosts that get an ``rra agent``: ``hosts``, checked against the system model,
        or every host of the model but the first."""
        sc, system = self.scenario, self.pkg.system
        declared = [h.name for h in system.hosts]
        placed = [c.host for c in system.components if c.host is not None]
        known = list(dict.fromkeys(declared + placed))
        if sc.hosts is None:
            return tuple(h for h in known if h != sc.host)
        for i, h in enumerate(sc.hosts):
            if h == sc.host:
                self.err(
                    f"host {h!r} is the first host ('host'), not another", self.doc.loc("hosts", i)
                )
            elif h not in known:
                self.err(unknown_name("host", h, known), self.doc.loc("hosts", i))
        return tuple(h for h in dict.fromkeys(sc.hosts) if h in known and h != sc.host)

    # -- timeline
    def timeline(
        self, c: Case | None, at: tuple[PathItem, ...], duration: float
    ) -> list[TimedStep]:
        entries: list[tuple[Step, tuple[PathItem, ...]]] = [
            (s, ("timeline", i)) for i, s in enumerate(self.scenario.timeline)
        ]
        if c is not None:
            entries += [(s, (*at, "timeline", i)) for i, s in enumerate(c.timeline)]
        out: list[TimedStep] = []
        seen: dict[str, Location] = {}
        for step, where in entries:
            loc = self.doc.loc(*where)
            if step.name is not None:
                if step.name in seen:
                    self.err(
                        f"duplicate step name '{step.name}' (first at line {seen[step.name].line})",
                        self.doc.loc(*where, "name"),
                    )
                seen.setdefault(step.name, loc)
            if step.at > duration:
                self.err(
                    f"step at {step.at:g} s is after the end of the run ({duration:g} s)",
                    self.doc.loc(*where, "at"),
                )
            key = self.check_step(step, where)
            label, n = step.label, 1
            while any(t.name == label for t in out):  # unnamed steps at the same time
                n += 1
                label = f"{step.label}#{n}"
            out.append(TimedStep(step, label, loc, key or ""))
        out.sort(key=lambda t: t.step.at)
        return out

    def check_step(self, step: Step, where: tuple[PathItem, ...]) -> str | None:
        """Check the names a step uses; the key it puts on, if any."""
        if step.set_params is not None:
            sp = step.set_params
            comp = self.node(sp.node, self.doc.loc(*where, "set_params", "node"))
            if comp is not None:
                known = set(comp.parameters)
                for name in sp.params:
                    if name not in known:
                        self.err(
                            unknown_name("parameter", name, known, f" of {sp.node}"),
                            self.doc.key_loc(*where, "set_params", "params", name),
                        )
        for action in ("kill", "freeze", "resume"):
            node = getattr(step, action)
            if node is not None:
                self.node(node, self.doc.loc(*where, action), engines=True)
        for action in LINK_ACTIONS:
            host = getattr(step, action)
            if host is not None and host not in self.hosts:  # a link is named by its host
                self.err(unknown_name("link", host, self.hosts), self.doc.loc(*where, action))
        if step.publish is not None:
            return self.topic(step.publish.port, self.doc.loc(*where, "publish", "port"))
        if step.malformed is not None:
            mf = step.malformed
            if mf.port is not None:
                return self.topic(mf.port, self.doc.loc(*where, "malformed", "port"))
            try:
                return check_topic(mf.key or "")
            except ValueError as e:
                self.err(str(e), self.doc.loc(*where, "malformed", "key"))
        return None

    def node(self, name: str, loc: Location, *, engines: bool = False) -> Any:
        comp = self.pkg.system.component(name)
        if comp is None and not (engines and name in ENGINES):
            known = [c.name for c in self.pkg.system.components]
            self.err(unknown_name("node", name, known + list(ENGINES if engines else ())), loc)
        return comp

    def topic(self, port: str, loc: Location) -> str | None:
        """``data/<topic>`` of a publisher port ``component.port``."""
        try:
            ep = parse_endpoint(port)
            return "data/" + topic_of(self.pkg.system, ep.component, ep.port)
        except (ValueError, RraError) as e:
            self.err(str(e), loc)
            return None

    # -- expectations
    def expectation(
        self, text: str, where: tuple[PathItem, ...], injections: set[str]
    ) -> x.Expectation | None:
        loc = self.doc.loc(*where)
        try:
            exp = x.parse(text, loc)
        except x.ExpectationError as e:
            self.err(f"expectation: {e.message}", self.text_loc(where, e.offset))
            return None
        before = len(self.errors)
        changes: dict[str, Any] = {}
        conflicts: dict[str, str] = {}
        for ref in exp.refs:
            rloc = self.text_loc(where, ref.offset)
            match ref.kind:
                case "feature":
                    name = self.pkg.features.resolve_name(ref.name)
                    if name is None:
                        self.err(
                            unknown_name("feature", ref.name, self.pkg.features.features), rloc
                        )
                    elif isinstance(exp, x.FeatureExpectation):
                        changes["feature"] = name
                case "node":
                    self.node(ref.name, rloc, engines=True)
                case "injection":
                    if ref.name not in injections:
                        self.err(unknown_name("injection", ref.name, injections), rloc)
                case "measurement" if not isinstance(exp, x.ValueExpectation):
                    known = [ms.name for ms in self.pkg.measurements.measurements]
                    if ref.name not in known:
                        self.err(unknown_name("measurement", ref.name, known), rloc)
                case "conflict":
                    target = self.conflict_target(ref.name, rloc)
                    if target is not None:
                        conflicts[ref.name] = target
                case "rewire":
                    node, _, port = ref.name.partition(".")
                    comp = self.pkg.system.component(node)
                    if comp is not None and comp.port(port) is None:
                        known = [p.name for p in comp.ports]
                        self.err(unknown_name("port", port, known, f" of '{node}'"), rloc)
                case _:
                    pass
        if isinstance(exp, x.ValueExpectation):
            q = self.quantity(exp.quantity, where, exp.refs)
            if q is not None:
                changes["quantity"] = q
                if q.kind == "implementation":
                    changes["value"] = self.implementation(q.name, exp.value)
        exp = _bind_events(exp, self.pkg.features, conflicts)
        if len(self.errors) > before:
            return None
        return dataclasses.replace(exp, **changes) if changes else exp

    def conflict_target(self, name: str, loc: Location) -> str | None:
        """What ``conflict(name)`` is over: a feature (by name or alias; the parent of an
        alternative group stands for the choice among its alternatives) or a CV attribute
        (``MaxVel`` or ``Feature.MaxVel``), one the package's rules claim; None after a
        located error."""
        fm = self.pkg.features
        cvs = {n: owner for n, (owner, a) in fm.attributes.items() if a.kind == "cv"}
        resolved = fm.resolve_name(name)
        if resolved is None:
            owner, _, attr = name.rpartition(".")
            if attr in cvs and (not owner or fm.resolve_name(owner) == cvs[attr]):
                resolved = f"{cvs[attr]}.{attr}"
        if resolved is None:
            known = [*fm.features, *cvs]
            msg = unknown_name("conflict target", name, known)
            self.err(msg + "; a conflict is over a feature or a CV attribute", loc)
            return None
        if self.pkg.adaptation is None:
            self.err(f"conflict({name}): the package has no adaptation rules", loc)
            return None
        targets = conflict_targets(self.pkg.adaptation, fm)
        if resolved not in targets:
            self.err(
                f"no rule claims '{name}', so no conflict is ever over it (conflict targets of"
                f" {self.pkg.manifest.adaptation}: {', '.join(sorted(targets)) or 'none'})",
                loc,
            )
            return None
        return resolved

    def quantity(
        self, q: x.Quantity, where: tuple[PathItem, ...], refs: Iterable[x.Ref]
    ) -> x.Quantity | None:
        kinds = ("measurement", "cv", "param", "port", "name", "node")
        ref = next(r for r in refs if r.kind in kinds)
        loc = self.text_loc(where, ref.offset)
        pkg = self.pkg
        measurements = [ms.name for ms in pkg.measurements.measurements]
        cvs = [n for n, (_, a) in pkg.features.attributes.items() if a.kind == "cv"]
        if q.decided and not (q.kind == "cv" or (q.kind == "name" and q.name in cvs)):
            self.err(f"'decided' applies to a feature or a CV value, not to {q.name!r}", loc)
            return None
        match q.kind:
            case "name":
                alias = self.scenario.quantities.get(q.name)
                if alias is not None:
                    return self.alias(q.name, alias)
                if q.name in measurements:
                    return x.Quantity("measurement", q.name)
                if q.name in cvs:
                    return x.Quantity("cv", q.name, decided=q.decided)
                known = [*self.scenario.quantities, *measurements, *cvs]
                self.err(unknown_name("quantity", q.name, known), loc)
            case "measurement":
                if q.name in measurements:
                    return q
                self.err(unknown_name("measurement", q.name, measurements), loc)
            case "cv":
                if q.name in cvs:
                    return q
                self.err(unknown_name("CV attribute", q.name, cvs), loc)
            case "param":
                node, _, param = q.name.partition(".")
                comp = self.node(node, loc)
                if comp is not None and param not in comp.parameters:
                    self.err(unknown_name("parameter", param, comp.parameters, f" of {node}"), loc)
                return q
            case "implementation":
                self.node(q.name, loc)
                return q
            case "data":
                topic = self.topic(q.name, loc)
                if topic is not None:
                    return dataclasses.replace(q, topic=topic.removeprefix("data/"))
        return None

    def implementation(self, node: str, value: Any) -> Any:
        """A named implementation of the node's component (``dynamic``) -> what runs."""
        comp = self.pkg.system.component(node)
        if comp is None or not isinstance(value, str):
            return value
        impl = comp.implementations.get(value)
        if impl is None:
            return value
        return impl if isinstance(impl, str) else " ".join(impl.command)

    def alias(self, name: str, text: str) -> x.Quantity | None:
        where = ("quantities", name)
        parser = x._Parser(text)
        try:
            q = parser.quantity()
            if parser.peek().kind != "eof":
                raise parser.error("unexpected text after the quantity")
        except x.ExpectationError as e:
            self.err(f"quantity: {e.message}", self.text_loc(where, e.offset))
            return None
        if q.kind == "name":
            self.err(
                f"quantity '{name}': an alias names a measurement, cv, param or data path",
                self.doc.loc(*where),
            )
            return None
        return self.quantity(q, where, parser.refs)

    def text_loc(self, where: tuple[PathItem, ...], offset: int) -> Location:
        """The position of character ``offset`` of the string at ``where``."""
        loc = self.doc.loc(*where)
        node = self.doc.node(*where)
        if not isinstance(node, ScalarNode) or node.start_mark.line != node.end_mark.line:
            return loc
        if node.style in ('"', "'"):
            return Location(loc.file, loc.line, loc.col + 1 + offset)
        if node.style is None:
            return Location(loc.file, loc.line, loc.col + offset)
        return loc


def _bind_events(
    exp: x.Expectation, fm: Any, conflicts: Mapping[str, str] | None = None
) -> x.Expectation:
    """Feature names inside ``select(F)``/``deselect(F)`` patterns -> canonical names, and
    ``conflict(T)`` targets -> the names conflict reports carry (``conflicts``)."""

    def fix(ev: x.EventPattern) -> x.EventPattern:
        if not ev.args:
            return ev
        if ev.kind == "conflict" and conflicts:
            return x.EventPattern(ev.kind, (conflicts.get(ev.args[0], ev.args[0]),))
        if ev.kind not in ("select", "deselect"):
            return ev
        name = fm.resolve_name(ev.args[0]) or ev.args[0]
        return x.EventPattern(ev.kind, (name,))

    def fix_ref(ref: x.TimeRef) -> x.TimeRef:
        if ref.event is None:
            return ref
        return dataclasses.replace(ref, event=fix(ref.event))

    stop = exp.when.stop
    when = x.When(exp.when.mode, fix_ref(exp.when.start), None if stop is None else fix_ref(stop))
    if isinstance(exp, x.EventExpectation):
        return dataclasses.replace(exp, when=when, event=fix(exp.event))
    return dataclasses.replace(exp, when=when)


def swap_pairs(system: Any) -> tuple[tuple[str, str], ...]:
    """Ordered pairs of components with the same (non-empty) peers: those the run-time
    resolution swaps for each other (`rra_agent.core.plan.diff`'s criterion)."""
    peers = {c.name: peers_of(system, c.name) for c in system.components}
    return tuple(
        (a, b) for a in peers for b in peers if a != b and peers[a] and peers[a] == peers[b]
    )
