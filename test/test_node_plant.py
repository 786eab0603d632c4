"""The plant node over real DDS: realtime output, NaN commands refused, and the product's whole
loop in lockstep: plant + excitation + identifier recover the plant's parameters, and two runs
give identical samples."""

from __future__ import annotations

import math

import numpy as np
import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.qos import QoSProfile, ReliabilityPolicy

from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.nodes.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS

from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros

RELIABLE = QoSProfile(depth=10000, reliability=ReliabilityPolicy.RELIABLE)


NS = "/sim"  # the probe node's namespace (conftest)


def test_realtime_plant_follows_commands_and_refuses_nan(node):
    from piezo_stage_msgs.msg import Displacement, Voltage

    proc = start_node("plant", "model_file:=ch10_patch.yaml", "rate_hz:=200.0", namespace="/sim")
    xs, vs, diags = [], [], []
    node.create_subscription(Displacement, "displacement", xs.append, SENSOR_QOS)
    node.create_subscription(Voltage, "voltage", vs.append, SENSOR_QOS)
    node.create_subscription(DiagnosticArray, "/diagnostics", diags.append, 10)
    cmd = node.create_publisher(Voltage, "voltage_command", COMMAND_QOS)
    try:
        assert spin_until(node, lambda: len(xs) > 20, 15.0)
        rest = xs[-1].displacement
        for _ in range(10):
            cmd.publish(Voltage(voltage=150.0))
            spin_until(node, lambda: False, 0.02)
        assert spin_until(node, lambda: vs and vs[-1].voltage == 150.0, 5.0)
        moved = xs[-1].displacement
        # the patch is driven by -v (input_sign -1): kappa_1 v dominates, 150 V moves it by ~20 um
        assert abs(moved - rest) > 5e-6 and all(x.status == Displacement.OK for x in xs)
        cmd.publish(Voltage(voltage=math.nan))
        cmd.publish(Voltage(voltage=math.inf))
        spin_until(node, lambda: False, 0.2)
        assert vs[-1].voltage == 150.0  # held
        # samples are stamped on the 200 Hz grid of the node clock (a late tick publishes the
        # samples it owes with their own stamps): increasing, spaced by whole periods
        spacing = np.diff([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in xs])
        assert np.all(spacing > 0) and np.all(spacing % 5_000_000 == 0), spacing
        assert spin_until(
            node,
            lambda: any(
                s.level == DiagnosticStatus.WARN and "rejected" in s.message
                for d in diags
                for s in d.status
            ),
            5.0,
        )
    finally:
        out, err = stop(proc)
    assert "rejected non-finite voltage command" in err


def _lockstep_run(node, ns: str, rate: float) -> tuple[np.ndarray, np.ndarray, list, list]:
    """plant (ch. 9 example) + excitation (its preset) + identifier, lockstep; returns the
    displacement stamps and values, and what the identifier published."""
    from piezo_stage_msgs.msg import BoucWenParameters, Displacement, LimitCycle, Voltage

    procs = [
        start_node(
            "plant",
            "model_file:=ch9_example.yaml",
            "clock_mode:=lockstep",
            f"rate_hz:={rate}",
            "wait_for_subscribers:=2",
            namespace=ns,
        ),  # the probe and the identifier
        start_node("identifier", "use_sim_time:=true", "stream_qos:=reliable", namespace=ns),
    ]
    samples: list = []
    params: list = []
    cycles: list = []
    sub = node.create_subscription(Displacement, f"{ns}/displacement", samples.append, RELIABLE)
    sub_v = node.create_subscription(Voltage, f"{ns}/voltage", lambda m: None, RELIABLE)
    sub_p = node.create_subscription(
        BoucWenParameters, f"{ns}/bouc_wen_parameters", params.append, LATCHED_QOS
    )
    sub_c = node.create_subscription(LimitCycle, f"{ns}/limit_cycles", cycles.append, COMMAND_QOS)
    try:
        # everyone listening before the commander appears (the plant starts stepping then)
        assert spin_until(
            node,
            lambda: (
                node.count_subscribers(f"{ns}/voltage") >= 1
                and node.count_publishers(f"{ns}/displacement") >= 1
            ),
            20.0,
        )
        spin_until(node, lambda: False, 1.0)
        procs.append(
            start_node(
                "excitation",
                "preset:=ch9_example",
                "trigger:=clock",
                "use_sim_time:=true",
                "on_done:=exit",
                "wait_for_subscribers:=1",
                namespace=ns,
            )
        )
        assert spin_until(
            node, lambda: procs[-1].poll() is not None, 120.0
        )  # keep reading meanwhile
        assert procs[-1].returncode == 0, stop(procs[-1])
        # the identification itself: 36 s seen from the end of the runs on a loaded 2-core host
        published = spin_until(node, lambda: len(params) == 1, 120.0)
    finally:
        logs = [stop(p) for p in procs]
        node.destroy_subscription(sub)
        node.destroy_subscription(sub_v)
        node.destroy_subscription(sub_p)
        node.destroy_subscription(sub_c)
    assert published, f"the identifier published nothing: {logs[1][1][-3000:]}"
    # the plant never waited for a command during the experiment (after it: nobody commands)
    late = [
        line
        for _, err in logs
        for line in err.splitlines()
        if "no command for step" in line and int(line.split("step ")[1].split()[0]) <= 14400
    ]
    assert not late, late
    t = np.array([s.header.stamp.sec + 1e-9 * s.header.stamp.nanosec for s in samples])
    x = np.array([s.displacement for s in samples])
    t, first = np.unique(t, return_index=True)  # step 0 may be offered twice to a late commander
    return t, x[first], params, cycles


@pytest.mark.slow
def test_lockstep_loop_identifies_the_plant_and_is_deterministic(node):
    true = shipped_parameter_set("ch9_example").bouc_wen
    t1, x1, params, cycles = _lockstep_run(node, "/lockstep_a", 400.0)
    assert len(cycles) == 2 and [c.offset for c in cycles] == [0.0, 0.1]
    p = params[0]
    for name in ("kappa_w", "rho", "sigma", "n"):
        assert getattr(p, name) == pytest.approx(getattr(true, name), rel=1e-4), name
    assert p.kappa[0] == pytest.approx(true.kappa[0], rel=1e-4)
    assert np.all(
        np.diff(t1) == pytest.approx(1 / 400.0, abs=1e-9)
    )  # one sample per step, none lost

    t2, x2, _, _ = _lockstep_run(node, "/lockstep_b", 400.0)
    n = min(len(t2), len(t1))
    assert n > 2900
    np.testing.assert_array_equal(t1[:n], t2[:n])
    np.testing.assert_array_equal(x1[:n], x2[:n])  # the same run twice: identical samples


@pytest.mark.slow
def test_lockstep_plant_steps_once_its_writers_have_matched_the_subscribers(node):
    """wait_for_subscribers:=2: with a commander present but one reader per stream, no /clock and
    no sample; once a second reader is matched, step 0 comes first, to both."""
    from rosgraph_msgs.msg import Clock

    from piezo_stage_msgs.msg import Displacement, Voltage

    ns = "/lockstep_wait"
    proc = start_node(
        "plant",
        "model_file:=ch9_example.yaml",
        "clock_mode:=lockstep",
        "rate_hz:=1000.0",
        "wait_for_subscribers:=2",
        namespace=ns,
    )
    second = rclpy.create_node("second", namespace=ns)
    ticks: list = []
    seen: list = []
    late: list = []
    node.create_publisher(Voltage, f"{ns}/voltage_command", COMMAND_QOS)  # the commander is there
    node.create_subscription(Clock, "/clock", ticks.append, RELIABLE)
    node.create_subscription(Displacement, f"{ns}/displacement", seen.append, RELIABLE)
    node.create_subscription(Voltage, f"{ns}/voltage", lambda m: None, RELIABLE)
    try:
        assert spin_until(
            node,
            lambda: (
                node.count_publishers("/clock") >= 1
                and node.count_subscribers(f"{ns}/displacement") >= 1
            ),
            20.0,
        )
        spin_until(node, lambda: False, 1.5)
        assert ticks == [] and seen == []  # waiting for its second reader
        second.create_subscription(Displacement, f"{ns}/displacement", late.append, RELIABLE)
        second.create_subscription(Voltage, f"{ns}/voltage", lambda m: None, RELIABLE)
        assert spin_until(node, lambda: bool(ticks) and bool(seen), 10.0)
        assert spin_until(second, lambda: bool(late), 5.0)
        assert ticks[0].clock.sec == 0 and ticks[0].clock.nanosec == 0
        assert (
            seen[0].header.stamp == late[0].header.stamp == ticks[0].clock
        )  # step 0, to both readers
    finally:
        stop(proc)
        second.destroy_node()


def test_realtime_plant_wakes_per_sample_only_while_commanded(node):
    """With no voltage_command publisher the plant holds and wakes every hold period (5 samples
    at 1 kHz), stepping the samples due in one batch; a commander brings the timer to the
    sample rate, and its going back to the hold period. The samples stay on the grid."""
    from piezo_stage.nodes.plant import hold_period
    from piezo_stage_msgs.msg import Displacement, Voltage

    hold = hold_period(1000.0)
    proc = start_node("plant", "model_file:=ch10_patch.yaml", "rate_hz:=1000.0", namespace=NS)
    stamps: list[int] = []
    period: list[float] = []

    def on_diag(msg: DiagnosticArray) -> None:
        for status in msg.status:
            for kv in status.values:
                if kv.key == "tick_period" and status.name == f"{NS}/plant":
                    period.append(float(kv.value))

    node.create_subscription(
        Displacement,
        "displacement",
        lambda m: stamps.append(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec),
        QoSProfile(depth=5000, reliability=ReliabilityPolicy.BEST_EFFORT),
    )
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    try:
        assert spin_until(node, lambda: period and period[-1] == pytest.approx(hold), 15.0)
        cmd = node.create_publisher(Voltage, "voltage_command", COMMAND_QOS)
        assert spin_until(node, lambda: period[-1] == pytest.approx(1e-3), 15.0), period
        cmd.publish(Voltage(voltage=50.0))
        node.destroy_publisher(cmd)
        assert spin_until(node, lambda: period[-1] == pytest.approx(hold), 15.0), period
        spin_until(node, lambda: False, 0.2)
    finally:
        stop(proc)
    spacing = np.diff(stamps)
    assert len(stamps) > 100 and np.all(spacing > 0) and np.all(spacing % 1_000_000 == 0)
