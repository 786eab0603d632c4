"""`piezo-stage record`: starts the recorder node in a namespace, forwards Ctrl-C, prints the
bag."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
from rclpy.duration import Duration
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

from piezo_stage.bag import bag_info, read_messages

from ros_support import ROOT, spin_until

pytestmark = pytest.mark.ros

NS = "/cli"  # the probe node's namespace (conftest)


def _cli(*args: str) -> subprocess.Popen:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")])
    return subprocess.Popen(
        [sys.executable, "-m", "piezo_stage.cli", *args],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_record_forwards_sigint_and_prints_the_complete_bag(node, tmp_path):
    from piezo_stage_msgs.msg import Voltage

    bag = tmp_path / "run1"
    proc = _cli(
        "record", "--ns", "/cli", "-o", str(bag), "--topics", "voltage", "--compression", "zstd"
    )
    try:
        pub = node.create_publisher(
            Voltage,
            "voltage",
            QoSProfile(
                depth=1, history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE
            ),
        )
        assert spin_until(node, lambda: pub.get_subscription_count() >= 1, 15.0)
        spin_until(node, lambda: False, 0.2)
        for k in range(50):
            pub.publish(Voltage(voltage=float(k)))
        assert pub.wait_for_all_acked(Duration(seconds=10))
        proc.send_signal(signal.SIGINT)  # the recorder drains what it has not written yet
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert f"recording /cli to {bag}" in out
    assert f"bag: {bag} (complete), 50 messages" in out
    assert "/cli/voltage: 50 [piezo_stage_msgs/msg/Voltage]" in out
    assert [m.voltage for _, _, m in read_messages(bag)] == [float(k) for k in range(50)]
    assert bag_info(bag)["compression"] == "zstd"


def test_record_duration_stops_by_itself(tmp_path):
    """--duration counts from the open bag, and "recording" is said once the bag is open (a user,
    or a script waiting for the line, may stop it then and keep a bag)."""
    bag = tmp_path / "short"
    proc = _cli("record", "--ns", "/cli_short", "-o", str(bag), "--duration", "1.0")
    first = proc.stdout.readline()
    opened_before = sorted(p.name for p in bag.glob("*.mcap"))
    out, err = proc.communicate(timeout=30)
    assert first.startswith(f"recording /cli_short to {bag}"), (first, err)
    assert opened_before, "said recording before its bag was open"
    assert proc.returncode == 0, err
    assert f"bag: {bag} (complete)" in out
    assert bag_info(bag)["complete"]


def test_record_refuses_an_existing_bag(tmp_path, capsys):
    from piezo_stage.cli import main

    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(SystemExit, match="^2$"):  # bad input, refused as it is parsed
        main(["record", "-o", str(tmp_path / "full")])
    assert "already exists" in capsys.readouterr().err
