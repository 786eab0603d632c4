"""The non-hysteretic polynomial Σ κ_i v^i (§10.2.2) and the offset y0 (10.17).

Two runs v(τ) and v(τ)+q share w̄(τ) (Theorem 2), so their difference is a polynomial of
degree N−1 in v (10.7): Σ_j g_j v^j. The g_j come from least squares on the matched branches,
and K = Q⁻¹·G (10.8-10.11) with Q upper triangular, Q[j, k-1] = C(k, k−j)·q^(k−j) (10.9).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np
from numpy.typing import NDArray

from .cycles import Branch
from .errors import InconsistentRunsError, TooFewSamplesError


def q_matrix(q: float, degree: int) -> NDArray[np.float64]:
    """Q of (10.8)-(10.10): G = Q·K, rows j = 0..N−1, columns κ_1..κ_N."""
    if degree < 1:
        raise ValueError(f"polynomial degree must be >= 1, got {degree}")
    Q = np.zeros((degree, degree))
    for j in range(degree):
        for k in range(j + 1, degree + 1):
            Q[j, k - 1] = comb(k, k - j) * q ** (k - j)
    return Q


def kappa_from_g(g: NDArray[np.float64], q: float) -> NDArray[np.float64]:
    """K = Q⁻¹·G (10.11); Q is invertible for q ≠ 0 (back substitution, upper triangular)."""
    if q == 0.0:
        raise InconsistentRunsError("q = 0: the two runs must differ by a non-zero offset (Step 2)")
    g = np.asarray(g, dtype=float)
    from scipy.linalg import solve_triangular

    return solve_triangular(q_matrix(q, len(g)), g, lower=False)


def polyval(
    kappa: NDArray[np.float64] | tuple[float, ...], v: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Σ_{i=1..N} κ_i v^i (10.4), Horner's scheme."""
    out = np.zeros_like(np.asarray(v, dtype=float))
    for k in reversed(kappa):
        out = (out + k) * v
    return out


@dataclass(frozen=True)
class PolynomialFit:
    """The polynomial part from two runs (:func:`fit_polynomial`, (10.7)-(10.11))."""

    kappa: NDArray[np.float64]  #: κ_1..κ_N
    g: NDArray[np.float64]  #: g_0..g_{N−1} of (10.7)
    q: float  #: offset of run B with respect to run A [input unit]
    residual_rms: float  #: RMS of the difference not explained by Σ g_j v^j
    samples: int


def offset_between(
    a: tuple[Branch, Branch], b: tuple[Branch, Branch], *, span_tolerance: float = 0.02
) -> float:
    """Offset q of run B against run A in v (Step 2), after checking both spans agree."""
    va = np.concatenate((a[0].v, a[1].v))
    vb = np.concatenate((b[0].v, b[1].v))
    span_a, span_b = float(np.ptp(va)), float(np.ptp(vb))
    if abs(span_a - span_b) > span_tolerance * span_a:
        raise InconsistentRunsError(
            f"the runs' input spans differ ({span_a:.6g} vs {span_b:.6g}, "
            f"{100 * abs(span_a - span_b) / span_a:.2g} %): the method needs x(t) and x(t)+q "
            "with the same waveform"
        )
    q = 0.5 * ((vb.max() + vb.min()) - (va.max() + va.min()))
    if abs(q) < 0.01 * span_a:
        raise InconsistentRunsError(
            f"the runs' offsets differ by q = {q:.3g} ({100 * abs(q) / span_a:.2g} % of the span): "
            "q must be clearly non-zero (Step 2; the thesis uses q = span/3 or so)"
        )
    return float(q)


def fit_polynomial(
    a: tuple[Branch, Branch], b: tuple[Branch, Branch], degree: int, q: float
) -> PolynomialFit:
    """Least squares of Φ_B(v+q) − Φ_A(v) = Σ g_j v^j (10.7) on both branches, then (10.11).

    Run B is interpolated at v+q along the same branch (loading with loading, unloading with
    unloading); the regression uses v scaled to [-1, 1] for conditioning.
    """
    vs, ds = [], []
    for ba, bb in zip(a, b):
        target = ba.v + q
        inside = (target >= bb.v.min()) & (target <= bb.v.max())
        order = np.argsort(bb.v, kind="stable")
        vs.append(ba.v[inside])
        ds.append(np.interp(target[inside], bb.v[order], bb.y[order]) - ba.y[inside])
    v = np.concatenate(vs)
    d = np.concatenate(ds)
    if len(v) < 4 * degree + 4:
        raise TooFewSamplesError(
            f"only {len(v)} matched samples between the two runs for a degree-{degree} polynomial"
        )
    scale = float(np.max(np.abs(v)))
    A = np.vander(v / scale, degree, increasing=True)
    g_scaled, *_ = np.linalg.lstsq(A, d, rcond=None)
    g = g_scaled / scale ** np.arange(degree)
    residual = d - A @ g_scaled
    kappa = kappa_from_g(g, q)
    return PolynomialFit(
        kappa=kappa, g=g, q=q, residual_rms=float(np.sqrt(np.mean(residual**2))), samples=len(v)
    )


def offset_y0(branches: list[tuple[Branch, Branch]], kappa: NDArray[np.float64]) -> float:
    """y0 of (10.17), the mean of y − Σ κ_i v^i over the cycle.

    (10.17) integrates over time using ∫ w̄ dτ = 0, which holds for symmetric triangles. What
    Theorem 2 gives for every T-wave is that the loading and unloading w̄ are point symmetric,
    so ∫ w̄_load dx + ∫ w̄_unload dx = 0: y0 is the average of the residual over both branches
    in the input variable (identical to 10.17 for a symmetric triangle), averaged over runs.
    """
    values = []
    for loading, unloading in branches:
        total, span = 0.0, 0.0
        for br in (loading, unloading):
            r = br.y - polyval(kappa, br.v)
            total += float(np.trapezoid(r, br.x))
            span += br.span
        values.append(total / span)
    return float(np.mean(values))
