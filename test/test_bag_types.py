"""Message types for bags: rosbag2's concatenated definitions, type hashes, CDR helpers."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from mcap_ros2._dynamic import generate_dynamic
from rosbags.typesys import get_types_from_msg

from piezo_stage.bag import types
from piezo_stage.bag.errors import UnknownMessageTypeError
from piezo_stage.bag.series import _decode_generic, decode_series, encode_series

pytestmark = pytest.mark.unit

SEP = "=" * 80 + "\n"
PROJECT = [
    "BoucWenParameters",
    "ControllerState",
    "Displacement",
    "ExcitationInfo",
    "LimitCycle",
    "LoopSamples",
    "Voltage",
]


def sections(text: str) -> list[tuple[str, str]]:
    """Split a concatenated definition into [(header, body)] (root header '')."""
    parts = text.split("\n" + SEP)
    out = [("", parts[0])]
    for part in parts[1:]:
        head, _, body = part.partition("\n")
        assert head.startswith("MSG: ")
        out.append((head[5:], body))
    return out


def test_project_types_are_registered():
    assert types.project_message_types() == [f"piezo_stage_msgs/msg/{n}" for n in PROJECT]
    store = types.typestore()
    assert all(f"piezo_stage_msgs/msg/{n}" in store.fielddefs for n in PROJECT)


def test_displacement_definition_matches_rosbag2_layout():
    text = types.message_definition("piezo_stage_msgs/msg/Displacement")
    parts = sections(text)
    assert [h for h, _ in parts] == ["", "std_msgs/Header", "builtin_interfaces/Time"]
    assert parts[0][1] == (types.SOURCE_MSG_DIR / "Displacement.msg").read_text()
    header_file = types.interface_file("std_msgs/msg/Header")
    assert header_file is not None and parts[1][1] == header_file.read_text()


def test_dependencies_are_depth_first_in_sorted_order():
    text = types.message_definition("diagnostic_msgs/msg/DiagnosticArray")
    assert [h for h, _ in sections(text)] == [
        "",
        "diagnostic_msgs/DiagnosticStatus",
        "diagnostic_msgs/KeyValue",
        "std_msgs/Header",
        "builtin_interfaces/Time",
    ]


@pytest.mark.parametrize("name", PROJECT)
def test_definitions_parse_with_independent_parsers(name):
    full = f"piezo_stage_msgs/msg/{name}"
    text = types.message_definition(full)
    assert full in generate_dynamic(full, text)  # mcap_ros2's own parser
    parsed = get_types_from_msg(text, full)  # rosbags' parser
    assert parsed[full] == types.typestore().fielddefs[full]


def test_type_hash_matches_rosidl_and_is_rihs01():
    json_file = types.interface_file("std_msgs/msg/Header", ".json")
    expected = json.loads(json_file.read_text())["type_hashes"][0]["hash_string"]
    assert types.type_hash("std_msgs/msg/Header") == expected
    for name in PROJECT:
        assert re.fullmatch(r"RIHS01_[0-9a-f]{64}", types.type_hash(f"piezo_stage_msgs/msg/{name}"))
    assert types.type_hash("piezo_stage_msgs/msg/Voltage") != types.type_hash(
        "piezo_stage_msgs/msg/Displacement"
    )
    # where piezo_stage_msgs was built (colcon), rosidl's hashes must equal rosbags' ones
    built = types.SOURCE_MSG_DIR.parents[1] / "install" / "piezo_stage_msgs" / "share"
    for path in (built / "piezo_stage_msgs" / "msg").glob("*.json"):
        entry = json.loads(path.read_text())["type_hashes"][0]
        assert types.typestore().hash_rihs01(entry["type_name"]) == entry["hash_string"]


def test_serialize_round_trip_and_short_type_names():
    cls = types.message_class("piezo_stage_msgs/Voltage")
    msg = cls(header=types.header(1_700_000_000_123_456_789, "amp"), voltage=-12.5)
    back = types.deserialize(types.serialize(msg), "piezo_stage_msgs/msg/Voltage")
    assert back.voltage == -12.5 and back.header.frame_id == "amp"
    assert (back.header.stamp.sec, back.header.stamp.nanosec) == (1_700_000_000, 123_456_789)


def test_unknown_types_raise():
    with pytest.raises(UnknownMessageTypeError, match="unknown message type"):
        types.message_definition("nope_msgs/msg/Nothing")
    with pytest.raises(UnknownMessageTypeError, match="invalid message type name"):
        types.message_definition("not a type")
    with pytest.raises(UnknownMessageTypeError):
        types.message_class("nope_msgs/msg/Nothing")


@pytest.mark.parametrize(
    "type_name,frame",
    [
        ("piezo_stage_msgs/msg/Displacement", "laser"),
        ("piezo_stage_msgs/msg/Voltage", ""),
        ("piezo_stage_msgs/msg/Voltage", "abcdefgh"),
    ],
)
def test_series_codec_is_byte_exact_and_inverse(type_name, frame):
    t_ns = np.array([0, 1_700_000_000_000_000_001, 5_000_000_999])
    values = np.array([1.5e-6, -np.inf, 300.0])
    status = np.array([0, 1, 4], dtype=np.uint8)
    has_status = type_name.endswith("Displacement")
    datas = encode_series(type_name, t_ns, values, status if has_status else None, frame)
    cls = types.message_class(type_name)
    for data, t, v, s in zip(datas, t_ns, values, status):
        fields = {"displacement": v, "status": int(s)} if has_status else {"voltage": v}
        assert data == types.serialize(cls(header=types.header(int(t), frame), **fields))
    for decoded in (decode_series(datas, type_name), _decode_generic(datas, type_name)):
        t, vals, st = decoded
        np.testing.assert_allclose(t, t_ns * 1e-9, rtol=1e-15)
        np.testing.assert_array_equal(vals, values)
        if has_status:
            np.testing.assert_array_equal(st, status)
        else:
            assert st is None


def _decoder_round_trip(schema_name: str, encoding: str, text: str, fields: dict):
    from mcap.records import Channel, Schema

    from piezo_stage.bag.decode import BagTypes

    bag_types = BagTypes()
    channel = Channel(id=1, topic="/t", message_encoding="cdr", schema_id=1, metadata={})
    name = bag_types.type_of(
        channel, Schema(id=1, name=schema_name, encoding=encoding, data=text.encode())
    )
    if name is None:
        return None, bag_types.skipped["/t"]
    message = bag_types.store.types[name](**fields)
    data = bytes(bag_types.store.serialize_cdr(message, name))
    return bag_types.deserialize(data, name), ""


def test_bag_types_read_ros2idl_and_old_type_names():
    idl = "module my_pkg { module msg { struct Point { double x; string label; }; }; };"
    decoded, _ = _decoder_round_trip("my_pkg/msg/Point", "ros2idl", idl, {"x": 1.5, "label": "a"})
    assert (decoded.x, decoded.label) == (1.5, "a")
    decoded, _ = _decoder_round_trip("my_pkg/Point", "ros2msg", "float64 x\n", {"x": 2.5})
    assert decoded.x == 2.5 and decoded.__msgtype__ == "my_pkg/msg/Point"


def test_bag_types_skip_what_they_cannot_parse_with_the_reason():
    decoded, why = _decoder_round_trip("my_pkg/msg/Bad", "ros2msg", "float64[ x\n", {})
    assert decoded is None and "my_pkg/msg/Bad not decodable" in why
    decoded, why = _decoder_round_trip("my_pkg/msg/J", "jsonschema", "{}", {})
    assert decoded is None and "not ros2msg" in why


def test_export_flattens_fields_named_like_python_keywords():
    from mcap.records import Channel, Schema

    from piezo_stage.bag.decode import BagTypes
    from piezo_stage.bag.export import flatten

    bag_types = BagTypes()
    channel = Channel(id=1, topic="/k", message_encoding="cdr", schema_id=1, metadata={})
    name = bag_types.type_of(
        channel, Schema(id=1, name="p/msg/K", encoding="ros2msg", data=b"int32 from\nint32 class\n")
    )
    message = bag_types.store.types[name](from_=1, class_=2)  # rosbags' names for keywords
    assert flatten(bag_types.store.fielddefs, message, name) == [("from", 1), ("class", 2)]
