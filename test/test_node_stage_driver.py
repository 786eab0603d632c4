"""voltage_driver over a stage, over real DDS, against an emulated E-727-class GCS controller
(three axes, axis i on output channel i) run in this process: each axis commanded on its own
topic reaches its channel, and the safety rules hold per axis on what the emulated device
received (its per-axis voltage log and its command lines)."""

from __future__ import annotations

import signal
import subprocess
import time

import pytest
from rclpy.qos import QoSProfile

from piezo_stage.hardware.emulators import EmulatorServer, GCSDeviceModel
from piezo_stage.nodes.qos import COMMAND_QOS, SENSOR_QOS

from rig_support import DiagnosticsProbe
from ros_support import spin_until, start_node, stop

pytestmark = pytest.mark.ros

NS = "/stage"
CAP_TIME = 0.025  # s: no write carries more slew than this
XYZ = {"x": "1", "y": "2", "z": "3"}  # config/xyz_scanner.yaml: axis -> channel


class Device:
    """The emulated controller: its command lines and, per channel, every voltage applied
    (what the amplifier saw, as ``emulate --log`` writes it)."""

    def __init__(self) -> None:
        self.log: list[tuple[str, float, float]] = []  # (channel, volts, arrival time)
        self.model = GCSDeviceModel(
            axes=("1", "2", "3"),
            v_min=-20.0,
            v_max=120.0,
            on_axis_voltage=lambda a, v, at: self.log.append((a, v, time.monotonic())),
        )

    def applied(self, channel: str) -> list[float]:
        return [v for a, v, _ in list(self.log) if a == channel]

    def svas(self) -> list[list[str]]:
        """Every SVA line's axis/value words."""
        return [c.split()[1:] for c in list(self.model.commands) if c.startswith("SVA ")]


@pytest.fixture()
def device():
    dev = Device()
    with EmulatorServer(dev.model, tcp_port=0) as server:
        dev.url = server.url
        yield dev


class StageNode:
    """A voltage_driver process over a stage (config/xyz_scanner.yaml unless told) plus the
    probe's command publishers, voltage subscriptions and diagnostics, per axis."""

    def __init__(self, probe, url: str, *params: str, stage: str = "xyz_scanner.yaml") -> None:
        from piezo_stage_msgs.msg import Voltage

        self.probe = probe
        self.proc = start_node(
            "voltage_driver",
            f"stage_file:={stage}",
            "backend:=gcs",
            f"url:={url}",
            *params,
            namespace=NS,
        )
        deep = QoSProfile(
            depth=1000, reliability=SENSOR_QOS.reliability, durability=SENSOR_QOS.durability
        )
        self.voltages: dict[str, list] = {a: [] for a in XYZ}
        self.cmd = {}
        self.diag = {}
        for axis in XYZ:
            probe.create_subscription(Voltage, f"{axis}/voltage", self.voltages[axis].append, deep)
            self.cmd[axis] = probe.create_publisher(Voltage, f"{axis}/voltage_command", COMMAND_QOS)
            self.diag[axis] = DiagnosticsProbe(probe, f"{NS}/voltage_driver/{axis}")
        self.link = DiagnosticsProbe(probe, f"{NS}/voltage_driver")
        ok = spin_until(
            probe,
            lambda: (
                all(c.get_subscription_count() > 0 for c in self.cmd.values())
                and self.link.latest is not None
                and all(d.latest is not None for d in self.diag.values())
            ),
            30.0,
        )
        assert ok, stop(self.proc)

    def send(self, axis: str, voltage: float) -> None:
        from piezo_stage_msgs.msg import Voltage

        msg = Voltage(voltage=voltage)
        msg.header.stamp = self.probe.get_clock().now().to_msg()
        self.cmd[axis].publish(msg)

    def wait(self, predicate, timeout: float = 30.0) -> bool:
        return spin_until(self.probe, predicate, timeout)


def _steps(values: list[float], start: float = 0.0) -> list[float]:
    return [abs(b - a) for a, b in zip([start] + values, values)]


def test_each_axis_commanded_on_its_own_topic_reaches_its_channel(probe, device):
    """write_rate_hz 0: each command is written as it arrives, naming its axis alone; the value
    is published on the axis's voltage topic; out-of-range commands are clamped and non-finite
    ones refused for that axis, never sent."""
    s = StageNode(probe, device.url, "command_timeout:=0.0", "readback_rate_hz:=0.0")
    try:
        for axis, v in (("x", 10.0), ("y", 20.0), ("z", 30.0)):
            s.send(axis, v)
        want = {"1": 10.0, "2": 20.0, "3": 30.0}
        assert s.wait(lambda: device.model.applied_voltages() == want), device.svas()
        assert all(len(words) == 2 for words in device.svas()), device.svas()  # one axis a line
        assert s.wait(
            lambda: all(
                s.voltages[a] and s.voltages[a][-1].voltage == want[c] for a, c in XYZ.items()
            )
        ), {a: [m.voltage for m in ms] for a, ms in s.voltages.items()}
        n = len(device.svas())
        s.send("y", float("nan"))
        s.send("x", 500.0)  # above v_max 100 V
        assert s.wait(lambda: device.model.applied_voltages()["1"] == 100.0), device.svas()
        assert s.wait(
            lambda: (
                s.diag["y"].value("rejected_nonfinite") == "1"
                and s.diag["x"].value("clamped_commands") == "1"
                and s.diag["x"].value("commands") == "2"
            )
        ), (s.diag["x"].values, s.diag["y"].values)
        assert device.svas()[n:] == [["1", "100.000000"]]  # the NaN never left the node
        assert device.model.applied_voltages() == {"1": 100.0, "2": 20.0, "3": 30.0}
        assert s.link.value("connected") == "True" and s.link.value("axes") == "x y z"
    finally:
        _, err = stop(s.proc)
    assert "y: rejected non-finite voltage command" in err


def test_apply_at_stamp_plays_each_axis_command_at_its_stamp_plus_the_delay(probe, device):
    """apply_at_stamp: each axis's commands leave at their stamp + command_delay, in stamp
    order per axis, not on arrival; an unstamped one is refused."""
    from builtin_interfaces.msg import Time

    from piezo_stage_msgs.msg import Voltage

    delay = 0.2
    s = StageNode(
        probe,
        device.url,
        "apply_at_stamp:=true",
        f"command_delay:={delay}",
        "command_timeout:=0.0",
        "readback_rate_hz:=0.0",
    )
    try:
        sent_at = time.monotonic()
        now = probe.get_clock().now().nanoseconds
        # x: 30 V due at +0.6 s, sent first; y: 20 V due at +0.3 s; x: 10 V due at +0.4 s
        for axis, volts, ahead in (("x", 30.0, 0.4), ("y", 20.0, 0.1), ("x", 10.0, 0.2)):
            msg = Voltage(voltage=volts)
            ns = now + round(ahead * 1e9)
            msg.header.stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
            s.cmd[axis].publish(msg)
        s.cmd["z"].publish(Voltage(voltage=5.0))  # no stamp
        assert s.wait(lambda: device.applied("1")[-1:] == [30.0]), device.log
        assert s.wait(lambda: s.diag["z"].value("rejected_stamp_unstamped") == "1"), s.diag[
            "z"
        ].values
    finally:
        stop(s.proc)
    at = {(c, v): t - sent_at for c, v, t in device.log}
    print({k: f"{v:.3f} s" for k, v in at.items()})
    # each at its due time or later (the host may be slow), never before; in stamp order
    assert at[("2", 20.0)] >= delay + 0.1 - 0.02
    assert at[("1", 10.0)] >= delay + 0.2 - 0.02
    assert at[("1", 30.0)] >= delay + 0.4 - 0.02
    assert at[("2", 20.0)] < at[("1", 10.0)] < at[("1", 30.0)]
    assert ("3", 5.0) not in at  # the unstamped command never left the node


def test_the_slew_cap_holds_per_axis_between_successive_writes(probe, device):
    rate = 40.0  # V/s: one write moves an axis at most rate x 25 ms = 1 V
    s = StageNode(probe, device.url, f"slew_rate:={rate}", "command_timeout:=0.0")
    try:
        deadline = time.monotonic() + 60.0
        while not (device.applied("1")[-1:] >= [20.0] and device.applied("2")[-1:] >= [10.0]):
            s.send("x", 60.0)
            s.send("y", 30.0)
            s.wait(lambda: False, 0.02)
            assert time.monotonic() < deadline, device.svas()[-5:]
    finally:
        stop(s.proc)  # SIGTERM: the shutdown ramp is capped too
    for channel in ("1", "2"):
        applied = device.applied(channel)
        assert len(applied) >= 10 and max(_steps(applied)) <= rate * CAP_TIME + 1e-6, channel
    assert max(device.applied("1")) < 60.0 and max(device.applied("2")) < 30.0  # never jumped


def test_one_axis_watchdog_ramps_that_axis_only(probe, device):
    s = StageNode(
        probe,
        device.url,
        "safe_voltage:=5.0",
        "slew_rate:=200.0",
        "command_timeout:=0.3",
        "readback_rate_hz:=10.0",
    )
    try:
        # (before any command every axis's watchdog has taken its output to 5 V once)
        assert s.wait(lambda: device.model.applied_voltages() == {c: 5.0 for c in "123"})
        deadline = time.monotonic() + 30.0
        while device.model.applied_voltages() != {"1": 40.0, "2": 40.0, "3": 5.0}:
            s.send("x", 40.0)
            s.send("y", 40.0)
            s.wait(lambda: False, 0.02)
            assert time.monotonic() < deadline, device.model.applied_voltages()
        n = len(device.applied("2"))
        trips_x = s.diag["x"].value("watchdog_trips")
        # x keeps being commanded, y falls silent: only y ramps back to safe_voltage
        end = time.monotonic() + 2.0
        while time.monotonic() < end:
            s.send("x", 40.0)
            s.wait(lambda: False, 0.02)
        assert device.model.applied_voltages() == {"1": 40.0, "2": 5.0, "3": 5.0}
        assert s.wait(
            lambda: s.diag["y"].value("state") == "safe" and s.diag["x"].value("state") == "active"
        ), (s.diag["x"].values, s.diag["y"].values)
        assert s.diag["x"].value("watchdog_trips") == trips_x
        assert s.wait(lambda: s.voltages["y"] and s.voltages["y"][-1].voltage == 5.0)
    finally:
        _, err = stop(s.proc)
    down = device.applied("2")[n:]
    assert len(down) > 5 and all(b <= a for a, b in zip(down, down[1:]))  # a ramp, not a jump
    assert max(_steps(down, 40.0)) <= 200.0 * CAP_TIME + 1e-6
    assert "y: no voltage command" in err


def test_sigint_ramps_every_axis_to_safe_voltage_and_exits_zero(probe, device):
    s = StageNode(
        probe, device.url, "safe_voltage:=2.0", "slew_rate:=500.0", "command_timeout:=0.0"
    )
    want = {"1": 60.0, "2": 50.0, "3": 40.0}
    try:
        deadline = time.monotonic() + 30.0
        while device.model.applied_voltages() != want:
            for axis, channel in XYZ.items():
                s.send(axis, want[channel])
            s.wait(lambda: False, 0.05)
            assert time.monotonic() < deadline, device.model.applied_voltages()
        n = {c: len(device.applied(c)) for c in want}
        lines = len(device.svas())
        s.proc.send_signal(signal.SIGINT)
        code = s.proc.wait(timeout=30.0)
    finally:
        _, err = stop(s.proc)
    assert code == 0, err
    assert device.model.applied_voltages() == {c: 2.0 for c in want}
    for channel, start in want.items():
        down = device.applied(channel)[n[channel] :]
        assert len(down) > 3 and max(_steps(down, start)) <= 500.0 * CAP_TIME + 1e-6
    assert device.svas()[lines][::2] == ["1", "2", "3"]  # all axes ramp together
    assert "shut down at x 2 V, y 2 V, z 2 V" in err
    assert any(c.startswith("SVO") for c in device.model.commands)  # left in open loop


def _stage_file(tmp_path, axes):
    """A stage file of ``axes``: (name, channel, model file) each."""
    path = tmp_path / "stage.yaml"
    entries = ", ".join(f"{a}: {{model_file: {m}, channel: '{c}'}}" for a, c, m in axes)
    path.write_text(f"name: bad\naxes: {{{entries}}}\n")
    return str(path)


@pytest.mark.parametrize(
    "axes, message",
    [
        ([("x", "1", "ch11_rig.yaml"), ("y", "4", "ch11_rig.yaml")], "['4'] not on controller"),
        ([("x", "1", "ch11_rig.yaml"), ("y", "1", "ch11_rig.yaml")], "channel '1' used twice"),
        ([("x", "1", "ch11_rig.yaml"), ("y", "2", "no_such_model.yaml")], "axes.y.model_file"),
    ],
)
def test_a_stage_the_device_cannot_serve_exits_2_and_nothing_is_sent(
    probe, device, tmp_path, axes, message
):
    proc = start_node(
        "voltage_driver",
        f"stage_file:={_stage_file(tmp_path, axes)}",
        f"url:={device.url}",
        namespace=NS,
    )
    try:
        code = proc.wait(timeout=60.0)
    except subprocess.TimeoutExpired:  # say where it hangs: every thread's stack (faulthandler)
        proc.send_signal(signal.SIGABRT)
        _, err = stop(proc, timeout=30.0)
        pytest.fail(f"voltage_driver did not exit within 60 s; its stacks:\n{err[-6000:]}")
    _, err = stop(proc)
    lines = err.strip().splitlines()
    assert code == 2 and message in lines[-1] and lines[-1].startswith("error: "), err
    assert "Traceback" not in err
    sent = [c for c in device.model.commands if c.split()[0] in ("SVA", "SVO", "ONL")]
    assert sent == [] and device.model.applied_voltages() == {c: 0.0 for c in "123"}


def test_write_rate_writes_every_axis_latest_command_in_one_sva_per_period(probe, device):
    """write_rate_hz 2: commands arrive every ~10 ms per axis (slower on a loaded host); the
    device gets one SVA per period naming every axis, the latest command of each."""
    rate = 2.0  # Hz
    s = StageNode(
        probe, device.url, f"write_rate_hz:={rate}", "command_timeout:=0.0", "readback_rate_hz:=0.0"
    )
    try:
        n = len(device.svas())
        start = time.monotonic()
        k = 0
        # at least 3 s, and more command rounds than twice the writes the rate allows (a loaded
        # host sends fewer per second): the bound below then says the writes follow the rate
        while (t := time.monotonic() - start) < 6.0 or (k <= 2 * (t * rate + 2) and t < 30.0):
            k += 1
            for axis, channel in XYZ.items():
                s.send(axis, 10.0 * int(channel) + 0.01 * k)
            s.wait(lambda: False, 0.01)
        want = {c: round(10.0 * int(c) + 0.01 * k, 6) for c in "123"}
        assert s.wait(lambda: device.model.applied_voltages() == want), device.svas()[-3:]
        elapsed = time.monotonic() - start
        written = device.svas()[n:]
    finally:
        stop(s.proc)
    batched = [w for w in written if w[::2] == ["1", "2", "3"]]
    assert k >= 30 and len(written) <= elapsed * rate + 2, (k, len(written), elapsed)
    assert len(written) < k / 2  # far fewer writes than commands
    assert len(batched) >= 5 and len(batched) >= len(written) - 2, written  # all axes a line


def test_exit_code_is_non_zero_when_the_link_is_gone_at_shutdown(probe):
    """The amplifier is gone when SIGINT comes: no axis can be ramped to safe_voltage, and the
    exit code says so (naming each channel, and which axis is on it)."""
    dev = Device()
    server = EmulatorServer(dev.model, tcp_port=0).start()
    s = StageNode(
        probe, server.url, "command_timeout:=0.0", "readback_rate_hz:=20.0", "slew_rate:=1000.0"
    )
    try:
        s.send("x", 20.0)
        assert s.wait(lambda: dev.model.applied_voltages()["1"] > 0.0)
        server.stop()
        assert s.wait(lambda: s.link.value("connected") == "False"), s.link.values
        s.proc.send_signal(signal.SIGINT)
        code = s.proc.wait(timeout=120.0)
    finally:
        _, err = stop(s.proc)
    assert code == 1 and "1: output not brought to safe_voltage" in err, err[-2000:]
    assert "(axes x on 1, y on 2, z on 3)" in err
