"""Trajectories x_d(t) to track (the thesis leaves tracking to future work, §11.6).

Every trajectory gives position, velocity and acceleration in closed form (vectorised
:meth:`Trajectory.evaluate`), so the feedforward m ẍ_d + c ẋ_d + ... and the controller's
x2 = ẋ − ẋ_d never differentiate a sampled signal. Shapes (``amplitude`` is half the
peak-to-peak range, ``offset`` the mid-range; each starts at its lowest point, ``offset −
amplitude``, at rest, t < 0 holds x_d(0)):

- ``sine``: x_d = offset − A·cos(2πft).
- ``triangle`` (a raster scan line): constant-velocity ramps joined by corners on which the
  velocity turns as v·cos(π τ/T_c), so ẍ_d is continuous and bounded by π v/T_c.
- ``steps``: offset − A and offset + A held for half a period each, joined by transitions
  x = lo + (hi − lo)·(τ/T_r − sin(2π τ/T_r)/(2π)) (zero velocity and acceleration at both ends).
- :class:`CsvTrajectory`: samples (t, x) from a CSV file through a C² cubic spline (zero
  velocity at its ends; held after the last sample).

Limits: ``v_max`` [m/s] and ``a_max`` [m/s²]; a triangle's corners and a step's transitions
lengthen to respect them, a shape that cannot is refused with the figure it would need.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import ClassVar, Protocol, cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import ControlError


class TrajectoryError(ControlError):
    """A trajectory that cannot be built (bad numbers, limits it cannot meet, unreadable CSV)."""


class Shape(str, Enum):
    """The periodic shapes of :class:`PeriodicTrajectory` (see the module docstring)."""

    SINE = "sine"
    TRIANGLE = "triangle"
    STEPS = "steps"


#: default share of a half period taken by a triangle's corner or a step's transition
DEFAULT_ROUNDING = 0.2

Evaluation = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
#: (x_d, ẋ_d, ẍ_d) at one time
Point = tuple[float, float, float]


def _finite(name: str, value: float, positive: bool = False) -> float:
    value = float(value)
    if not math.isfinite(value) or (positive and value <= 0):
        raise TrajectoryError(f"{name} must be {'> 0' if positive else 'finite'}, got {value}")
    return value


@dataclass(frozen=True)
class PeriodicTrajectory:
    """A periodic shape (see the module docstring); times in s, positions in m."""

    periodic: ClassVar[bool] = True  #: a feedforward table of one period serves it
    shape: Shape
    amplitude: float
    frequency: float
    offset: float | None = None
    rounding: float = DEFAULT_ROUNDING
    v_max: float = math.inf
    a_max: float = math.inf

    def __post_init__(self) -> None:
        object.__setattr__(self, "shape", Shape(self.shape))
        _finite("amplitude", self.amplitude, positive=True)
        _finite("frequency", self.frequency, positive=True)
        if self.offset is None:
            object.__setattr__(self, "offset", float(self.amplitude))  # from 0 up to 2A
        _finite("offset", self._center)
        if not 0.0 < self.rounding <= 1.0:
            raise TrajectoryError(f"rounding must be in (0, 1], got {self.rounding}")
        for name in ("v_max", "a_max"):
            if not getattr(self, name) > 0:
                raise TrajectoryError(f"{name} must be > 0, got {getattr(self, name)}")
        object.__setattr__(self, "_blend", self._blend_time())
        v, a = self.peak_velocity, self.peak_acceleration
        if v > self.v_max * (1 + 1e-9):
            raise TrajectoryError(
                f"{self.shape.value} needs a velocity of {v:.4g} m/s > v_max "
                f"{self.v_max:.4g} m/s: lower the frequency or the amplitude"
            )
        if a > self.a_max * (1 + 1e-9):
            raise TrajectoryError(
                f"{self.shape.value} needs an acceleration of {a:.4g} m/s² > a_max "
                f"{self.a_max:.4g} m/s²: lower the frequency or the amplitude"
            )

    # ------------------------------------------------------------------ geometry
    @property
    def period(self) -> float:
        """One period, 1 / frequency [s]."""
        return 1.0 / self.frequency

    @property
    def _center(self) -> float:
        """``offset`` once set: the amplitude when it was given as None [m]."""
        return cast(float, self.offset)  # __post_init__ replaced None

    @property
    def range(self) -> float:
        """Peak-to-peak range [m]."""
        return 2.0 * self.amplitude

    @property
    def blend_time(self) -> float:
        """T_c (triangle corner) or T_r (step transition) [s]; 0 for the sine."""
        blend: float = self._blend  # type: ignore[attr-defined]  # set in __post_init__
        return blend

    def _ramp_velocity(self, tc: float) -> float:
        """Triangle: the ramp velocity v with corners T_c: 2·v·T_c/π + v·(P/2 − T_c) = 2A."""
        return self.range / (0.5 * self.period - tc * (1.0 - 2.0 / math.pi))

    def _peaks(self, blend: float) -> tuple[float, float]:
        a, w = self.amplitude, 2.0 * math.pi * self.frequency
        if self.shape is Shape.SINE:
            return a * w, a * w * w
        if self.shape is Shape.TRIANGLE:
            v = self._ramp_velocity(blend)
            return v, math.pi * v / blend
        return 2.0 * self.range / blend, 2.0 * math.pi * self.range / blend**2

    def _blend_time(self) -> float:
        """The shortest blend ≥ rounding·P/2 that meets the limits falling as it lengthens
        (bisection up to P/2): a step's v and a both; a triangle's a = π·v/T_c alone, since its
        ramp velocity v grows with the corner, so no longer corner can then meet v_max
        (``__post_init__`` refuses it with the figure).
        """
        if self.shape is Shape.SINE:
            return 0.0
        half = 0.5 * self.period
        lo = self.rounding * half
        v_max = math.inf if self.shape is Shape.TRIANGLE else self.v_max

        def ok(blend: float) -> bool:
            v, a = self._peaks(blend)
            return v <= v_max and a <= self.a_max

        if ok(lo):
            return lo
        if not ok(half):
            return half  # refused in __post_init__ with the figure it needs
        hi = half
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if ok(mid) else (mid, hi)
        return hi

    @property
    def peak_velocity(self) -> float:
        """Largest |ẋ_d| [m/s]."""
        return self._peaks(self.blend_time)[0]

    @property
    def peak_acceleration(self) -> float:
        """Largest |ẍ_d| [m/s²]."""
        return self._peaks(self.blend_time)[1]

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, t: ArrayLike) -> Evaluation:
        """(x_d, ẋ_d, ẍ_d) at times ``t`` [s] (vectorised)."""
        t = np.maximum(np.asarray(t, dtype=np.float64), 0.0)
        if self.shape is Shape.SINE:
            w = 2.0 * math.pi * self.frequency
            c, s = np.cos(w * t), np.sin(w * t)
            return (
                self._center - self.amplitude * c,
                self.amplitude * w * s,
                self.amplitude * w * w * c,
            )
        half = 0.5 * self.period
        k = np.floor(t / half)
        tau = t - k * half  # time into the current half period
        sign = np.where(k % 2 == 0, 1.0, -1.0)  # rising on even halves
        if self.shape is Shape.TRIANGLE:
            x, v, a = self._rising_triangle(tau)
        else:
            x, v, a = self._rising_step(tau)
        low = self._center - self.amplitude
        return low + np.where(sign > 0, x, self.range - x), sign * v, sign * a

    def at(self, t: float) -> Point:
        """(x_d, ẋ_d, ẍ_d) at one time ``t`` [s]: :meth:`evaluate` in scalar arithmetic (a
        controller's per-sample call, where numpy costs microseconds per operation).
        """
        t = max(float(t), 0.0)
        a = self.amplitude
        if self.shape is Shape.SINE:
            w = 2.0 * math.pi * self.frequency
            c, s = math.cos(w * t), math.sin(w * t)
            return self._center - a * c, a * w * s, a * w * w * c
        half = 0.5 * self.period
        k = math.floor(t / half)
        tau = t - k * half
        x, v, acc = (
            self._rise_triangle_at(tau) if self.shape is Shape.TRIANGLE else self._rise_step_at(tau)
        )
        low = self._center - a
        if k % 2 == 0:
            return low + x, v, acc
        return low + (self.range - x), -v, -acc

    def _rise_triangle_at(self, tau: float) -> Point:
        """:meth:`_rising_triangle` at one time."""
        tc, half = self.blend_time, 0.5 * self.period
        v = self._ramp_velocity(tc)
        r, wc = v * tc / math.pi, math.pi / tc
        if tau < 0.5 * tc:
            return (
                r * (1.0 - math.cos(wc * tau)),
                v * math.sin(wc * tau),
                v * wc * math.cos(wc * tau),
            )
        if tau > half - 0.5 * tc:
            u = half - tau
            return (
                self.range - r * (1.0 - math.cos(wc * u)),
                v * math.sin(wc * u),
                -v * wc * math.cos(wc * u),
            )
        return r + v * (tau - 0.5 * tc), v, 0.0

    def _rise_step_at(self, tau: float) -> Point:
        """:meth:`_rising_step` at one time."""
        tr, span, two_pi = self.blend_time, self.range, 2.0 * math.pi
        if tau >= tr:
            return span * (1.0 - math.sin(two_pi) / two_pi), 0.0, 0.0
        s = max(tau / tr, 0.0)
        return (
            span * (s - math.sin(two_pi * s) / two_pi),
            span / tr * (1.0 - math.cos(two_pi * s)),
            span * two_pi / tr**2 * math.sin(two_pi * s),
        )

    def _rising_triangle(self, tau: NDArray[np.float64]) -> Evaluation:
        """One rise from the bottom corner's middle to the top corner's middle."""
        tc, half = self.blend_time, 0.5 * self.period
        v = self._ramp_velocity(tc)
        r = v * tc / math.pi  # rise over half a corner
        wc = math.pi / tc
        first = tau < 0.5 * tc
        last = tau > half - 0.5 * tc
        u = half - tau  # time left to the top corner's middle
        x = np.where(
            first,
            r * (1.0 - np.cos(wc * tau)),
            np.where(last, self.range - r * (1.0 - np.cos(wc * u)), r + v * (tau - 0.5 * tc)),
        )
        vel = np.where(first, v * np.sin(wc * tau), np.where(last, v * np.sin(wc * u), v))
        acc = np.where(
            first, v * wc * np.cos(wc * tau), np.where(last, -v * wc * np.cos(wc * u), 0.0)
        )
        return x, vel, acc

    def _rising_step(self, tau: NDArray[np.float64]) -> Evaluation:
        """Transition over [0, T_r], then held at the top for the rest of the half period."""
        tr = self.blend_time
        s = np.clip(tau / tr, 0.0, 1.0)
        moving = tau < tr
        two_pi = 2.0 * math.pi
        x = self.range * (s - np.sin(two_pi * s) / two_pi)
        vel = np.where(moving, self.range / tr * (1.0 - np.cos(two_pi * s)), 0.0)
        acc = np.where(moving, self.range * two_pi / tr**2 * np.sin(two_pi * s), 0.0)
        return x, vel, acc


@dataclass(frozen=True)
class CsvTrajectory:
    """x_d(t) from samples through a clamped C² cubic spline (analytic ẋ_d, ẍ_d)."""

    periodic: ClassVar[bool] = False  #: the record is taken whole
    t: NDArray[np.float64]
    x: NDArray[np.float64]
    name: str = ""
    v_max: float = math.inf
    a_max: float = math.inf

    def __post_init__(self) -> None:
        from scipy.interpolate import CubicSpline

        t, x = np.asarray(self.t, dtype=float), np.asarray(self.x, dtype=float)
        if t.ndim != 1 or t.shape != x.shape or t.size < 2:
            raise TrajectoryError(f"{self.name or 'trajectory'}: need at least two (t, x) samples")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(x))):
            raise TrajectoryError(f"{self.name or 'trajectory'}: NaN or infinite samples")
        if not np.all(np.diff(t) > 0):
            raise TrajectoryError(f"{self.name or 'trajectory'}: times must increase strictly")
        spline = CubicSpline(t - t[0], x, bc_type="clamped")
        object.__setattr__(self, "t", t - t[0])
        object.__setattr__(self, "x", x)
        object.__setattr__(self, "_spline", spline)
        fine = np.linspace(0.0, float(self.t[-1]), 20 * t.size + 1)
        v, a = np.abs(spline(fine, 1)).max(), np.abs(spline(fine, 2)).max()
        if v > self.v_max:
            raise TrajectoryError(f"{self.name}: velocity {v:.4g} m/s > v_max {self.v_max:.4g} m/s")
        if a > self.a_max:
            raise TrajectoryError(
                f"{self.name}: acceleration {a:.4g} m/s² > a_max {self.a_max:.4g} m/s²"
            )

    @property
    def period(self) -> float:
        """The file's duration [s] (its figures are taken over the whole file)."""
        return float(self.t[-1])

    @property
    def range(self) -> float:
        """Peak-to-peak range of the samples [m]."""
        return float(np.ptp(self.x))

    def evaluate(self, t: ArrayLike) -> Evaluation:
        """(x_d, ẋ_d, ẍ_d); before the first sample x_d(0), after the last x_d(end), at rest."""
        t = np.asarray(t, dtype=float)
        inside = (t >= 0.0) & (t <= self.t[-1])
        tc = np.clip(t, 0.0, self.t[-1])
        spline = self._spline  # type: ignore[attr-defined]  # set in __post_init__
        return (
            spline(tc),
            np.where(inside, spline(tc, 1), 0.0),
            np.where(inside, spline(tc, 2), 0.0),
        )

    def at(self, t: float) -> Point:
        """:meth:`evaluate` at one time (the spline's own scalar call)."""
        x, v, a = self.evaluate(t)
        return float(x), float(v), float(a)

    @classmethod
    def read(
        cls, path: str | Path, *, v_max: float = math.inf, a_max: float = math.inf
    ) -> "CsvTrajectory":
        """Two columns t [s], x [m]; a header line and '#' comments are skipped."""
        path = Path(path)
        rows: list[tuple[float, float]] = []
        try:
            with path.open(newline="", encoding="utf-8") as handle:
                for line_no, row in enumerate(csv.reader(handle), start=1):
                    cells = [c.strip() for c in row if c.strip()]
                    if not cells or cells[0].startswith("#"):
                        continue
                    try:
                        rows.append((float(cells[0]), float(cells[1])))
                    except (ValueError, IndexError):
                        if rows:
                            raise TrajectoryError(
                                f"{path}:{line_no}: expected two numbers 't, x', got {row!r}"
                            ) from None
        except OSError as exc:
            raise TrajectoryError(f"cannot read trajectory {path}: {exc.strerror}") from exc
        if not rows:
            raise TrajectoryError(f"{path}: no (t, x) samples")
        t, x = np.array(rows).T
        return cls(t, x, name=str(path), v_max=v_max, a_max=a_max)


class Trajectory(Protocol):
    """What a controller follows: x_d, ẋ_d, ẍ_d at any time (:class:`PeriodicTrajectory`,
    :class:`CsvTrajectory`, one axis of a raster scan: :class:`~.scan.ScanAxis`).
    """

    periodic: ClassVar[bool]  #: a feedforward table of one :attr:`period` serves it

    @property
    def period(self) -> float:
        """The time after which the trajectory repeats (periodic) or ends [s]."""
        ...

    @property
    def range(self) -> float:
        """Max x_d - min x_d [m]."""
        ...

    def evaluate(self, t: ArrayLike) -> Evaluation:
        """(x_d, ẋ_d, ẍ_d) at the times ``t``."""
        ...

    def at(self, t: float) -> Point:
        """(x_d, ẋ_d, ẍ_d) at one time ``t``, as :meth:`evaluate` gives it, in floats."""
        ...


@dataclass(frozen=True)
class SetPoint:
    """x_d = ``position`` at all times (an axis held while another moves); no period."""

    position: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _finite("position", self.position))

    def evaluate(self, t: ArrayLike) -> Evaluation:
        """(x_d, ẋ_d, ẍ_d) at ``t``: the position, 0, 0."""
        t = np.asarray(t, dtype=float)
        return np.full_like(t, self.position), np.zeros_like(t), np.zeros_like(t)

    def at(self, t: float) -> Point:
        """The position, 0, 0."""
        return self.position, 0.0, 0.0
