"""voltage_driver node over real DDS against amplifier emulators run in this process: each safety
rule (limits, NaN/inf, late commands, slew, watchdog, SIGINT/SIGTERM, reconnect) checked on what
the emulated device actually received, and the apply_at_stamp playout."""

from __future__ import annotations

import math
import signal

import pytest
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.qos import QoSProfile
from rclpy.time import Time

from piezo_stage.hardware.emulators import EmulatorServer, GCSDeviceModel, MDTDeviceModel
from piezo_stage.nodes.qos import COMMAND_QOS, SENSOR_QOS

from rig_support import DiagnosticsProbe, sva_values
from ros_support import call_idempotent, spin_until, start_node, stop

pytestmark = pytest.mark.ros

NS = "/rig"
CAP_TIME = 0.025  # s: no write carries more slew than this


@pytest.fixture()
def gcs():
    """GCS controller (VMI -20 V, VMA 120 V) on loopback TCP."""
    model = GCSDeviceModel(v_min=-20.0, v_max=120.0)
    with EmulatorServer(model, tcp_port=0) as server:
        yield model, server


class Driver:
    """A voltage_driver process plus the probe's command publisher, voltage and diagnostics."""

    def __init__(self, probe, url: str, *params: str, backend: str = "gcs") -> None:
        from piezo_stage_msgs.msg import Voltage

        self.probe = probe
        self.proc = start_node(
            "voltage_driver", f"backend:={backend}", f"url:={url}", *params, namespace=NS
        )
        self.voltages: list = []
        # best effort as the driver offers, but a deep history: the sensor-data depth of 5 loses
        # the playout's 500 Hz values whenever this probe spins late on a loaded host
        deep = QoSProfile(
            depth=1000, reliability=SENSOR_QOS.reliability, durability=SENSOR_QOS.durability
        )
        probe.create_subscription(Voltage, "voltage", self.voltages.append, deep)
        self.diag = DiagnosticsProbe(probe, f"{NS}/voltage_driver")
        self.cmd = probe.create_publisher(Voltage, "voltage_command", COMMAND_QOS)
        ok = spin_until(
            probe,
            lambda: self.cmd.get_subscription_count() > 0 and self.diag.latest is not None,
            20.0,
        )
        assert ok, stop(self.proc)

    def send(self, voltage: float, stamp: Time | None = None) -> None:
        from piezo_stage_msgs.msg import Voltage

        msg = Voltage(voltage=voltage)
        msg.header.stamp = (stamp or self.probe.get_clock().now()).to_msg()
        self.cmd.publish(msg)

    def wait(self, predicate, timeout: float = 5.0) -> bool:
        return spin_until(self.probe, predicate, timeout)


@pytest.mark.parametrize("backend", ["gcs", "mdt69x"])
def test_out_of_range_commands_are_clamped_to_configured_and_device_limits(probe, backend):
    # configured [-50, 100] V; device GCS [-20, 120] V, MDT69x [0, 75] V (vlimit switch)
    model = (
        GCSDeviceModel(v_min=-20.0, v_max=120.0)
        if backend == "gcs"
        else MDTDeviceModel(vlimit=75.0)
    )
    server = (
        EmulatorServer(model, tcp_port=0) if backend == "gcs" else EmulatorServer(model, pty=True)
    )
    lo, hi = (-20.0, 100.0) if backend == "gcs" else (0.0, 75.0)
    with server:
        d = Driver(
            probe,
            server.url,
            "v_min:=-50.0",
            "v_max:=100.0",
            "command_timeout:=0.0",
            "readback_rate_hz:=0.0",
            backend=backend,
        )
        try:
            d.send(500.0)
            assert d.wait(lambda: sva_values(model)[-1:] == [hi]), sva_values(model)
            d.send(-500.0)
            assert d.wait(lambda: sva_values(model)[-1:] == [lo]), sva_values(model)
            d.send(12.5)
            assert d.wait(lambda: sva_values(model)[-1:] == [12.5])
            assert d.wait(
                lambda: d.voltages and d.voltages[-1].voltage == 12.5
            )  # acknowledged value
            assert d.wait(lambda: d.diag.value("clamped_commands") == "2", 3.0), d.diag.values
            assert float(d.diag.value("v_min")) == lo and float(d.diag.value("v_max")) == hi
        finally:
            stop(d.proc)
    assert min(sva_values(model)) >= lo and max(sva_values(model)) <= hi


def test_nonfinite_and_late_commands_never_reach_the_amplifier(probe, gcs):
    model, server = gcs
    d = Driver(
        probe, server.url, "command_timeout:=0.0", "readback_rate_hz:=0.0", "max_command_age:=0.5"
    )
    try:
        d.send(10.0)
        assert d.wait(lambda: sva_values(model)[-1:] == [10.0])
        n = len(sva_values(model))
        for bad in (math.nan, math.inf, -math.inf):
            d.send(bad)
        d.send(20.0, stamp=probe.get_clock().now() - rclpy.duration.Duration(seconds=5.0))  # late
        d.send(30.0, stamp=Time())  # unstamped: refused when stamps are checked
        assert d.wait(
            lambda: (
                d.diag.value("rejected_nonfinite") == "3"
                and d.diag.value("rejected_late") == "1"
                and d.diag.value("rejected_stamp_unstamped") == "1"
            ),
            5.0,
        ), d.diag.values
        assert len(sva_values(model)) == n and model.applied_voltage == 10.0  # device unchanged
        assert d.diag.latest.level == DiagnosticStatus.WARN
        d.send(11.0)  # a fresh command still goes through
        assert d.wait(lambda: sva_values(model)[-1:] == [11.0])
    finally:
        _, err = stop(d.proc)
    assert "rejected non-finite voltage command" in err and "rejected late voltage command" in err


def test_slew_rate_limits_every_step(probe, gcs):
    model, server = gcs
    rate = 40.0  # V/s; one write moves at most rate x min(watchdog_period, 25 ms)
    d = Driver(
        probe, server.url, f"slew_rate:={rate}", "command_timeout:=0.0", "readback_rate_hz:=0.0"
    )
    try:
        while not (sva_values(model) and sva_values(model)[-1] >= 20.0):
            d.send(100.0)
            assert d.wait(lambda: False, 0.02) is False
            assert len(sva_values(model)) < 400, sva_values(model)
    finally:
        stop(d.proc)
    sent = [0.0] + [
        v for v in sva_values(model) if v < 99.0
    ]  # the ramp up (shutdown ramps back down)
    steps = [b - a for a, b in zip(sent, sent[1:])]
    assert len(steps) >= 10 and max(abs(s) for s in steps) <= rate * CAP_TIME + 1e-6
    assert max(sva_values(model)) < 100.0  # never jumped to the request


def test_apply_at_stamp_plays_commands_at_their_stamps_with_a_first_order_hold(probe, gcs):
    """apply_at_stamp: commands stamped ahead (the excitation's lead) and arriving out of order are
    written at their stamps, in stamp order, with hold_period values interpolated in between;
    every value written is published (``voltage`` is what the device applies), the commands never
    before their stamps."""
    from rclpy.duration import Duration

    model, server = gcs
    d = Driver(
        probe,
        server.url,
        "apply_at_stamp:=true",
        "hold_period:=0.002",
        "command_timeout:=0.0",
        "readback_rate_hz:=0.0",
    )
    try:
        now = probe.get_clock().now()  # 80 ms apart: within the playout's 0.1 s interpolation gap
        commands = {
            10.0: now + Duration(seconds=1.0),
            30.0: now + Duration(seconds=1.08),
            50.0: now + Duration(seconds=1.16),
        }
        for v in (50.0, 10.0, 30.0):  # out of order
            d.send(v, commands[v])
        assert d.wait(lambda: any(m.voltage == 50.0 for m in d.voltages), 20.0), sva_values(model)
        d.wait(lambda: False, 0.2)
    finally:
        stop(d.proc)
    sent = sva_values(model)
    first = sent.index(10.0)
    played = sent[first : sent.index(50.0) + 1]
    assert 30.0 in played and played == sorted(played)  # 10 -> 30 -> 50, monotone
    assert sum(10.0 < v < 30.0 for v in played) >= 3  # the first-order hold between 10 and 30 V
    assert sum(30.0 < v < 50.0 for v in played) >= 3
    published = {
        m.voltage: Time.from_msg(m.header.stamp) for m in d.voltages if m.voltage in commands
    }
    assert set(published) == set(commands)
    written = [
        m.voltage for m in d.voltages if m.voltage != 0.0
    ]  # the interpolated values too, in order
    assert written[written.index(10.0) : written.index(50.0) + 1] == played
    stamps = [Time.from_msg(m.header.stamp).nanoseconds for m in d.voltages]
    assert stamps == sorted(stamps)
    for v, stamp in commands.items():
        assert published[v] >= stamp, v  # written at (not before) its stamp


def test_a_watchdog_turn_between_a_write_and_its_publication_publishes_it_once(probe, gcs):
    """The watchdog timer (executor thread) publishes a ramp step when the value last written
    differs from the one last published. A command written by another thread (the playout, the
    rig loop) and not yet published is no ramp step: here the timer fires right after the write,
    and the value is still published once (and, with the read-back off, nothing else is)."""
    import threading

    from rclpy.parameter import Parameter

    from piezo_stage.nodes.voltage_driver import VoltageDriverNode

    _, server = gcs
    settings = {"backend": "gcs", "url": server.url, "command_timeout": 0.0}
    settings["readback_rate_hz"] = 0.0  # only the commands are published
    node = VoltageDriverNode(overrides=[Parameter(k, value=v) for k, v in settings.items()])
    published: list[float] = []
    (axis,) = node.axes.values()  # the one axis, its topics unprefixed
    axis.publish = lambda voltage, stamp: published.append(voltage)
    turns: list[threading.Thread] = []
    driver = node.driver.drivers[axis.channel]
    write = driver.set_voltage

    def write_then_timer(voltage, received=None):
        result = write(voltage, received)
        turns.append(threading.Thread(target=node._watchdog))  # the timer fires now
        turns[-1].start()
        turns[-1].join(timeout=0.5)  # it may wait for the command to be published
        return result

    driver.set_voltage = write_then_timer
    try:
        node.set_voltages({axis.channel: 12.0})
        node.set_voltages({axis.channel: 34.0})
        for turn in turns:
            turn.join(timeout=5.0)
    finally:
        node.driver.close()
        node.destroy_node()
    assert published == [12.0, 34.0]


def test_realtime_priority_covers_the_playout_and_the_executor_thread(probe, gcs):
    """realtime_priority: the playout thread and the executor's thread (which holds the GIL the
    playout needs) both run SCHED_FIFO when the system allows it, and /diagnostics says which."""
    import os

    _, server = gcs
    d = Driver(
        probe,
        server.url,
        "apply_at_stamp:=true",
        "realtime_priority:=5",
        "command_timeout:=0.0",
        "readback_rate_hz:=0.0",
    )
    try:
        assert d.wait(lambda: d.diag.value("executor_priority") != "", 10.0), d.diag.values
        playout, executor = d.diag.value("playout_priority"), d.diag.value("executor_priority")
        policy = os.sched_getscheduler(d.proc.pid)  # the process's main thread runs the executor
    finally:
        stop(d.proc)
    assert playout == executor  # both granted, or both refused for the same reason
    if executor == "5":
        assert policy == os.SCHED_FIFO
    else:
        assert "refused" in executor and policy != os.SCHED_FIFO


def test_watchdog_ramps_to_safe_voltage_when_commands_stop(probe, gcs):
    model, server = gcs
    d = Driver(
        probe,
        server.url,
        "safe_voltage:=5.0",
        "slew_rate:=200.0",
        "command_timeout:=0.3",
        "readback_rate_hz:=20.0",
    )
    try:
        # (before any command the watchdog has already taken the output to safe_voltage once)
        for _ in range(30):  # -> 40 V at 200 V/s, commands every 20 ms
            d.send(40.0)
            d.wait(lambda: False, 0.02)
        assert model.applied_voltage == 40.0, sva_values(model)
        n = len(sva_values(model))
        while d.diag.value("state") != "active":  # diagnostics of the commanded phase
            d.send(40.0)
            assert (
                d.wait(lambda: d.diag.value("state") == "active", 0.1)
                or len(sva_values(model)) < n + 50
            )
        trips = int(d.diag.value("watchdog_trips"))
        n = len(sva_values(model))
        assert d.wait(lambda: model.applied_voltage == 5.0, 5.0), sva_values(model)[-10:]
        assert d.wait(
            lambda: (
                d.diag.value("watchdog_trips") == str(trips + 1) and d.diag.value("state") == "safe"
            ),
            3.0,
        ), d.diag.values
        assert d.wait(
            lambda: d.voltages and d.voltages[-1].voltage == 5.0, 2.0
        )  # read-back published
    finally:
        _, err = stop(d.proc)
    down = sva_values(model)[n:]
    assert len(down) > 5 and all(b <= a for a, b in zip(down, down[1:]))  # a ramp, not a jump
    assert max(a - b for a, b in zip([40.0] + down, down)) <= 200.0 * CAP_TIME + 1e-6
    assert "no voltage command" in err


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_ramps_to_safe_voltage_and_exits_zero(probe, gcs, sig):
    model, server = gcs
    d = Driver(probe, server.url, "safe_voltage:=2.0", "slew_rate:=500.0", "command_timeout:=0.0")
    try:
        d.send(60.0)
        while model.applied_voltage != 60.0:
            d.send(60.0)
            assert (
                d.wait(lambda: model.applied_voltage == 60.0, 0.05) or len(sva_values(model)) < 200
            )
        n = len(sva_values(model))
        d.proc.send_signal(sig)
        code = d.proc.wait(timeout=10.0)
    finally:
        _, err = stop(d.proc)
    assert code == 0, err
    assert model.applied_voltage == 2.0 and sva_values(model)[-1] == 2.0
    down = sva_values(model)[n:]
    assert (
        len(down) > 3 and max(a - b for a, b in zip([60.0] + down, down)) <= 500.0 * CAP_TIME + 1e-6
    )
    assert "shut down at 2 V" in err
    assert any(c.startswith("SVO") and c.split()[-1] == "0" for c in model.commands)  # open loop


def test_reconnects_after_the_link_drops(probe, gcs):
    model, server = gcs
    d = Driver(probe, server.url, "command_timeout:=0.0", "readback_rate_hz:=20.0")
    try:
        d.send(7.0)
        assert d.wait(lambda: model.applied_voltage == 7.0)
        server.disconnect()
        d.wait(lambda: False, 0.3)  # the read-back notices the hang-up and reopens the link
        d.send(8.0)
        assert d.wait(lambda: model.applied_voltage == 8.0, 5.0), d.diag.values
        assert d.wait(
            lambda: (
                int(d.diag.value("reconnects", "0")) >= 1 and d.diag.value("connected") == "True"
            ),
            3.0,
        ), d.diag.values
        assert d.diag.latest.level == DiagnosticStatus.OK
        assert model.commands.count("*IDN?") >= 2  # really opened twice
    finally:
        stop(d.proc)


# --- stamps, use_sim_time, queued commands, silent device, exit codes ------------------
def _stamp(sec: int, nanosec: int = 0):
    from builtin_interfaces.msg import Time as TimeMsg

    return TimeMsg(sec=sec, nanosec=nanosec)


def test_bad_stamps_are_counted_rejections_never_a_crash(probe, gcs):
    """sec = -1 made the driver exit 1 ("Seconds value must not be negative"); a stamp in 2038
    was applied."""
    from piezo_stage_msgs.msg import Voltage

    model, server = gcs
    d = Driver(
        probe, server.url, "command_timeout:=0.0", "readback_rate_hz:=0.0", "max_command_age:=0.5"
    )
    try:
        d.send(10.0)
        assert d.wait(lambda: sva_values(model)[-1:] == [10.0])
        n = len(sva_values(model))
        for stamp in (_stamp(-1), _stamp(-2_000_000_000, 5), _stamp(2_147_000_000)):
            msg = Voltage(voltage=50.0)
            msg.header.stamp = stamp
            d.cmd.publish(msg)
        d.send(11.0)  # still alive, and the bad ones never reached the device
        assert d.wait(lambda: sva_values(model)[-1:] == [11.0]), d.proc.poll()
        assert sva_values(model)[n:] == [11.0]
        assert d.wait(
            lambda: (
                d.diag.value("rejected_stamp_negative") == "2"
                and d.diag.value("rejected_stamp_ahead") == "1"
            ),
            5.0,
        ), d.diag.values
    finally:
        stop(d.proc)


def test_use_sim_time_cannot_be_switched_on_at_run_time(probe, gcs):
    """With use_sim_time switched on, the clock read 0 and commands stamped 1 h old were applied."""
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    model, server = gcs
    d = Driver(
        probe, server.url, "command_timeout:=0.0", "readback_rate_hz:=0.0", "max_command_age:=0.5"
    )
    try:
        client = probe.create_client(SetParameters, f"{NS}/voltage_driver/set_parameters")
        assert client.wait_for_service(timeout_sec=10.0)
        req = SetParameters.Request(
            parameters=[Parameter("use_sim_time", value=True).to_parameter_msg()]
        )
        result = call_idempotent(probe, client, req, 10.0)
        assert result is not None and not result.results[0].successful
        n = len(sva_values(model))
        d.send(40.0, stamp=probe.get_clock().now() - rclpy.duration.Duration(seconds=3600.0))
        assert d.wait(lambda: d.diag.value("rejected_late") == "1", 5.0), d.diag.values
        assert len(sva_values(model)) == n
    finally:
        stop(d.proc)


@pytest.mark.slow
def test_watchdog_clears_queued_commands_when_the_publisher_stops(probe, gcs):
    """apply_at_stamp, commands stamped 4 s ahead: the publisher stops; the watchdog fires
    command_timeout after the last *received* command and the queued commands never reach the
    device after that (they kept it away from safe_voltage for 4.86 s)."""
    model, server = gcs
    d = Driver(
        probe,
        server.url,
        "command_timeout:=0.5",
        "readback_rate_hz:=0.0",
        "apply_at_stamp:=true",
        "slew_rate:=1000.0",
    )
    try:
        # no command yet: the watchdog fires once, 0.5 s after start
        assert d.wait(lambda: d.diag.value("watchdog_trips") == "1", 5.0), d.diag.values
        ahead = rclpy.duration.Duration(seconds=4.0)
        for k in range(50):  # 0.5 s of commands, each due 4 s after it is sent
            d.send(30.0 + 0.1 * k, stamp=probe.get_clock().now() + ahead)
            d.wait(lambda: False, 0.01)
        assert d.wait(lambda: d.diag.value("watchdog_trips") == "2", 3.0), d.diag.values
        n = len(sva_values(model))
        d.wait(lambda: False, 5.0)  # past the time the queued commands were due
        assert all(v == 0.0 for v in sva_values(model)[n:]), sva_values(model)[n:]
        assert model.applied_voltage == 0.0 and d.diag.value("pending_playout") == "0"
    finally:
        stop(d.proc)


def test_silent_device_is_an_error_and_diagnostics_keep_coming(probe):
    """Reconnects ran in the executor: the first ERROR came after 7.3 s and /diagnostics was
    silent for 8.1 s, a whole round of reconnect attempts. Here a round is long (10 attempts,
    each waiting io_timeout 3 s for a device that does not answer: ~30 s), so an executor that
    runs it sends nothing for that long; the driver's statuses must keep coming meanwhile: 4
    more ERRORs (one is due every second; a generous 20 s to get them), all while the device
    is silent, none of them another level. Counted, not timed; then the link comes back."""
    from piezo_stage.hardware.emulators import Faults

    model = GCSDeviceModel()
    faults = Faults()
    with EmulatorServer(model, tcp_port=0, faults=faults) as server:
        d = Driver(
            probe,
            server.url,
            "command_timeout:=0.0",
            "readback_rate_hz:=20.0",
            "io_timeout:=3.0",
            "reconnect_attempts:=10",
        )
        try:
            statuses: list[DiagnosticStatus] = []
            probe.create_subscription(
                DiagnosticArray,
                "/diagnostics",
                lambda m: statuses.extend(s for s in m.status if s.name == d.diag.fqn),
                10,
            )
            assert d.wait(lambda: d.diag.value("connected") == "True", 10.0), d.diag.values
            faults.silent = True
            # the read-back times out after io_timeout: ERROR (a generous wait)
            assert d.wait(lambda: d.diag.latest.level == DiagnosticStatus.ERROR, 30.0), (
                d.diag.values
            )
            first = len(statuses)
            assert d.wait(lambda: len(statuses) >= first + 4, 20.0), [s.message for s in statuses]
            silent = statuses[first:]  # the device is still silent: it is told after this
            faults.silent = False
            assert all(s.level == DiagnosticStatus.ERROR for s in silent), [
                s.message for s in silent
            ]
            assert all(s.values and "disconnected" in s.message for s in silent)
            assert d.wait(lambda: d.diag.value("connected") == "True", 30.0), d.diag.values
        finally:
            stop(d.proc)


def test_exit_code_is_non_zero_when_safe_voltage_was_not_reached(probe):
    """The link is down at shutdown: the output cannot be ramped to safe_voltage (exit 0 before)."""
    model = GCSDeviceModel()
    server = EmulatorServer(model, tcp_port=0).start()
    d = Driver(
        probe, server.url, "command_timeout:=0.0", "readback_rate_hz:=20.0", "slew_rate:=1000.0"
    )
    try:
        d.send(20.0)
        assert d.wait(lambda: model.applied_voltage > 0.0, 5.0)
        server.stop()  # the amplifier is gone
        d.wait(lambda: False, 0.5)
        d.proc.send_signal(signal.SIGINT)
        code = d.proc.wait(timeout=30.0)
    finally:
        _, err = stop(d.proc)
    assert code != 0 and "safe_voltage" in err, (code, err[-2000:])
