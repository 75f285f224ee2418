"""The resolution core: deployment/run-time resolution, topics, diff -> plan; the two packages."""

from __future__ import annotations

import inspect
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any

import msgspec
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from rra_agent.core.plan import (
    Plan,
    Rewire,
    SetImplementation,
    SetParameters,
    StartComponent,
    StopComponent,
    SwapComponent,
    diff,
    subscriptions,
    topic_of,
)
from rra_agent.core.resolution import resolve_deployment, resolve_runtime
from rra_agent.errors import ResolutionError, SelectionError
from rra_agent.models.features import (
    Attribute,
    Constraint,
    Feature,
    FeatureModel,
    Group,
    Implies,
    Ref,
)
from rra_agent.models.manifest import Manifest
from rra_agent.models.measurements import MeasurementsModel
from rra_agent.models.resolution import DeploymentResolutionModel, RuntimeResolutionModel
from rra_agent.models.system import Component, Connection, Parameter, Port, SystemModel

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ROOT / "scenarios"
YAML_FILES = {
    "rra.yaml": ("manifest", Manifest),
    "system.yaml": ("system", SystemModel),
    "deployment.yaml": ("deployment", DeploymentResolutionModel),
    "runtime.yaml": ("runtime", RuntimeResolutionModel),
    "measurements.yaml": ("measurements", MeasurementsModel),
}


# ---------------------------------------------------------------------------------------------
# Fixtures: the packages from file, the feature models built as Structs
# ---------------------------------------------------------------------------------------------
def load(package: str, file: str) -> Any:
    text = (SCENARIOS / package / file).read_text()
    return msgspec.convert(yaml.safe_load(text), YAML_FILES[file][1])


def feat(name: str, *groups: Group, **attrs: Any) -> Feature:
    return Feature(
        name=name,
        attributes=tuple(Attribute(name=k, value=v) for k, v in attrs.items()),
        groups=groups,
    )


def grp(kind: Any, *children: Feature) -> Group:
    return Group(kind=kind, children=children)


def object_storing_fm() -> FeatureModel:
    """scenarios/object_storing/features.uvl, as Structs."""
    latency = {"kind": "cim", "scale": ["Low", "High"]}
    root = feat(
        "ObjectStoring",
        grp(
            "mandatory",
            feat("Task", grp("alternative", feat("Detection"), feat("Manipulation"))),
            feat(
                "Environment",
                grp(
                    "alternative",
                    feat("Static"),
                    feat(
                        "Dynamic",
                        VelocityLimit={
                            "kind": "nfr",
                            "tag": "max",
                            "value": 0.5,
                            "unit": "m/s",
                            "constrains": "MaxVel",
                        },
                    ),
                ),
                binding="runtime",
            ),
            feat(
                "Communic. Channel",
                grp(
                    "alternative",
                    feat(
                        "ChannelA",
                        Latency={**latency, "value": "High"},
                        PowerConsump={"kind": "cim", "value": 0.5, "unit": "%/min"},
                    ),
                    feat(
                        "ChannelB",
                        Latency={**latency, "value": "Low"},
                        PowerConsump={"kind": "cim", "value": 1.2, "unit": "%/min"},
                    ),
                ),
                binding="runtime",
                alias="CommunicChannel",
            ),
            feat(
                "Motion Behavior",
                binding="runtime",
                alias="MotionBehavior",
                MaxVel={"kind": "cv", "lower": 0.4, "upper": 0.8, "unit": "m/s"},
            ),
        ),
        grp(
            "optional",
            feat("RackSize", grp("alternative", feat("Small"), feat("Large")), binding="runtime"),
            feat("Material", grp("alternative", feat("Fragile"), feat("Firm")), binding="runtime"),
        ),
        abstract=None,
    )
    rule = Constraint(expr=Implies(left=Ref(name="Material"), right=Ref(name="Manipulation")))
    return FeatureModel(root=root, constraints=(rule,), namespace="ObjectStoring")


def quadcopter_fm() -> FeatureModel:
    """scenarios/quadcopter/features.uvl, as Structs."""
    root = feat(
        "Quadcopter",
        grp(
            "mandatory",
            feat("Flight", grp("alternative", feat("Hover"), feat("Waypoints"), feat("Circle"))),
            feat(
                "Controller",
                grp(
                    "alternative",
                    feat("Standard", Motors={"kind": "cim", "value": 4}),
                    feat("Proploss", Motors={"kind": "cim", "value": 2}),
                ),
                binding="runtime",
            ),
        ),
        abstract=None,
    )
    return FeatureModel(root=root, namespace="Quadcopter")


OS_FM = object_storing_fm()
QC_FM = quadcopter_fm()
OS_TEMPLATE: SystemModel = load("object_storing", "system.yaml")
OS_DEPLOYMENT: DeploymentResolutionModel = load("object_storing", "deployment.yaml")
OS_RUNTIME: RuntimeResolutionModel = load("object_storing", "runtime.yaml")
QC_TEMPLATE: SystemModel = load("quadcopter", "system.yaml")
QC_DEPLOYMENT: DeploymentResolutionModel = load("quadcopter", "deployment.yaml")
QC_RUNTIME: RuntimeResolutionModel = load("quadcopter", "runtime.yaml")

MANIPULATION = {"arm_controller", "grasp_planner", "object_storing"}
RADIO_A = {
    ("radio_driver_a.rx", "radio_switch.radio_in"),
    ("radio_switch.radio_out", "radio_driver_a.tx"),
}
RADIO_B = {
    ("radio_driver_b.rx", "radio_switch.radio_in"),
    ("radio_switch.radio_out", "radio_driver_b.tx"),
}
BASE_RT = ("ChannelA", "Static", "MotionBehavior", "Small", "Firm")


def names(system: SystemModel) -> list[str]:
    return [c.name for c in system.components]


def keys(system: SystemModel) -> set[tuple[str, str]]:
    return {c.key for c in system.connections}


def touching(system: SystemModel, comps: Collection[str]) -> set[tuple[str, str]]:
    return {k for k in keys(system) if {e.split(".")[0] for e in k} & set(comps)}


def param(system: SystemModel, comp: str, name: str) -> Any:
    c = system.component(comp)
    assert c is not None, comp
    return c.parameters[name].value


def os_configured(*selection: str) -> SystemModel:
    return resolve_deployment(OS_TEMPLATE, OS_DEPLOYMENT, OS_FM, selection or ["Manipulation"])


def os_runtime(*selection: str, max_vel: float = 0.55, task: str = "Manipulation") -> SystemModel:
    return resolve_runtime(
        os_configured(task), OS_RUNTIME, OS_FM, selection or BASE_RT, {"MaxVel": max_vel}
    )


def qc_runtime(*selection: str, flight: str = "Circle") -> SystemModel:
    configured = resolve_deployment(QC_TEMPLATE, QC_DEPLOYMENT, QC_FM, [flight])
    return resolve_runtime(configured, QC_RUNTIME, QC_FM, selection, {})


# ---------------------------------------------------------------------------------------------
# The packages
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("package", ["object_storing", "quadcopter"])
@pytest.mark.parametrize("file", sorted(YAML_FILES))
def test_package_yaml_loads_and_names_its_schema(package: str, file: str) -> None:
    text = (SCENARIOS / package / file).read_text()
    schema = YAML_FILES[file][0]
    first = text.splitlines()[0]
    assert first == f"# yaml-language-server: $schema=../../schemas/{schema}.schema.json"
    assert isinstance(load(package, file), YAML_FILES[file][1])


def test_manifests_select_a_deployment_variant() -> None:
    assert load("object_storing", "rra.yaml").default_selection == ["Manipulation"]
    qc = load("quadcopter", "rra.yaml")
    assert qc.name == "quadcopter" and qc.default_selection == ["Circle"]


@pytest.mark.parametrize(("package", "built"), [("object_storing", OS_FM), ("quadcopter", QC_FM)])
def test_struct_feature_models_match_the_uvl_files(package: str, built: FeatureModel) -> None:
    uvl = pytest.importorskip("rra_agent.dsl.uvl")
    path = SCENARIOS / package / "features.uvl"
    first = next(iter(inspect.signature(uvl.load_uvl).parameters))
    fm = (
        uvl.load_uvl(path.read_text()) if first in ("text", "source", "src") else uvl.load_uvl(path)
    )
    assert list(fm.features) == list(built.features)
    assert fm.binding == built.binding
    assert fm.aliases == built.aliases
    assert {n: a.kind for n, (_, a) in fm.attributes.items()} == {
        n: a.kind for n, (_, a) in built.attributes.items()
    }
    template, deployment = load(package, "system.yaml"), load(package, "deployment.yaml")
    for variant in ("Manipulation", "Detection") if package == "object_storing" else ("Hover",):
        assert resolve_deployment(template, deployment, fm, [variant]) == resolve_deployment(
            template, deployment, built, [variant]
        )


@pytest.mark.parametrize("package", ["object_storing", "quadcopter"])
def test_packages_pass_cross_reference_validation(package: str, tmp_path: Path) -> None:
    pytest.importorskip("rra_agent.dsl.uvl")
    loader = pytest.importorskip("rra_agent.package.loader")
    validate = pytest.importorskip("rra_agent.package.validate")
    # The models of this package, without its adaptation model (checked with the rule DSL).
    for name in ("features.uvl", *YAML_FILES):
        text = (SCENARIOS / package / name).read_text()
        if name == "rra.yaml":
            text = text.replace("adaptation: adaptation.rra", "adaptation: null")
        (tmp_path / name).write_text(text)
    pkg = loader.load_package(tmp_path, validate=False)
    assert [str(e) for e in validate.validate_package(pkg)] == []


def test_every_port_type_is_a_declared_data_type() -> None:
    for package in ("object_storing", "quadcopter"):
        system: SystemModel = load(package, "system.yaml")
        types = {t.name for t in load(package, "measurements.yaml").data_types}
        used = {p.type for c in system.components for p in c.ports}
        assert used <= types, used - types


# ---------------------------------------------------------------------------------------------
# Deployment-time resolution
# ---------------------------------------------------------------------------------------------
def test_manipulation_includes_the_manipulation_components_and_connections() -> None:
    configured = os_configured("Manipulation")
    assert set(names(configured)) >= MANIPULATION
    manip = touching(OS_TEMPLATE, MANIPULATION)
    assert len(manip) == 7
    assert manip <= keys(configured)
    for c in configured.components:
        if c.name in MANIPULATION:
            assert not c.optional  # bound now: no longer a variation point
    assert all(not c.optional for c in configured.connections if c.key in manip)


def test_detection_has_no_manipulation_components() -> None:
    configured = os_configured("Detection")
    assert not MANIPULATION & set(names(configured))
    assert not touching(configured, MANIPULATION)
    stable = {c.key for c in OS_TEMPLATE.connections if not c.optional}
    assert stable <= keys(configured)


def test_run_time_variation_points_are_kept() -> None:
    for task in ("Detection", "Manipulation"):
        configured = os_configured(task)
        for name in ("radio_driver_a", "radio_driver_b"):
            c = configured.component(name)
            assert c is not None and c.optional and c.binding == "runtime"
        radio = {c.key: c for c in configured.connections if c.key in RADIO_A | RADIO_B}
        assert set(radio) == RADIO_A | RADIO_B
        assert all(c.optional and c.binding == "runtime" for c in radio.values())
        # Only run-time variation points are left.
        parts = [*configured.components, *configured.connections]
        assert all(p.binding == "runtime" for p in parts if p.optional)


def test_deployment_output_is_deterministic_and_in_template_order() -> None:
    a = resolve_deployment(OS_TEMPLATE, OS_DEPLOYMENT, OS_FM, ["Manipulation", "ChannelA"])
    b = resolve_deployment(OS_TEMPLATE, OS_DEPLOYMENT, OS_FM, ("ChannelA", "Manipulation"))
    assert a == b
    assert names(a) == names(OS_TEMPLATE)
    template_order = [c.key for c in OS_TEMPLATE.connections]
    assert [c.key for c in a.connections] == [k for k in template_order if k in keys(a)]


def test_quadcopter_flight_sets_the_trajectory_mode() -> None:
    for flight, mode in (("Hover", "hover"), ("Waypoints", "waypoints"), ("Circle", "circle")):
        configured = resolve_deployment(QC_TEMPLATE, QC_DEPLOYMENT, QC_FM, [flight])
        assert param(configured, "trajectory_generator", "mode") == mode
        proploss = configured.component("proploss_controller")
        assert proploss is not None and proploss.optional and proploss.binding == "runtime"


def dep_model(**features: list[dict]) -> DeploymentResolutionModel:
    return msgspec.convert({"features": features}, DeploymentResolutionModel)


def rt_model(**features: list[dict]) -> RuntimeResolutionModel:
    return msgspec.convert({"features": features}, RuntimeResolutionModel)


def deploy_error(model: DeploymentResolutionModel, *selection: str) -> str:
    with pytest.raises(ResolutionError) as info:
        resolve_deployment(OS_TEMPLATE, model, OS_FM, selection)
    return str(info.value)


def sp(comp: str, name: str, value: Any) -> dict:
    return {"set_parameter": {"component": comp, "parameter": name, "value": value}}


def test_two_features_setting_one_parameter_differently_conflict() -> None:
    msg = deploy_error(
        dep_model(
            Detection=[sp("local_navigation", "max_vel", 0.5)],
            Manipulation=[sp("local_navigation", "max_vel", 0.7)],
        ),
        "Detection",
        "Manipulation",
    )
    assert "conflict" in msg
    assert "'Detection' (set_parameter local_navigation.max_vel = 0.5)" in msg
    assert "'Manipulation' (set_parameter local_navigation.max_vel = 0.7)" in msg


def test_two_features_setting_the_same_value_agree() -> None:
    model = dep_model(
        Detection=[sp("local_navigation", "max_vel", 0.5)],
        Manipulation=[sp("local_navigation", "max_vel", 0.5)],
    )
    out = resolve_deployment(OS_TEMPLATE, model, OS_FM, ["Detection", "Manipulation"])
    assert param(out, "local_navigation", "max_vel") == 0.5


def test_a_boolean_is_not_the_number_one() -> None:
    template = msgspec.structs.replace(
        OS_TEMPLATE,
        components=[
            *OS_TEMPLATE.components,
            Component(
                name="x", implementation="m.X", parameters={"p": Parameter(type="list", value=[])}
            ),
        ],
    )
    model = dep_model(Detection=[sp("x", "p", [1])], Manipulation=[sp("x", "p", [True])])
    with pytest.raises(ResolutionError, match="conflict"):
        resolve_deployment(template, model, OS_FM, ["Detection", "Manipulation"])


def test_two_implementations_for_one_component_conflict() -> None:
    def si(impl: str) -> dict:
        return {"set_implementation": {"component": "local_navigation", "implementation": impl}}

    msg = deploy_error(
        dep_model(Detection=[si("static")], Manipulation=[si("dynamic")]),
        "Detection",
        "Manipulation",
    )
    assert "'Detection' (set_implementation local_navigation -> static)" in msg
    assert "'Manipulation' (set_implementation local_navigation -> dynamic)" in msg


def test_include_and_remove_of_one_component_conflict() -> None:
    msg = deploy_error(
        dep_model(
            Detection=[{"remove_component": "arm_controller"}],
            Manipulation=[{"include_component": "arm_controller"}],
        ),
        "Manipulation",
        "Detection",
    )
    assert "'Detection' (remove_component arm_controller)" in msg
    assert "'Manipulation' (include_component arm_controller)" in msg


def test_add_and_remove_of_one_connection_conflict() -> None:
    ref = {"from": "task_manager.store", "to": "object_storing.request"}
    msg = deploy_error(
        dep_model(
            Detection=[{"remove_connection": ref}],
            Manipulation=[{"include_component": "object_storing"}, {"add_connection": ref}],
        ),
        "Detection",
        "Manipulation",
    )
    assert "'Detection' (remove_connection task_manager.store -> object_storing.request)" in msg
    assert "'Manipulation' (add_connection task_manager.store -> object_storing.request)" in msg


@pytest.mark.parametrize(
    ("transformations", "needle"),
    [
        ([{"include_component": "gripper"}], "no component 'gripper'"),
        ([{"remove_component": "gripper"}], "no component 'gripper'"),
        (
            [sp("arm_controller", "grip_force", 3.0)],
            "'arm_controller' is not included",
        ),
        ([sp("local_navigation", "max_speed", 0.3)], "no parameter 'max_speed'"),
        ([sp("local_navigation", "max_vel", "fast")], "'fast' is not of type float"),
        (
            [{"set_implementation": {"component": "local_navigation", "implementation": "x"}}],
            "no implementation 'x' (known: dynamic, static)",
        ),
        (
            [
                {
                    "set_parameter": {
                        "component": "local_navigation",
                        "parameter": "max_vel",
                        "from_attribute": "MaxVel",
                    }
                }
            ],
            "from_attribute is only allowed at run time",
        ),
        ([{"include_component": "radio_driver_a"}], "is bound at run time"),
        ([{"include_component": "task_manager"}], "'task_manager' is not optional"),
        (
            [{"add_connection": {"from": "laser_scanner.scan", "to": "object_detector.request"}}],
            "connection is not declared",
        ),
        (
            [{"add_connection": {"from": "task_manager.store", "to": "object_storing.request"}}],
            "'object_storing' is not included",
        ),
        (
            [{"remove_connection": {"from": "laser_scanner.scan", "to": "robot_driver.cmd_vel"}}],
            "no such connection",
        ),
    ],
)
def test_referencing_something_absent_is_an_error(transformations: list, needle: str) -> None:
    msg = deploy_error(dep_model(Detection=transformations), "Detection")
    assert needle in msg
    assert "'Detection'" in msg


def test_a_change_to_a_removed_component_names_the_remover() -> None:
    msg = deploy_error(
        dep_model(
            Detection=[{"remove_component": "object_detector"}],
            Manipulation=[sp("object_detector", "subsampling", 3)],
        ),
        "Detection",
        "Manipulation",
    )
    assert "'Manipulation' (set_parameter object_detector.subsampling = 3)" in msg
    assert "removed by feature 'Detection' (remove_component object_detector)" in msg


def test_every_problem_is_reported_at_once() -> None:
    msg = deploy_error(
        dep_model(Detection=[{"include_component": "a"}, {"include_component": "b"}]), "Detection"
    )
    assert "2 problems" in msg and "'a'" in msg and "'b'" in msg


def test_removing_a_component_removes_its_connections() -> None:
    model = dep_model(Detection=[{"remove_component": "rgbd_camera"}])
    out = resolve_deployment(OS_TEMPLATE, model, OS_FM, ["Detection"])
    assert "rgbd_camera" not in names(out)
    assert not touching(out, {"rgbd_camera"})


def test_unknown_features_are_errors() -> None:
    with pytest.raises(SelectionError, match="Teleport"):
        resolve_deployment(OS_TEMPLATE, OS_DEPLOYMENT, OS_FM, ["Teleport"])
    assert "unknown feature 'Fly'" in deploy_error(dep_model(Fly=[]), "Detection")
    msg = deploy_error(dep_model(ChannelA=[]), "Detection")
    assert "feature 'ChannelA', which is bound at run time" in msg


def test_a_feature_is_found_by_its_alias() -> None:
    model = dep_model(Detection=[])
    out = resolve_deployment(OS_TEMPLATE, model, OS_FM, ["Detection", "CommunicChannel"])
    assert out == os_configured("Detection")


# ---------------------------------------------------------------------------------------------
# Run-time resolution
# ---------------------------------------------------------------------------------------------
def test_channel_a_and_b_differ_exactly_by_the_radio_driver_and_its_links() -> None:
    a = os_runtime("ChannelA", "Static", "MotionBehavior")
    b = os_runtime("ChannelB", "Static", "MotionBehavior")
    assert set(names(a)) - set(names(b)) == {"radio_driver_a"}
    assert set(names(b)) - set(names(a)) == {"radio_driver_b"}
    assert keys(a) - keys(b) == RADIO_A
    assert keys(b) - keys(a) == RADIO_B
    common = set(names(a)) & set(names(b))
    assert all(a.component(n) == b.component(n) for n in common)


def test_unselected_run_time_variation_points_are_absent() -> None:
    out = os_runtime("Static", "MotionBehavior")
    assert not {"radio_driver_a", "radio_driver_b"} & set(names(out))
    assert not keys(out) & (RADIO_A | RADIO_B)
    # Everything left runs: optional parts are there only because a feature launched them.
    a = os_runtime()
    assert [c.name for c in a.components if c.optional] == ["radio_driver_a"]
    assert {c.key for c in a.connections if c.optional} == RADIO_A


def test_max_vel_lands_in_local_navigation() -> None:
    assert param(os_runtime(max_vel=0.55), "local_navigation", "max_vel") == 0.55
    assert param(os_runtime(max_vel=0.8), "local_navigation", "max_vel") == 0.8
    # Without Motion Behavior selected the deployed value stays.
    assert param(os_runtime("ChannelA", "Static"), "local_navigation", "max_vel") == 0.6


def test_a_missing_cv_value_is_an_error() -> None:
    with pytest.raises(ResolutionError, match="no current value for 'MaxVel'"):
        resolve_runtime(os_configured(), OS_RUNTIME, OS_FM, ["Motion Behavior"], {})


def test_from_attribute_needs_a_cv_attribute() -> None:
    model = rt_model(
        Static=[
            {
                "set_parameter": {
                    "component": "local_navigation",
                    "parameter": "max_vel",
                    "from_attribute": "VelocityLimit",
                }
            }
        ]
    )
    with pytest.raises(ResolutionError, match="'VelocityLimit' is not a Continuous Variability"):
        resolve_runtime(os_configured(), model, OS_FM, ["Static"], {"VelocityLimit": 0.5})


def test_environment_sets_the_obstacle_avoidance() -> None:
    static, dynamic = os_runtime("Static"), os_runtime("Dynamic")
    assert static.component("local_navigation").implementation.endswith(".VfhLocalNavigation")  # type: ignore[union-attr]
    assert dynamic.component("local_navigation").implementation.endswith(".DwaLocalNavigation")  # type: ignore[union-attr]
    assert param(static, "local_navigation", "obstacle_avoidance") == "vfh"
    assert param(dynamic, "local_navigation", "obstacle_avoidance") == "dwa"


def test_rack_size_and_material_configure_detector_and_arm() -> None:
    small, large = os_runtime("Small", "Fragile"), os_runtime("Large", "Firm")
    assert param(small, "object_detector", "subsampling") == 1
    assert param(large, "object_detector", "subsampling") == 4
    assert param(small, "object_detector", "roi") != param(large, "object_detector", "roi")
    assert param(small, "arm_controller", "grip_force") < param(
        large, "arm_controller", "grip_force"
    )
    assert param(small, "arm_controller", "approach_speed") == 0.05


def test_material_without_manipulation_is_an_error() -> None:
    with pytest.raises(
        ResolutionError,
        match=r"'Fragile'.*'arm_controller' is not in the deployment-time configured",
    ):
        os_runtime("Fragile", task="Detection")


def test_run_time_conflicts_name_both_features() -> None:
    with pytest.raises(ResolutionError) as info:
        os_runtime("Static", "Dynamic")
    msg = str(info.value)
    assert "'Static' (set_implementation local_navigation -> static)" in msg
    assert "'Dynamic' (set_implementation local_navigation -> dynamic)" in msg
    assert "'Static' (set_parameter local_navigation.obstacle_avoidance = 'vfh')" in msg


def test_run_time_input_must_be_deployment_configured() -> None:
    with pytest.raises(ResolutionError, match="deployment-time variation point"):
        resolve_runtime(OS_TEMPLATE, OS_RUNTIME, OS_FM, ["Static"], {})


def test_quadcopter_standard_runs_the_deployed_architecture() -> None:
    out = qc_runtime("Standard")
    assert names(out) == ["trajectory_generator", "estimator", "controller", "vehicle_simulator"]
    assert not touching(out, {"proploss_controller"})
    assert qc_runtime() == out  # Standard transforms nothing


def test_quadcopter_proploss_swaps_the_controller() -> None:
    out = qc_runtime("Proploss")
    assert "controller" not in names(out)
    assert "proploss_controller" in names(out)
    assert touching(out, {"proploss_controller"}) == {
        ("estimator.estimate", "proploss_controller.estimate"),
        ("trajectory_generator.setpoint", "proploss_controller.setpoint"),
        ("vehicle_simulator.telemetry", "proploss_controller.telemetry"),
        ("proploss_controller.motor_cmd", "vehicle_simulator.motor_cmd"),
    }
    assert subscriptions(out)[("vehicle_simulator", "motor_cmd")] == (
        "proploss_controller/motor_cmd",
    )


# ---------------------------------------------------------------------------------------------
# Topics
# ---------------------------------------------------------------------------------------------
def test_topic_of_a_publisher() -> None:
    assert topic_of(QC_TEMPLATE, "controller", "motor_cmd") == "controller/motor_cmd"
    named = SystemModel(
        system="s",
        components=[
            Component(
                name="c",
                implementation="m.C",
                ports=[Port(name="out", direction="publish", type="T", topic="shared/out")],
            )
        ],
    )
    assert topic_of(named, "c", "out") == "shared/out"
    with pytest.raises(ResolutionError, match="does not publish"):
        topic_of(QC_TEMPLATE, "controller", "estimate")
    with pytest.raises(ResolutionError, match="no port 'x'"):
        topic_of(QC_TEMPLATE, "controller", "x")
    with pytest.raises(ResolutionError, match="no component 'x'"):
        topic_of(QC_TEMPLATE, "x", "y")


def test_subscriptions_list_every_subscriber_port_with_sorted_topics() -> None:
    subs = subscriptions(os_configured())
    assert subs[("radio_switch", "radio_in")] == ("radio_driver_a/rx", "radio_driver_b/rx")
    assert subs[("local_navigation", "scan")] == ("laser_scanner/scan",)
    standard = subscriptions(qc_runtime("Standard"))
    assert standard[("vehicle_simulator", "motor_cmd")] == ("controller/motor_cmd",)
    lonely = SystemModel(
        system="s",
        components=[
            Component(
                name="c",
                implementation="m.C",
                ports=[Port(name="in", direction="subscribe", type="T")],
            )
        ],
    )
    assert subscriptions(lonely) == {("c", "in"): ()}
    dangling = msgspec.structs.replace(
        lonely, connections=[Connection(source="gone.out", target="c.in")]
    )
    with pytest.raises(ResolutionError, match="no component 'gone'"):
        subscriptions(dangling)


# ---------------------------------------------------------------------------------------------
# Diff
# ---------------------------------------------------------------------------------------------
def test_plan_is_empty_for_equal_models() -> None:
    for model in (os_runtime(), qc_runtime("Proploss"), os_configured(), QC_TEMPLATE):
        assert diff(model, model).empty
        copy = msgspec.convert(msgspec.to_builtins(model), SystemModel)
        assert diff(model, copy) == Plan()


def test_proploss_is_a_swap_plus_the_rewire_of_the_simulator_input() -> None:
    standard, proploss = qc_runtime("Standard"), qc_runtime("Proploss")
    plan = diff(standard, proploss)
    assert plan.steps == (
        SwapComponent(
            component="controller",
            replacement="proploss_controller",
            definition=proploss.component("proploss_controller"),  # type: ignore[arg-type]
            inputs={
                "estimate": ("estimator/estimate",),
                "setpoint": ("trajectory_generator/setpoint",),
                "telemetry": ("vehicle_simulator/telemetry",),
            },
            outputs={"motor_cmd": "proploss_controller/motor_cmd"},
        ),
        Rewire(
            component="vehicle_simulator",
            port="motor_cmd",
            topics=("proploss_controller/motor_cmd",),
        ),
    )
    back = diff(proploss, standard)
    assert [type(s) for s in back.steps] == [SwapComponent, Rewire]
    assert back.steps[0].component == "proploss_controller"
    assert back.steps[1] == Rewire(
        component="vehicle_simulator", port="motor_cmd", topics=("controller/motor_cmd",)
    )


def test_channel_switch_swaps_the_radio_driver() -> None:
    plan = diff(os_runtime("ChannelA"), os_runtime("ChannelB"))
    assert [(type(s), s.component) for s in plan.steps] == [
        (SwapComponent, "radio_driver_a"),
        (Rewire, "radio_switch"),
    ]
    assert plan.started == ("radio_driver_b",) and plan.stopped == ("radio_driver_a",)
    assert plan.steps[1] == Rewire(
        component="radio_switch", port="radio_in", topics=("radio_driver_b/rx",)
    )


def test_launching_and_stopping_a_variation_point() -> None:
    none, a = os_runtime("Static"), os_runtime("Static", "ChannelA")
    plan = diff(none, a)
    assert plan.steps == (
        StartComponent(
            component="radio_driver_a",
            definition=a.component("radio_driver_a"),  # type: ignore[arg-type]
            inputs={"tx": ("radio_switch/radio_out",)},
            outputs={"rx": "radio_driver_a/rx"},
        ),
        Rewire(component="radio_switch", port="radio_in", topics=("radio_driver_a/rx",)),
    )
    assert diff(a, none).steps == (
        Rewire(component="radio_switch", port="radio_in", topics=()),
        StopComponent(component="radio_driver_a"),
    )


def test_implementation_change_is_a_restart_with_the_new_definition() -> None:
    static, dynamic = os_runtime("Static"), os_runtime("Dynamic")
    plan = diff(static, dynamic)
    (step,) = plan.steps
    assert isinstance(step, SetImplementation)
    assert step.component == "local_navigation"
    assert step.implementation == "rra_agent.nodes.object_storing.DwaLocalNavigation"
    assert step.previous == "rra_agent.nodes.object_storing.VfhLocalNavigation"
    assert step.definition == dynamic.component("local_navigation")
    assert step.definition.parameters["obstacle_avoidance"].value == "dwa"
    assert step.inputs["scan"] == ("laser_scanner/scan",)
    assert step.outputs == {"cmd_vel": "local_navigation/cmd_vel"}


def test_parameter_changes_are_one_step_per_component() -> None:
    plan = diff(os_runtime(max_vel=0.5), os_runtime(max_vel=0.7))
    assert plan.steps == (SetParameters(component="local_navigation", values={"max_vel": 0.7}),)
    small = os_runtime("ChannelA", "Static", "MotionBehavior", "Small", "Firm")
    large = os_runtime("ChannelA", "Static", "MotionBehavior", "Large", "Fragile")
    steps = diff(small, large).steps
    assert [s.component for s in steps] == ["object_detector", "arm_controller"]  # target order
    assert steps[0].values == {  # type: ignore[union-attr]
        "subsampling": 4,
        "roi": [-0.8, -0.6, 0.3, 0.8, 0.6, 2.2],
    }


def test_steps_come_in_canonical_order() -> None:
    current = os_runtime("ChannelA", "Static", "MotionBehavior", "Small", "Firm", max_vel=0.5)
    target = os_runtime("ChannelB", "Dynamic", "MotionBehavior", "Large", "Firm", max_vel=0.7)
    extra = Component(
        name="logger",
        implementation="m.Logger",
        ports=[Port(name="scan", direction="subscribe", type="LaserScan")],
    )
    current = msgspec.structs.replace(current, components=[*current.components, extra])
    target = msgspec.structs.replace(
        target,
        components=[msgspec.structs.replace(extra, name="recorder"), *target.components],
        connections=[
            *target.connections,
            Connection(source="laser_scanner.scan", target="recorder.scan"),
        ],
    )
    plan = diff(current, target)
    assert [type(s).__name__ for s in plan.steps] == [
        "StartComponent",
        "SwapComponent",
        "SetImplementation",
        "SetParameters",
        "Rewire",
        "StopComponent",
    ]
    assert plan.started == ("recorder", "radio_driver_b")
    assert plan.stopped == ("radio_driver_a", "logger")


def lone(name: str, *ports: Port) -> Component:
    return Component(name=name, implementation=f"m.{name.title()}", ports=list(ports))


def test_only_components_with_the_same_peers_are_swapped() -> None:
    base = qc_runtime("Standard")
    isolated = msgspec.structs.replace(base, components=[*base.components, lone("x")])
    other = msgspec.structs.replace(base, components=[*base.components, lone("y")])
    plan = diff(isolated, other)  # no peers at all: nothing says y replaces x
    assert [(type(s), s.component) for s in plan.steps] == [
        (StartComponent, "y"),
        (StopComponent, "x"),
    ]
    # proploss_controller without its estimate input is not a replacement of controller.
    proploss = qc_runtime("Proploss")
    partial = msgspec.structs.replace(
        proploss,
        connections=[c for c in proploss.connections if c.target != "proploss_controller.estimate"],
    )
    kinds = [type(s) for s in diff(base, partial).steps]
    assert SwapComponent not in kinds
    assert kinds == [StartComponent, Rewire, StopComponent]


def test_topics_are_sorted_whatever_the_connection_order() -> None:
    pubs = [lone(f"p{i}", Port(name="out", direction="publish", type="T")) for i in range(12)]
    sub = lone("sub", Port(name="in", direction="subscribe", type="T"))
    conns = [Connection(source=f"{p.name}.out", target="sub.in") for p in reversed(pubs)]
    system = SystemModel(system="s", components=[*pubs, sub], connections=conns)
    topics = subscriptions(system)[("sub", "in")]
    assert topics == tuple(sorted(f"p{i}/out" for i in range(12)))


def test_plans_round_trip_through_msgpack() -> None:
    plan = diff(qc_runtime("Standard"), qc_runtime("Proploss"))
    assert msgspec.msgpack.decode(msgspec.msgpack.encode(plan), type=Plan) == plan
    tags = [s["op"] for s in msgspec.to_builtins(plan)["steps"]]
    assert tags == ["swap_component", "rewire"]


def test_diff_needs_one_system() -> None:
    with pytest.raises(ResolutionError, match="cannot diff"):
        diff(QC_TEMPLATE, OS_TEMPLATE)


# ---------------------------------------------------------------------------------------------
# Properties: applying a plan to the running view of `current` yields that of `target`
# ---------------------------------------------------------------------------------------------
View = dict[str, tuple[Any, dict[str, Any], dict[str, tuple[str, ...]]]]


def view(system: SystemModel) -> View:
    """What runs, computed independently of the module under test."""
    topic = {
        f"{c.name}.{p.name}": p.topic or f"{c.name}/{p.name}"
        for c in system.components
        for p in c.ports
    }
    inputs: dict[str, dict[str, set[str]]] = {
        c.name: {p.name: set() for p in c.ports if p.direction == "subscribe"}
        for c in system.components
    }
    for conn in system.connections:
        comp, port = conn.target.split(".")
        inputs[comp][port].add(topic[conn.source])
    return {
        c.name: (
            c.implementation,
            {k: p.value for k, p in c.parameters.items()},
            {p: tuple(sorted(t)) for p, t in inputs[c.name].items()},
        )
        for c in system.components
    }


def apply(running: View, plan: Plan) -> View:
    out = dict(running)

    def launch(name: str, d: Component, inputs: Mapping[str, tuple[str, ...]]) -> None:
        out[name] = (d.implementation, {k: p.value for k, p in d.parameters.items()}, dict(inputs))

    for s in plan.steps:
        match s:
            case StartComponent() | SetImplementation():
                launch(s.component, s.definition, s.inputs)
            case SwapComponent():
                del out[s.component]
                launch(s.replacement, s.definition, s.inputs)
            case StopComponent():
                del out[s.component]
            case SetParameters():
                impl, params, inputs = out[s.component]
                out[s.component] = (impl, {**params, **s.values}, inputs)
            case Rewire():
                impl, params, inputs = out[s.component]
                out[s.component] = (impl, params, {**inputs, s.port: s.topics})
    return out


RANK = {
    StartComponent: 0,
    SwapComponent: 1,
    SetImplementation: 2,
    SetParameters: 3,
    Rewire: 4,
    StopComponent: 5,
}


def check_plan(a: SystemModel, b: SystemModel) -> Plan:
    plan = diff(a, b)
    assert apply(view(a), plan) == view(b)
    assert plan.empty == (view(a) == view(b))
    assert set(plan.started) == set(names(b)) - set(names(a))
    assert set(plan.stopped) == set(names(a)) - set(names(b))
    ranks = [RANK[type(s)] for s in plan.steps]
    assert ranks == sorted(ranks)
    assert diff(b, b).empty
    return plan


@st.composite
def variants(draw: st.DrawFn, template: SystemModel = OS_TEMPLATE) -> SystemModel:
    """A random running configuration of the template's components."""
    comps = []
    for c in template.components:
        if not draw(st.booleans()):
            continue
        impl = draw(st.sampled_from([c.implementation, *c.implementations.values()]))
        params = {
            k: msgspec.structs.replace(p, value=draw(st.sampled_from([p.value, 0.3, 0.7])))
            if p.type == "float"
            else p
            for k, p in c.parameters.items()
        }
        comps.append(
            msgspec.structs.replace(
                c, implementation=impl, parameters=params, optional=False, binding="deployment"
            )
        )
    present = {c.name for c in comps}
    conns = [
        Connection(source=k.source, target=k.target)
        for k in template.connections
        if {e.split(".")[0] for e in k.key} <= present and draw(st.booleans())
    ]
    return SystemModel(system=template.system, components=comps, connections=conns)


@settings(max_examples=200, deadline=None)
@given(variants(), variants())
def test_applying_the_plan_reaches_the_target(a: SystemModel, b: SystemModel) -> None:
    check_plan(a, b)


@settings(max_examples=50, deadline=None)
@given(variants())
def test_a_configuration_against_itself_is_an_empty_plan(a: SystemModel) -> None:
    assert check_plan(a, a).empty


@st.composite
def runtime_selections(draw: st.DrawFn) -> tuple[list[str], float]:
    pick = [
        draw(st.sampled_from(group))
        for group in (
            ["", "ChannelA", "ChannelB"],
            ["", "Static", "Dynamic"],
            ["", "Small", "Large"],
        )
    ]
    pick += draw(st.sampled_from([[], ["Fragile"], ["Firm"]]))
    pick += draw(st.sampled_from([[], ["MotionBehavior"]]))
    return [p for p in pick if p], draw(st.sampled_from([0.4, 0.55, 0.8]))


@settings(max_examples=100, deadline=None)
@given(runtime_selections(), runtime_selections())
def test_run_time_reconfigurations_reach_their_target(
    s1: tuple[list[str], float], s2: tuple[list[str], float]
) -> None:
    a, b = (
        os_runtime(*s1[0] or ["Static"], max_vel=s1[1]),
        os_runtime(*s2[0] or ["Static"], max_vel=s2[1]),
    )
    plan = check_plan(a, b)
    assert plan.empty == (a == b)
    radio = {"radio_driver_a", "radio_driver_b"}
    if len(set(names(a)) & radio) == len(set(names(b)) & radio) == 1 and a.component(
        "radio_driver_a"
    ) != b.component("radio_driver_a"):
        assert [type(s) for s in plan.steps].count(SwapComponent) == 1
