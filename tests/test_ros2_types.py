"""Message and service types from rosbags' offline stores: CDR round trips (property-based)
for the types rra-agent uses, rosidl's type hashes, custom interface files, and bad input
refused with `FieldError` / `DecodeError` / `UnknownType` only."""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rra_agent.ros2.errors import BadName, DecodeError, FieldError, UnknownType
from rra_agent.ros2.names import NO_TYPE_HASH
from rra_agent.ros2.params import from_value, to_value
from rra_agent.ros2.types import TypeRegistry, get_field

CUSTOM = Path(__file__).parent / "data" / "ros2" / "custom"
REG = TypeRegistry()

f32 = st.floats(width=32, allow_nan=False)
f64 = st.floats(allow_nan=False)
text = st.text(st.characters(blacklist_categories=["Cs"], blacklist_characters="\x00"),
               max_size=20)
i64 = st.integers(-(2**63), 2**63 - 1)
stamps = st.fixed_dictionaries({"sec": st.integers(-(2**31), 2**31 - 1),
                                "nanosec": st.integers(0, 2**32 - 1)})
headers = st.fixed_dictionaries({"stamp": stamps, "frame_id": text})
batteries = st.fixed_dictionaries({
    "header": headers, "voltage": f32, "temperature": f32, "current": f32, "charge": f32,
    "capacity": f32, "design_capacity": f32, "percentage": f32,
    "power_supply_status": st.integers(0, 255), "power_supply_health": st.integers(0, 255),
    "power_supply_technology": st.integers(0, 255), "present": st.booleans(),
    "cell_voltage": st.lists(f32, max_size=6), "cell_temperature": st.lists(f32, max_size=6),
    "location": text, "serial_number": text,
})
param_values = st.one_of(
    st.none(), st.booleans(), i64, f64, text, st.binary(max_size=8),
    st.lists(st.booleans(), min_size=1, max_size=4), st.lists(i64, min_size=1, max_size=4),
    st.lists(f64, min_size=1, max_size=4), st.lists(text, min_size=1, max_size=4),
)
parameters = st.lists(st.tuples(text, param_values), max_size=4)
transitions = st.fixed_dictionaries({"id": st.integers(0, 255), "label": text})


def full(ros_type: str, value: dict[str, Any]) -> dict[str, Any]:
    """``value`` with every field the type has (what decode returns)."""
    return REG.decode(ros_type, REG.encode(ros_type, value))


def round_trip(ros_type: str, value: dict[str, Any]) -> None:
    data = REG.encode(ros_type, value)
    assert data[:4] == b"\x00\x01\x00\x00"
    assert REG.decode(ros_type, data) == value
    # and the bytes are rosbags' own serialization of the same message
    obj = REG.store.deserialize_cdr(data, ros_type)
    assert bytes(REG.store.serialize_cdr(obj, ros_type)) == data


@settings(deadline=None)
@given(text)
def test_string_round_trip(s: str) -> None:
    round_trip("std_msgs/msg/String", {"data": s})


@settings(max_examples=60, deadline=None)
@given(batteries)
def test_battery_state_round_trip(msg: dict[str, Any]) -> None:
    round_trip("sensor_msgs/msg/BatteryState", msg)


@settings(max_examples=60, deadline=None)
@given(parameters)
def test_set_parameters_round_trip(params: list[tuple[str, Any]]) -> None:
    req = {"parameters": [{"name": n, "value": to_value(v)} for n, v in params]}
    back = REG.decode("rcl_interfaces/srv/SetParameters_Request",
                      REG.encode("rcl_interfaces/srv/SetParameters_Request", req))
    assert [(p["name"], from_value(p["value"])) for p in back["parameters"]] == params
    resp = {"results": [{"successful": i % 2 == 0, "reason": n} for i, (n, _) in
                        enumerate(params)]}
    round_trip("rcl_interfaces/srv/SetParameters_Response", resp)


@settings(max_examples=60, deadline=None)
@given(st.lists(text, max_size=4), st.lists(param_values, max_size=4))
def test_get_parameters_round_trip(names: list[str], values: list[Any]) -> None:
    round_trip("rcl_interfaces/srv/GetParameters_Request", {"names": names})
    resp = {"values": [to_value(v) for v in values]}
    back = REG.decode("rcl_interfaces/srv/GetParameters_Response",
                      REG.encode("rcl_interfaces/srv/GetParameters_Response", resp))
    assert [from_value(v) for v in back["values"]] == values


@settings(deadline=None)
@given(transitions, st.booleans())
def test_change_state_round_trip(transition: dict[str, Any], success: bool) -> None:
    round_trip("lifecycle_msgs/srv/ChangeState_Request", {"transition": transition})
    round_trip("lifecycle_msgs/srv/ChangeState_Response", {"success": success})


def test_missing_fields_take_zero_values() -> None:
    msg = full("sensor_msgs/msg/BatteryState", {"percentage": 0.5})
    assert msg["percentage"] == 0.5 and msg["voltage"] == 0.0 and msg["present"] is False
    assert msg["cell_voltage"] == [] and msg["header"] == {
        "stamp": {"sec": 0, "nanosec": 0}, "frame_id": ""}


@pytest.mark.parametrize(("ros_type", "want"), [
    # rmw_zenoh's design.md examples and what zenoh-ros2-sdk keyed BatteryState with
    ("std_msgs/msg/String",
     "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"),
    ("sensor_msgs/msg/BatteryState",
     "RIHS01_4bee5dfce981c98faa6828b868307a0a73f992ed0789f374ee96c8f840e69741"),
])
def test_type_hashes_are_rosidls(ros_type: str, want: str) -> None:
    assert REG.type_hash(ros_type) == want


def test_service_hashes_are_rosidls_char_read_as_uint8() -> None:
    reg = TypeRegistry()
    reg.register_srv("example_interfaces/srv/AddTwoInts", "int64 a\nint64 b\n---\nint64 sum\n")
    assert reg.type_hash("example_interfaces/srv/AddTwoInts") == (
        "RIHS01_e118de6bf5eeb66a2491b5bda11202e7b68f198d6f67922cf30364858239c81a")


def test_service_hashes_agree_with_zenoh_ros2_sdk() -> None:
    utils = pytest.importorskip("zenoh_ros2_sdk.utils")
    for srv in ("rcl_interfaces/srv/SetParameters", "lifecycle_msgs/srv/ChangeState"):
        deps = {}
        for part in ("Request", "Response"):
            deps.update({d: REG.msg_text(d) for d in REG.dependencies(f"{srv}_{part}")})
        theirs = utils.compute_service_type_hash(
            srv, REG.msg_text(f"{srv}_Request"), REG.msg_text(f"{srv}_Response"), deps)
        assert REG.type_hash(srv) == theirs


def test_humble_has_no_type_hashes() -> None:
    assert TypeRegistry("humble").type_hash("std_msgs/msg/String") == NO_TYPE_HASH


def test_an_unknown_distribution_or_type_is_one_clear_error() -> None:
    with pytest.raises(UnknownType, match="unknown ROS 2 distribution 'melodic'"):
        TypeRegistry("melodic")
    with pytest.raises(UnknownType, match="unknown ROS 2 type 'nav_msgs/msg/Nope'"):
        REG.encode("nav_msgs/msg/Nope", {})
    with pytest.raises(BadName):
        REG.require("not a type")
    with pytest.raises(UnknownType, match="service"):
        REG.require_service("std_srvs/srv/Nope")


@pytest.mark.parametrize(("value", "match"), [
    ({"percentage": "full"}, "percentage: expected a number"),
    ({"nope": 1}, "nope: no such field in sensor_msgs/msg/BatteryState"),
    ({"cell_voltage": [1.0, "x"]}, r"cell_voltage\.1: expected a number"),
    ({"cell_voltage": 3.0}, "cell_voltage: expected a list"),
    ({"power_supply_status": 256}, "256 is out of range for uint8"),
    ({"present": 1}, "present: expected a bool"),
    ({"header": {"stamp": {"sec": 1.5}}}, r"header\.stamp\.sec: expected an integer"),
    ({"header": "x"}, "header: expected a mapping"),
])
def test_values_that_do_not_fit_are_field_errors(value: dict[str, Any], match: str) -> None:
    with pytest.raises(FieldError, match=match):
        REG.encode("sensor_msgs/msg/BatteryState", value)


def test_a_bounded_or_fixed_sequence_is_checked() -> None:
    reg = TypeRegistry()
    reg.register_folder(CUSTOM)
    with pytest.raises(FieldError, match="expected 4 elements, got 1"):
        reg.encode("rover_msgs/msg/Status", {"wheels": [{}]})


def test_field_paths() -> None:
    assert REG.field_type("sensor_msgs/msg/BatteryState", "percentage") == "float32"
    assert REG.field_type("sensor_msgs/msg/BatteryState", "header.stamp.sec") == "int32"
    assert REG.field_type("sensor_msgs/msg/BatteryState", "header") == "std_msgs/msg/Header"
    assert REG.field_type("sensor_msgs/msg/BatteryState", "cell_voltage") == "float32[]"
    assert REG.field_type("sensor_msgs/msg/BatteryState", "cell_voltage.2") == "float32"
    msg = full("sensor_msgs/msg/BatteryState",
               {"header": {"frame_id": "b"}, "cell_voltage": [3.5, 3.75]})
    assert get_field(msg, "header.frame_id") == "b"
    assert get_field(msg, "cell_voltage.1") == 3.75


@pytest.mark.parametrize(("path", "match"), [
    ("percent", "has no field 'percent' \\(did you mean 'percentage'\\? .*percentage"),
    ("header.stamp.secs",
     r"'header.stamp.secs' \(did you mean 'sec'\? builtin_interfaces/msg/Time has: sec, nano"),
    ("header.xyzzy", r"'header.xyzzy' \(std_msgs/msg/Header has: stamp, frame_id"),
    ("percentage.x", "percentage is float32, it has no field 'x'"),
    ("cell_voltage.x", r"cell_voltage is float32\[\], it has no field 'x'"),
])
def test_bad_field_paths_name_what_is_there(path: str, match: str) -> None:
    with pytest.raises(FieldError, match=match):
        REG.field_type("sensor_msgs/msg/BatteryState", path)
    with pytest.raises(FieldError):
        get_field(full("sensor_msgs/msg/BatteryState", {}), path)


def test_custom_interface_files_of_a_package() -> None:
    reg = TypeRegistry()
    names = reg.register_folder(CUSTOM)
    assert set(names) >= {"rover_msgs/msg/Wheel", "rover_msgs/msg/Status",
                          "rover_msgs/srv/SetLimit", "rover_msgs/msg/Dock"}
    status = {"header": {"stamp": {"sec": 1, "nanosec": 2}, "frame_id": "r"},
              "wheels": [{"name": f"w{i}", "speed": i / 2, "state": 0} for i in range(4)],
              "temperatures": [20.5]}
    assert reg.decode("rover_msgs/msg/Status", reg.encode("rover_msgs/msg/Status", status)) == (
        status)
    assert reg.field_type("rover_msgs/msg/Status", "wheels.3.speed") == "float64"
    assert reg.decode("rover_msgs/msg/Dock", reg.encode("rover_msgs/msg/Dock", {"x": 1.5})) == {
        "name": "", "x": 1.5, "occupied": False}
    resp = {"accepted": True, "wheels": [{"name": "a", "speed": 1.0, "state": 1}]}
    assert reg.decode("rover_msgs/srv/SetLimit_Response",
                      reg.encode("rover_msgs/srv/SetLimit_Response", resp)) == resp
    assert reg.type_hash("rover_msgs/srv/SetLimit").startswith("RIHS01_")


def test_a_definition_with_an_unknown_type_is_refused(tmp_path: Path) -> None:
    (tmp_path / "pkg_a" / "msg").mkdir(parents=True)
    (tmp_path / "pkg_a" / "msg" / "A.msg").write_text("Missing thing\n")
    with pytest.raises(UnknownType, match=r"refers to unknown type.*pkg_a/msg/Missing"):
        TypeRegistry().register_folder(tmp_path)
    (tmp_path / "pkg_a" / "msg" / "A.msg").write_text("float64[ x\n")
    with pytest.raises(UnknownType, match="not a valid definition"):
        TypeRegistry().register_folder(tmp_path)
    with pytest.raises(UnknownType, match="no such folder"):
        TypeRegistry().register_folder(tmp_path / "nowhere")


def test_export_writes_an_offline_message_directory(tmp_path: Path) -> None:
    written = REG.export(tmp_path, ["sensor_msgs/msg/BatteryState",
                                    "rcl_interfaces/srv/SetParameters"])
    rel = {str(p.relative_to(tmp_path)) for p in written}
    assert {"sensor_msgs/msg/BatteryState.msg", "std_msgs/msg/Header.msg",
            "builtin_interfaces/msg/Time.msg", "rcl_interfaces/srv/SetParameters.srv",
            "rcl_interfaces/msg/ParameterValue.msg"} <= rel
    srv = (tmp_path / "rcl_interfaces/srv/SetParameters.srv").read_text()
    assert srv == ("rcl_interfaces/Parameter[] parameters\n---\n"
                   "rcl_interfaces/SetParametersResult[] results\n")
    reg = TypeRegistry()
    reg.register_msg("copy_msgs/msg/Battery",
                     (tmp_path / "sensor_msgs/msg/BatteryState.msg").read_text())
    assert reg.field_names("copy_msgs/msg/Battery") == REG.field_names(
        "sensor_msgs/msg/BatteryState")


CDR = REG.encode("sensor_msgs/msg/BatteryState", {"percentage": 0.5, "cell_voltage": [1.0]})


@pytest.mark.parametrize("data", [b"", b"\x00", b"\x07\x07\x00\x00", CDR[:-5], CDR[:10],
                                  CDR + b"\x00" * 16, b"\x00\x01\x00\x00" + b"\xff" * 60])
def test_truncated_or_garbage_cdr_is_a_decode_error(data: bytes) -> None:
    with pytest.raises(DecodeError, match="bytes are not"):
        REG.decode("sensor_msgs/msg/BatteryState", data)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=120), st.sampled_from([
    "sensor_msgs/msg/BatteryState", "std_msgs/msg/String",
    "rcl_interfaces/srv/SetParameters_Request", "lifecycle_msgs/srv/ChangeState_Request"]))
def test_any_bytes_decode_or_are_refused(data: bytes, ros_type: str) -> None:
    with contextlib.suppress(DecodeError):
        REG.decode(ros_type, b"\x00\x01\x00\x00" + data)


@settings(deadline=None)
@given(st.integers(0, len(CDR) - 1))
def test_every_truncation_is_refused(n: int) -> None:
    with pytest.raises(DecodeError):
        REG.decode("sensor_msgs/msg/BatteryState", CDR[:n])


def test_parameter_values() -> None:
    assert to_value(True) == {"type": 1, "bool_value": True}
    assert to_value(3) == {"type": 2, "integer_value": 3}
    assert to_value([1.0, 2.0]) == {"type": 8, "double_array_value": [1.0, 2.0]}
    assert from_value({"type": 5, "byte_array_value": [1, 2]}) == b"\x01\x02"
    with pytest.raises(FieldError):
        to_value({"a": 1})
    with pytest.raises(FieldError):
        to_value([1, "a"])
    with pytest.raises(FieldError):
        from_value({"type": 42})
    assert np.float32(0.5) == full("sensor_msgs/msg/BatteryState", {"percentage": 0.5})[
        "percentage"]
