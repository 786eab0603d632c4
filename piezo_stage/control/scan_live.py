"""A raster scan's image as its samples arrive: the record of a running scan (each axis's
loop samples) placed as :func:`~.scan_image.scan_image` places a frame, line by line, each
line overwriting the previous frame's (as an instrument's display does).

The scan's time origin is not in the samples: a stage's loop starts every axis from one
sample's stamp and steps each from its first sample at or after it
(:mod:`piezo_stage.nodes.stage_loop`), so it is the stamp of a recorded sample at or before
the first stepped one (:func:`scan_origin`), the one from which every recorded set point is the
scan's.
"""

from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from .scan import RasterScan, ScanAxis, ScanError
from .scan_image import Sample

__all__ = ["ORIGIN_TOLERANCE", "ScanAccumulator", "origin_error", "scan_origin"]

#: [m] largest difference between a recorded set point and the scan at the origin found
ORIGIN_TOLERANCE = 1e-9
#: [ns] how far before the first stepped sample the origin is looked for
ORIGIN_SEARCH_NS = 50_000_000

#: an axis's record: ``stamp`` [ns] and ``reference`` [m] arrays (NaN: not stepped)
Columns = Mapping[str, NDArray[Any]]


def origin_error(scan: RasterScan, columns: Sequence[Columns], t0: int) -> float:
    """[m] the largest difference between an axis's recorded set points (axis i of
    ``columns``: the scan's axis i) and the scan from ``t0`` [ns], its time computed as a
    controller computes it (stamp·1e-9 − t0·1e-9).
    """
    worst = 0.0
    for index, column in enumerate(columns):
        stepped = np.isfinite(column["reference"])
        if not stepped.any():
            continue
        t = column["stamp"][stepped] * 1e-9 - t0 * 1e-9
        error = np.abs(ScanAxis(scan, index).evaluate(t)[0] - column["reference"][stepped])
        worst = max(worst, float(error.max()))
    return worst


def scan_origin(scan: RasterScan, columns: Sequence[Columns]) -> int:
    """[ns] the scan's time origin in a record that holds its start (module docstring):
    the latest recorded stamp at or before the first stepped sample (within 50 ms) from which
    both axes' set points are the scan's; :class:`~.scan.ScanError` when none is.
    """
    stepped = [np.isfinite(c["reference"]) for c in columns]
    if not all(s.any() for s in stepped):
        raise ScanError("the record holds no stepped sample of one of the axes")
    first = min(int(c["stamp"][s][0]) for c, s in zip(columns, stepped))
    stamps = np.unique(np.concatenate([c["stamp"] for c in columns]))
    candidates = stamps[(stamps <= first) & (stamps >= first - ORIGIN_SEARCH_NS)][::-1]
    errors = []
    for t0 in candidates:
        errors.append(origin_error(scan, columns, int(t0)))
        if errors[-1] <= ORIGIN_TOLERANCE:
            return int(t0)
    raise ScanError(
        "the recorded set points do not follow the scan from any sample of the loop's first "
        f"cycle (off by {min(errors) * 1e9:.3g} nm at best): the record missed the start"
    )


class ScanAccumulator:
    """The image of ``scan`` of ``sample`` as samples arrive (:meth:`add`): per pixel the mean
    height at the measured positions of the samples whose desired position is in it; a line
    restarts when it is scanned again in a later frame. Per line and axis the RMS error of its
    last scan (:meth:`line_rms`).
    """

    def __init__(self, scan: RasterScan, sample: Sample) -> None:
        self.scan, self.sample = scan, sample
        shape = (scan.lines, scan.pixels)
        self._sum, self._count = np.zeros(shape), np.zeros(shape, dtype=np.int64)
        self._sq, self._n = np.zeros((scan.lines, 2)), np.zeros(scan.lines, dtype=np.int64)
        self._frame = np.full(scan.lines, -1, dtype=np.int64)  # the frame each line holds
        self.last_line = -1  # the last line a sample went to (-1: none yet)
        self.samples = 0

    def add(self, t: NDArray[np.float64], measured: NDArray[np.float64]) -> None:
        """Samples at scan times ``t`` [s] (from the origin) with ``measured`` (2, N) positions
        [m], fast and slow axis; NaN positions are left out.
        """
        scan = self.scan
        t = np.asarray(t, dtype=float)
        pos = np.asarray(measured, dtype=float)
        line, _ = scan.line_index(t)
        (xd, _, _), (yd, _, _) = scan.evaluate(t)
        col = scan.pixel_of(xd)
        use = (line >= 0) & np.all(np.isfinite(pos), axis=0)
        if not use.any():
            return
        frame = np.floor(t / scan.frame_time).astype(np.int64)
        for k, f in {(int(a), int(b)) for a, b in zip(line[use], frame[use])}:
            if f > self._frame[k]:  # line k scanned anew: its last frame's values go
                self._sum[k], self._count[k], self._sq[k], self._n[k] = 0.0, 0, 0.0, 0
                self._frame[k] = f
        fresh = use & (frame >= self._frame[np.maximum(line, 0)])
        err = pos[:, fresh] - np.vstack([xd[fresh], yd[fresh]])
        np.add.at(self._sq, line[fresh], err.T**2)
        np.add.at(self._n, line[fresh], 1)
        pix = fresh & (col >= 0)
        heights = self.sample.height(pos[0, pix], pos[1, pix])
        np.add.at(self._sum, (line[pix], col[pix]), heights)
        np.add.at(self._count, (line[pix], col[pix]), 1)
        self.last_line = int(line[fresh][-1]) if fresh.any() else self.last_line
        self.samples += int(fresh.sum())

    def image(self) -> NDArray[np.float64]:
        """(lines, pixels) heights [m]; NaN where no sample has been."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self._count > 0, self._sum / np.maximum(self._count, 1), math.nan)

    def line_rms(self) -> NDArray[np.float64]:
        """(lines, 2) RMS error of each line's last scan per axis [m] (NaN: not scanned)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self._n[:, None] > 0, np.sqrt(self._sq / self._n[:, None]), math.nan)
