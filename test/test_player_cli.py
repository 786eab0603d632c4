"""`piezo-stage play`: runs the player node on a bag, with rate, topic filter, remap and clock."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from piezo_stage.bag import BagWriter, qos, read_raw
from piezo_stage.bag.series import encode_series

from ros_support import ROOT, spin_until

pytestmark = pytest.mark.ros

T0 = 1_700_000_000_000_000_000


def test_play_filters_remaps_and_publishes_the_clock(node, tmp_path):
    import numpy as np

    from piezo_stage_msgs.msg import Voltage

    bag = tmp_path / "bag"
    t = T0 + np.arange(20) * 5_000_000
    with BagWriter(bag) as writer:
        for topic in ("/piezo/voltage", "/piezo/voltage_command"):
            writer.add_topic(topic, "piezo_stage_msgs/msg/Voltage", [qos.RELIABLE])
            for t_ns, data in zip(
                t, encode_series("piezo_stage_msgs/msg/Voltage", t, np.arange(20.0))
            ):
                writer.write(topic, data, int(t_ns))
    recorded = [d for topic, _, _, d in read_raw(bag) if topic == "/piezo/voltage"]
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    got, other, clocks = [], [], []
    keep_all = QoSProfile(
        depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE
    )
    node.create_subscription(
        Voltage, "/replay/voltage", lambda d: got.append(d), keep_all, raw=True
    )
    node.create_subscription(
        Voltage, "/piezo/voltage_command", lambda d: other.append(d), keep_all, raw=True
    )
    node.create_subscription(Clock, "/clock", lambda m: clocks.append(m), keep_all)
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "piezo_stage.cli",
            "play",
            str(bag),
            "--rate",
            "2",
            "--clock",
            "0",
            "--topics",
            "/piezo/voltage",
            "--remap",
            "/piezo/voltage:=/replay/voltage",
            "--wait-for-subscribers",
            "1",
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert spin_until(node, lambda: proc.poll() is not None, 30.0)
        spin_until(node, lambda: False, 0.2)
    finally:
        if proc.poll() is None:
            proc.kill()
        _, err = proc.communicate()
    assert proc.returncode == 0, err
    assert len(got) == 20 and not other
    assert all(g[: len(r)] == r for g, r in zip(got, recorded))
    assert len(clocks) >= 10  # --clock 0: one tick before every message (some before matching)


def test_play_missing_bag(tmp_path, capsys):
    from piezo_stage.cli import main

    assert main(["play", str(tmp_path / "nope")]) == 2
    assert "no bag" in capsys.readouterr().err
