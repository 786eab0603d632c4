"""Noise level and robust values/derivatives on a branch parametrised by the input.

The Table 10.2 expressions need dθ/dx and θ at a few design points. Raw sample differences (as
in 9.39) amplify noise; instead a polynomial is fitted by least squares to the samples around
the point (a Savitzky-Golay filter on the branch parametrised by the input, with non-uniform
spacing allowed), and the window is widened only as far as the noise requires.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

#: 1.4826 * MAD = std for Gaussian noise; the third difference of white noise has variance 20 σ²
_MAD_TO_STD = 1.482602218505602
_D3_VARIANCE = 20.0


def noise_std(y: NDArray[np.float64]) -> float:
    """Standard deviation of the white noise on a smooth sampled signal.

    Estimated from the third differences (a smooth signal contributes ~h³·y''', negligible;
    corners only touch a few of them, which the median ignores).
    """
    y = np.asarray(y, dtype=float)
    if len(y) < 8:
        return 0.0
    d3 = np.diff(y, 3)
    mad = np.median(np.abs(d3 - np.median(d3)))
    return float(_MAD_TO_STD * mad / np.sqrt(_D3_VARIANCE))


@dataclass(frozen=True)
class LocalFit:
    """Value and slope at ``x0`` of a local polynomial fit, with their standard deviations
    under white noise of the given level.
    """

    x0: float
    value: float
    slope: float
    value_std: float
    slope_std: float
    samples: int
    half_width: float


def _window(x: NDArray[np.float64], x0: float, m: int) -> slice:
    """Contiguous index window of ``m`` samples of the sorted ``x`` centred on ``x0``
    (one-sided near the ends).
    """
    c = int(np.searchsorted(x, x0))
    lo = max(0, c - m // 2)
    hi = min(len(x), lo + m)
    lo = max(0, hi - m)
    return slice(lo, hi)


def local_fit(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    x0: float,
    m: int,
    *,
    degree: int = 3,
    noise: float = 0.0,
) -> LocalFit:
    """Least-squares polynomial of ``degree`` through the ``m`` samples of sorted ``x`` nearest
    ``x0``; returns its value and slope at ``x0``.
    """
    w = _window(x, x0, m)
    xs, ys = x[w], y[w]
    half = float(max(xs[-1] - x0, x0 - xs[0], np.finfo(float).tiny))
    u = (xs - x0) / half
    deg = max(1, min(degree, len(xs) - 1))
    A = np.vander(u, deg + 1, increasing=True)
    coef, *_ = np.linalg.lstsq(A, ys, rcond=None)
    # covariance of (c0, c1) for unit noise: (AᵀA)⁻¹ via the pseudo-inverse
    cov = np.linalg.pinv(A.T @ A)
    return LocalFit(
        x0=float(x0),
        value=float(coef[0]),
        slope=float(coef[1] / half),
        value_std=float(noise * np.sqrt(cov[0, 0])),
        slope_std=float(noise * np.sqrt(cov[1, 1]) / half),
        samples=len(xs),
        half_width=half,
    )


def adaptive_fit(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    x0: float,
    *,
    noise: float,
    slope_scale: float,
    rel_tol: float = 2e-4,
    degree: int = 3,
    min_samples: int = 8,
    max_fraction: float = 0.1,
) -> LocalFit:
    """:func:`local_fit` with the narrowest window whose slope standard deviation is below
    ``rel_tol * slope_scale`` (noise-free data keep the narrowest window, which keeps the bias
    of a non-analytic point such as x*, where θ is only C^n, small).

    The window never exceeds ``max_fraction`` of the branch samples (but at least
    ``min_samples``).
    """
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    m_max = max(min_samples, int(max_fraction * len(x)))
    m = min_samples
    fit = local_fit(x, y, x0, m, degree=degree, noise=noise)
    while fit.slope_std > rel_tol * abs(slope_scale) and m < m_max:
        m = min(m_max, int(np.ceil(m * 1.3)))
        fit = local_fit(x, y, x0, m, degree=degree, noise=noise)
    return fit


def local_root(
    x: NDArray[np.float64],
    y: NDArray[np.float64],
    x_start: float,
    *,
    noise: float,
    slope_scale: float,
    rel_tol: float = 2e-4,
    degree: int = 3,
    iterations: int = 4,
) -> LocalFit:
    """Zero of the smoothed ``y(x)`` near ``x_start`` (Newton steps on local fits, 9.38-9.39's
    'linear interpolation' made robust); the returned fit is centred on the zero.
    """
    x0 = float(x_start)
    tol = 1e-12 * (x[-1] - x[0])
    for _ in range(iterations + 1):
        fit = adaptive_fit(
            x, y, x0, noise=noise, slope_scale=slope_scale, rel_tol=rel_tol, degree=degree
        )
        if fit.slope == 0.0:
            break
        x_new = float(np.clip(x0 - fit.value / fit.slope, x[0], x[-1]))
        if abs(x_new - x0) <= tol:
            break
        x0 = x_new
    return fit
