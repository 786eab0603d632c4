"""The voltage driver of a multi-channel device: every axis's safety rules, one link, one write
per cycle.

:class:`StageDriver` holds one :class:`~.driver.VoltageDriver` per axis, each over a
:class:`~.axis_link.ChannelAmplifier` of one shared :class:`~.axis_link.AxisLink`: per axis its
own limits, slew cap between every two writes, watchdog from its own last command, read-back and
reconnect, exactly as for one axis. What the stage adds: the writes of one call
(:meth:`set_voltages`, :meth:`tick`, each step of the shutdown ramp) leave as one device command
(GCS ``SVA 1 a 2 b 3 c``), a failed command marks every axis in it down (the link reopens once,
for all), and :meth:`shutdown` ramps all axes to their safe voltages together.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager, nullcontext
from typing import ContextManager

from .amplifier import Amplifier, DeviceInfo
from .axis_link import AxisLink, ChannelAmplifier
from .driver import LINK_FAULTS, DriverConfig, DriverState, SetResult, VoltageDriver
from .errors import ConfigError, HardwareError, SafeStateNotReached

__all__ = ["StageDriver"]


class _OwnLink:
    """The link of a one-axis stage on a device of its own (a single-channel amplifier): its
    writes are its axis's (:meth:`StageDriver.of_one`).
    """

    def __init__(self, axis: str) -> None:
        self.axes = (axis,)
        self.driver: VoltageDriver | None = None

    def batch(self) -> ContextManager[None]:
        return nullcontext()

    @property
    def writes(self) -> int:
        return self.driver.writes if self.driver is not None else 0


class StageDriver:
    """Every axis of ``link``'s device (module docstring); ``configs[axis]`` its safety."""

    def __init__(
        self,
        link: AxisLink,
        configs: Mapping[str, DriverConfig],
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        missing = [a for a in link.axes if a not in configs]
        extra = [a for a in configs if a not in link.axes]
        if missing or extra:
            raise ConfigError(
                f"one driver configuration per axis of the link {list(link.axes)}; "
                f"missing {missing}, unknown {extra}"
            )
        self.link: AxisLink | _OwnLink = link
        self.sleep = sleep
        self.drivers = {
            axis: VoltageDriver(ChannelAmplifier(link, axis), configs[axis], clock, sleep)
            for axis in link.axes
        }

    @classmethod
    def of_one(
        cls,
        amplifier: Amplifier,
        config: DriverConfig,
        axis: str = "",
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> StageDriver:
        """The stage of one axis, ``axis``, on ``amplifier``'s device alone (the single-axis rig:
        its wire exchanges are the amplifier's own).
        """
        stage = cls.__new__(cls)
        link = _OwnLink(axis)
        link.driver = VoltageDriver(amplifier, config, clock, sleep)
        stage.link, stage.sleep, stage.drivers = link, sleep, {axis: link.driver}
        return stage

    def connect(self) -> dict[str, DeviceInfo]:
        """Open the link and take over every axis's output; on a refusal the axes already
        connected are closed again.
        """
        infos = {}
        try:
            for axis, driver in self.drivers.items():
                infos[axis] = driver.connect()
        except HardwareError:
            self.close()
            raise
        return infos

    @contextmanager
    def _one_command(self, axes: list[str]) -> Iterator[None]:
        """The writes of the block leave as one command; if it fails, ``axes`` go down."""
        try:
            with self.link.batch():
                yield
        except LINK_FAULTS as exc:
            for axis in axes:
                driver = self.drivers[axis]
                with driver._lock:
                    driver._link_down(exc)
            raise

    def set_voltages(
        self,
        values: Mapping[str, float],
        received: float | Mapping[str, float | None] | None = None,
    ) -> dict[str, SetResult | HardwareError]:
        """Apply one request per named axis with all of its checks, as one device command; per
        axis what was sent, or the refusal (non-finite, out of range, expired, not connected)
        for that axis alone. ``received``: when the requests arrived, one time for all or per
        axis (:meth:`VoltageDriver.set_voltage`). A failed command raises (every axis in it
        reconnects).
        """
        unknown = [a for a in values if a not in self.drivers]
        if unknown:
            raise ConfigError(f"no axis {unknown} on this stage (axes {list(self.drivers)})")
        results: dict[str, SetResult | HardwareError] = {}
        with self._one_command(list(values)):
            for axis, value in values.items():
                at = received.get(axis) if isinstance(received, Mapping) else received
                try:
                    results[axis] = self.drivers[axis].set_voltage(value, at)
                except HardwareError as exc:
                    results[axis] = exc
        return results

    def command_received(self, axis: str, received: float | None = None) -> None:
        """A valid command for ``axis`` arrived (its watchdog counts from here)."""
        self.drivers[axis].command_received(received)

    def tick(self, now: float | None = None) -> dict[str, DriverState]:
        """Every axis's watchdog and ramp step, the steps written as one command."""
        try:
            with self._one_command(list(self.drivers)):
                return {axis: d.tick(now) for axis, d in self.drivers.items()}
        except LINK_FAULTS:
            return {axis: d.state for axis, d in self.drivers.items()}

    def read_voltages(self) -> dict[str, float]:
        """Every axis's applied voltage as the device reports it."""
        return {axis: d.read_voltage() for axis, d in self.drivers.items()}

    def _ramp_all_to_safe(self) -> None:
        """Step every connected axis toward its safe voltage, all in one command per step."""
        period = min(d.config.ramp_period for d in self.drivers.values())
        live = {a: d for a, d in self.drivers.items() if d.connected}
        for driver in live.values():
            with driver._lock:
                driver.target = driver.config.safe_voltage
        while live:
            with self._one_command(list(live)):
                for driver in live.values():
                    with driver._lock:
                        driver._write_step()
            live = {
                a: d for a, d in live.items() if d.last_sent != d._rounded(d.config.safe_voltage)
            }
            if live:
                self.sleep(period)

    def shutdown(self) -> dict[str, float]:
        """Ramp all axes together to their safe voltages, then each axis's own shutdown (read
        back, close). Raises :class:`SafeStateNotReached` naming the axes that did not get
        there; every axis is shut down all the same.
        """
        try:
            self._ramp_all_to_safe()
        except LINK_FAULTS:
            pass  # each axis's shutdown waits for the reconnect and ramps on its own
        applied: dict[str, float] = {}
        failed: list[str] = []
        for axis, driver in self.drivers.items():
            try:
                applied[axis] = driver.shutdown()
            except SafeStateNotReached as exc:
                applied[axis] = math.nan
                failed.append(f"{axis}: {exc}")
        if failed:
            raise SafeStateNotReached("; ".join(failed))
        return applied

    def close(self) -> None:
        """Close every axis without touching the outputs."""
        for driver in self.drivers.values():
            driver.close()

    @property
    def states(self) -> dict[str, DriverState]:
        """Every axis's driver state."""
        return {axis: d.state for axis, d in self.drivers.items()}
