"""Voltage driver under faults: ramps that hold after pauses, reconnects, watchdog and
shutdown; watchdog from the last received command; reconnects that never block; stamp checks.

The amplifier is the GCS emulator behind an in-process loopback transport on a fake clock: every
voltage the device applied is recorded with its (fake) time, and the invariants are checked on
that record — per write at most ``max_step``, over any interval at most ``slew_rate`` × length +
``max_step`` — over hand-made and hypothesis-drawn schedules of commands, pauses and link faults.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from piezo_stage.hardware.amplifier import GCSAmplifier
from piezo_stage.hardware.driver import DriverConfig, DriverState, VoltageDriver
from piezo_stage.hardware.emulators import Faults, GCSDeviceModel, LoopbackTransport, ManualClock
from piezo_stage.hardware.emulators.gcs_device import IDN
from piezo_stage.hardware.errors import HardwareError
from piezo_stage.hardware.timing import CommandPlayout

from property_support import examples

pytestmark = pytest.mark.unit

CAP_TIME = 0.025  # s: the most slew one write may carry
WRITE_PERIOD = 0.01  # s: the driver's default write (tick) period, the period the tests tick at


def Clock() -> ManualClock:
    return ManualClock(100.0)


class Bench:
    """GCS emulator + loopback link + driver on one fake clock; ``applied``: (t, V) at the device"""

    def __init__(
        self, faults: Faults | None = None, transport_cls=LoopbackTransport, **cfg
    ) -> None:
        self.clock = Clock()
        self.model = GCSDeviceModel(v_min=-30.0, v_max=130.0)
        self.applied: list[tuple[float, float]] = [(self.clock.t, self.model.voltage)]
        self.model.on_voltage = lambda v, at=None: self.applied.append((self.clock.t, float(v)))
        self.transport = transport_cls(self.model, faults, clock=self.clock)
        cfg = {"v_min": 0.0, "v_max": 100.0, "reconnect_delay": 0.001, **cfg}
        self.config = DriverConfig(**cfg)
        self.driver = VoltageDriver(
            GCSAmplifier(self.transport, timeout=0.02),
            self.config,
            clock=self.clock,
            sleep=self.clock.sleep,
        )
        self.driver.connect()

    def command(self, voltage: float) -> None:
        try:
            self.driver.set_voltage(voltage)
        except HardwareError:
            pass
        self.recover()  # let the background reconnect finish (the clock stands still meanwhile)

    def tick(self) -> DriverState:
        state = self.driver.tick()
        self.recover()
        return state

    def recover(self) -> None:
        if self.driver.state is DriverState.DISCONNECTED:
            self.driver.wait_connected(5.0)

    def run_for(self, seconds: float, period: float = 0.01) -> None:
        for _ in range(int(round(seconds / period))):
            self.clock.t += period
            self.tick()

    def max_step(self) -> float:
        return self.config.slew_rate * min(WRITE_PERIOD, CAP_TIME)

    def assert_ramps(self) -> None:
        """No write steps more than max_step; no interval sees more than slew × length + max_step"""
        t, v = np.array(self.applied).T
        cap = self.max_step() + 1e-6
        assert np.all(np.abs(np.diff(v)) <= cap), (
            f"largest step {np.max(np.abs(np.diff(v))):.4g} V > {cap:.4g} V"
        )
        dv = np.abs(v[None, :] - v[:, None])
        dt = np.abs(t[None, :] - t[:, None])
        excess = dv - self.config.slew_rate * dt - cap
        assert np.all(excess <= 0), f"slew exceeded by {excess.max():.4g} V over an interval"
        assert np.all((v >= self.config.v_min) & (v <= self.config.v_max))


# --- row 2: pauses, watchdog and shutdown ramps --------------------------------------------------
def test_pauses_never_allow_a_big_step():
    """2000 V/s, 0-100 V: 100 -> 0 -> 100 after pauses reached the device as single 100 V steps."""
    bench = Bench(slew_rate=2000.0)
    for target in (100.0, 0.0, 100.0):
        bench.clock.t += 0.3  # a pause longer than any former slew interval
        bench.command(target)
        bench.run_for(0.2)  # the ramp continues on the driver's ticks
        assert bench.model.voltage == pytest.approx(target)
    bench.assert_ramps()
    assert len(bench.applied) > 3 * 100.0 / bench.max_step()  # ramps of many writes


def test_watchdog_and_shutdown_ramps_are_ramps():
    bench = Bench(slew_rate=2000.0, command_timeout=0.1)
    bench.driver.ramp_to(100.0)
    n = len(bench.applied)
    bench.clock.t += 0.5  # no commands: the watchdog fires at its next tick
    bench.run_for(0.2)
    assert bench.driver.state is DriverState.SAFE and bench.model.voltage == 0.0
    assert len(bench.applied) - n >= 100.0 / bench.max_step()
    bench.driver.ramp_to(100.0)
    bench.clock.t += 1.0  # a pause, then shutdown
    assert bench.driver.shutdown() == pytest.approx(0.0)
    bench.assert_ramps()


# --- row 3: the link is down for 0.5 s while commands keep arriving ------------------------------
class SlowReconnectTransport(LoopbackTransport):
    """After a hang-up the device is back only 0.5 s (fake clock) later."""

    back_at = -math.inf

    def disconnect(self) -> None:
        super().disconnect()
        self.back_at = self.clock() + 0.5

    def open(self) -> None:
        self.down = self.clock() < self.back_at
        super().open()


def test_reconnect_does_not_turn_the_pause_into_a_step_nor_trip_the_watchdog():
    bench = Bench(slew_rate=200.0, command_timeout=0.3, transport_cls=SlowReconnectTransport)
    bench.driver.ramp_to(50.0)
    trips = []
    for k in range(300):  # a command every 10 ms toward 40 V, the link hung up now and then
        bench.clock.t += 0.01
        if k % 100 == 10:
            bench.transport.disconnect()
        try:
            bench.driver.set_voltage(40.0 - 10.0 * (k > 200))
        except HardwareError:
            pass
        if bench.driver.tick() is DriverState.TIMED_OUT:
            trips.append(bench.clock.t)
        if bench.clock.t > bench.transport.back_at:  # the background reconnect gets in
            bench.recover()
    bench.recover()
    bench.run_for(0.2)
    assert bench.driver.reconnects >= 3 and not trips  # commands kept arriving: no trip
    assert bench.model.voltage == pytest.approx(30.0)
    bench.assert_ramps()


class SlowOpenTransport(LoopbackTransport):
    """Opening takes 0.5 s of the clock (a TCP connect and the identification round trips)."""

    def open(self) -> None:
        if not self.is_open and self.opened:
            self.clock.sleep(0.5)
        super().open()


def test_a_slow_reconnect_is_not_followed_by_a_step():
    """200 V/s: after a 0.5 s reconnect the next write stepped 10 V (the time before the reconnect
    was stored as the last write); the ramp must go on from the read-back at the slew rate."""
    bench = Bench(slew_rate=200.0, command_timeout=5.0, transport_cls=SlowOpenTransport)
    bench.driver.ramp_to(50.0)
    for k in range(200):
        bench.clock.t += 0.01
        if k % 50 == 10:
            bench.transport.disconnect()  # found dead by the next command, which moves away
        bench.command(40.0 if (k - 10) // 50 % 2 == 0 else 60.0)
        bench.tick()
    assert bench.driver.reconnects >= 3
    bench.assert_ramps()


# --- row 5: the watchdog counts from received commands and clears the queue ----------------------
def test_watchdog_counts_from_received_commands_and_clears_queued_ones():
    """Commands stamped 4 s ahead (apply_at_stamp) stop arriving: safe within command_timeout +
    ramp time, and nothing queued before the trip reaches the device after it."""
    bench = Bench(slew_rate=1000.0, command_timeout=0.5)
    wall = Clock()
    driver = bench.driver

    def apply(voltage: float, is_command: bool, received: float) -> None:
        driver.set_voltage(voltage, received=received)

    # a playout on a fake clock, stepped by hand: push (stamp, voltage); due ones applied in order
    queue: list[tuple[float, float, float]] = []
    playout = CommandPlayout(lambda v, c, r: None, 0.0, clock=wall)
    driver.on_timeout.append(playout.clear)
    driver.on_timeout.append(queue.clear)
    for _ in range(100):  # 1 s of commands at 100 Hz, each stamped 4 s ahead
        bench.clock.t += 0.01
        wall.t += 0.01
        driver.command_received()
        queue.append((wall.t + 4.0, 60.0, bench.clock.t))
        playout.push(wall.t + 4.0, 60.0)
        bench.tick()
    t_last = bench.clock.t
    t_safe = None
    for _ in range(1000):
        bench.clock.t += 0.01
        wall.t += 0.01
        while queue and queue[0][0] <= wall.t:
            _, v, received = queue.pop(0)
            apply(v, True, received)
        if bench.tick() is DriverState.SAFE and t_safe is None:
            t_safe = bench.clock.t
    assert t_safe is not None and t_safe - t_last <= 0.5 + 0.02  # nothing to ramp: 0 V already
    assert playout.pending == 0 and not queue
    assert all(v == 0.0 for t, v in bench.applied if t > t_last)


def test_commands_received_before_the_trip_are_refused():
    bench = Bench(slew_rate=1000.0, command_timeout=0.2)
    driver = bench.driver
    received = bench.clock.t
    bench.clock.t += 0.5
    bench.tick()
    assert driver.state in (DriverState.TIMED_OUT, DriverState.SAFE)
    with pytest.raises(HardwareError):
        driver.set_voltage(50.0, received=received)
    assert driver.expired == 1 and bench.model.voltage == 0.0


# --- row 6: reconnects never block the caller ----------------------------------------------------
class BlockingOpenTransport(LoopbackTransport):
    """After the first open, opening hangs until released (a device that never answers)."""

    def __init__(self, *a, **kw) -> None:
        super().__init__(*a, **kw)
        self.release = threading.Event()

    def open(self) -> None:
        if self.opened >= 1 and not self.is_open:
            self.release.wait(30.0)
        super().open()


def test_a_hanging_reconnect_never_blocks_tick_or_commands():
    bench = Bench(slew_rate=1000.0, command_timeout=0.2, transport_cls=BlockingOpenTransport)
    driver = bench.driver
    bench.transport.disconnect()
    results = []

    def caller() -> None:
        for _ in range(20):
            bench.clock.t += 0.01
            try:
                driver.set_voltage(10.0)
            except HardwareError as exc:
                results.append(type(exc).__name__)
            results.append(driver.tick())

    thread = threading.Thread(target=caller, daemon=True)
    thread.start()
    thread.join(timeout=10.0)  # generous: each call returns at once
    blocked = thread.is_alive()
    bench.transport.release.set()
    thread.join(timeout=10.0)
    assert not blocked
    assert driver.state is DriverState.DISCONNECTED or driver.wait_connected(5.0)
    assert "NotConnected" in results
    driver.close()


# --- row 7 (core): a shutdown that cannot reach safe_voltage says so -----------------------------
def test_shutdown_with_the_link_down_raises():
    from piezo_stage.hardware.errors import SafeStateNotReached

    bench = Bench(slew_rate=1000.0, shutdown_timeout=0.2, reconnect_attempts=1)
    bench.driver.ramp_to(20.0)
    bench.transport.down = True
    bench.transport.disconnect()
    with pytest.raises(SafeStateNotReached):
        bench.driver.shutdown()
    assert bench.driver.state is DriverState.SHUT_DOWN and bench.model.voltage == 20.0


# --- property: random schedules of commands, pauses and link faults ------------------------------
EVENTS = st.one_of(
    st.tuples(st.just("cmd"), st.floats(0.0, 0.4), st.floats(-50.0, 150.0)),
    st.tuples(st.just("tick"), st.floats(0.0, 0.05), st.just(0.0)),
    st.tuples(st.just("hangup"), st.just(0.0), st.just(0.0)),
    st.tuples(st.just("corrupt"), st.just(0.0), st.sampled_from([0.0, 0.01, 0.05])),
    st.tuples(st.just("shutdown"), st.floats(0.0, 1.0), st.just(0.0)),
)


@settings(max_examples=examples(200), deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    slew=st.sampled_from([50.0, 200.0, 2000.0, 1e5]),
    schedule=st.lists(EVENTS, max_size=120),
    seed=st.integers(0, 2**16),
)
def test_property_ramps_and_limits_hold_under_any_schedule(slew, schedule, seed):
    faults = Faults(seed=seed)
    bench = Bench(faults, slew_rate=slew, command_timeout=0.2)
    for kind, dt, value in schedule:
        bench.clock.t += dt
        if kind == "cmd":
            bench.command(value)
        elif kind == "tick":
            bench.tick()
        elif kind == "hangup":
            bench.transport.disconnect()
        elif kind == "corrupt":
            faults.corrupt = value
        else:
            faults.corrupt = 0.0
            bench.recover()
            bench.driver.shutdown()
            assert bench.model.voltage == 0.0
            break
        assert not math.isnan(bench.model.voltage)
    bench.driver.close()
    bench.assert_ramps()


# --- the emulator's faults themselves ------------------------------------------------------------
def test_fault_injection_stall_hangup_garbage():
    clock = Clock()
    faults = Faults(seed=1)
    model = GCSDeviceModel()
    link = LoopbackTransport(model, faults, clock=clock)
    link.open()
    faults.garbage = 1.0  # every reply preceded by 1-32 random bytes
    link.write(b"*IDN?\n")
    reply = link.read(0.0)
    assert reply.endswith(IDN.encode() + b"\n") and len(reply) > len(IDN) + 1
    faults.garbage, faults.hangup = 0.0, 1.0  # the reply is cut and the line dropped
    link.write(b"*IDN?\n")
    assert len(link.read(0.0)) < 60
    with pytest.raises(HardwareError):
        link.write(b"*IDN?\n")
    faults.hangup, faults.stall, faults.stall_time = 0.0, 1.0, 0.5
    link.open()
    link.write(b"*IDN?\n")  # the device stalls: no answer, input ignored for 0.5 s
    assert link.read(0.0) == b"" and faults.muted(clock.t + 0.4) and not faults.muted(clock.t + 0.6)
    faults.stall = 0.0
    clock.t += 0.6
    link.write(b"*IDN?\n")
    assert link.read(0.0).endswith(b"emulator)\n")
