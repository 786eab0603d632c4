"""Recorder pieces that need no second process: QoS adaptation, type lookup, bad parameters,
the Fast DDS transport profile."""

from __future__ import annotations

import os
import re

import pytest
import rclpy
from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy, qos_profile_sensor_data

from piezo_stage.nodes import (
    dds,
    recorder,
    topics,
)
from piezo_stage.nodes.errors import RosParameterError
from piezo_stage.nodes.qos import COMMAND_QOS, LATCHED_QOS, adapted_qos


@pytest.mark.unit
def test_adapted_qos_follows_the_weakest_offer():
    reliable = adapted_qos([COMMAND_QOS], 100)
    assert reliable.reliability == ReliabilityPolicy.RELIABLE
    assert (
        reliable.history == HistoryPolicy.KEEP_ALL
        and reliable.durability == DurabilityPolicy.VOLATILE
    )
    latched = adapted_qos([LATCHED_QOS, LATCHED_QOS], 100)
    assert latched.durability == DurabilityPolicy.TRANSIENT_LOCAL
    mixed = adapted_qos([LATCHED_QOS, qos_profile_sensor_data], 100)
    assert mixed.reliability == ReliabilityPolicy.BEST_EFFORT
    assert mixed.durability == DurabilityPolicy.VOLATILE
    assert mixed.history == HistoryPolicy.KEEP_LAST and mixed.depth == 100
    assert adapted_qos([], 5).reliability == ReliabilityPolicy.BEST_EFFORT  # no offer known


@pytest.mark.unit
def test_message_type_lookup():
    from piezo_stage_msgs.msg import Voltage

    assert topics.message_type("piezo_stage_msgs/msg/Voltage") is Voltage
    assert topics.message_type("piezo_stage_msgs/Voltage") is Voltage
    with pytest.raises(topics.MessageTypeError, match="cannot import"):
        topics.message_type("no_such_pkg/msg/Thing")
    with pytest.raises(topics.MessageTypeError, match="invalid"):
        topics.message_type("Voltage")


@pytest.mark.unit
def test_default_bag_name_is_rosbag2_style():
    assert re.fullmatch(r"rosbag2_\d{4}_\d\d_\d\d-\d\d_\d\d_\d\d", recorder.default_bag_name())


@pytest.mark.ros
@pytest.mark.parametrize(
    "param, error, message",
    [
        ("compression:=lz4", RosParameterError, "compression: 'lz4' is not one of none, zstd"),
        ("topic_regex:=(", recorder.RecorderError, "not a valid regular expression"),
    ],
)
def test_bad_parameters_are_refused(tmp_path, param, error, message):
    rclpy.init(args=["x", "--ros-args", "-p", f"bag:={tmp_path / 'bag'}", "-p", param])
    try:
        with pytest.raises(error, match=re.escape(message)):
            recorder.RecorderNode()
    finally:
        rclpy.shutdown()
    assert not (tmp_path / "bag").exists()  # refused before any file is created


@pytest.mark.unit
def test_transport_profile_set_unless_the_user_has_one(monkeypatch):
    for var in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    path = dds.use_recorder_transport_profile()
    assert path is not None and path.name == dds.PROFILE_FILE  # shipped: nothing written to /tmp
    assert "<port_queue_capacity>16384</port_queue_capacity>" in path.read_text()
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(path)
    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", "/user/own.xml")
    assert dds.use_recorder_transport_profile() is None
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/user/own.xml"
    monkeypatch.delenv("FASTRTPS_DEFAULT_PROFILES_FILE")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")
    assert dds.use_recorder_transport_profile() is None
