"""How many samples a recording's output lags its input, before any model is fitted.

A class I Bouc-Wen hysteresis is rate-independent and turns when its input turns: with
ẇ = ρ·ẋ·(1 − (σ·sgn(ẋw) + 1 − σ)|w|^n) (8.2) and the output y = Σκ_i x^i + κw·w, the output's
slope is ẏ = (κ'(x) + κw·ρ·(…))·ẋ with a factor that keeps its sign (κ'(x) > 0 over the run and
(…) ≥ 1 − |w|^n ≥ 0), so y has its extrema where x has them. The input of a T-wave run turns
at the triangle's corners: around each, both signals are two straight pieces meeting at a kink
(:func:`kink`), and the output's kink comes ``lag`` samples after the input's. The estimate is
the median over the corners (robust to a corner a stall or a glitch bent).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from .derivatives import noise_std
from .recording import Recording

#: samples each side of a corner in the kink fit, at most a quarter of a branch
KINK_HALF_WIDTH = 6
#: largest lag looked for, as a share of a branch ...
MAX_LAG_SHARE = 0.2
#: ... and in samples: a data recorder's branch holds 10^4 samples, and the fit's cost grows
#: with the square of the window (a lag of 64 samples is 3 ms at 20 kHz: dynamics, not a lag)
MAX_LAG_SAMPLES = 64
#: sub-sample resolution of the kink's location
RESOLUTION = 0.02
#: an input whose white noise exceeds this share of its change per sample has no corners to
#: time (it is measured, not commanded: every few samples its slope changes sign)
NOISY_INPUT = 0.1
#: kink locations fitted together (bounds the batch's memory: ~ batch × samples × 5 floats)
KINK_BATCH = 512


@dataclass(frozen=True)
class LagEstimate:
    """``samples``: the output's lag [samples] (median over ``corners`` corners); ``spread``:
    the corners' median absolute deviation from it [samples]; ``seconds`` with the run's
    sample period.
    """

    samples: float
    spread: float
    corners: int
    seconds: float


def kink(y: NDArray[np.float64], lo: float, hi: float) -> float:
    """The location in [lo, hi] (index units) where two pieces fitted to ``y`` meet with least
    squared error: y ≈ c + s1·m + s2·p + c1·m² + c2·p², m = min(k − τ, 0), p = max(k − τ, 0)
    (the curvature terms take the output's bend after a reversal, which would otherwise pull
    a straight-piece kink late). τ runs over a grid of step ``RESOLUTION``; the least-squares
    fits of all τ are solved together (a QR factorisation per τ, batched), a fit of rank < 5
    (numpy's ``lstsq`` rule) is left out.
    """
    k = np.arange(y.size, dtype=float)
    taus = np.arange(lo, hi + RESOLUTION / 2, RESOLUTION)
    best, best_tau = math.inf, float("nan")
    for start in range(0, taus.size, KINK_BATCH):
        tau = taus[start : start + KINK_BATCH, None]
        d = k[None, :] - tau
        m, p = np.minimum(d, 0.0), np.maximum(d, 0.0)
        a = np.stack([np.ones_like(d), m, p, m * m, p * p], axis=-1)  # (taus, samples, 5)
        q, r = np.linalg.qr(a)
        sv = np.linalg.svd(r, compute_uv=False)  # the singular values of a
        full = sv[:, -1] > sv[:, 0] * np.finfo(float).eps * max(y.size, 5)
        qty = np.einsum("tni,n->ti", q, y)
        coef = np.linalg.solve(np.where(full[:, None, None], r, np.eye(5)), qty[..., None])
        res = np.einsum("tni,ti->tn", a, coef[..., 0]) - y
        err = np.where(full, np.einsum("tn,tn->t", res, res), math.inf)
        i = int(np.argmin(err))
        if err[i] < best:
            best, best_tau = float(err[i]), float(taus[start + i])
    return best_tau


def corners(x: NDArray[np.float64], min_gap: int) -> NDArray[np.int_]:
    """Indices where the input turns (the slope changes sign), at least ``min_gap`` apart."""
    slope = np.sign(np.diff(x))
    nz = np.flatnonzero(slope)
    if nz.size < 2:
        return np.empty(0, dtype=int)
    s = slope[nz]
    turns = nz[1:][s[1:] != s[:-1]]
    out: list[int] = []
    for i in turns:
        if not out or i - out[-1] >= min_gap:
            out.append(int(i))
    return np.asarray(out, dtype=int)


def measured(x: NDArray[np.float64]) -> bool:
    """Whether ``x`` is measured, not commanded: its white noise exceeds
    :data:`NOISY_INPUT` of its change per sample.
    """
    x = np.asarray(x, dtype=float)
    return bool(x.size > 8 and noise_std(x) > NOISY_INPUT * float(np.median(np.abs(np.diff(x)))))


def estimate_lag(rec: Recording) -> LagEstimate | None:
    """The output's lag behind the input (module docstring), or None when the run has no
    corner far enough from its ends to fit (it is no T-wave run) or its input is too noisy to
    time one (:data:`NOISY_INPUT`).
    """
    x, y = np.asarray(rec.input, dtype=float), np.asarray(rec.output, dtype=float)
    if measured(x):
        return None  # a measured input (the ch. 11 form's x): its noise makes the corners
    turns = corners(x, min_gap=8)
    if turns.size < 2:
        return None
    branch = float(np.median(np.diff(turns)))
    half = int(max(3, min(KINK_HALF_WIDTH, branch // 4)))
    reach = max(1.0, min(MAX_LAG_SHARE * branch, MAX_LAG_SAMPLES))
    lags = []
    for i in turns:
        lo, hi = i - half - 1, int(math.ceil(i + half + reach + 1))
        if lo < 0 or hi >= x.size:
            continue
        tx = kink(x[lo : hi + 1], half - 0.5, half + 2.5)  # the input's own corner, sub-sample
        ty = kink(y[lo : hi + 1], half - 0.5, half + 1.5 + reach)
        if math.isfinite(tx) and math.isfinite(ty):
            lags.append(ty - tx)
    if not lags:
        return None
    lag = float(np.median(lags))
    spread = float(np.median(np.abs(np.asarray(lags) - lag)))
    dt = float(np.median(np.diff(rec.t))) if len(rec.t) > 1 else math.nan
    return LagEstimate(lag, spread, len(lags), lag * dt)


#: [samples] a smaller lag is left alone: the analytic method's error from it stays below its
#: noise (the ch. 10 patch at 100 samples per period: 0.25 sample shifts n by ~2 %)
LAG_TOLERANCE = 0.25


def runs_lag(runs: "list[Recording]") -> LagEstimate | None:
    """The lag of a set of runs (all recorded through the same rig): the median of theirs."""
    found = [e for e in (estimate_lag(r) for r in runs) if e is not None]
    if not found:
        return None
    samples = float(np.median([e.samples for e in found]))
    seconds = float(np.median([e.seconds for e in found]))
    spread = float(np.median([e.spread for e in found]))
    return LagEstimate(samples, spread, sum(e.corners for e in found), seconds)


#: [samples] (half-width, step) of the grids around the corners' estimate on which
#: :func:`refine_lag` measures the model's residual: a coarse one, then a fine one around its
#: least value (the residual's growth is not symmetric about the lag: a parabola over a wide
#: step puts its vertex off by a share of the step)
REFINE_GRIDS = ((0.3, 0.1), (0.04, 0.02), (0.01, 0.005))


def refine_lag(lag: LagEstimate, residual: Callable[[float], tuple[float, int]]) -> LagEstimate:
    """The lag that minimises a model's residual, with its standard error.

    ``residual(samples)`` is the sum of squared output errors and their count of the model
    identified on the runs shifted by ``samples``: the corners locate the lag to a few hundredths
    of a sample, but the analytic method moves ~0.5 % per hundredth (the ch. 10 patch at 100
    samples per period). On each grid of ``REFINE_GRIDS`` (extended while the least value is at
    an edge), the parabola through the least mean square S/N and its neighbours gives τ* and
    S/N ≈ σ² + a(τ − τ*)², whence var(τ*) = σ² / (N a), σ² the noise variance (the profile
    likelihood of a Gaussian error). Returned as ``samples`` = τ*, ``spread`` = its standard
    error [samples]; ``lag`` itself when the residual has no minimum to find.
    """
    dt = lag.seconds / lag.samples if lag.samples else math.nan
    seen: dict[float, tuple[float, int]] = {}

    def mean_square(tau: float) -> float:
        key = round(tau, 6)
        if key not in seen:
            seen[key] = residual(key)
        sse, n = seen[key]
        return sse / n if n > 0 else math.inf

    centre, found = lag.samples, None
    for reach, step in REFINE_GRIDS:
        taus = [centre + k * step for k in range(-round(reach / step), round(reach / step) + 1)]
        for _ in range(10):  # the least value at an edge: walk on
            best = min(taus, key=mean_square)
            if best not in (taus[0], taus[-1]):
                break
            taus.append(best - step if best == taus[0] else best + step)
            taus.sort()
        i = taus.index(min(taus, key=mean_square))
        if i in (0, len(taus) - 1):
            return lag
        # per sample: a shift past a whole sample drops one sample from the runs' start
        m0, m1, m2 = (mean_square(t) for t in taus[i - 1 : i + 2])
        a = (m0 - 2.0 * m1 + m2) / (2.0 * step * step)
        if not (a > 0 and math.isfinite(a)):
            return lag
        tau = taus[i] - (m2 - m0) / (4.0 * a * step)
        n = seen[round(taus[i], 6)][1]
        found = (tau, math.sqrt(max(m1 - a * (taus[i] - tau) ** 2, 0.0) / (n * a)))
        centre = tau
    assert found is not None
    return LagEstimate(float(found[0]), float(found[1]), lag.corners, float(found[0] * dt))


def shift_output(rec: Recording, seconds: float) -> Recording:
    """``rec`` with the lag taken off: the input delayed by ``seconds`` (x'(t) = x(t − seconds),
    linearly interpolated: the input is the clean, commanded signal; the noisy output is left
    as measured), the first samples, whose delayed input falls before the start, dropped. So
    the run's last period stays whole (the cycle extraction averages whole periods; the first
    one settles anyway). A :func:`measured` input is left as measured and the output advanced
    instead (y'(t) = y(t + seconds), held past the ends): interpolating noise would smooth it
    below the noise level the branches' checks expect.
    """
    t = np.asarray(rec.t, dtype=float)
    if measured(np.asarray(rec.input, dtype=float)):
        y = np.interp(t + seconds, t, np.asarray(rec.output, dtype=float))
        return Recording(t, np.asarray(rec.input, dtype=float), y, name=rec.name)
    eps = 1e-12 * max(abs(t[0]), abs(t[-1]), 1.0)
    keep = t - seconds >= t[0] - eps if seconds >= 0 else t - seconds <= t[-1] + eps
    x = np.interp(t[keep] - seconds, t, np.asarray(rec.input, dtype=float))
    return Recording(t[keep], x, np.asarray(rec.output, dtype=float)[keep], name=rec.name)


__all__ = [
    "LAG_TOLERANCE",
    "LagEstimate",
    "corners",
    "estimate_lag",
    "kink",
    "measured",
    "refine_lag",
    "runs_lag",
    "shift_output",
]
