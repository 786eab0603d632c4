"""Last step: the whole `emulated_rig` graph (emulate rig + voltage_driver + laser_reader +
identifier + excitation) started by piezo_stage.launch.Launcher: the excitation's voltage reaches
the emulated amplifier, the emulated stage moves the emulated sensor, the reader publishes it,
and Ctrl-C ramps the amplifier to safe_voltage before the emulator goes away.

(The identification itself is not asserted here: on this shared 2-core machine the stamp jitter
of a real-time graph moves the input's crossing times by 1-2 % of a 1.5 s period, above the
identifier's 1 % periodicity tolerance; and the full experiment takes ~35 s.)"""

from __future__ import annotations

import os
import socket

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

from piezo_stage.launch import Launcher  # noqa: E402
from piezo_stage.nodes.common import SENSOR_QOS  # noqa: E402
from ros_support import spin_until  # noqa: E402

NS = "/emulated"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_emulated_rig_graph_runs_the_excitation_through_the_devices(tmp_path):
    from piezo_stage_msgs.msg import Displacement, Voltage

    port, link = free_port(), tmp_path / "sensor"
    lines: list[str] = []
    rclpy.init()
    probe = rclpy.create_node("probe", namespace=NS)
    xs: list = []
    vs: list = []
    probe.create_subscription(Displacement, "displacement", xs.append, SENSOR_QOS)
    probe.create_subscription(Voltage, "voltage", vs.append, SENSOR_QOS)
    launch = Launcher("emulated_rig", namespace=NS, timeout=30.0,
                      env={**os.environ, "PIEZO_RIG_SENSOR": str(link), "PIEZO_RIG_AMP_PORT": str(port)},
                      params=[f"voltage_driver.url:=tcp://127.0.0.1:{port}", f"laser_reader.url:={link}",
                              f"identifier.output_file:={tmp_path / 'identified.yaml'}"],
                      sink=lambda name, line, is_err: lines.append(f"[{name}] {line}"))
    try:
        launch.start()
        launch.wait_ready(timeout=30.0)
        moved = spin_until(probe, lambda: len(vs) > 100 and len(xs) > 100 and max(v.voltage for v in vs) > 60.0,
                           20.0)
        spin_until(probe, lambda: False, 0.5)
    finally:
        code = launch.stop()
        probe.destroy_node()
        rclpy.shutdown()
    log = "\n".join(line for line in lines if "[launch] started" not in line)[-6000:]
    assert moved, log
    assert code == 0, log
    assert any("shut down at 0 V" in line for line in lines), log  # ramped before the emulator stopped
    v = np.array([m.voltage for m in vs])
    x = np.array([m.displacement for m in xs])
    assert v.min() >= 0.0 and v.max() <= 100.0  # the excitation's 0-100 V triangle, inside the limits
    assert all(m.status == Displacement.OK for m in xs) and len(xs) > 100
    # the ch. 10 patch moves ~0.14 um/V: a triangle to > 60 V spans several micrometres
    assert np.ptp(x) > 5e-6, np.ptp(x)
