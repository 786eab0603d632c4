"""Raster scans: a fast axis sweeping lines and a slow axis stepping or ramping over a frame,
in closed form (x_d, ẋ_d, ẍ_d per axis, as :mod:`.trajectory` gives one axis), and
``make_trajectory``: any trajectory a controller follows, by name or file.

Geometry (times in s, positions in m). ``range`` and ``centre`` are the *image*'s, per axis;
the fast axis over-travels them by its turnarounds (an instrument's overscan):

- The fast axis runs a :class:`~.trajectory.PeriodicTrajectory` at the line rate f_L (one
  trace and one retrace per period P = 1/f_L), from its lowest point at rest at t = 0.
  ``triangle``: the image is the constant-velocity ramp of each half period (the corners, a
  share ``rounding`` of it, are turnaround), so with T_c = rounding·P/2 the ramp covers the
  range R when A = R/2·(1 − rounding·(1 − 2/π))/(1 − rounding). ``sine``: the image is the
  middle ``sine_share`` of each half period in time, A = R/(2 sin(π/2·sine_share)).
- Line k (row k of the image, at y_k = c_y − R_y/2 + (k + ½)·R_y/lines) is imaged in window
  [a_k, b_k]: on traces only (``raster``: one line per period), or on traces and retraces
  (``serpentine``: one line per half period, every other one swept backwards). A frame is
  ``flyback_lines`` periods of fly-back, then the lines; frames repeat. The scan starts at
  rest where a frame ends (the slow axis on the last line) and flies back before the first
  frame's first line, so every frame after it is the same.
- The slow axis holds y_k over each window and steps between them (``staircase``), or moves
  at the constant velocity that passes y_k in the middle of window k (``ramp``). Every
  transition (a step, a fly-back) is the quintic through its end points with their
  velocities and zero acceleration: ẍ_d is continuous and bounded.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from enum import Enum
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .trajectory import (
    DEFAULT_ROUNDING,
    CsvTrajectory,
    Evaluation,
    PeriodicTrajectory,
    Point,
    Shape,
    Trajectory,
    TrajectoryError,
)

__all__ = [
    "FastShape",
    "Order",
    "RasterScan",
    "ScanAxis",
    "ScanError",
    "SlowMotion",
    "make_trajectory",
    "quintic_transition",
]


class ScanError(TrajectoryError):
    """A scan that cannot be built (bad numbers, a line rate or pixel count it cannot meet)."""


class FastShape(str, Enum):
    """The fast axis's line shape."""

    TRIANGLE = "triangle"
    SINE = "sine"


class SlowMotion(str, Enum):
    """How the slow axis goes from one line to the next."""

    STAIRCASE = "staircase"
    RAMP = "ramp"


class Order(str, Enum):
    """Which half periods are image lines: traces only, or traces and retraces."""

    RASTER = "raster"
    SERPENTINE = "serpentine"


#: share of a sine's half period that is image by default (the middle, nearly linear part)
DEFAULT_SINE_SHARE = 0.6


@overload
def quintic_transition(
    tau: float, duration: float, p0: float, v0: float, p1: float, v1: float
) -> Point: ...
@overload
def quintic_transition(
    tau: NDArray[np.float64],
    duration: float,
    p0: float | NDArray[np.float64],
    v0: float,
    p1: float | NDArray[np.float64],
    v1: float,
) -> Evaluation: ...
def quintic_transition(tau: Any, duration: float, p0: Any, v0: float, p1: Any, v1: float) -> Any:
    """The quintic from (p0, v0) at τ = 0 to (p1, v1) at τ = T, at zero acceleration at both.

    For v0 = v1 = 0 it is the minimum-jerk step::

        x = p0 + v0 T s + (10 D − 6 v0 T − 4 v1 T) s³ + (−15 D + 8 v0 T + 7 v1 T) s⁴
               + (6 D − 3 v0 T − 3 v1 T) s⁵,   s = τ/T,  D = p1 − p0.
    """
    T = duration
    s = tau / T
    d = p1 - p0  # floats in, floats out: the scalar path of :meth:`RasterScan.slow_at`
    a0, a1 = v0 * T, v1 * T
    c3 = 10.0 * d - 6.0 * a0 - 4.0 * a1
    c4 = -15.0 * d + 8.0 * a0 + 7.0 * a1
    c5 = 6.0 * d - 3.0 * a0 - 3.0 * a1
    x = p0 + a0 * s + s**3 * (c3 + s * (c4 + s * c5))
    v = (a0 + s**2 * (3.0 * c3 + s * (4.0 * c4 + s * 5.0 * c5))) / T
    a = (s * (6.0 * c3 + s * (12.0 * c4 + s * 20.0 * c5))) / T**2
    return x, v, a


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (math.isfinite(value) and value > 0):
        raise ScanError(f"{name} must be > 0, got {value}")
    return value


@dataclass(frozen=True)
class RasterScan:
    """A raster scan over an image of ``lines`` × ``pixels`` (module docstring)."""

    lines: int
    pixels: int
    line_rate: float  #: [Hz] fast-axis periods per second
    range: tuple[float, float]  #: [m] image size (fast, slow)
    centre: tuple[float, float] = (0.0, 0.0)  #: [m] image centre (fast, slow)
    fast_shape: FastShape = FastShape.TRIANGLE
    slow_motion: SlowMotion = SlowMotion.STAIRCASE
    order: Order = Order.RASTER
    rounding: float = DEFAULT_ROUNDING  #: triangle: share of a half period in the corners
    sine_share: float = DEFAULT_SINE_SHARE  #: sine: share of a half period that is image
    flyback_lines: int = 1  #: periods of fly-back per frame

    def __post_init__(self) -> None:
        for name, kind in (
            ("fast_shape", FastShape),
            ("slow_motion", SlowMotion),
            ("order", Order),
        ):
            try:
                object.__setattr__(self, name, kind(getattr(self, name)))
            except ValueError:
                choices = ", ".join(k.value for k in kind)
                raise ScanError(
                    f"{name} must be one of {choices}, got {getattr(self, name)!r}"
                ) from None
        for name in ("lines", "pixels", "flyback_lines"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < (0 if name[0] == "f" else 1):
                raise ScanError(f"{name} must be a whole number ≥ 1, got {value!r}")
        if self.order is Order.SERPENTINE and self.lines % 2:
            raise ScanError(
                f"a serpentine frame needs an even number of lines (it ends on a retrace), "
                f"got {self.lines}"
            )
        _positive("line_rate", self.line_rate)
        if len(self.range) != 2 or len(self.centre) != 2:
            raise ScanError("range and centre take two values: fast axis, slow axis")
        object.__setattr__(self, "range", tuple(_positive("range", r) for r in self.range))
        centre = tuple(float(c) for c in self.centre)
        if not all(math.isfinite(c) for c in centre):
            raise ScanError(f"centre must be finite, got {self.centre}")
        object.__setattr__(self, "centre", centre)
        if not 0.0 < self.rounding < 1.0:
            raise ScanError(f"rounding must be in (0, 1), got {self.rounding}")
        if not 0.0 < self.sine_share < 1.0:
            raise ScanError(f"sine_share must be in (0, 1), got {self.sine_share}")

    def to_dict(self) -> dict[str, Any]:
        """The scan as plain JSON values (:meth:`from_dict` reads it back)."""
        data = asdict(self)
        data.update(range=list(self.range), centre=list(self.centre))
        data.update({k: getattr(self, k).value for k in ("fast_shape", "slow_motion", "order")})
        return data

    @classmethod
    def from_dict(cls, data: Any) -> "RasterScan":
        """A scan from :meth:`to_dict`'s values; :class:`ScanError` for what does not fit."""
        if not isinstance(data, dict):
            raise ScanError(f"a scan is a mapping of its fields, got {type(data).__name__}")
        try:
            values = dict(data)
            for key in ("range", "centre"):
                if key in values:
                    values[key] = tuple(values[key])
            return cls(**values)
        except TypeError as exc:
            raise ScanError(f"scan: {exc}") from None

    # ------------------------------------------------------------------ geometry
    @property
    def period(self) -> float:
        """P: one fast-axis period, trace and retrace [s]."""
        return 1.0 / self.line_rate

    @property
    def line_spacing(self) -> float:
        """Time from one image line's window to the next [s]."""
        return self.period if self.order is Order.RASTER else 0.5 * self.period

    @property
    def window(self) -> float:
        """Duration of one line's image window [s]."""
        share = 1.0 - self.rounding if self.fast_shape is FastShape.TRIANGLE else self.sine_share
        return share * 0.5 * self.period

    @property
    def frame_time(self) -> float:
        """One frame, fly-back included [s]."""
        return self.flyback_lines * self.period + self.lines * self.line_spacing

    @cached_property
    def fast(self) -> PeriodicTrajectory:
        """The fast axis's periodic trajectory (its amplitude covers the image and the
        turnarounds).
        """
        r, c = self.range[0], self.centre[0]
        if self.fast_shape is FastShape.TRIANGLE:
            k = (1.0 - self.rounding * (1.0 - 2.0 / math.pi)) / (1.0 - self.rounding)
            return PeriodicTrajectory(
                Shape.TRIANGLE, 0.5 * r * k, self.line_rate, c, rounding=self.rounding
            )
        amplitude = 0.5 * r / math.sin(0.5 * math.pi * self.sine_share)
        return PeriodicTrajectory(Shape.SINE, amplitude, self.line_rate, c)

    def row_positions(self) -> NDArray[np.float64]:
        """y_k of every line: the centres of the image's rows [m]."""
        r, c = self.range[1], self.centre[1]
        return c - 0.5 * r + (np.arange(self.lines, dtype=np.float64) + 0.5) * (r / self.lines)

    def window_start(self, k: ArrayLike) -> NDArray[np.float64]:
        """a_k: when line k's image window opens, in the frame's time [s]."""
        half = 0.5 * self.period
        lead = 0.5 * (half - self.window)  # a half period's turnaround before its window
        return self.flyback_lines * self.period + np.asarray(k) * self.line_spacing + lead

    def samples_per_window(self, rate_hz: float) -> float:
        """Loop samples in one line's image window at ``rate_hz``."""
        return self.window * rate_hz

    def check_rate(
        self, rate_hz: float, min_samples_per_line: int = 20, per_pixel: bool = True
    ) -> None:
        """Refuse a loop rate that cannot sample the lines or fill the pixels: fewer than
        ``min_samples_per_line`` samples in an image window, or (``per_pixel``: the loop's
        samples are the pixels') fewer than one per pixel.
        """
        n = self.samples_per_window(_positive("rate_hz", rate_hz))
        if n < min_samples_per_line:
            raise ScanError(
                f"{self.line_rate:g} Hz lines at a {rate_hz:g} Hz loop give {n:.1f} samples per "
                f"image line (at least {min_samples_per_line}): lower the line rate"
            )
        if per_pixel and n < self.pixels:
            raise ScanError(
                f"{self.pixels} pixels per line at a {rate_hz:g} Hz loop: only {n:.1f} samples "
                "in each line's image window (one per pixel at least): fewer pixels, a slower "
                "line or a faster loop"
            )

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, t: ArrayLike) -> tuple[Evaluation, Evaluation]:
        """((x_d, ẋ_d, ẍ_d) of the fast axis, the same of the slow axis) at ``t`` (vectorised;
        t < 0 holds the start at rest).
        """
        t = np.maximum(np.asarray(t, dtype=np.float64), 0.0)
        return self.fast.evaluate(t), self._slow(t)

    def slow_velocity(self) -> float:
        """The slow axis's velocity over a frame in ``ramp`` mode [m/s] (0 for staircase)."""
        if self.slow_motion is SlowMotion.STAIRCASE:
            return 0.0
        return (self.range[1] / self.lines) / self.line_spacing

    @cached_property
    def _slow_geometry(self) -> tuple[tuple[float, ...], float, float, float, float, float]:
        """The slow axis's row positions, a_0, b_last, its ramp velocity, and its positions
        at a_0 and b_last (ramp: y(a_0) = y_0 − v·W/2, y(b_last) = y_last + v·W/2).
        """
        rows = tuple(float(y) for y in self.row_positions())
        first = float(self.window_start(0))
        last = float(self.window_start(self.lines - 1)) + self.window
        v, half_window = self.slow_velocity(), 0.5 * self.window
        return rows, first, last, v, rows[0] - v * half_window, rows[-1] + v * half_window

    def slow_at(self, t: float) -> Point:
        """The slow axis's (x_d, ẋ_d, ẍ_d) of :meth:`evaluate` at one time ``t``, in scalar
        arithmetic (a controller's per-sample call).
        """
        t = max(float(t), 0.0)
        rows, first, last, v, y_first, y_last = self._slow_geometry
        frame = self.frame_time
        f = math.floor(t / frame)
        tau = t - f * frame
        if first <= tau <= last:
            if self.slow_motion is SlowMotion.RAMP:
                return y_first + v * (tau - first), v, 0.0
            spacing, window = self.line_spacing, self.window
            k = min(math.floor((tau - first) / spacing), self.lines - 1)
            since = tau - first - k * spacing
            if since > window and k < self.lines - 1:
                return quintic_transition(
                    since - window, spacing - window, rows[k], 0.0, rows[k + 1], 0.0
                )
            return rows[k], 0.0, 0.0
        if tau > last or f > 0:
            local = tau - last if tau > last else tau + frame - last
            return quintic_transition(local, frame - last + first, y_last, v, y_first, v)
        return quintic_transition(tau, first, y_last, 0.0, y_first, v)

    def _slow(self, t: NDArray[np.float64]) -> Evaluation:
        row_list, first, last, v, y_first, y_last = self._slow_geometry
        rows = np.array(row_list)
        spacing, window, frame = self.line_spacing, self.window, self.frame_time
        ramp = self.slow_motion is SlowMotion.RAMP
        f = np.floor(t / frame)
        tau = t - f * frame
        x, vel, acc = np.zeros_like(t), np.zeros_like(t), np.zeros_like(t)

        # the lines: a_0 <= tau <= b_last
        inside = (tau >= first) & (tau <= last)
        ti = tau[inside]
        if ramp:
            x[inside] = y_first + v * (ti - first)
            vel[inside] = v
        else:
            k = np.minimum(np.floor((ti - first) / spacing), self.lines - 1).astype(int)
            since = ti - first - k * spacing  # time since line k's window opened
            step = (since > window) & (k < self.lines - 1)  # (the last line: rounding)
            xs, vs, as_ = quintic_transition(
                since[step] - window, spacing - window, rows[k[step]], 0.0, rows[k[step] + 1], 0.0
            )
            xi = rows[k].copy()
            vi, ai = np.zeros_like(ti), np.zeros_like(ti)
            xi[step], vi[step], ai[step] = xs, vs, as_
            x[inside], vel[inside], acc[inside] = xi, vi, ai

        # the fly-back: after b_last, or before a_0 in a frame after the first
        flyback = frame - last + first
        after = tau > last
        before = (tau < first) & (f > 0)
        for mask, local in ((after, tau - last), (before, tau + frame - last)):
            x[mask], vel[mask], acc[mask] = quintic_transition(
                local[mask], flyback, y_last, v, y_first, v
            )
        # the first frame's fly-back, from rest where a frame ends (the first frame is like
        # the others but for its shorter fly-back)
        lead = (tau < first) & (f == 0)
        x[lead], vel[lead], acc[lead] = quintic_transition(
            tau[lead], first, y_last, 0.0, y_first, v
        )
        return x, vel, acc

    def line_index(self, t: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.int8]]:
        """For each time: the image line it is in (−1 in a turnaround or a fly-back) and the
        fast axis's direction there (+1 trace, −1 retrace, 0 outside).
        """
        tau = np.mod(np.maximum(np.asarray(t, dtype=np.float64), 0.0), self.frame_time)
        first = float(self.window_start(0))
        rel = tau - first
        k = np.floor(rel / self.line_spacing).astype(np.int64)
        since = rel - k * self.line_spacing
        ok = (rel >= 0) & (k < self.lines) & (since <= self.window)
        k = np.where(ok, k, -1)
        if self.order is Order.RASTER:
            direction = np.where(ok, 1, 0)
        else:
            direction = np.where(ok, np.where(k % 2 == 0, 1, -1), 0)
        return k, direction.astype(np.int8)

    def pixel_of(self, x: ArrayLike) -> NDArray[np.int64]:
        """The image column a fast-axis position falls in (−1 outside the image)."""
        r, c = self.range[0], self.centre[0]
        col = np.floor((np.asarray(x, dtype=float) - (c - 0.5 * r)) / (r / self.pixels))
        return np.where((col >= 0) & (col < self.pixels), col, -1).astype(np.int64)


#: file format of one axis of a scan (a controller's ``trajectory``)
SCAN_AXIS_FORMAT = "piezo_stage raster scan axis 1"


@dataclass(frozen=True)
class ScanAxis:
    """One axis of a raster scan as a trajectory (``index`` 0 the fast axis, 1 the slow one):
    x_d, ẋ_d, ẍ_d of :meth:`RasterScan.evaluate`; it repeats every line period (fast) or every
    frame (slow; the first frame's fly-back starts from rest).
    """

    scan: RasterScan
    index: int

    periodic: ClassVar[bool] = True  #: a feedforward table of one :attr:`period` serves it

    def __post_init__(self) -> None:
        if self.index not in (0, 1):
            raise ScanError(f"a scan axis is 0 (fast) or 1 (slow), got {self.index!r}")

    def evaluate(self, t: ArrayLike) -> Evaluation:
        """(x_d, ẋ_d, ẍ_d) of this axis at ``t``."""
        t = np.asarray(t, dtype=float)
        if self.index == 0:
            return self.scan.fast.evaluate(np.maximum(t, 0.0))
        return self.scan.evaluate(t)[1]

    def at(self, t: float) -> Point:
        """:meth:`evaluate` at one time, in scalar arithmetic."""
        return self.scan.fast.at(t) if self.index == 0 else self.scan.slow_at(t)

    @property
    def period(self) -> float:
        """The line period (fast axis) or the frame time (slow axis) [s]."""
        return self.scan.period if self.index == 0 else self.scan.frame_time

    @property
    def range(self) -> float:
        """The image's size along this axis [m]."""
        return self.scan.range[self.index]

    def save(self, path: str | Path) -> Path:
        """Write the axis as JSON (a controller's ``trajectory`` file)."""
        path = Path(path)
        data = {"format": SCAN_AXIS_FORMAT, "axis": self.index, "scan": self.scan.to_dict()}
        path.write_text(json.dumps(data, indent=1), encoding="utf-8")
        return path

    @classmethod
    def read(cls, path: str | Path) -> "ScanAxis":
        """What :meth:`save` wrote; :class:`ScanError` naming the file when it cannot."""
        try:
            data = json.loads(Path(path).read_text(encoding="utf-8"))
        except OSError as exc:
            raise ScanError(f"cannot read scan {path}: {exc.strerror}") from None
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ScanError(f"{path} is not JSON: {exc}") from None
        if not isinstance(data, dict) or data.get("format") != SCAN_AXIS_FORMAT:
            raise ScanError(f"{path} is not a scan axis ({SCAN_AXIS_FORMAT!r})")
        try:
            return cls(RasterScan.from_dict(data.get("scan")), data.get("axis"))  # type: ignore[arg-type]
        except ScanError as exc:
            raise ScanError(f"{path}: {exc}") from None


def make_trajectory(
    kind: str,
    *,
    amplitude: float = 10e-6,
    frequency: float = 10.0,
    offset: float | None = None,
    rounding: float = DEFAULT_ROUNDING,
    v_max: float = math.inf,
    a_max: float = math.inf,
) -> Trajectory:
    """``kind``: sine | triangle | steps, the path of a CSV file (t [s], x [m]), or of one
    axis of a raster scan (JSON, :class:`ScanAxis`).
    """
    if kind in {s.value for s in Shape}:
        return PeriodicTrajectory(Shape(kind), amplitude, frequency, offset, rounding, v_max, a_max)
    if kind.endswith(".json"):
        return ScanAxis.read(kind)
    if kind.endswith(".csv") or Path(kind).is_file():
        return CsvTrajectory.read(kind, v_max=v_max, a_max=a_max)
    raise TrajectoryError(
        f"unknown trajectory {kind!r}: expected sine, triangle, steps, a .csv file or a "
        "scan axis's .json file"
    )
