"""The excitation node over real DDS: timer and /clock triggers, run/steady info, exit when done."""

from __future__ import annotations

import signal

import pytest
import rclpy
from builtin_interfaces.msg import Time
from rosgraph_msgs.msg import Clock

from piezo_stage.model.excitation import plan_from
from piezo_stage.nodes.qos import COMMAND_QOS

from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros

PLAN = [
    "waveform:=triangle",
    "period:=0.1",
    "low:=-1.0",
    "amplitude:=2.0",
    "offsets:=[0.0, 0.5]",
    "settle_periods:=1",
    "record_periods:=1",
]


NS = "/exc"  # the probe node's namespace (conftest)


def test_clock_trigger_publishes_the_plan_stamped_with_sim_time(node):
    from piezo_stage_msgs.msg import ExcitationInfo, Voltage

    proc = start_node(
        "excitation",
        *PLAN,
        "trigger:=clock",
        "on_done:=exit",
        "use_sim_time:=true",
        namespace="/exc",
    )
    cmds: dict[float, float] = {}
    infos: list[ExcitationInfo] = []
    node.create_subscription(
        Voltage,
        "voltage_command",
        lambda m: cmds.__setitem__(m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec, m.voltage),
        COMMAND_QOS,
    )
    node.create_subscription(ExcitationInfo, "excitation", infos.append, COMMAND_QOS)
    clock = node.create_publisher(Clock, "/clock", COMMAND_QOS)
    try:
        assert spin_until(
            node,
            lambda: (
                node.count_subscribers("/clock") >= 1
                and node.count_publishers("voltage_command") >= 1
            ),
            15.0,
        )
        spin_until(node, lambda: False, 0.5)
        dt, t0 = 0.001, 100.0
        ticks = [
            t0 + k * dt for k in range(401)
        ]  # both runs (0.4 s) and the first tick after: done
        for t in ticks:
            sec = int(t)
            clock.publish(Clock(clock=Time(sec=sec, nanosec=int(round((t - sec) * 1e9)))))
            spin_until(node, lambda t=t: any(abs(s - t) < 1e-7 for s in cmds), 2.0)
        assert len(cmds) == len(ticks)
        plan = plan_from(
            None,
            waveform="triangle",
            period=0.1,
            low=-1.0,
            amplitude=2.0,
            offsets=[0.0, 0.5],
            settle_periods=1,
            record_periods=1,
        )
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
    node.create_subscription(
        Voltage, "voltage_command", lambda m: got.append(m.voltage), COMMAND_QOS
    )
    try:
        assert spin_until(node, lambda: len(got) >= 40, 20.0)
        assert min(got) >= -1.0 - 1e-9 and max(got) <= 1.5 + 1e-9
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10) == 0
    finally:
        out, err = stop(proc)
    assert "Traceback" not in err


@pytest.mark.slow
def test_lockstep_reader_lagging_thousands_of_steps_loses_no_command_or_mark(node):
    """trigger=clock runs as fast as the graph: a reliable reader that falls behind (a recorder
    under load) must still get every command and mark, including those published just before the
    node leaves (it waits for their acknowledgement). The lagging reader here takes nothing until
    the plan is done: 6001 steps, more than its KEEP_ALL history holds (Fast DDS: 5000 samples).
    Past that, the writer keeps what the reader has not acknowledged. Each step then costs the
    graph about 80 ms instead of about 1 ms (measured: the writer resends what the full reader
    refuses), so the overflow is kept to a few hundred steps."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy

    from piezo_stage_msgs.msg import ExcitationInfo, Voltage

    n_ticks, dt = 6001, 0.4 / 6000  # both runs of PLAN and the first tick after: done
    proc = start_node(
        "excitation",
        *PLAN,
        "trigger:=clock",
        "on_done:=exit",
        "use_sim_time:=true",
        "info_rate_hz:=10000.0",
        "exit_ack_timeout:=120.0",  # more than the reader below is given: a loaded host is slow
        namespace="/exc",
    )
    lagging = rclpy.create_node("lagging", namespace="/exc")
    keep_all = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
    seen: set[tuple[int, int]] = set()
    infos: list[ExcitationInfo] = []
    late_cmds: list[Voltage] = []
    late_infos: list[ExcitationInfo] = []
    node.create_subscription(
        Voltage,
        "voltage_command",
        lambda m: seen.add((m.header.stamp.sec, m.header.stamp.nanosec)),
        keep_all,
    )
    node.create_subscription(ExcitationInfo, "excitation", infos.append, keep_all)
    lagging.create_subscription(Voltage, "voltage_command", late_cmds.append, keep_all)
    lagging.create_subscription(ExcitationInfo, "excitation", late_infos.append, keep_all)
    clock = node.create_publisher(Clock, "/clock", COMMAND_QOS)
    try:
        assert spin_until(
            node,
            lambda: (
                node.count_subscribers("/clock") >= 1
                and node.count_subscribers("voltage_command") >= 2
                and node.count_publishers("voltage_command") >= 1
            ),
            15.0,
        )
        spin_until(node, lambda: False, 0.5)
        for k in range(n_ticks):  # lockstep: the next tick once the command for this one is in
            t = 100.0 + k * dt
            sec, nanosec = int(t), int(round((t - int(t)) * 1e9))
            clock.publish(Clock(clock=Time(sec=sec, nanosec=nanosec)))
            assert spin_until(node, lambda sec=sec, nanosec=nanosec: (sec, nanosec) in seen, 5.0), (
                f"no command for tick {k}"
            )
        assert spin_until(lagging, lambda: len(late_cmds) >= n_ticks, 60.0), (
            f"the lagging reader got {len(late_cmds)} of {n_ticks} commands"
        )
        spin_until(lagging, lambda: proc.poll() is not None, 30.0)
        assert proc.wait(timeout=5) == 0  # it left once the lagging reader had everything
        spin_until(node, lambda: False, 0.5)
        spin_until(lagging, lambda: False, 0.5)
        stamps = [(m.header.stamp.sec, m.header.stamp.nanosec) for m in late_cmds]
        assert len(stamps) == n_ticks and set(stamps) == seen and stamps == sorted(stamps)
        assert len(infos) > n_ticks // 3  # a mark every 2 steps at this info rate, and the changes
        assert [
            (m.header.stamp.sec, m.header.stamp.nanosec, m.run, m.steady) for m in late_infos
        ] == [(m.header.stamp.sec, m.header.stamp.nanosec, m.run, m.steady) for m in infos]
    finally:
        stop(proc)
        lagging.destroy_node()


def test_wait_for_subscribers_starts_the_plan_once_its_writers_have_matched_them(node):
    """wait_for_subscribers:=2: ticks before the second subscriber is matched publish nothing, and
    the plan (run 0, settling) starts at the first tick after: no reader misses its beginning."""
    from piezo_stage_msgs.msg import ExcitationInfo, Voltage

    proc = start_node(
        "excitation",
        *PLAN,
        "trigger:=clock",
        "use_sim_time:=true",
        "wait_for_subscribers:=2",
        namespace="/exc",
    )
    cmds: list[Voltage] = []
    infos: list[ExcitationInfo] = []
    node.create_subscription(Voltage, "voltage_command", cmds.append, COMMAND_QOS)
    node.create_subscription(ExcitationInfo, "excitation", infos.append, COMMAND_QOS)
    clock = node.create_publisher(Clock, "/clock", COMMAND_QOS)
    second = rclpy.create_node("second", namespace="/exc")
    try:
        assert spin_until(node, lambda: node.count_subscribers("/clock") >= 1, 15.0)
        for k in range(20):  # one subscriber each: the plan waits
            clock.publish(Clock(clock=Time(sec=50, nanosec=k * 1000)))
            spin_until(node, lambda: False, 0.05)
        assert cmds == [] and infos == []
        late: list[ExcitationInfo] = []
        second.create_subscription(Voltage, "voltage_command", lambda m: None, COMMAND_QOS)
        second.create_subscription(ExcitationInfo, "excitation", late.append, COMMAND_QOS)
        ns = 100_000
        while not cmds and ns < 10_000_000_000:
            clock.publish(Clock(clock=Time(sec=50, nanosec=ns)))
            spin_until(node, lambda: bool(cmds), 0.1)
            ns += 1000
        assert cmds, "the plan did not start once both subscribers were there"
        assert spin_until(node, lambda: bool(infos), 5.0) and spin_until(
            second, lambda: bool(late), 5.0
        )
        first = cmds[0].header.stamp
        assert (infos[0].run, infos[0].steady) == (0, False) and infos[0].header.stamp == first
        assert late[0].header.stamp == first  # the second reader has the first mark too
        assert cmds[0].voltage == pytest.approx(-1.0)  # the triangle's start: the plan's t = 0
    finally:
        stop(proc)
        second.destroy_node()
