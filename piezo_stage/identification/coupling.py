"""The static coupling of a multi-axis stage from runs that excite one axis at a time.

With y = y0 + C (y* - y0) (docs/design.md section 10) and every axis but j held, each held
axis's own displacement y*_k is constant, so axis j's measured displacement is y*_j plus a
constant and every other axis i reads

    y_i = a_ij + C[i][j] y_j

a straight line in axis j's measured displacement: C[i][j] is its slope, estimated by ordinary
least squares with its standard error (the sensor noise is white; the noise on y_j biases the
slope by var(noise) / var(y_j), 1e-6 at a noise of 1e-3 of the span). No rclpy.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .errors import InputDataError, NonFiniteDataError, TooFewSamplesError

__all__ = ["CouplingEstimate", "MIN_SAMPLES", "coupling_slope", "identify_coupling"]

#: fewer samples than this in a run cannot give a slope and its standard error
MIN_SAMPLES = 10


@dataclass(frozen=True)
class CouplingEstimate:
    """C (ones on the diagonal) and the standard error of each off-diagonal entry (0 on the
    diagonal), rows and columns in the order of ``names``.
    """

    names: tuple[str, ...]
    coupling: NDArray[np.float64]
    standard_errors: NDArray[np.float64]


def coupling_slope(driven: NDArray[np.float64], seen: NDArray[np.float64]) -> tuple[float, float]:
    """(slope, standard error) of ``seen = a + slope * driven`` by least squares.

    Standard error: sqrt(s^2 / sum (x - mean x)^2), s^2 the residual variance with n - 2
    degrees of freedom.
    """
    x = np.asarray(driven, dtype=float)
    y = np.asarray(seen, dtype=float)
    if x.shape != y.shape or x.ndim != 1:
        raise InputDataError(f"driven and seen must be 1-D of one length, got {x.shape}, {y.shape}")
    if x.size < MIN_SAMPLES:
        raise TooFewSamplesError(f"{x.size} samples; the coupling needs at least {MIN_SAMPLES}")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
        raise NonFiniteDataError("NaN or inf in the displacements")
    dx = x - x.mean()
    sxx = float(dx @ dx)
    if not sxx > 0.0:
        raise InputDataError("the driven axis did not move: no coupling can be seen")
    slope = float(dx @ (y - y.mean())) / sxx
    residual = y - y.mean() - slope * dx
    s2 = float(residual @ residual) / (x.size - 2)
    return slope, math.sqrt(s2 / sxx)


def identify_coupling(
    names: Sequence[str], runs: Mapping[str, NDArray[np.float64]]
) -> CouplingEstimate:
    """C from one run per driven axis: ``runs[j]`` is an (samples x axes) array of the measured
    displacements, columns in the order of ``names``, while axis j moved and the others held.
    Raises an :class:`~.errors.InputDataError` naming the run that cannot be used.
    """
    names = tuple(names)
    n = len(names)
    missing = [name for name in names if name not in runs]
    if missing:
        raise InputDataError(f"no run drives axis/axes {missing}; each axis needs its own run")
    coupling = np.eye(n)
    errors = np.zeros((n, n))
    for j, name in enumerate(names):
        data = np.asarray(runs[name], dtype=float)
        if data.ndim != 2 or data.shape[1] != n:
            raise InputDataError(
                f"run driving {name}: expected samples x {n} axes, got shape {data.shape}"
            )
        for i in range(n):
            if i == j:
                continue
            try:
                coupling[i, j], errors[i, j] = coupling_slope(data[:, j], data[:, i])
            except InputDataError as exc:
                raise type(exc)(f"run driving {name}: {exc}") from None
    return CouplingEstimate(names, coupling, errors)
