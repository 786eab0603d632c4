"""`scan_view` over real DDS: a scan's two axes' loop_samples (as the scanner's loop publishes
them, from before the scan starts) become the scan's image, the one the core makes of the same
samples, and the last line's errors; started after the scan, it says it missed the start."""

from __future__ import annotations

import numpy as np
import pytest

from piezo_stage.control.scan import RasterScan, ScanAxis
from piezo_stage.control.scan_image import load_sample, scan_image
from piezo_stage.nodes.qos import BATCH_QOS, SENSOR_QOS

from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros

NS = "/scan_view_test"
SCAN = RasterScan(4, 16, 20.0, (20e-6, 10e-6), (20e-6, 10e-6))
RATE = 1000.0
T0 = 1_700_000_000_000_000_000


def _batches(axis: int, first: int, last: int, gated: int = 3):
    """LoopSamples of one axis, 10 samples each, ``gated`` rows before the scan's start (not
    stepped), the slow axis 0.3 ms after the fast one; positions the set points + 20 nm."""
    from piezo_stage_msgs.msg import LoopSamples

    offset = 300_000 * axis
    out = []
    for start in range(first, last, 10):
        k = np.arange(start, min(start + 10, last))
        stamp = T0 + offset + (k - gated) * 1_000_000
        reference = ScanAxis(SCAN, axis).evaluate(stamp * 1e-9 - T0 * 1e-9)[0]
        reference[k < gated] = np.nan
        msg = LoopSamples()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(stamp[0]), 10**9)
        msg.stamp = stamp.tolist()
        msg.displacement = (np.nan_to_num(reference, nan=0.0) + 20e-9).tolist()
        msg.status = [0] * k.size
        msg.reference = reference.tolist()
        msg.u = msg.u_ff = msg.applied = [0.0] * k.size
        msg.loop_closed = (k >= gated).tolist()
        out.append(msg)
    return out


def test_the_scan_fills_the_image_the_core_makes(node, tmp_path):
    from geometry_msgs.msg import PointStamped
    from sensor_msgs.msg import Image

    from piezo_stage_msgs.msg import LoopSamples

    scan_file = ScanAxis(SCAN, 0).save(tmp_path / "scan_x.json")
    proc = start_node("scan_view", f"scan_file:={scan_file}", "publish_rate_hz:=20.0", namespace=NS)
    images, lines = [], []
    node.create_subscription(Image, "scan_image", images.append, SENSOR_QOS)
    node.create_subscription(PointStamped, "scan_line_rms", lines.append, SENSOR_QOS)
    pubs = [node.create_publisher(LoopSamples, f"{a}/loop_samples", BATCH_QOS) for a in "xy"]
    n = int(SCAN.frame_time * RATE) + 3
    # the core's image of the same samples (the slow axis at the fast axis's stamps)
    t = np.arange(n - 3) / RATE
    (x, _, _), _ = SCAN.evaluate(t)
    y = np.interp(t, t + 3e-4, SCAN.evaluate(t + 3e-4)[1][0])
    sample = load_sample("grating", SCAN)
    want = scan_image(SCAN, sample, t, np.vstack([x, y]) + 20e-9)
    lo, span = want.ideal.min(), np.ptp(want.ideal)
    grey = np.clip((want.image - lo) / span * 255.0, 0, 255).astype(np.uint8)

    def shown() -> np.ndarray:
        data = np.frombuffer(bytes(images[-1].data), np.uint8)
        return data.reshape(SCAN.lines, SCAN.pixels)[::-1]  # its first row is the top line

    try:
        assert spin_until(node, lambda: all(p.get_subscription_count() for p in pubs), 20.0)
        # the probe sees the node's readers before the node sees its writers (discovery is
        # one-sided for a while): what is published before both see each other is lost
        spin_until(node, lambda: False, 1.0)
        for part in zip(_batches(0, 0, n), _batches(1, 0, n)):
            pubs[1].publish(part[1])
            pubs[0].publish(part[0])
            spin_until(node, lambda: False, 0.005)  # a batch every 5 ms, as a loop sends them
        # the image as the node shows it once every batch has arrived
        last = SCAN.lines - 1
        spin_until(
            node,
            lambda: (
                bool(images and lines)
                and lines[-1].point.z == last
                and np.array_equal(shown(), grey)
            ),
            15.0,
        )
    finally:
        _, err = stop(proc)
    assert "Traceback" not in err, err
    image = images[-1]
    assert (image.height, image.width, image.encoding) == (SCAN.lines, SCAN.pixels, "mono8")
    np.testing.assert_array_equal(shown(), grey)
    assert lines and lines[-1].point.z == SCAN.lines - 1
    # the last line's errors, 20 nm on both axes (the set points recorded on the controllers'
    # float time, to 0.2 ns here)
    assert lines[-1].point.x == pytest.approx(20e-9, abs=0.5e-9), lines[-1].point
    assert lines[-1].point.y == pytest.approx(20e-9, abs=0.5e-9), lines[-1].point


def test_started_after_the_scan_it_says_it_missed_the_start(node, tmp_path):
    from diagnostic_msgs.msg import DiagnosticArray

    from piezo_stage_msgs.msg import LoopSamples

    scan_file = ScanAxis(SCAN, 1).save(tmp_path / "scan_y.json")
    proc = start_node("scan_view", f"scan_file:={scan_file}", namespace=NS)
    said = []
    node.create_subscription(
        DiagnosticArray,
        "/diagnostics",
        lambda m: said.extend(s.message for s in m.status if "scan_view" in s.name),
        10,
    )
    pubs = [node.create_publisher(LoopSamples, f"{a}/loop_samples", BATCH_QOS) for a in "xy"]
    try:
        assert spin_until(node, lambda: all(p.get_subscription_count() for p in pubs), 20.0)
        spin_until(node, lambda: False, 1.0)  # (as above)
        for part in zip(_batches(0, 500, 800), _batches(1, 500, 800)):  # from mid-scan
            pubs[1].publish(part[1])
            pubs[0].publish(part[0])
        assert spin_until(node, lambda: any("missed the start" in m for m in said), 10.0), said
    finally:
        _, err = stop(proc)
    assert "Traceback" not in err, err


def test_with_nothing_to_hear_it_says_what_it_waits_for_in_one_line(node, tmp_path):
    """No scan anywhere: its diagnostics and, after NOTHING_AFTER s, one log line name the two
    topics it listens on and its ROS domain (a view in the wrong namespace or domain says so)."""
    import os

    from diagnostic_msgs.msg import DiagnosticArray

    from piezo_stage.nodes.scan_view import NOTHING_AFTER

    scan_file = ScanAxis(SCAN, 0).save(tmp_path / "scan_x.json")
    space = f"{NS}/nothing"
    proc = start_node("scan_view", f"scan_file:={scan_file}", namespace=space)
    said = []
    node.create_subscription(
        DiagnosticArray,
        "/diagnostics",
        lambda m: said.extend(s.message for s in m.status if s.name == f"{space}/scan_view"),
        10,
    )
    domain = os.environ.get("ROS_DOMAIN_ID", "0")
    waits = (
        f"waiting for {space}/x/loop_samples and {space}/y/loop_samples on ROS domain {domain}: "
        "nothing received"
    )
    try:
        assert spin_until(node, lambda: any(waits in m for m in said), 20.0), said
        spin_until(node, lambda: False, NOTHING_AFTER + 1.5)  # its log line is due
    finally:
        _, err = stop(proc)
    assert "Traceback" not in err, err
    assert [line for line in err.splitlines() if waits in line], err
    assert len([line for line in err.splitlines() if "waiting for" in line]) == 1, err
