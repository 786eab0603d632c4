"""A displacement sensor's published frame, in one place for the ``laser_reader`` node and the
composed loops that read its sensor themselves.

A reading d (the distance from the sensor, metres) is published as
``displacement = sign · (d − zero_offset)`` when its status is OK, NaN otherwise, stamped at
the instant it measured: its arrival stamp minus the sensor's ``latency``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

from .optoncdt import Status

__all__ = ["SensorFrame"]

_OK = int(Status.OK)


@dataclass(frozen=True)
class SensorFrame:
    """``zero_offset`` [m], ``sign`` (±1) and ``latency`` [s] of a sensor (module docstring)."""

    zero_offset: float = 0.0
    sign: float = 1.0
    latency: float = 0.0
    latency_ns: int = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "latency_ns", round(self.latency * 1e9))

    def value(self, d: float, ok: bool) -> float:
        """One reading in the published frame (NaN when not valid)."""
        return self.sign * (d - self.zero_offset) if ok else math.nan

    def values(self, d: Sequence[float], status: Sequence[int]) -> list[float]:
        """Readings in the published frame, NaN where the status is not OK."""
        zero, sign = self.zero_offset, self.sign
        return [sign * (x - zero) if st == _OK else math.nan for x, st in zip(d, status)]

    def stamp(self, arrival_ns: int) -> int:
        """The instant [ns] a reading that arrived at ``arrival_ns`` measured."""
        return arrival_ns - self.latency_ns

    def stamps(self, arrival_ns: Sequence[int]) -> Sequence[int]:
        """:meth:`stamp` of each (``arrival_ns`` itself when there is no latency)."""
        latency = self.latency_ns
        return [t - latency for t in arrival_ns] if latency else arrival_ns
