"""The voltage driver: every safety rule between a voltage request and the amplifier.

:class:`VoltageDriver` wraps an :class:`~piezo_stage.hardware.amplifier.Amplifier` and
guarantees, whatever the caller sends and whatever the link does:

- NaN/inf is refused with :class:`NonFiniteVoltageError` and nothing reaches the device;
- no value outside [min, max] = configured limits ∩ device limits (VMI?/VMA?, vlimit?) is ever
  written — requests outside are clamped (``clamp=True``, reported in :class:`SetResult`) or
  refused with :class:`VoltageOutOfRangeError`;
- **ramps**: a write is an instantaneous step on the device, so no write moves the output by
  more than :attr:`DriverConfig.max_step` = ``slew_rate`` × min(``write_period``, 25 ms), nor by
  more than ``slew_rate`` × the time since the previous write. Over any interval [a, b] the
  output therefore moves at most ``slew_rate`` (b − a) + ``max_step`` — after pauses, after a
  reconnect (the output continues from the read-back), in the watchdog's ramp and in the
  shutdown ramp. A request further away is reached by a ramp of many writes: each command
  writes one step and :meth:`tick` (every ``write_period``) keeps stepping toward the target;
  the limits win over slew;
- the watchdog (:meth:`tick`): ``command_timeout`` after the last *received* valid command
  (:meth:`command_received`, called on arrival also for commands queued for later) the output
  ramps to ``safe_voltage``; firing calls the ``on_timeout`` callbacks (the node clears its
  queue of stamped commands) and commands received before it fired are refused
  (:class:`CommandExpired`) when they come up for application;
- a dropped link is reopened by a background thread (never in the caller's thread): meanwhile
  writes raise :class:`NotConnected` at once, and the output continues from the voltage read
  back from the device;
- :meth:`shutdown` ramps to ``safe_voltage``, leaves the amplifier in open loop there and closes
  the link; it raises :class:`SafeStateNotReached` when it could not.

Nodes call ``connect()``, ``command_received()``/``set_voltage(v)`` per command, ``tick()`` from
a timer and ``shutdown()`` on exit; ``read_voltage()`` gives the applied voltage to publish.
"""

from __future__ import annotations

import enum
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

from .amplifier import Amplifier, DeviceInfo
from .errors import (
    CommandExpired,
    ConfigError,
    DeviceError,
    HardwareError,
    NonFiniteVoltageError,
    NotConnected,
    ProtocolError,
    SafeStateNotReached,
    TransportError,
    VoltageOutOfRangeError,
)
from .safety import VoltageLimits, round_within, slew_step

log = logging.getLogger(__name__)

MAX_STEP_TIME = 0.025  # s: no single write carries more than this much slew
# what a device exchange can fail with when the link is bad: the write may or may not have landed
LINK_FAULTS = (TransportError, ProtocolError, DeviceError)
READBACK_TOLERANCE = 0.05  # V: two read-backs after a reconnect must agree (the ramp starts there)


@dataclass(frozen=True)
class DriverConfig:
    """Safety settings of a :class:`VoltageDriver` (volts, seconds)."""

    v_min: float
    v_max: float
    safe_voltage: float = 0.0
    slew_rate: float = math.inf  # V/s
    write_period: float = 0.01  # s: period of tick(); one write steps at most slew_rate * this
    command_timeout: float = 0.5  # s without a received command before ramping to safe; inf = off
    ramp_period: float = 0.005  # s between steps of a blocking ramp (shutdown, ramp_to)
    clamp: bool = True  # False: refuse out-of-range requests instead of clamping
    reconnect_attempts: int = 3  # 0: never reopen a dropped link
    reconnect_delay: float = 0.2  # s between attempts of the background reconnect
    shutdown_timeout: float = 5.0  # s shutdown waits for a dropped link to come back

    def __post_init__(self) -> None:
        VoltageLimits(self.v_min, self.v_max)  # raises LimitsError when empty or not finite
        if not math.isfinite(self.safe_voltage):
            raise ConfigError(f"safe_voltage must be finite, got {self.safe_voltage}")
        if not self.slew_rate > 0:
            raise ConfigError(f"slew_rate must be > 0 V/s (inf = unlimited), got {self.slew_rate}")
        for name in ("write_period", "command_timeout", "ramp_period"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0 s, got {getattr(self, name)}")
        if self.reconnect_attempts < 0 or self.reconnect_delay < 0 or self.shutdown_timeout < 0:
            raise ConfigError(
                "reconnect_attempts, reconnect_delay and shutdown_timeout must be >= 0"
            )

    @property
    def max_step(self) -> float:
        """Largest change of one write [V]: slew_rate × min(write_period, 25 ms)."""
        return self.slew_rate * min(self.write_period, MAX_STEP_TIME)


@dataclass(frozen=True)
class SetResult:
    """What :meth:`VoltageDriver.set_voltage` did with a request."""

    requested: float
    sent: float
    clamped: bool  # the request lay outside [min, max]
    slew_limited: bool  # the step was cut by the slew-rate limit (tick() continues the ramp)


class DriverState(enum.Enum):
    """Driver states (module docstring); SAFE: at ``safe_voltage`` after a watchdog timeout."""

    DISCONNECTED = "disconnected"
    ACTIVE = "active"  # commands arriving
    TIMED_OUT = "timed_out"  # watchdog fired, ramping toward safe_voltage
    SAFE = "safe"  # at safe_voltage after a timeout
    SHUT_DOWN = "shut_down"


class VoltageDriver:
    """Safe open-loop voltage output through an :class:`Amplifier` (see module docstring)."""

    def __init__(
        self,
        amplifier: Amplifier,
        config: DriverConfig,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.amplifier = amplifier
        self.config = config
        self.clock = clock
        self.sleep = sleep
        self.state = DriverState.DISCONNECTED
        self.info: DeviceInfo | None = None
        self.limits: VoltageLimits | None = None
        self.last_sent = math.nan  # last voltage written (or read back after (re)connecting)
        self.target = math.nan  # where the output is ramping to (limits applied)
        self.writes = 0
        self.reconnects = 0
        self.expired = 0  # commands refused because the watchdog fired after they were received
        self.trips = 0  # times the watchdog fired
        self.last_link_error = ""
        self.on_timeout: list[
            Callable[[], None]
        ] = []  # called (under the lock) when the watchdog fires
        self._t_sent = 0.0
        self._t_command = 0.0  # when the last valid command was received
        self._t_trip = -math.inf  # when the watchdog last fired
        self._may_reconnect = False  # True between connect() and close()/shutdown()
        self._lock = threading.RLock()
        self._connected = threading.Condition(self._lock)
        self._reconnector: threading.Thread | None = None
        self._resume = DriverState.ACTIVE  # state to return to after a reconnect
        self._stop = threading.Event()

    # --- link -----------------------------------------------------------------------------------
    def connect(self) -> DeviceInfo:
        """Open the amplifier, compute the effective limits and take over its present output."""
        info = self.amplifier.open()
        with self._lock:
            self._install(info)
            self._may_reconnect = True
            self._stop.clear()
            lim = self.limits
            assert lim is not None  # set by _install
            log.info(
                "connected to %s axis %s, limits [%g, %g] V, output %g V",
                info.identity,
                info.axis,
                lim.v_min,
                lim.v_max,
                info.applied,
            )
            return info

    def _install(self, info: DeviceInfo, first: bool = True) -> None:
        """Take over an opened device: limits, and its read-back as the output now (ramps
        continue from there). After a reconnect the target and the watchdog's state are kept.
        """
        configured = VoltageLimits(self.config.v_min, self.config.v_max)
        limits = configured.intersect(VoltageLimits(info.v_min, info.v_max))
        if not limits.contains(self.config.safe_voltage):
            self.amplifier.close()
            raise VoltageOutOfRangeError(
                f"safe_voltage {self.config.safe_voltage} V outside "
                f"[{limits.v_min}, {limits.v_max}] V"
            )
        self.info, self.limits = info, limits
        self.last_sent = info.applied
        self._t_sent = self.clock()
        if first:
            self.target = limits.clamp(info.applied)
            self._t_command = self._t_sent
            self.state = DriverState.ACTIVE
        else:
            self.state = self._resume
        self._connected.notify_all()

    def reconnect(self) -> DeviceInfo:
        """Close and reopen the link now (``reconnect_attempts`` tries, in the caller's thread)."""
        with self._lock:
            self._mark_down()
        self.amplifier.drop()
        last: Exception | None = None
        for attempt in range(max(self.config.reconnect_attempts, 1)):
            if attempt and self._stop.wait(self.config.reconnect_delay):
                break
            try:
                info = self.amplifier.open()
                again = self.amplifier.read_voltage()
                if abs(again - info.applied) > READBACK_TOLERANCE:  # one of them was garbled
                    raise ProtocolError(f"read-back {info.applied} V then {again} V")
            except HardwareError as exc:  # silent, garbled or refusing: try again
                last = exc
                self.amplifier.drop()
                continue
            with self._lock:
                if not self._may_reconnect:
                    self.amplifier.close()
                    raise NotConnected("voltage driver was closed while reconnecting")
                self.reconnects += 1
                self._install(info, first=False)
                log.info(
                    "reconnected to %s, output %g V", self.amplifier.transport.url, info.applied
                )
                return info
        raise NotConnected(f"could not reconnect to {self.amplifier.transport.url}: {last}")

    def _link_down(self, exc: Exception) -> None:
        """Mark the link down and reopen it in the background (never in the caller's thread)."""
        self.last_link_error = str(exc)
        self._mark_down()
        self.amplifier.drop()
        if self.config.reconnect_attempts <= 0 or not self._may_reconnect:
            return
        if self._reconnector is None or not self._reconnector.is_alive():
            log.warning(
                "link to %s lost (%s); reconnecting in the background",
                self.amplifier.transport.url,
                exc,
            )
            self._reconnector = threading.Thread(
                target=self._reconnect_loop, daemon=True, name="voltage-driver-reconnect"
            )
            self._reconnector.start()

    def _mark_down(self) -> None:
        if self.state in (DriverState.DISCONNECTED, DriverState.SHUT_DOWN):
            return
        timed_out = self.state in (DriverState.TIMED_OUT, DriverState.SAFE)
        self._resume = DriverState.TIMED_OUT if timed_out else DriverState.ACTIVE
        self.state = DriverState.DISCONNECTED

    def _reconnect_loop(self) -> None:
        while self._may_reconnect and not self._stop.is_set():
            try:
                self.reconnect()
            except Exception as exc:  # still down, garbled, or a bug: say so, never stop trying
                log.error("amplifier link still down: %s", exc)
                self.last_link_error = str(exc)
                self._stop.wait(self.config.reconnect_delay)
                continue
            return

    def wait_connected(self, timeout: float) -> bool:
        """Wait up to ``timeout`` s (real time) for a background reconnect; True when connected."""
        deadline = time.monotonic() + timeout
        with self._connected:
            while self.state is DriverState.DISCONNECTED and self._may_reconnect:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or self._reconnector is None or not self._reconnector.is_alive():
                    break
                self._connected.wait(min(remaining, 0.05))
            return self.connected

    def close(self) -> None:
        """Close the link without touching the output (use shutdown() to ramp to safe first)."""
        with self._lock:
            self._may_reconnect = False
            self._stop.set()
            self.amplifier.close()
            if self.state is not DriverState.SHUT_DOWN:
                self.state = DriverState.DISCONNECTED
        self._join_reconnector()

    def _join_reconnector(self) -> None:
        thread = self._reconnector
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=10.0)

    @property
    def connected(self) -> bool:
        """Whether the link is up: neither disconnected nor shut down."""
        return self.state not in (DriverState.DISCONNECTED, DriverState.SHUT_DOWN)

    # --- commands -------------------------------------------------------------------------------
    def command_received(self, received: float | None = None) -> None:
        """A valid command arrived at ``received`` (default now): the watchdog counts from here."""
        with self._lock:
            received = self.clock() if received is None else received
            self._t_command = max(self._t_command, received)

    def set_voltage(self, voltage: float, received: float | None = None) -> SetResult:
        """Apply one voltage request with all safety checks; returns what was sent.

        ``received``: when the command arrived (for commands applied later than that, e.g. at
        their stamp); one received before the watchdog last fired raises :class:`CommandExpired`.
        """
        voltage = float(voltage)
        if not math.isfinite(voltage):
            raise NonFiniteVoltageError(f"refusing non-finite voltage {voltage!r}; nothing sent")
        with self._lock:
            received = self.clock() if received is None else received
            if received <= self._t_trip:
                self.expired += 1
                raise CommandExpired(
                    f"command received {self._t_trip - received:.3g} s before the "
                    "watchdog fired; dropped"
                )
            self._t_command = max(self._t_command, received)  # the watchdog counts from here
            limits = self._require_limits()  # raises at once while the link is down
            if not limits.contains(voltage) and not self.config.clamp:
                raise VoltageOutOfRangeError(
                    f"{voltage} V outside [{limits.v_min}, {limits.v_max}] V; nothing sent"
                )
            self.state = DriverState.ACTIVE
            self.target = limits.clamp(voltage)
            sent = self._write_step()
            return SetResult(
                voltage, sent, not limits.contains(voltage), sent != self._rounded(self.target)
            )

    def read_voltage(self) -> float:
        """The applied voltage the amplifier reports [V]."""
        with self._lock:
            self._require_limits()
            try:
                return self.amplifier.read_voltage()
            except TransportError as exc:  # a garbled reply (ProtocolError) leaves the link up
                self._link_down(exc)
                raise

    def tick(self, now: float | None = None) -> DriverState:
        """Every ``write_period``: watchdog, and one more step of the ramp toward the target.

        After ``command_timeout`` without a received command the target becomes safe_voltage.
        Never blocks on a dead link: a reconnect runs in the background.
        """
        with self._lock:
            if (
                self.state in (DriverState.SHUT_DOWN, DriverState.DISCONNECTED)
                or not self._may_reconnect
            ):
                return self.state
            now = self.clock() if now is None else now
            # fires once per silence: also when commands arrived (to be applied later) since the
            # last time it fired, so their queue is cleared command_timeout after the last one
            silent = now - self._t_command > self.config.command_timeout
            if silent and (self.state is DriverState.ACTIVE or self._t_command > self._t_trip):
                log.warning(
                    "no voltage command for %.3g s: ramping to %g V",
                    now - self._t_command,
                    self.config.safe_voltage,
                )
                self._trip(now)
            goal = self._rounded(self.target)
            if self.last_sent != goal:
                try:
                    self._write_step()
                except LINK_FAULTS:
                    return self.state  # link marked down; the background reconnect takes over
            if self.state is DriverState.TIMED_OUT and self.last_sent == goal:
                self.state = DriverState.SAFE
            return self.state

    def _trip(self, now: float) -> None:
        self.trips += 1
        self.state = DriverState.TIMED_OUT
        self._t_trip = now
        self.target = self.config.safe_voltage
        for callback in self.on_timeout:
            callback()

    def ramp_to(self, target: float) -> float:
        """Blocking ramp to ``target`` at the slew rate; returns the final voltage sent."""
        target = float(target)
        if not math.isfinite(target):
            raise NonFiniteVoltageError(f"refusing non-finite ramp target {target!r}")
        with self._lock:
            limits = self._require_limits()
            if not limits.contains(target):
                raise VoltageOutOfRangeError(
                    f"ramp target {target} V outside [{limits.v_min}, {limits.v_max}] V"
                )
            self.target = target
            goal = self._rounded(target)
            while True:
                sent = self._write_step()
                self._t_command = max(self._t_command, self._t_sent)
                if sent == goal:
                    return sent
                self.sleep(self.config.ramp_period)

    def shutdown(self) -> float:
        """Ramp to safe_voltage, leave the amplifier there in open loop, close; returns read-back.

        Raises :class:`SafeStateNotReached` (link closed all the same) when that failed.
        """
        with self._lock:
            if self.state is DriverState.SHUT_DOWN:
                return self.last_sent
        safe = self.config.safe_voltage
        applied = math.nan
        try:
            deadline = time.monotonic() + self.config.shutdown_timeout
            while True:
                if not self.wait_connected(max(deadline - time.monotonic(), 0.0)):
                    raise SafeStateNotReached(
                        f"output not brought to safe_voltage {safe:g} V: amplifier link down "
                        f"({self.last_link_error or 'not connected'}); "
                        f"last sent {self.last_sent:g} V"
                    )
                try:
                    self.ramp_to(safe)
                    applied = self.read_voltage()
                    break
                except LINK_FAULTS:
                    if time.monotonic() > deadline:
                        raise
            if abs(applied - self._rounded(safe)) > 1.5 * 10.0**-self.amplifier.decimals + 1e-9:
                raise SafeStateNotReached(
                    f"amplifier reads back {applied:g} V after the ramp to safe_voltage {safe:g} V"
                )
        except LINK_FAULTS as exc:
            raise SafeStateNotReached(
                f"output not brought to safe_voltage {safe:g} V: {exc}"
            ) from exc
        finally:
            with self._lock:
                self._may_reconnect = False
                self._stop.set()
                self.amplifier.close()
                self.state = DriverState.SHUT_DOWN
            self._join_reconnector()
        log.info("shut down at %g V (read back %g V)", self.last_sent, applied)
        return applied

    # --- internals ------------------------------------------------------------------------------
    def _require_limits(self) -> VoltageLimits:
        """The effective limits; refuses while the link is down and after close()/shutdown()."""
        if self.limits is None or not self._may_reconnect:
            raise NotConnected("voltage driver is not connected; call connect()")
        if self.state is DriverState.DISCONNECTED:
            raise NotConnected(f"amplifier link down ({self.last_link_error}); reconnecting")
        return self.limits

    def _rounded(self, voltage: float) -> float:
        assert self.limits is not None
        return round_within(voltage, self.limits, self.amplifier.decimals)

    def _write_step(self) -> float:
        """Write one step toward ``target``: at most max_step and slew_rate × (time since the
        previous write); the clock is read just before the write. Returns the value sent.
        """
        assert self.limits is not None
        now = self.clock()
        dt = max(now - self._t_sent, 0.0)
        step = slew_step(self.last_sent, self.target, self.config.slew_rate, dt)
        if not math.isinf(self.config.slew_rate):
            cap = self.config.max_step
            step = min(max(step, self.last_sent - cap), self.last_sent + cap)
        value = self._rounded(self.limits.clamp(step))
        if not self.limits.contains(value):  # cannot happen; kept as the last line of defence
            raise VoltageOutOfRangeError(f"internal error: {value} V outside {self.limits}")
        try:
            self.amplifier.write_voltage(value)
        except LINK_FAULTS as exc:
            # whether the device took the value is unknown: reopen, which reads the output back
            self._link_down(exc)
            raise
        self.last_sent, self._t_sent = value, now
        self.writes += 1
        return value


class Watchdog:
    """A thread calling :meth:`VoltageDriver.tick` every ``period`` seconds (for non-ROS use)."""

    def __init__(self, driver: VoltageDriver, period: float | None = None) -> None:
        period = driver.config.write_period if period is None else period
        if not period > 0:
            raise ConfigError(f"watchdog period must be > 0 s, got {period}")
        self.driver = driver
        self.period = period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="voltage-watchdog", daemon=True)
        self.error: Exception | None = None

    def start(self) -> "Watchdog":
        """Start the thread; returns the watchdog."""
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the thread and wait for it."""
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.wait(self.period):
            try:
                self.driver.tick()
            except Exception as exc:  # keep the last error for the owner; never die silently
                self.error = exc
                log.error("watchdog tick failed: %s", exc)

    def __enter__(self) -> "Watchdog":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
