"""The Foxglove layout (config/foxglove/piezo_stage.json): current with its builder, and every
message path in it names a field that the topic's message really has, live or in the
project's bags."""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from piezo_stage.bag import bag_info
from piezo_stage.bag.types import typestore
from piezo_stage.plotting.live_layout import layout_json, message_paths, write_layout

pytestmark = pytest.mark.unit

ROOT = Path(__file__).resolve().parents[1]
COMMITTED = ROOT / "config" / "foxglove" / "piezo_stage.json"
#: the interface contract's types (docs/design.md §3)
TYPES = {
    "displacement": "piezo_stage_msgs/msg/Displacement",
    "reference": "piezo_stage_msgs/msg/Displacement",
    "voltage": "piezo_stage_msgs/msg/Voltage",
    "voltage_command": "piezo_stage_msgs/msg/Voltage",
    "controller_state": "piezo_stage_msgs/msg/ControllerState",
    "limit_cycles": "piezo_stage_msgs/msg/LimitCycle",
    "loop_samples": "piezo_stage_msgs/msg/LoopSamples",
    "bouc_wen_parameters": "piezo_stage_msgs/msg/BoucWenParameters",
    "excitation": "piezo_stage_msgs/msg/ExcitationInfo",
    # scan_view's (a raster scan)
    "scan_image": "sensor_msgs/msg/Image",
    "scan_position": "geometry_msgs/msg/PointStamped",
    "scan_line_rms": "geometry_msgs/msg/PointStamped",
}


def split(path: str, namespace: str = "/piezo") -> tuple[str, list[str]]:
    """(contract topic or global topic, [field, ...]) of a Foxglove message path."""
    topic, _, fields = path.partition(".")
    if topic.startswith(namespace + "/"):
        topic = topic[len(namespace) + 1 :]
    return topic, [re.sub(r"\[.*\]$", "", f) for f in fields.split(".") if f]


def test_the_committed_layout_is_current():
    assert json.loads(COMMITTED.read_text()) == json.loads(layout_json("/piezo")), (
        "run: piezo-stage view --write-layout config/foxglove/piezo_stage.json"
    )


def test_every_message_path_names_a_real_field():
    data = json.loads(COMMITTED.read_text())
    paths = message_paths(data)
    store = typestore()
    topics = set()
    assert len(paths) >= 15
    for path in paths:
        topic, fields = split(path)
        topics.add(topic)
        if topic == "/diagnostics":
            assert not fields
            continue
        assert topic in TYPES, path
        type_name = TYPES[topic]
        for field in fields:  # down nested messages (point.x)
            members = dict(store.fielddefs[type_name][1])
            assert field in members, (path, list(members))
            type_name = members[field][1]
    # what the issue of watching the stage asks to see
    assert {
        "displacement",
        "reference",
        "voltage",
        "voltage_command",
        "controller_state",
        "limit_cycles",
        "bouc_wen_parameters",
        "/diagnostics",
    } <= topics


def test_another_namespace_moves_every_path(tmp_path):
    data = json.loads(write_layout(tmp_path / "stage2.json", "/stage2").read_text())
    paths = message_paths(data)
    assert paths and all(p.startswith("/stage2/") or p == "/diagnostics" for p in paths)
    assert len(paths) == len(message_paths(json.loads(COMMITTED.read_text())))


@pytest.mark.parametrize("bag", ["ch10_identification", "perturbation_pid_tv"])
def test_the_layout_reads_the_project_bags(bag):
    """The bags record the same topics with the same types: the layout opens them as it
    watches a running stage."""
    info = bag_info(ROOT / "bags" / bag)
    used = {split(p)[0] for p in message_paths(json.loads(COMMITTED.read_text()))}
    shown = 0
    for name, topic in info["topics"].items():
        short = split(name)[0]
        if short in used and short in TYPES:
            assert topic["type"] == TYPES[short], (name, topic["type"])
            shown += 1
    assert shown >= 1, info["topics"]
