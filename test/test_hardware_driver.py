"""Voltage driver safety, each item against a real emulator: limits, NaN/inf, slew, watchdog,
shutdown, reconnect."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from piezo_stage.hardware.amplifier import GCSAmplifier, MDT69xAmplifier, make_amplifier
from piezo_stage.hardware.driver import DriverConfig, DriverState, VoltageDriver, Watchdog
from piezo_stage.hardware.emulators import (
    EmulatorServer,
    Faults,
    GCSDeviceModel,
    ManualClock,
    MDTDeviceModel,
)
from piezo_stage.hardware.errors import (
    ConfigError,
    ConnectionLost,
    DeviceTimeout,
    LimitsError,
    NonFiniteVoltageError,
    NotConnected,
    VoltageOutOfRangeError,
)
from piezo_stage.hardware.safety import VoltageLimits, round_within, slew_step

pytestmark = pytest.mark.ros


FakeClock = ManualClock  # deterministic time for the driver (the emulators run on real time)


def sent_voltages(model) -> list[float]:
    """Every voltage the driver wrote, from the emulator's command log."""
    if isinstance(model, GCSDeviceModel):
        return [float(c.split()[2]) for c in model.commands if c.startswith("SVA ")]
    return [float(c.split("=")[1]) for c in model.commands if c.startswith("xvoltage=")]


@pytest.fixture(params=["gcs", "mdt69x"])
def rig(request):
    """(model, server, kind) for each amplifier: GCS on loopback TCP, MDT69x on a pty."""
    if request.param == "gcs":
        model = GCSDeviceModel(v_min=-20.0, v_max=120.0)
        server = EmulatorServer(model, tcp_port=0)
    else:
        model = MDTDeviceModel(vlimit=100.0)
        server = EmulatorServer(model, pty=True)
    with server:
        yield model, server, request.param


def make_driver(server, kind, clock=None, timeout=0.3, **cfg) -> VoltageDriver:
    cfg.setdefault("v_min", 0.0)
    cfg.setdefault("v_max", 150.0)
    amp = make_amplifier(kind, server.url, timeout=timeout)
    if clock is None:
        return VoltageDriver(amp, DriverConfig(**cfg))
    return VoltageDriver(amp, DriverConfig(**cfg), clock=clock, sleep=clock.sleep)


# --- pure arithmetic -----------------------------------------------------------------------------
def test_limits_arithmetic():
    a = VoltageLimits(0.0, 150.0)
    assert a.intersect(VoltageLimits(-20.0, 120.0)) == VoltageLimits(0.0, 120.0)
    with pytest.raises(LimitsError):
        a.intersect(VoltageLimits(200.0, 300.0))
    with pytest.raises(LimitsError):
        VoltageLimits(1.0, 0.0)
    with pytest.raises(LimitsError):
        VoltageLimits(0.0, math.inf)
    lim = VoltageLimits(0.0, 99.99951)
    assert round_within(99.9999, lim, 3) == 99.999  # rounds inward at the limit
    assert slew_step(0.0, 10.0, 100.0, 0.01) == pytest.approx(1.0)
    assert slew_step(0.0, -10.0, 100.0, 0.01) == pytest.approx(-1.0)
    assert slew_step(0.0, 10.0, math.inf, 0.0) == 10.0


@pytest.mark.parametrize(
    "bad",
    [
        dict(slew_rate=0.0),
        dict(command_timeout=-1.0),
        dict(safe_voltage=math.nan),
        dict(v_min=5.0, v_max=1.0),
        dict(reconnect_attempts=-1),
    ],
)
def test_config_validation(bad):
    with pytest.raises((ConfigError, LimitsError)):
        DriverConfig(**{"v_min": 0.0, "v_max": 100.0, **bad})


# --- limits --------------------------------------------------------------------------------------
def test_effective_limits_are_configured_intersect_device(rig):
    model, server, kind = rig
    driver = make_driver(server, kind, v_min=-50.0, v_max=200.0)
    info = driver.connect()
    device_max = 120.0 if kind == "gcs" else 100.0
    assert info.v_max == device_max
    assert driver.limits == VoltageLimits(max(-50.0, info.v_min), device_max)
    result = driver.set_voltage(1e4)
    assert result.clamped and result.sent == device_max
    result = driver.set_voltage(-1e4)
    assert result.clamped and result.sent == driver.limits.v_min
    for v in np.random.default_rng(1).uniform(-500, 500, 50):
        driver.set_voltage(v)
    sent = sent_voltages(model)
    assert len(sent) == 52
    assert min(sent) >= driver.limits.v_min and max(sent) <= driver.limits.v_max
    driver.close()


def test_refuse_mode_sends_nothing_out_of_range(rig):
    model, server, kind = rig
    driver = make_driver(server, kind, v_max=80.0, clamp=False)
    driver.connect()
    with pytest.raises(VoltageOutOfRangeError):
        driver.set_voltage(80.5)
    assert sent_voltages(model) == []
    assert driver.set_voltage(80.0).sent == 80.0
    driver.close()


def test_disjoint_limits_and_unsafe_safe_voltage_refuse_to_connect(rig):
    model, server, kind = rig
    with pytest.raises(LimitsError):
        make_driver(server, kind, v_min=200.0, v_max=300.0).connect()
    with pytest.raises(VoltageOutOfRangeError):
        make_driver(server, kind, v_min=10.0, v_max=50.0, safe_voltage=0.0).connect()
    assert sent_voltages(model) == []


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_voltage_is_rejected_and_nothing_sent(rig, bad):
    model, server, kind = rig
    driver = make_driver(server, kind)
    driver.connect()
    n_commands = len(model.commands)
    with pytest.raises(NonFiniteVoltageError):
        driver.set_voltage(bad)
    with pytest.raises(NonFiniteVoltageError):
        driver.ramp_to(bad)
    assert len(model.commands) == n_commands
    driver.close()


def test_open_loop_mode_is_selected_on_connect():
    model = GCSDeviceModel()  # servo on at power-up, SVA refused with error 79 until SVO 0
    with EmulatorServer(model, tcp_port=0) as server:
        driver = make_driver(server, "gcs")
        driver.connect()
        assert model.servo_on is False and model.online == {model.axis: True}
        assert driver.set_voltage(10.0).sent == 10.0
        assert driver.read_voltage() == 10.0
        driver.close()


# --- slew rate -----------------------------------------------------------------------------------
def test_slew_rate_limits_every_step(rig):
    model, server, kind = rig
    clock = FakeClock()
    driver = make_driver(server, kind, clock, slew_rate=100.0, write_period=0.01)
    driver.connect()
    times = np.concatenate([np.arange(1, 41) * 0.01, [10.0, 10.001, 10.002]])
    targets = [50.0] * 40 + [0.0, 90.0, 90.0]
    results = []
    for t, target in zip(times, targets):
        clock.t = t
        results.append(driver.set_voltage(target))
    sent = np.array([r.sent for r in results])
    assert sent[0] == pytest.approx(1.0) and results[0].slew_limited
    assert sent[39] == pytest.approx(40.0)
    assert sent[40] == pytest.approx(39.0)  # 9.6 s pause: one write still moves 100 V/s * 10 ms
    dt = np.minimum(np.diff(np.concatenate([[0.0], times])), 0.01)
    assert np.all(np.abs(np.diff(np.concatenate([[0.0], sent]))) <= 100.0 * dt + 1e-3)
    assert sent_voltages(model) == pytest.approx(list(sent), abs=1e-3)
    driver.close()


def test_limits_win_over_slew():
    """A device above the configured maximum is brought inside at once, never left outside."""
    model = GCSDeviceModel(servo_on=False)
    model.voltages[model.axis] = 110.0
    with EmulatorServer(model, tcp_port=0) as server:
        clock = FakeClock()
        driver = make_driver(server, "gcs", clock, v_max=100.0, slew_rate=10.0)
        driver.connect()
        clock.t = 0.01
        assert driver.set_voltage(100.0).sent == 100.0
        driver.close()


# --- watchdog ------------------------------------------------------------------------------------
def test_watchdog_ramps_to_safe_voltage_after_command_timeout(rig):
    model, server, kind = rig
    clock = FakeClock()
    driver = make_driver(
        server, kind, clock, safe_voltage=5.0, slew_rate=100.0, command_timeout=0.1
    )
    driver.connect()
    clock.t = 1.0
    driver.ramp_to(30.0)
    assert driver.state is DriverState.ACTIVE
    t_last = clock.t
    clock.t = t_last + 0.05
    assert driver.tick() is DriverState.ACTIVE
    n_before = len(sent_voltages(model))
    states = []
    for k in range(1, 40):
        clock.t = t_last + 0.1 + 0.01 * k
        states.append(driver.tick())
    assert states[0] is DriverState.TIMED_OUT and states[-1] is DriverState.SAFE
    assert driver.read_voltage() == pytest.approx(5.0)
    ramp = np.array(sent_voltages(model)[n_before:])
    assert ramp[0] == pytest.approx(29.0)  # first step: 100 V/s over one 10 ms write period
    assert np.all(np.diff(ramp) < 0) and np.all(np.abs(np.diff(ramp)) <= 1.0 + 1e-3)
    assert ramp[-1] == pytest.approx(5.0) and len(ramp) == 25
    clock.t += 0.01
    driver.set_voltage(6.0)  # commands resume
    assert driver.state is DriverState.ACTIVE
    driver.close()


def test_watchdog_reaches_safe_voltage_when_the_link_dropped():
    model = GCSDeviceModel()
    with EmulatorServer(model, tcp_port=0) as server:
        clock = FakeClock()
        driver = make_driver(
            server, "gcs", clock, safe_voltage=0.0, slew_rate=100.0, command_timeout=0.1
        )
        driver.connect()
        clock.t = 1.0
        driver.ramp_to(10.0)
        server.disconnect()  # the commands stop because the link died
        time.sleep(0.1)
        for _ in range(1, 30):
            clock.t += 0.01
            driver.tick()  # never blocks: the link is reopened in the background
            if driver.state is DriverState.DISCONNECTED:
                assert driver.wait_connected(5.0)
        assert driver.state is DriverState.SAFE and driver.reconnects == 1
        assert model.applied_voltage == 0.0
        driver.close()


def test_watchdog_thread_brings_output_to_safe_voltage():
    model = GCSDeviceModel()
    with EmulatorServer(model, tcp_port=0) as server:
        driver = make_driver(
            server, "gcs", safe_voltage=2.0, slew_rate=2000.0, command_timeout=0.05
        )
        driver.connect()
        driver.set_voltage(20.0)
        with Watchdog(driver, period=0.005):
            deadline = time.monotonic() + 5.0
            while driver.state is not DriverState.SAFE and time.monotonic() < deadline:
                time.sleep(0.01)
        assert driver.state is DriverState.SAFE
        assert model.applied_voltage == pytest.approx(2.0)
        driver.close()


# --- shutdown ------------------------------------------------------------------------------------
def test_shutdown_ramps_to_safe_and_leaves_known_state(rig):
    model, server, kind = rig
    clock = FakeClock()
    driver = make_driver(server, kind, clock, safe_voltage=3.0, slew_rate=200.0, ramp_period=0.005)
    driver.connect()
    driver.ramp_to(40.0)
    n_before = len(sent_voltages(model))
    applied = driver.shutdown()
    assert applied == pytest.approx(3.0)
    ramp = sent_voltages(model)[n_before:]
    assert ramp[-1] == pytest.approx(3.0) and len(ramp) > 10
    assert np.all(np.abs(np.diff(ramp)) <= 200.0 * 0.005 + 1e-3)
    assert driver.state is DriverState.SHUT_DOWN and not driver.amplifier.transport.is_open
    assert model.applied_voltage == pytest.approx(3.0)
    if kind == "gcs":
        assert model.servo_on is False
    assert driver.shutdown() == 3.0  # idempotent


# --- reconnect -----------------------------------------------------------------------------------
def test_reconnect_after_tcp_hang_up():
    model = GCSDeviceModel()
    with EmulatorServer(model, tcp_port=0) as server:
        clock = FakeClock()
        driver = make_driver(server, "gcs", clock, slew_rate=1000.0)
        driver.connect()
        assert driver.ramp_to(20.0) == pytest.approx(20.0)
        server.disconnect()
        time.sleep(0.1)
        clock.t += 0.01
        with pytest.raises(ConnectionLost):  # link found dead: reopened in the background
            driver.set_voltage(25.0)
        assert driver.wait_connected(5.0)
        result = driver.set_voltage(25.0)  # continues from the read-back
        assert driver.reconnects == 1 and driver.state is DriverState.ACTIVE
        assert result.sent == pytest.approx(20.0)  # no time elapsed since the read-back: hold
        clock.t += 0.01
        assert driver.set_voltage(25.0).sent == pytest.approx(25.0)
        assert model.applied_voltage == pytest.approx(25.0)
        driver.close()


def test_reconnect_after_pty_unplug_through_stable_link(tmp_path):
    model = MDTDeviceModel()
    link = str(tmp_path / "mdt")
    with EmulatorServer(model, pty=True, pty_link=link) as server:
        driver = make_driver(server, "mdt69x")
        assert server.url == link
        driver.connect()
        driver.set_voltage(10.0)
        old_target = server._pty_path
        server.disconnect()
        deadline = time.monotonic() + 2.0
        while server._pty_path == old_target and time.monotonic() < deadline:
            time.sleep(0.01)
        with pytest.raises(ConnectionLost):
            driver.read_voltage()
        assert driver.wait_connected(5.0)
        assert driver.read_voltage() == pytest.approx(10.0)
        assert driver.reconnects == 1
        driver.close()


def test_silent_device_times_out_then_recovers():
    faults = Faults()
    model = GCSDeviceModel()
    with EmulatorServer(model, tcp_port=0, faults=faults) as server:
        driver = make_driver(server, "gcs", timeout=0.1, reconnect_attempts=2, reconnect_delay=0.0)
        driver.connect()
        faults.silent = True
        with pytest.raises(DeviceTimeout):
            driver.set_voltage(10.0)
        assert driver.state is DriverState.DISCONNECTED
        with pytest.raises(NotConnected):  # at once, while the background reconnect tries
            driver.set_voltage(10.0)
        faults.silent = False
        assert driver.wait_connected(5.0)
        assert driver.set_voltage(10.0).sent == 10.0
        driver.close()


def test_without_reconnect_the_link_error_surfaces():
    model = GCSDeviceModel()
    with EmulatorServer(model, tcp_port=0, faults=Faults(reply_delay=0.0)) as server:
        driver = make_driver(server, "gcs", timeout=0.1, reconnect_attempts=0)
        driver.connect()
        server.faults.reply_delay = 0.5
        with pytest.raises(DeviceTimeout):
            driver.read_voltage()
        assert driver.state is DriverState.DISCONNECTED
        driver.close()
        with pytest.raises(NotConnected):  # closed on purpose: no silent reopening
            driver.set_voltage(1.0)


def test_amplifier_classes_reject_bad_settings():
    with pytest.raises(ConfigError):
        make_amplifier("keithley", "tcp://127.0.0.1:1")
    with pytest.raises(ConfigError):
        make_amplifier("mdt69x", "/dev/null", axis="w")
    with pytest.raises(ConfigError):
        make_amplifier("gcs", "tcp://127.0.0.1")
    assert isinstance(make_amplifier("gcs", "tcp://127.0.0.1:50000"), GCSAmplifier)
    assert isinstance(make_amplifier("mdt69x", "/dev/ttyUSB0"), MDT69xAmplifier)


def test_unknown_gcs_axis_is_a_config_error():
    with EmulatorServer(GCSDeviceModel(axis="Z"), tcp_port=0) as server:
        amp = make_amplifier("gcs", server.url, axis="Q")
        with pytest.raises(ConfigError):
            amp.open()
        amp.close()
