"""A multi-channel device driven by one StageDriver: per-axis safety, one command per cycle, one
reconnect for all axes, a shutdown that ramps every axis together."""

from __future__ import annotations

import math
import time

import pytest

from piezo_stage.hardware.axis_link import GCSAxisLink, MDTAxisLink, make_axis_link
from piezo_stage.hardware.driver import DriverConfig, DriverState
from piezo_stage.hardware.emulators import (
    EmulatorServer,
    GCSDeviceModel,
    LoopbackTransport,
    ManualClock,
    MDTDeviceModel,
)
from piezo_stage.hardware.errors import (
    CommandExpired,
    ConfigError,
    ConnectionLost,
    NonFiniteVoltageError,
    NotConnected,
)
from piezo_stage.hardware.stage_driver import StageDriver
from piezo_stage.hardware.transport import make_transport

pytestmark = pytest.mark.ros  # the MDT693B test serves a pty

AXES = ("1", "2", "3")


def _stage(clock=None, axes=AXES, device_axes=AXES, **config):
    clock = clock or ManualClock()
    log: list[tuple[str, float, float]] = []
    model = GCSDeviceModel(
        axes=device_axes,
        v_min=0.0,
        v_max=100.0,
        on_axis_voltage=lambda axis, v, at: log.append((axis, v, clock())),
    )
    transport = LoopbackTransport(model, clock=clock, sleep=clock.sleep)
    config.setdefault("v_min", 0.0)
    config.setdefault("v_max", 100.0)
    configs = {a: DriverConfig(**config) for a in axes}
    driver = StageDriver(GCSAxisLink(transport, axes, timeout=0.1), configs, clock, clock.sleep)
    return driver, model, transport, clock, log


def _writes(model):
    return [c.split()[1:] for c in model.commands if c.startswith("SVA ")]


def test_every_axis_is_opened_in_open_loop_and_written_in_one_command():
    driver, model, transport, _, _ = _stage()
    infos = driver.connect()
    assert {a: (i.v_min, i.v_max, i.applied) for a, i in infos.items()} == {
        a: (0.0, 100.0, 0.0) for a in AXES
    }
    assert model.servo == {a: False for a in AXES} and transport.opened == 1
    results = driver.set_voltages({"1": 10.0, "2": 20.0, "3": 30.0})
    assert {a: r.sent for a, r in results.items()} == {"1": 10.0, "2": 20.0, "3": 30.0}
    assert _writes(model) == [["1", "10.000000", "2", "20.000000", "3", "30.000000"]]
    assert driver.read_voltages() == {"1": 10.0, "2": 20.0, "3": 30.0}


def test_a_refused_value_refuses_that_axis_alone():
    driver, model, _, _, _ = _stage()
    driver.connect()
    results = driver.set_voltages({"1": 10.0, "2": math.nan, "3": 130.0})
    assert isinstance(results["2"], NonFiniteVoltageError)
    assert results["3"].sent == 100.0 and results["3"].clamped  # clamped to the limit
    assert model.applied_voltages() == {"1": 10.0, "2": 0.0, "3": 100.0}
    with pytest.raises(ConfigError, match=r"no axis \['4'\]"):
        driver.set_voltages({"4": 1.0})


def test_each_axis_keeps_its_slew_cap_and_the_ramp_is_one_command_per_tick():
    driver, model, _, clock, log = _stage(slew_rate=100.0, write_period=0.01)
    driver.connect()
    driver.set_voltages({"1": 50.0, "2": 5.0, "3": 0.5})
    for _ in range(60):
        clock.sleep(0.01)
        for axis in AXES:
            driver.command_received(axis)
        driver.tick()
    assert model.applied_voltages() == {"1": 50.0, "2": 5.0, "3": 0.5}
    for axis in AXES:
        rows = [(t, v) for a, v, t in log if a == axis]
        steps = [abs(b[1] - a[1]) for a, b in zip([(0.0, 0.0)] + rows, rows)]
        assert max(steps) <= 1.0 + 1e-9  # max_step = 100 V/s x 10 ms
    # every write of the ramp carried every axis still moving, in one line
    assert all(len(w) % 2 == 0 for w in _writes(model))
    # the request itself (0 s after connecting: no step yet), then 50 ticks of 1 V for axis 1;
    # the others ride along in the same lines while they move
    assert len(_writes(model)) == 51


def test_the_watchdog_ramps_the_silent_axis_only():
    driver, model, _, clock, _ = _stage(command_timeout=0.5, slew_rate=1000.0)
    driver.connect()
    driver.set_voltages({"1": 40.0, "2": 40.0, "3": 40.0})
    for _ in range(100):  # 1 s: axis 1 keeps receiving commands, 2 and 3 do not
        clock.sleep(0.01)
        driver.command_received("1")
        states = driver.tick()
    assert states == {"1": DriverState.ACTIVE, "2": DriverState.SAFE, "3": DriverState.SAFE}
    assert model.applied_voltages() == {"1": 40.0, "2": 0.0, "3": 0.0}


def test_a_dropped_link_is_reopened_once_for_every_axis():
    driver, model, transport, clock, _ = _stage(reconnect_delay=0.0)
    driver.connect()
    driver.set_voltages({"1": 10.0, "2": 20.0, "3": 30.0})
    transport.disconnect()
    with pytest.raises(ConnectionLost):
        driver.set_voltages({"1": 11.0, "2": 21.0, "3": 31.0})
    for d in driver.drivers.values():
        assert d.wait_connected(5.0)
    assert transport.opened == 2  # one reopen for the three axes
    assert driver.read_voltages() == model.applied_voltages()
    results = driver.set_voltages({"1": 12.0, "2": 22.0, "3": 32.0})
    assert {a: r.sent for a, r in results.items()} == {"1": 12.0, "2": 22.0, "3": 32.0}


def test_shutdown_ramps_every_axis_together_to_its_safe_voltage():
    driver, model, transport, clock, log = _stage(slew_rate=100.0, write_period=0.01)
    driver.connect()
    for _ in range(40):
        clock.sleep(0.01)
        driver.set_voltages({"1": 30.0, "2": 20.0, "3": 10.0})
    assert model.applied_voltages() == {"1": 30.0, "2": 20.0, "3": 10.0}
    before = len(_writes(model))
    assert driver.shutdown() == {"1": 0.0, "2": 0.0, "3": 0.0}
    ramp = _writes(model)[before:]
    assert ramp[0][::2] == ["1", "2", "3"]  # all axes move from the first step
    # together: axis 1's 30 V at 0.5 V a step (100 V/s x 5 ms ramp period) and the repeat of
    # the value the ramp starts from; one axis after another would take 120 steps
    assert len(ramp) <= 30 / 0.5 + 4
    assert not transport.is_open
    assert all(d.state is DriverState.SHUT_DOWN for d in driver.drivers.values())


def test_an_axis_the_controller_does_not_list_is_refused_and_nothing_is_written():
    driver, model, transport, _, _ = _stage(axes=("1", "4"), device_axes=AXES)
    with pytest.raises(ConfigError, match=r"axis/axes \['4'\] not on controller"):
        driver.connect()
    assert _writes(model) == [] and not transport.is_open


def test_a_configuration_per_axis_is_required():
    link = GCSAxisLink(LoopbackTransport(GCSDeviceModel(axes=AXES)), AXES)
    with pytest.raises(ConfigError, match=r"missing \['3'\], unknown \['9'\]"):
        StageDriver(
            link, {"1": DriverConfig(0, 1), "2": DriverConfig(0, 1), "9": DriverConfig(0, 1)}
        )


def test_an_mdt693b_writes_its_three_channels_in_one_command():
    model = MDTDeviceModel("MDT693B", vlimit=100.0)
    with EmulatorServer(model, pty=True) as server:
        link = MDTAxisLink(make_transport(server.url, 115200), ("x", "y", "z"), timeout=0.5)
        driver = StageDriver(link, {a: DriverConfig(0.0, 100.0) for a in "xyz"})
        driver.connect()
        driver.set_voltages({"x": 10.0, "y": 20.0, "z": 30.0})
        assert model.applied_voltages() == {"x": 10.0, "y": 20.0, "z": 30.0}
        assert [c for c in model.commands if "voltage=" in c] == ["xyzvoltage=10.000,20.000,30.000"]
        driver.set_voltages({"y": 25.0})
        assert model.commands[-1] == "yvoltage=25.000"
        assert driver.shutdown() == {"x": 0.0, "y": 0.0, "z": 0.0}
    assert isinstance(driver.set_voltages({"x": 1.0})["x"], NotConnected)


def test_make_axis_link_maps_numbered_gcs_axes_to_their_channels():
    link = make_axis_link("gcs", "tcp://127.0.0.1:1", ("2", "3"))
    assert isinstance(link, GCSAxisLink) and link.channels == {"2": 2, "3": 3}
    assert isinstance(make_axis_link("mdt69x", "/dev/null", ("x", "z")), MDTAxisLink)
    with pytest.raises(ConfigError, match="MDT69x channels"):
        make_axis_link("mdt69x", "/dev/null", ("1",))
    with pytest.raises(ConfigError, match="share output channels"):
        make_axis_link("gcs", "tcp://127.0.0.1:1", ("A", "1"))


def test_set_voltages_checks_each_axis_against_its_own_arrival_time():
    """A command received before its axis's watchdog fired is expired; the other axis's, in the
    same call, received after, is written."""
    driver, model, _, clock, _ = _stage(command_timeout=0.5)
    driver.connect()
    clock.sleep(1.0)
    driver.tick()  # every axis's watchdog fires
    before, after = clock() - 0.1, clock() + 0.1
    clock.sleep(0.2)
    results = driver.set_voltages({"1": 10.0, "2": 20.0}, {"1": before, "2": after})
    assert isinstance(results["1"], CommandExpired) and results["2"].sent == 20.0
    assert model.applied_voltages() == {"1": 0.0, "2": 20.0, "3": 0.0}


def test_a_pipelined_link_does_not_wait_for_each_err_reply_and_reports_a_refusal_late():
    """pipeline 4 on a controller answering 1 s late: four multi-axis writes leave at once,
    a query waits for their ERR? replies; a refused write (error 66, out of range) is raised at
    a later write or at the next query, never lost."""
    from piezo_stage.hardware.emulators import Faults
    from piezo_stage.hardware.errors import GCSError

    model = GCSDeviceModel(axes=AXES, v_min=0.0, v_max=100.0)
    with EmulatorServer(model, tcp_port=0) as server, make_transport(server.url) as transport:
        link = GCSAxisLink(transport, AXES, timeout=5.0, pipeline=4)
        link.open_device()
        server.faults = Faults(reply_delay=1.0)
        started = time.monotonic()
        for k in range(4):
            link.write_many({"1": 10.0 + k, "2": 20.0 + k})
        assert time.monotonic() - started < 0.9  # no write waited for its reply (4 s if so)
        assert link.read_one("1") == 13.0  # the query settled the four replies first
        server.faults = Faults()
        with pytest.raises(GCSError) as err:
            link.write_many({"3": 500.0})
            link.read_one("3")
        assert err.value.code == 66 and "SVA 3 500" in err.value.command
        assert model.applied_voltages()["3"] == 0.0
