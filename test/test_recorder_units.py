"""Recorder pieces that need no second process: QoS adaptation, type lookup, bad parameters,
the Fast DDS transport profile."""

from __future__ import annotations

import os
import re

import pytest


rclpy = pytest.importorskip("rclpy")
from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy, qos_profile_sensor_data  # noqa: E402

from piezo_stage.nodes import recorder  # noqa: E402
from piezo_stage.nodes.common import COMMAND_QOS, LATCHED_QOS  # noqa: E402


@pytest.mark.unit
def test_adapted_qos_follows_the_weakest_offer():
    reliable = recorder.adapted_qos([COMMAND_QOS], 100)
    assert reliable.reliability == ReliabilityPolicy.RELIABLE
    assert reliable.history == HistoryPolicy.KEEP_ALL and reliable.durability == DurabilityPolicy.VOLATILE
    latched = recorder.adapted_qos([LATCHED_QOS, LATCHED_QOS], 100)
    assert latched.durability == DurabilityPolicy.TRANSIENT_LOCAL
    mixed = recorder.adapted_qos([LATCHED_QOS, qos_profile_sensor_data], 100)
    assert mixed.reliability == ReliabilityPolicy.BEST_EFFORT
    assert mixed.durability == DurabilityPolicy.VOLATILE
    assert mixed.history == HistoryPolicy.KEEP_LAST and mixed.depth == 100
    assert recorder.adapted_qos([], 5).reliability == ReliabilityPolicy.BEST_EFFORT  # no offer known


@pytest.mark.unit
def test_message_type_lookup():
    from piezo_stage_msgs.msg import Voltage

    assert recorder.message_type("piezo_stage_msgs/msg/Voltage") is Voltage
    assert recorder.message_type("piezo_stage_msgs/Voltage") is Voltage
    with pytest.raises(recorder.MessageTypeError, match="cannot import"):
        recorder.message_type("no_such_pkg/msg/Thing")
    with pytest.raises(recorder.MessageTypeError, match="invalid"):
        recorder.message_type("Voltage")


@pytest.mark.unit
def test_default_bag_name_is_rosbag2_style():
    assert re.fullmatch(r"rosbag2_\d{4}_\d\d_\d\d-\d\d_\d\d_\d\d", recorder.default_bag_name())


@pytest.mark.parametrize("param, message", [("compression:=lz4", "compression must be one of"),
                                            ("topic_regex:=(", "not a valid regular expression")])
@pytest.mark.ros
def test_bad_parameters_are_refused(tmp_path, param, message):
    rclpy.init(args=["x", "--ros-args", "-p", f"bag:={tmp_path / 'bag'}", "-p", param])
    try:
        with pytest.raises(recorder.RecorderError, match=re.escape(message)):
            recorder.RecorderNode()
    finally:
        rclpy.shutdown()
    assert not (tmp_path / "bag").exists()  # refused before any file is created


@pytest.mark.unit
def test_transport_profile_set_unless_the_user_has_one(monkeypatch, tmp_path):
    monkeypatch.setattr(recorder.tempfile, "gettempdir", lambda: str(tmp_path))
    for var in ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE"):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    path = recorder.use_recorder_transport_profile()
    assert path is not None and path.read_text() == recorder.FASTDDS_PROFILE
    assert "<port_queue_capacity>16384</port_queue_capacity>" in recorder.FASTDDS_PROFILE
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(path)
    monkeypatch.setenv("FASTRTPS_DEFAULT_PROFILES_FILE", "/user/own.xml")
    assert recorder.use_recorder_transport_profile() is None
    assert os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/user/own.xml"
    monkeypatch.delenv("FASTRTPS_DEFAULT_PROFILES_FILE")
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_cyclonedds_cpp")
    assert recorder.use_recorder_transport_profile() is None

