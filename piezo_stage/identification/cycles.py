"""Steady-state limit cycle extraction from a recorded run (Steps 1-2 of 9.1.3, §10.3.2).

Theorem 2 says the output of a T-wave excited Bouc-Wen system converges to a limit cycle.
On real data that cycle has to be found: estimate the period from the input's upward
mid-level crossings, cut the run into whole periods on a common phase grid, check that the
trailing periods agree with the last one (steady state), and average those within the noise
level of it (no transient bias). The averaged cycle starts at the input minimum, so its first
part is the loading branch of v.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import cast

import numpy as np
from numpy.typing import NDArray

from .derivatives import noise_std
from .errors import (
    IdentificationError,
    NonMonotoneBranchError,
    NoSteadyStateError,
    NotPeriodicError,
    TooFewSamplesError,
)
from .filtering import THESIS_BANDWIDTH_RATIO, THESIS_ZETA, zero_phase_periodic
from .recording import Recording, check_recording


@dataclass(frozen=True)
class CycleOptions:
    """Knobs of the extraction (defaults suit simulated and lab data alike)."""

    min_steady_periods: int = 2  #: periods that must agree to call it steady
    steady_periods: int | None = None  #: use exactly this many trailing periods (no detection)
    noise_factor: float = 3.0  #: periods agree if RMS difference ≤ factor·√2·noise ...
    steady_tolerance: float = 1e-5  #: ... + this fraction of the output span
    period_tolerance: float = 0.01  #: max relative deviation of one period from the mean
    input_tolerance: float = 0.01  #: input periods must agree to this fraction of span
    clip_fraction: float = 0.02  #: see recording.check_recording
    min_branch_samples: int = 40  #: samples per branch of one period
    data_filter: bool = False  #: apply the §10.3.2 filter (zero phase) to the cycle
    filter_ratio: float = THESIS_BANDWIDTH_RATIO
    filter_zeta: float = THESIS_ZETA


@dataclass(frozen=True)
class SteadyCycle:
    """One period of the steady state, averaged over ``periods`` periods, uniformly sampled
    from ``start_time`` (at the input minimum): ``input[j]``, ``output[j]`` at
    ``start_time + j * period / len(input)``.
    """

    period: float
    input: NDArray[np.float64]
    output: NDArray[np.float64]
    start_time: float
    periods: int
    raw_samples: int
    noise_input: float  #: white-noise std on the averaged input
    noise_output: float  #: white-noise std on the averaged output
    i_max: int  #: index of the input maximum (end of the v-loading branch)
    period_rms: tuple[float, ...] = ()  #: robust spread of each period's output minus the last
    name: str = ""
    meta: dict[str, object] = field(default_factory=dict, compare=False)

    @property
    def t(self) -> NDArray[np.float64]:
        """Phase times [s] of the samples, from 0."""
        # (numpy's stubs give floating[Any] for an integer array times a float: float64 here)
        m = len(self.input)
        return cast(NDArray[np.float64], np.arange(m) * (self.period / m))

    @property
    def input_span(self) -> float:
        """Peak-to-peak range of the cycle's input."""
        return float(np.ptp(self.input))

    @property
    def output_span(self) -> float:
        """Peak-to-peak range of the cycle's output."""
        return float(np.ptp(self.output))


def upward_crossings(t: NDArray[np.float64], x: NDArray[np.float64]) -> NDArray[np.float64]:
    """Times at which ``x`` rises through its mid level, with a Schmitt trigger of ±¼ span
    against noise; each time comes from a line fitted to the samples inside the band.
    """
    lo, hi = np.percentile(x, [1.0, 99.0])
    mid, band = 0.5 * (lo + hi), 0.25 * (hi - lo)
    if band <= 0:
        return np.empty(0)
    state = np.where(x > mid + band, 1, np.where(x < mid - band, -1, 0))
    idx = np.flatnonzero(state)
    if len(idx) < 2:
        return np.empty(0)
    s = state[idx]
    ups = np.flatnonzero((s[:-1] == -1) & (s[1:] == 1))
    times = []
    for k in ups:
        a, b = idx[k], idx[k + 1] + 1  # last 'low' sample .. first 'high' sample
        ts, xs = t[a:b], x[a:b]
        slope, icpt = np.polyfit(ts - ts[0], xs, 1)
        if slope <= 0:
            continue
        times.append(ts[0] + (mid - icpt) / slope)
    return np.asarray(times)


def estimate_period(
    rec: Recording, options: CycleOptions = CycleOptions()
) -> tuple[float, NDArray[np.float64]]:
    """Period T of the input and the upward crossing times that delimit whole periods.

    With ``steady_periods`` = K only the last K + 1 crossings count: the periods before the ones
    used (the settling ones) may be disturbed without spoiling the run (a host that stalled
    the amplifier's playout for a few tens of ms while the previous run was identified).
    """
    crossings = upward_crossings(rec.t, rec.input)
    if options.steady_periods is not None and len(crossings) > options.steady_periods + 1:
        crossings = crossings[-(options.steady_periods + 1) :]
    if len(crossings) < 2:
        raise NotPeriodicError(
            f"{rec.label}: the input does not repeat (found {len(crossings)} rising mid-level "
            "crossing(s)); a T-wave periodic excitation over at least two periods is needed"
        )
    intervals = np.diff(crossings)
    period = float((crossings[-1] - crossings[0]) / len(intervals))
    worst = float(np.max(np.abs(intervals - period)) / period)
    if worst > options.period_tolerance:
        raise NotPeriodicError(
            f"{rec.label}: successive input periods differ by up to {100 * worst:.2g} % "
            f"(tolerance {100 * options.period_tolerance:.2g} %): the input is not periodic"
        )
    return period, crossings


def _period_grid(
    rec: Recording, period: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Interpolate every whole period onto a common grid of M = round(T/dt) phases, from the
    first sample on. When T is within 2 % of a sample of a whole number of sampling intervals
    it is taken as exactly that, so the grid falls on the samples (no interpolation error).
    """
    dt = float(np.median(np.diff(rec.t)))
    m = int(round(period / dt))
    if abs(period / dt - m) < 0.02 and np.allclose(np.diff(rec.t), dt, rtol=1e-6, atol=0.0):
        period = m * dt
    t0 = float(rec.t[0])
    n_periods = int(np.floor((rec.t[-1] - t0) / period + 1e-9))
    if n_periods < 1:
        raise NoSteadyStateError(f"{rec.label}: not a single whole period recorded")
    grid = t0 + np.arange(n_periods)[:, None] * period + np.arange(m)[None, :] * (period / m)
    X = np.interp(grid, rec.t, rec.input)
    Y = np.interp(grid, rec.t, rec.output)
    return X, Y, period


_MAD_SCALE = 1.482602218505602
#: relative difference between periods that is rounding, not transient
_ROUNDOFF = 1e-12


def _steady_count(
    rec: Recording, X: NDArray[np.float64], Y: NDArray[np.float64], options: CycleOptions
) -> tuple[int, tuple[float, ...]]:
    """Number of trailing periods to average: those within the noise level of the last one
    (the limit cycle is reached when ``min_steady_periods`` agree within the tolerances).
    """
    n_periods = X.shape[0]
    # robust spread (1.4826·median|d|, the std for Gaussian noise): a transient or drift moves
    # every sample, while interpolating across a turning point between samples only spoils one
    rms_y = _MAD_SCALE * np.median(np.abs(Y - Y[-1]), axis=1)
    rms_x = _MAD_SCALE * np.median(np.abs(X - X[-1]), axis=1)
    noise_y, noise_x = noise_std(rec.output), noise_std(rec.input)
    span_y, span_x = float(np.ptp(Y[-1])), float(np.ptp(X[-1]))
    tol_y = options.noise_factor * np.sqrt(2.0) * noise_y + options.steady_tolerance * span_y
    tol_x = options.noise_factor * np.sqrt(2.0) * noise_x + options.input_tolerance * span_x
    if options.steady_periods is not None:
        count = options.steady_periods
        if not 1 <= count <= n_periods:
            raise NoSteadyStateError(
                f"{rec.label}: {count} steady periods requested but only {n_periods} recorded"
            )
    else:
        # average only the periods that differ from the last by no more than the noise: a
        # settling period within the span tolerance still carries its transient (bias)
        # (white noise from the third differences of the last two periods' difference:
        # smooth signal and transient cancel there)
        noise_d = noise_std(Y[-1] - Y[-2]) / np.sqrt(2.0) if n_periods > 1 else noise_y
        tol_avg = options.noise_factor * np.sqrt(2.0) * min(noise_y, noise_d) + _ROUNDOFF * span_y
        count = 1
        while count < n_periods and rms_y[-1 - count] <= tol_avg and rms_x[-1 - count] <= tol_x:
            count += 1
        agree = 1
        while agree < n_periods and rms_y[-1 - agree] <= tol_y and rms_x[-1 - agree] <= tol_x:
            agree += 1
    used = slice(n_periods - count, n_periods)
    if np.any(rms_x[used] > tol_x):
        worst = float(np.max(rms_x[used]) / span_x)
        raise NotPeriodicError(
            f"{rec.label}: input periods differ by {100 * worst:.2g} % of the span: the "
            "excitation is not periodic"
        )
    if options.steady_periods is None and agree < options.min_steady_periods:
        if n_periods < options.min_steady_periods:
            raise NoSteadyStateError(
                f"{rec.label}: {n_periods} whole period(s) recorded; at least "
                f"{options.min_steady_periods} are needed to verify the steady state (Theorem 2)"
            )
        raise NoSteadyStateError(
            f"{rec.label}: the last two periods differ by {rms_y[-2] / span_y:.3g} of the "
            f"output span, tolerance {tol_y / span_y:.3g}: the limit cycle is not reached "
            "(record more periods, or the system drifts)"
        )
    return count, tuple(float(r) for r in rms_y)


def extract_cycle(rec: Recording, options: CycleOptions = CycleOptions()) -> SteadyCycle:
    """The averaged steady-state cycle of a run, starting at its input minimum."""
    check_recording(rec, clip_fraction=options.clip_fraction)
    period, _ = estimate_period(rec, options)
    X, Y, period = _period_grid(rec, period)
    t0 = float(rec.t[0])
    count, period_rms = _steady_count(rec, X, Y, options)
    v = X[-count:].mean(axis=0)
    y = Y[-count:].mean(axis=0)
    # white-noise levels before the filter: filtered noise is coloured and its third
    # differences would understate it (the fits' windows must still average it out)
    noise_input, noise_output = noise_std(v), noise_std(y)
    if options.data_filter:
        v = zero_phase_periodic(v, ratio=options.filter_ratio, zeta=options.filter_zeta)
        y = zero_phase_periodic(y, ratio=options.filter_ratio, zeta=options.filter_zeta)
    m = len(v)
    i_min = extreme_index(v, -1)
    v, y = np.roll(v, -i_min), np.roll(y, -i_min)
    i_max = extreme_index(v, 1)
    half = 0.5 * period / m
    raw_samples = int(
        np.count_nonzero(
            (rec.t >= t0 + (X.shape[0] - count) * period - half)
            & (rec.t < t0 + X.shape[0] * period - half)
        )
    )
    cycle = SteadyCycle(
        period=period,
        input=v,
        output=y,
        start_time=t0 + (X.shape[0] - count) * period + i_min * period / m,
        periods=count,
        raw_samples=raw_samples,
        noise_input=noise_input,
        noise_output=noise_output,
        i_max=i_max,
        period_rms=period_rms,
        name=rec.label,
    )
    for label, n in (("loading", i_max + 1), ("unloading", m - i_max + 1)):
        if n < options.min_branch_samples:
            raise TooFewSamplesError(
                f"{rec.label}: the {label} branch holds {n} samples per period; at least "
                f"{options.min_branch_samples} are needed (sample faster or slow the excitation)"
            )
    return cycle


def extreme_index(v: NDArray[np.float64], sign: int) -> int:
    """Index of the cycle's maximum (sign=1) or minimum (-1): located on a smoothed copy
    (robust to noise), then on the samples within that smoothing width (a moving average
    shifts the peak of an asymmetric T-wave).
    """
    i = int(np.argmax(sign * _rough_smooth(v)))
    k = max(1, len(v) // 100)
    idx = np.arange(i - k, i + k + 1) % len(v)
    return int(idx[np.argmax(sign * v[idx])])


def _rough_smooth(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Circular moving average over ~1 % of the period, only to locate the extremes robustly."""
    k = max(1, len(v) // 100) | 1
    if k == 1:
        return v
    pad = np.concatenate((v[-(k // 2) :], v, v[: k // 2]))
    return np.convolve(pad, np.ones(k) / k, mode="valid")


# ----------------------------------------------------------------------------- branches


@dataclass(frozen=True)
class Branch:
    """A branch of the cycle in the model's input x = input_sign·v, sorted by increasing x.
    ``loading`` means x increases with time (9.16-9.17).
    """

    x: NDArray[np.float64]
    v: NDArray[np.float64]
    y: NDArray[np.float64]
    loading: bool

    @property
    def span(self) -> float:
        """Extent of the branch in x."""
        return float(self.x[-1] - self.x[0])


def smooth_input(cycle: SteadyCycle) -> NDArray[np.float64]:
    """The cycle's input with measurement noise removed branch by branch (cubic
    Savitzky-Golay in time: exact on triangles; untouched when the input is noise-free),
    checked to be monotone on each branch (a T-wave, 9.1.1): a noisy one away from its
    turning points' uncertainty.
    """
    v = cycle.input.copy()
    m, i_max = len(v), cycle.i_max
    span = cycle.input_span
    noisy = cycle.noise_input > 1e-9 * span
    if noisy:
        from scipy.signal import savgol_filter  # lazy: scipy.signal costs seconds to import

        for seg in (slice(0, i_max + 1), slice(i_max, m)):
            n = seg.stop - seg.start
            window = min(n - (1 - n % 2), max(7, (n // 10) | 1))
            if window > 4:
                v[seg] = savgol_filter(cycle.input[seg], window, 3, mode="interp")
    tol = 5.0 * cycle.noise_input + 1e-9 * span
    rising = v[: i_max + 1]
    falling = np.concatenate((v[i_max:], v[:1]))
    # a noisy input's turning points are known to within the extremes' search (1 % of the
    # period, :func:`extreme_index`): a reversal that close to a branch's end is the split's
    # (the fit's end bends to a sample of the other side), not the excitation's
    k = max(1, m // 100) if noisy else 0
    if min(rising.size, falling.size) > 2 * k + 2:
        rising, falling = rising[k : rising.size - k], falling[k : falling.size - k]
    dip = float(np.max(np.maximum.accumulate(rising) - rising))
    bump = float(np.max(falling - np.minimum.accumulate(falling)))
    if max(dip, bump) > tol:
        raise NonMonotoneBranchError(
            f"{cycle.name or 'cycle'}: the input reverses by {max(dip, bump) / span:.3g} of its "
            f"span inside a {'loading' if dip >= bump else 'unloading'} branch: not a T-wave "
            "(one rise and one fall per period) - minor loops cannot be identified by this method"
        )
    return v


def split_branches(
    cycle: SteadyCycle, input_sign: int, v_smooth: NDArray[np.float64] | None = None
) -> tuple[Branch, Branch]:
    """Loading and unloading branches in x = input_sign·v, each sorted by increasing x."""
    v = smooth_input(cycle) if v_smooth is None else v_smooth
    y = cycle.output
    i_max = cycle.i_max
    up = (v[: i_max + 1], y[: i_max + 1])  # v increasing
    down = (np.concatenate((v[i_max:], v[:1]))[::-1], np.concatenate((y[i_max:], y[:1]))[::-1])
    if input_sign not in (1, -1):
        raise IdentificationError(f"input_sign must be +1 or -1, got {input_sign!r}")
    load_v, unload_v = (up, down) if input_sign == 1 else (down, up)
    branches = []
    for (bv, by), loading in ((load_v, True), (unload_v, False)):
        x = input_sign * bv
        order = np.argsort(x, kind="stable")
        branches.append(Branch(x=x[order], v=bv[order], y=by[order], loading=loading))
    return branches[0], branches[1]
