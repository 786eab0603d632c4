"""Excitation signals as pure functions of time: T-wave triangles (9.1.1), sine, steps, noise.

A T-wave periodic signal (9.1.1) is continuous, T-periodic, increasing on (0, T+) and
decreasing on (T+, T), with X_min = x(0) and X_max = x(T+). The identification uses two of
them, x(t) and x(t) + q (Step 2 of 9.1.3).
"""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

from .errors import InputSignalError

Array: TypeAlias = NDArray[np.float64]

__all__ = ["triangle", "t_wave_pair", "sine", "step", "band_limited_noise", "check_period"]


def check_period(period: float, name: str = "period") -> float:
    """Return ``period`` as float, or raise :class:`InputSignalError` unless finite and > 0."""
    period = float(period)
    if not (np.isfinite(period) and period > 0.0):
        raise InputSignalError(f"{name} must be finite and > 0, got {period!r}")
    return period


def triangle(
    t: Array,
    period: float,
    low: float,
    high: float,
    phase: float = 0.0,
    rise_fraction: float = 0.5,
) -> Array:
    """T-wave triangle (9.1.1): ``low`` at t = 0 (phase 0), rising to ``high`` at
    T+ = rise_fraction*T.

    ``phase`` is in cycles (0.25 starts a quarter period later in the cycle).
    """
    period = check_period(period)
    if not high > low:
        raise InputSignalError(f"triangle needs high > low, got low={low!r}, high={high!r}")
    if not 0.0 < rise_fraction < 1.0:
        raise InputSignalError(f"rise_fraction must be in (0, 1), got {rise_fraction!r}")
    tau = np.mod(np.asarray(t, dtype=float) / period + phase, 1.0)
    rising = tau / rise_fraction
    falling = (1.0 - tau) / (1.0 - rise_fraction)
    return low + (high - low) * np.where(tau <= rise_fraction, rising, falling)


def t_wave_pair(
    t: Array,
    period: float,
    low: float,
    high: float,
    q: float,
    phase: float = 0.0,
    rise_fraction: float = 0.5,
) -> tuple[Array, Array]:
    """The two identification inputs x(t) and x1(t) = x(t) + q (Step 2 of 9.1.3, (9.20))."""
    if q == 0.0 or not np.isfinite(q):
        raise InputSignalError(f"offset q must be a nonzero finite number, got {q!r}")
    x = triangle(t, period, low, high, phase, rise_fraction)
    return x, x + q


def sine(
    t: Array, frequency: float, amplitude: float, offset: float = 0.0, phase: float = 0.0
) -> Array:
    """Sine offset + amplitude * sin(2 pi f t + phase) (the dither of (11.17)-(11.18))."""
    check_period(frequency, "frequency")
    return offset + amplitude * np.sin(2.0 * np.pi * frequency * np.asarray(t, dtype=float) + phase)


def step(t: Array, at: float, before: float, after: float) -> Array:
    """``before`` for t < at, ``after`` from t >= at."""
    return np.where(np.asarray(t, dtype=float) < at, before, after)


def band_limited_noise(
    t: Array,
    bandwidth: float,
    amplitude: float,
    seed: int = 0,
    offset: float = 0.0,
    components: int = 64,
) -> Array:
    """Seeded random multisine with flat spectrum on (0, bandwidth] and RMS ``amplitude``.

    A pure function of t (a sum of ``components`` sinusoids with frequencies uniform in
    (0, bandwidth] and random phases), so it can be sampled at any instant, like the
    [0, 100 Hz] random excitation of Figure 11.4.
    """
    check_period(bandwidth, "bandwidth")
    if components < 1:
        raise InputSignalError(f"components must be >= 1, got {components!r}")
    rng = np.random.default_rng(seed)
    freqs = rng.uniform(0.0, bandwidth, components)
    freqs[freqs == 0.0] = bandwidth
    phases = rng.uniform(0.0, 2.0 * np.pi, components)
    t = np.asarray(t, dtype=float)
    total: Array = np.sin(2.0 * np.pi * np.multiply.outer(t, freqs) + phases).sum(axis=-1)
    noise: Array = offset + amplitude * np.sqrt(2.0 / components) * total
    return noise
