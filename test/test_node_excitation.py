"""The excitation node over real DDS: timer and /clock triggers, run/steady info, exit when done."""

from __future__ import annotations

import signal

import pytest

rclpy = pytest.importorskip("rclpy")
from builtin_interfaces.msg import Time  # noqa: E402
from rosgraph_msgs.msg import Clock  # noqa: E402

from piezo_stage.model.excitation import plan_from  # noqa: E402
from piezo_stage.nodes.common import COMMAND_QOS  # noqa: E402
from ros_support import spin_until, start_node, stop  # noqa: E402

PLAN = ["waveform:=triangle", "period:=0.1", "low:=-1.0", "amplitude:=2.0", "offsets:=[0.0, 0.5]",
        "settle_periods:=1", "record_periods:=1"]


@pytest.fixture()
def node():
    rclpy.init()
    n = rclpy.create_node("probe", namespace="/exc")
    yield n
    n.destroy_node()
    rclpy.shutdown()


def test_clock_trigger_publishes_the_plan_stamped_with_sim_time(node):
    from piezo_stage_msgs.msg import ExcitationInfo, Voltage

    proc = start_node("excitation", *PLAN, "trigger:=clock", "on_done:=exit", "use_sim_time:=true",
                      namespace="/exc")
    cmds: dict[float, float] = {}
    infos: list[ExcitationInfo] = []
    node.create_subscription(Voltage, "voltage_command",
                             lambda m: cmds.__setitem__(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec, m.voltage),
                             COMMAND_QOS)
    node.create_subscription(ExcitationInfo, "excitation", infos.append, COMMAND_QOS)
    clock = node.create_publisher(Clock, "/clock", COMMAND_QOS)
    try:
        assert spin_until(node, lambda: node.count_subscribers("/clock") >= 1 and
                          node.count_publishers("voltage_command") >= 1, 15.0)
        spin_until(node, lambda: False, 0.5)
        dt, t0 = 0.001, 100.0
        ticks = [t0 + k * dt for k in range(401)]  # both runs (0.4 s) and the first tick after: done
        for t in ticks:
            sec = int(t)
            clock.publish(Clock(clock=Time(sec=sec, nanosec=int(round((t - sec) * 1e9)))))
            spin_until(node, lambda t=t: any(abs(s - t) < 1e-7 for s in cmds), 2.0)
        assert len(cmds) == len(ticks)
        plan = plan_from(None, waveform="triangle", period=0.1, low=-1.0, amplitude=2.0, offsets=[0.0, 0.5],
                         settle_periods=1, record_periods=1)
        for t in ticks:
            got = next(v for s, v in cmds.items() if abs(s - t) < 1e-7)
            assert got == pytest.approx(float(plan.values(t - t0)), abs=1e-9)
        runs = {(i.run, i.steady) for i in infos}
        assert {(0, False), (0, True), (1, False), (1, True)} <= runs
        assert all(i.offset == (0.5 if i.run == 1 else 0.0) for i in infos)
        assert proc.wait(timeout=10) == 0  # on_done: exit
    finally:
        stop(proc)


def test_timer_trigger_runs_on_wall_clock_and_stops_cleanly_on_sigint(node):
    from piezo_stage_msgs.msg import Voltage

    proc = start_node("excitation", *PLAN, "rate_hz:=200.0", namespace="/exc")
    got: list[float] = []
    node.create_subscription(Voltage, "voltage_command", lambda m: got.append(m.voltage), COMMAND_QOS)
    try:
        assert spin_until(node, lambda: len(got) >= 40, 20.0)
        assert min(got) >= -1.0 - 1e-9 and max(got) <= 1.5 + 1e-9
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    finally:
        out, err = stop(proc)
    assert "Traceback" not in err
