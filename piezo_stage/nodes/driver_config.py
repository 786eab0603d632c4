"""What the amplifier nodes share: the :class:`~piezo_stage.hardware.driver.DriverConfig` of an
axis, built from voltage_driver's safety parameters (its one axis, or every axis of its stage
from the same table entries).
"""

from __future__ import annotations

import math
from typing import Protocol

from piezo_stage.hardware import DriverConfig

#: voltage_driver's parameters that are one axis's safety rules (a stage: every axis's)
AXIS_SAFETY = (
    "v_min",
    "v_max",
    "safe_voltage",
    "slew_rate",
    "command_timeout",
    "watchdog_period",
    "reconnect_attempts",
)


class SafetySettings(Protocol):
    """The settings fields :func:`driver_config` reads (:data:`AXIS_SAFETY`)."""

    @property
    def v_min(self) -> float: ...
    @property
    def v_max(self) -> float: ...
    @property
    def safe_voltage(self) -> float: ...
    @property
    def slew_rate(self) -> float: ...
    @property
    def command_timeout(self) -> float: ...
    @property
    def watchdog_period(self) -> float: ...
    @property
    def reconnect_attempts(self) -> int: ...


def driver_config(s: SafetySettings) -> DriverConfig:
    """One axis's safety: 0 for ``slew_rate`` or ``command_timeout`` is "off" (inf); the
    watchdog timer's period is the driver's write period (each tick writes one ramp step)."""
    return DriverConfig(
        v_min=s.v_min,
        v_max=s.v_max,
        safe_voltage=s.safe_voltage,
        slew_rate=s.slew_rate or math.inf,
        command_timeout=s.command_timeout or math.inf,
        write_period=s.watchdog_period,
        reconnect_attempts=s.reconnect_attempts,
    )
