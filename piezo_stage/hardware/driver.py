"""The voltage driver: every safety rule between a voltage request and the amplifier.

:class:`VoltageDriver` wraps an :class:`~piezo_stage.hardware.amplifier.Amplifier` and
guarantees, whatever the caller sends:

- NaN/inf is refused with :class:`NonFiniteVoltageError` and nothing reaches the device;
- no value outside [min, max] = configured limits ∩ device limits (VMI?/VMA?, vlimit?) is ever
  written — requests outside are clamped (``clamp=True``, reported in :class:`SetResult`) or
  refused with :class:`VoltageOutOfRangeError`;
- consecutive writes differ by at most ``slew_rate * dt`` (dt capped at ``max_slew_interval`` so
  a request after a long pause cannot jump); the limits win over slew;
- the watchdog (:meth:`tick`, called by a timer or by :class:`Watchdog`): if no command arrives
  for ``command_timeout`` the output ramps to ``safe_voltage`` at the slew rate;
- :meth:`shutdown` ramps to ``safe_voltage`` and leaves the amplifier in open loop at that
  voltage, then closes the link;
- a dropped link is reopened (``reconnect_attempts``) and the output continues from the
  voltage read back from the device.

Nodes call ``connect()``, ``set_voltage(v)`` per command, ``tick()`` from a timer and
``shutdown()`` on exit; ``read_voltage()`` gives the applied voltage to publish.
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
from .errors import (ConfigError, ConnectionLost, NonFiniteVoltageError, NotConnected, TransportError,
                     VoltageOutOfRangeError)
from .safety import VoltageLimits, round_within, slew_step

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DriverConfig:
    """Safety settings of a :class:`VoltageDriver` (volts, seconds)."""

    v_min: float
    v_max: float
    safe_voltage: float = 0.0
    slew_rate: float = math.inf  # V/s
    max_slew_interval: float = 0.05  # s; cap on dt in the slew limit
    command_timeout: float = 0.5  # s without a command before ramping to safe_voltage; inf = off
    ramp_period: float = 0.005  # s between steps of a blocking ramp (shutdown, ramp_to)
    clamp: bool = True  # False: refuse out-of-range requests instead of clamping
    reconnect_attempts: int = 3
    reconnect_delay: float = 0.2  # s between attempts

    def __post_init__(self) -> None:
        VoltageLimits(self.v_min, self.v_max)  # raises LimitsError when empty or not finite
        if not math.isfinite(self.safe_voltage):
            raise ConfigError(f"safe_voltage must be finite, got {self.safe_voltage}")
        if not self.slew_rate > 0:
            raise ConfigError(f"slew_rate must be > 0 V/s (inf = unlimited), got {self.slew_rate}")
        for name in ("max_slew_interval", "command_timeout", "ramp_period"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be > 0 s, got {getattr(self, name)}")
        if self.reconnect_attempts < 0 or self.reconnect_delay < 0:
            raise ConfigError("reconnect_attempts and reconnect_delay must be >= 0")


@dataclass(frozen=True)
class SetResult:
    """What :meth:`VoltageDriver.set_voltage` did with a request."""

    requested: float
    sent: float
    clamped: bool  # the request lay outside [min, max]
    slew_limited: bool  # the step was cut by the slew-rate limit


class DriverState(enum.Enum):
    DISCONNECTED = "disconnected"
    ACTIVE = "active"  # commands arriving
    TIMED_OUT = "timed_out"  # watchdog fired, ramping toward safe_voltage
    SAFE = "safe"  # at safe_voltage after a timeout
    SHUT_DOWN = "shut_down"


class VoltageDriver:
    """Safe open-loop voltage output through an :class:`Amplifier` (see module docstring)."""

    def __init__(self, amplifier: Amplifier, config: DriverConfig,
                 clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        self.amplifier = amplifier
        self.config = config
        self.clock = clock
        self.sleep = sleep
        self.state = DriverState.DISCONNECTED
        self.info: DeviceInfo | None = None
        self.limits: VoltageLimits | None = None
        self.last_sent = math.nan  # last voltage written (or read back after (re)connecting)
        self._t_sent = 0.0
        self._t_command = 0.0
        self.reconnects = 0
        self._may_reconnect = False  # True between connect() and close()/shutdown()
        self._lock = threading.RLock()

    # --- link -----------------------------------------------------------------------------------
    def connect(self) -> DeviceInfo:
        """Open the amplifier, compute the effective limits and take over its present output."""
        with self._lock:
            info = self.amplifier.open()
            configured = VoltageLimits(self.config.v_min, self.config.v_max)
            limits = configured.intersect(VoltageLimits(info.v_min, info.v_max))
            if not limits.contains(self.config.safe_voltage):
                self.amplifier.close()
                raise VoltageOutOfRangeError(
                    f"safe_voltage {self.config.safe_voltage} V outside [{limits.v_min}, {limits.v_max}] V")
            self.info, self.limits = info, limits
            self.last_sent = info.applied
            now = self.clock()
            self._t_sent = self._t_command = now
            self.state = DriverState.ACTIVE
            self._may_reconnect = True
            log.info("connected to %s axis %s, limits [%g, %g] V, output %g V",
                     info.identity, info.axis, limits.v_min, limits.v_max, info.applied)
            return info

    def reconnect(self) -> DeviceInfo:
        """Close and reopen the link (``reconnect_attempts`` tries); raises ConnectionLost."""
        with self._lock:
            self.amplifier.close()
            self.state = DriverState.DISCONNECTED
            last: Exception | None = None
            for attempt in range(max(self.config.reconnect_attempts, 1)):
                if attempt:
                    self.sleep(self.config.reconnect_delay)
                try:
                    info = self.connect()
                    self.reconnects += 1
                    return info
                except TransportError as exc:
                    last = exc
                    self.amplifier.close()
            raise ConnectionLost(f"could not reconnect to {self.amplifier.transport.url}: {last}") from last

    def close(self) -> None:
        """Close the link without touching the output (use shutdown() to ramp to safe first)."""
        with self._lock:
            self._may_reconnect = False
            self.amplifier.close()
            if self.state is not DriverState.SHUT_DOWN:
                self.state = DriverState.DISCONNECTED

    @property
    def connected(self) -> bool:
        return self.state not in (DriverState.DISCONNECTED, DriverState.SHUT_DOWN)

    # --- commands -------------------------------------------------------------------------------
    def set_voltage(self, voltage: float, now: float | None = None) -> SetResult:
        """Apply one voltage request with all safety checks; returns what was sent."""
        voltage = float(voltage)
        if not math.isfinite(voltage):
            raise NonFiniteVoltageError(f"refusing non-finite voltage {voltage!r}; nothing sent")
        with self._lock:
            limits = self._require_limits()
            if not limits.contains(voltage) and not self.config.clamp:
                raise VoltageOutOfRangeError(
                    f"{voltage} V outside [{limits.v_min}, {limits.v_max}] V; nothing sent")
            now = self.clock() if now is None else now
            sent, slewed = self._write_step(limits.clamp(voltage), now)
            self._t_command = now
            self.state = DriverState.ACTIVE
            return SetResult(voltage, sent, not limits.contains(voltage), slewed)

    def read_voltage(self) -> float:
        """The applied voltage the amplifier reports [V]."""
        with self._lock:
            self._require_limits()
            return self._with_reconnect(self.amplifier.read_voltage)

    def tick(self, now: float | None = None) -> DriverState:
        """Watchdog step: after ``command_timeout`` without commands, ramp toward safe_voltage.

        A link that dropped is reopened here too, so the output still reaches safe_voltage when
        the commands stopped because the link died.
        """
        with self._lock:
            if self.state is DriverState.SHUT_DOWN or not self._may_reconnect:
                return self.state
            now = self.clock() if now is None else now
            if self.state is DriverState.DISCONNECTED:
                t_command = self._t_command
                try:
                    self.reconnect()
                except TransportError as exc:
                    log.error("watchdog: link still down: %s", exc)
                    return self.state
                self._t_command = t_command  # the silence before the drop still counts
            if self.state is DriverState.ACTIVE and now - self._t_command > self.config.command_timeout:
                log.warning("no voltage command for %.3g s: ramping to %g V",
                            now - self._t_command, self.config.safe_voltage)
                self.state = DriverState.TIMED_OUT
            if self.state is DriverState.TIMED_OUT:
                t_command = self._t_command
                sent, _ = self._write_step(self.config.safe_voltage, now)  # may reconnect
                self._t_command = t_command
                safe = sent == self._rounded(self.config.safe_voltage)
                self.state = DriverState.SAFE if safe else DriverState.TIMED_OUT
            return self.state

    def ramp_to(self, target: float) -> float:
        """Blocking ramp to ``target`` at the slew rate; returns the final voltage sent."""
        target = float(target)
        if not math.isfinite(target):
            raise NonFiniteVoltageError(f"refusing non-finite ramp target {target!r}")
        with self._lock:
            limits = self._require_limits()
            if not limits.contains(target):
                raise VoltageOutOfRangeError(f"ramp target {target} V outside [{limits.v_min}, {limits.v_max}] V")
            goal = self._rounded(target)
            while True:
                now = self.clock()
                sent, _ = self._write_step(target, now)
                self._t_command = now
                if sent == goal:
                    return sent
                self.sleep(self.config.ramp_period)

    def shutdown(self) -> float:
        """Ramp to safe_voltage, leave the amplifier there in open loop, close; returns read-back."""
        with self._lock:
            if self.state is DriverState.SHUT_DOWN:
                return self.last_sent
            self.ramp_to(self.config.safe_voltage)  # reopens a dropped link first
            applied = self.read_voltage()
            self.amplifier.close()
            self._may_reconnect = False
            self.state = DriverState.SHUT_DOWN
            log.info("shut down at %g V (read back %g V)", self.last_sent, applied)
            return applied

    # --- internals ------------------------------------------------------------------------------
    def _require_limits(self) -> VoltageLimits:
        """The effective limits; reopens a link that dropped, refuses after close()/shutdown()."""
        if self.limits is None or not self._may_reconnect:
            raise NotConnected("voltage driver is not connected; call connect()")
        if self.state is DriverState.DISCONNECTED:
            self.reconnect()
        return self.limits

    def _rounded(self, voltage: float) -> float:
        assert self.limits is not None
        return round_within(voltage, self.limits, self.amplifier.decimals)

    def _write_step(self, target: float, now: float) -> tuple[float, bool]:
        """Write one slew-limited, limit-checked step toward ``target``; returns (sent, slew-cut)."""
        def attempt() -> tuple[float, bool]:
            assert self.limits is not None
            dt = min(now - self._t_sent, self.config.max_slew_interval)
            stepped = slew_step(self.last_sent, target, self.config.slew_rate, dt)
            value = self._rounded(self.limits.clamp(stepped))
            if not self.limits.contains(value):  # cannot happen; kept as the last line of defence
                raise VoltageOutOfRangeError(f"internal error: {value} V outside {self.limits}")
            self.amplifier.write_voltage(value)
            self.last_sent, self._t_sent = value, now
            return value, value != self._rounded(target)

        return self._with_reconnect(attempt)

    def _with_reconnect(self, operation):
        try:
            return operation()
        except TransportError as exc:
            if self.config.reconnect_attempts <= 0:
                self.state = DriverState.DISCONNECTED
                raise
            log.warning("link to %s lost (%s); reconnecting", self.amplifier.transport.url, exc)
            self.reconnect()
            return operation()


class Watchdog:
    """A thread calling :meth:`VoltageDriver.tick` every ``period`` seconds (for non-ROS use)."""

    def __init__(self, driver: VoltageDriver, period: float = 0.01) -> None:
        if not period > 0:
            raise ConfigError(f"watchdog period must be > 0 s, got {period}")
        self.driver = driver
        self.period = period
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="voltage-watchdog", daemon=True)
        self.error: Exception | None = None

    def start(self) -> "Watchdog":
        self._thread.start()
        return self

    def stop(self) -> None:
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
