"""The image a raster scan makes of a sample, and what it costs in errors and distortion.

As an instrument does, each loop sample reads the sample's height at the stage's *measured*
position and is placed at the pixel of its *desired* position (:class:`~.scan.RasterScan`'s
rows and columns); a pixel is the mean of its samples. The ideal image is the height at the
pixel centres. Figures (:func:`scan_figures`): per axis the RMS and largest error over the image
windows (turnarounds and fly-back excluded), and the distortion: where in the image (desired
coordinates) the stage crosses each edge of the sample, against where the edge is, in pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .scan import RasterScan, ScanError

__all__ = [
    "Grating",
    "HeightMap",
    "Sample",
    "ScanFigures",
    "ScanImage",
    "detector_samples",
    "load_sample",
    "scan_figures",
    "scan_image",
]


#: pitches of the default grating across the fast axis's range
GRATING_PITCHES = 8


class Sample(Protocol):
    """A surface to scan: its height at positions [m], and where its edges are."""

    def height(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """Height [m] at positions x, y [m] (vectorised)."""
        ...

    def edges(self, axis: int, lo: float, hi: float) -> NDArray[np.float64]:
        """Positions [m] in [lo, hi] along ``axis`` (0 fast, 1 slow) where the height steps."""
        ...


@dataclass(frozen=True)
class Grating:
    """A calibration grating: square pits of side ``duty``·``pitch`` and depth ``depth`` on a
    square lattice of ``pitch`` [m], a pit's corner at ``origin``.
    """

    pitch: float = 2e-6
    depth: float = 100e-9
    duty: float = 0.5
    origin: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.pitch) and self.pitch > 0):
            raise ScanError(f"grating pitch must be > 0, got {self.pitch}")
        if not (math.isfinite(self.depth) and self.depth > 0):
            raise ScanError(f"grating depth must be > 0, got {self.depth}")
        if not 0.0 < self.duty < 1.0:
            raise ScanError(f"grating duty must be in (0, 1), got {self.duty}")

    def height(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """−depth inside a pit, 0 on the plateau."""
        side = self.duty * self.pitch
        px = np.mod(np.asarray(x) - self.origin[0], self.pitch) < side
        py = np.mod(np.asarray(y) - self.origin[1], self.pitch) < side
        return np.where(px & py, -self.depth, 0.0)

    def edges(self, axis: int, lo: float, hi: float) -> NDArray[np.float64]:
        """Both walls of every pit between ``lo`` and ``hi``."""
        o = self.origin[axis]
        first = math.floor((lo - o) / self.pitch) - 1
        cells = o + self.pitch * np.arange(first, first + (hi - lo) / self.pitch + 3)
        walls = np.sort(np.concatenate([cells, cells + self.duty * self.pitch]))
        return walls[(walls >= lo) & (walls <= hi)]


@dataclass(frozen=True)
class HeightMap:
    """Heights on a grid (rows along the slow axis), stretched over ``extent`` (x0, x1, y0,
    y1) [m]; read by nearest pixel. Edges: where a grid row or column steps by more than half
    the map's height range (a map of smooth relief has none, and no distortion figure).
    """

    heights: NDArray[np.float64]
    extent: tuple[float, float, float, float]

    def _index(self, v: NDArray[np.float64], axis: int) -> NDArray[np.intp]:
        n = self.heights.shape[1 - axis]
        lo, hi = self.extent[2 * axis], self.extent[2 * axis + 1]
        index: NDArray[np.intp] = np.clip(np.floor((v - lo) / (hi - lo) * n), 0, n - 1).astype(
            np.intp
        )
        return index

    def height(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """The height of the grid cell holding (x, y); the border cell outside the map."""
        return self.heights[self._index(np.asarray(y), 1), self._index(np.asarray(x), 0)]

    def edges(self, axis: int, lo: float, hi: float) -> NDArray[np.float64]:
        """Cell borders where the height steps by more than half its range somewhere."""
        h = self.heights if axis == 0 else self.heights.T
        span = float(np.ptp(h)) or 1.0
        steps = np.flatnonzero(np.any(np.abs(np.diff(h, axis=1)) > 0.5 * span, axis=0)) + 1
        a, b = self.extent[2 * axis], self.extent[2 * axis + 1]
        walls: NDArray[np.float64] = a + steps * (b - a) / h.shape[1]
        return walls[(walls >= lo) & (walls <= hi)]


def load_sample(source: str, scan: RasterScan) -> Sample:
    """``grating``: pits 100 nm deep, eight pitches across the fast axis's range, a pit's
    corner on the image's (its walls fall on pixel borders when the pixels per line are a
    multiple of 16); or a PNG (grey levels, 1 = 100 nm) or CSV (heights in m, rows along the
    slow axis) file stretched over the scan's image.
    """
    r, c = scan.range, scan.centre
    extent = (c[0] - r[0] / 2, c[0] + r[0] / 2, c[1] - r[1] / 2, c[1] + r[1] / 2)
    if source == "grating":
        return Grating(pitch=r[0] / GRATING_PITCHES, origin=(extent[0], extent[2]))
    path = Path(source)
    try:
        if path.suffix.lower() == ".png":
            import matplotlib.image

            grey = np.asarray(matplotlib.image.imread(path), dtype=float)
            if grey.ndim == 3:
                grey = grey[..., :3].mean(axis=2)
            heights = 100e-9 * grey[::-1]  # an image's first row is its top
        elif path.suffix.lower() == ".csv":
            heights = np.loadtxt(path, delimiter=",", ndmin=2, comments="#")
        else:
            raise ScanError(f"sample {source!r}: expected 'grating', a .png or a .csv file")
    except (OSError, ValueError, SyntaxError) as exc:
        raise ScanError(f"sample {source}: cannot read it ({exc})") from None
    if heights.ndim != 2 or min(heights.shape) < 2 or not np.all(np.isfinite(heights)):
        raise ScanError(f"sample {source}: need a 2-D grid of finite heights, got {heights.shape}")
    return HeightMap(heights, extent)


@dataclass(frozen=True)
class ScanImage:
    """The images of one frame: ``ideal``, ``image`` (the scanned), ``counts`` (samples per
    pixel; a pixel no sample reached is NaN in ``image``), rows along the slow axis.
    """

    ideal: NDArray[np.float64]
    image: NDArray[np.float64]
    counts: NDArray[np.int64]

    @property
    def difference(self) -> NDArray[np.float64]:
        """Image − ideal [m]."""
        return self.image - self.ideal


def scan_image(
    scan: RasterScan,
    sample: Sample,
    t: ArrayLike,
    measured: ArrayLike,
) -> ScanImage:
    """The frame scanned by samples at times ``t`` [s] with ``measured`` positions (2, N)
    [fast, slow] in m: each sample's height at its measured position, in the pixel of its
    desired position (row: its line, column: :meth:`RasterScan.pixel_of` x_d).
    """
    t = np.asarray(t, dtype=float)
    pos = np.asarray(measured, dtype=float)
    (xd, _, _), _ = scan.evaluate(t)
    line, _ = scan.line_index(t)
    col = scan.pixel_of(xd)
    use = (line >= 0) & (col >= 0) & np.all(np.isfinite(pos), axis=0)
    flat = line[use] * scan.pixels + col[use]
    size = scan.lines * scan.pixels
    counts = np.bincount(flat, minlength=size)
    total = np.bincount(flat, weights=sample.height(pos[0, use], pos[1, use]), minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        image = np.where(counts > 0, total / np.maximum(counts, 1), np.nan)
    r, c = scan.range, scan.centre
    xs = c[0] - r[0] / 2 + (np.arange(scan.pixels) + 0.5) * (r[0] / scan.pixels)
    gx, gy = np.meshgrid(xs, scan.row_positions())
    shape = (scan.lines, scan.pixels)
    return ScanImage(sample.height(gx, gy), image.reshape(shape), counts.reshape(shape))


def detector_samples(
    scan: RasterScan, t: ArrayLike, measured: ArrayLike, per_pixel: int = 1
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A detector on a clock of its own, ``per_pixel`` samples a pixel across each image line's
    window of the frame ``t`` covers (times at the sub-pixels' centres), and the stage's
    position (2, N) [m] at each, interpolated linearly between the record's samples ``t``,
    ``measured``: what an instrument sampling faster than its controller's recorder images.
    """
    t = np.asarray(t, dtype=float)
    pos = np.asarray(measured, dtype=float)
    frame = math.floor(float(t[0]) / scan.frame_time + 1e-9) * scan.frame_time
    n = scan.pixels * per_pixel
    offsets = (np.arange(n) + 0.5) * (scan.window / n)
    starts = frame + scan.window_start(np.arange(scan.lines))
    times = (starts[:, None] + offsets[None, :]).ravel()
    times = times[(times >= t[0]) & (times <= t[-1])]
    return times, np.vstack([np.interp(times, t, pos[a]) for a in (0, 1)])


@dataclass(frozen=True)
class ScanFigures:
    """Errors over the image windows per axis [m], and the image's distortion [pixels]."""

    rms_error: tuple[float, float]
    max_error: tuple[float, float]
    line_rms: NDArray[np.float64]  #: (lines, 2) RMS error of each line, per axis
    distortion_px_max: float
    distortion_px_rms: float
    edges: int  #: edge crossings the distortion was measured on


def _crossings(
    desired: NDArray[np.float64], measured: NDArray[np.float64], walls: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Desired − wall at every wall the measured sequence crosses, the desired position
    interpolated between the two samples either side of the crossing.
    """
    out = []
    for wall in walls:
        side = measured - wall
        k = np.flatnonzero(side[:-1] * side[1:] < 0)
        if k.size == 0:
            continue
        frac = side[k] / (side[k] - side[k + 1])
        out.append(desired[k] + frac * (desired[k + 1] - desired[k]) - wall)
    return np.concatenate(out) if out else np.empty(0)


def scan_figures(
    scan: RasterScan, sample: Sample, t: ArrayLike, measured: ArrayLike
) -> ScanFigures:
    """Errors e = measured − desired over the image windows, per axis and per line, and the
    distortion: along each line (fast axis) and down each column (slow axis, a line's mean
    position at that pixel), the desired position at which the measured one crosses each of
    the sample's edges, less the edge's position, in pixels of that axis.
    """
    t = np.asarray(t, dtype=float)
    pos = np.asarray(measured, dtype=float)
    (xd, _, _), (yd, _, _) = scan.evaluate(t)
    desired = np.vstack([xd, yd])
    line, _ = scan.line_index(t)
    inside = line >= 0
    err = pos[:, inside] - desired[:, inside]
    if err.shape[1] == 0:
        raise ScanError("no sample falls in an image window: the record does not cover a line")
    rms_x, rms_y = (float(v) for v in np.sqrt(np.mean(err**2, axis=1)))
    peak_x, peak_y = (float(v) for v in np.abs(err).max(axis=1))
    sums = np.zeros((scan.lines, 2))
    np.add.at(sums, line[inside], err.T**2)
    n = np.bincount(line[inside], minlength=scan.lines)[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        line_rms = np.sqrt(sums / n)
    r, c = scan.range, scan.centre
    lo, hi = [c[a] - r[a] / 2 for a in (0, 1)], [c[a] + r[a] / 2 for a in (0, 1)]
    # along the lines: each line's samples in time order
    fast_walls = sample.edges(0, lo[0], hi[0])
    shifts = [
        _crossings(xd[line == k], pos[0, line == k], fast_walls) / (r[0] / scan.pixels)
        for k in range(scan.lines)
    ]
    # down the columns: each line's mean measured slow position at each pixel
    col = scan.pixel_of(xd)
    use = inside & (col >= 0)
    flat = line[use] * scan.pixels + col[use]
    size = scan.lines * scan.pixels
    count = np.bincount(flat, minlength=size)
    with np.errstate(invalid="ignore", divide="ignore"):
        y_mean = (np.bincount(flat, weights=pos[1, use], minlength=size) / count).reshape(
            scan.lines, scan.pixels
        )
        y_want = (np.bincount(flat, weights=yd[use], minlength=size) / count).reshape(
            scan.lines, scan.pixels
        )
    slow_walls = sample.edges(1, lo[1], hi[1])
    for j in range(scan.pixels):
        ok = np.isfinite(y_mean[:, j])
        shifts.append(_crossings(y_want[ok, j], y_mean[ok, j], slow_walls) / (r[1] / scan.lines))
    d = np.abs(np.concatenate(shifts)) if shifts else np.empty(0)
    return ScanFigures(
        (rms_x, rms_y),
        (peak_x, peak_y),
        line_rms,
        float(d.max()) if d.size else float("nan"),
        float(np.sqrt(np.mean(d**2))) if d.size else float("nan"),
        int(d.size),
    )
