"""Voltage limits, rounding inside them and slew-rate stepping: the arithmetic of driver safety."""

from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import LimitsError


@dataclass(frozen=True)
class VoltageLimits:
    """A closed voltage interval [v_min, v_max] in volts."""

    v_min: float
    v_max: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.v_min) and math.isfinite(self.v_max)):
            raise LimitsError(f"voltage limits must be finite, got [{self.v_min}, {self.v_max}]")
        if self.v_min > self.v_max:
            raise LimitsError(f"empty voltage range: v_min {self.v_min} V > v_max {self.v_max} V")

    def intersect(self, other: "VoltageLimits") -> "VoltageLimits":
        """The common part of both intervals; :class:`LimitsError` when they do not overlap."""
        lo, hi = max(self.v_min, other.v_min), min(self.v_max, other.v_max)
        if lo > hi:
            raise LimitsError(
                f"configured limits [{self.v_min}, {self.v_max}] V and device limits "
                f"[{other.v_min}, {other.v_max}] V do not overlap"
            )
        return VoltageLimits(lo, hi)

    def contains(self, voltage: float) -> bool:
        """Whether ``voltage`` lies in [v_min, v_max]."""
        return self.v_min <= voltage <= self.v_max

    def clamp(self, voltage: float) -> float:
        """Clamp ``voltage`` to [v_min, v_max]."""
        return min(max(voltage, self.v_min), self.v_max)


def round_within(voltage: float, limits: VoltageLimits, decimals: int) -> float:
    """Round to ``decimals`` places, rounding inward at the limits so the result stays inside."""
    scale = 10.0**decimals
    value = round(voltage, decimals)
    if value > limits.v_max:
        value = math.floor(limits.v_max * scale) / scale
    if value < limits.v_min:
        value = math.ceil(limits.v_min * scale) / scale
    if not limits.contains(value):  # limits narrower than one quantum: no representable value
        raise LimitsError(
            f"no {decimals}-decimal voltage inside [{limits.v_min}, {limits.v_max}] V"
        )
    return value


def slew_step(previous: float, target: float, slew_rate: float, dt: float) -> float:
    """Move from ``previous`` toward ``target`` by at most ``slew_rate * dt`` volts."""
    if math.isinf(slew_rate):
        return target
    max_step = slew_rate * max(dt, 0.0)
    return previous + min(max(target - previous, -max_step), max_step)
