"""Synthetic T-wave identification runs from the model (for tests, benches and demos).

Two triangle runs x(t) and x(t)+q (Steps 1-2 of 9.1.3) are fed through the model's
``model_output``; by default each starts on its limit cycle (Theorem 2: w = −ψ(ρ·span) at the
minimum of input_sign·v), so every recorded period is steady.
"""

from __future__ import annotations

from typing import TypedDict, Unpack, cast

import numpy as np
from numpy.typing import NDArray

from piezo_stage.model.bouc_wen import BoucWenParameters, model_output
from piezo_stage.model.limit_cycle import limit_cycle
from piezo_stage.model.signals import triangle

from .recording import Recording


def limit_cycle_start(params: BoucWenParameters, low: float, high: float) -> float:
    """Hysteretic state w on the limit cycle when the triangle is at its ``low`` end (9.13-9.15)."""
    x_lo, x_hi = sorted((params.input_sign * low, params.input_sign * high))
    w_load, w_unload = limit_cycle(
        params.rho, params.sigma, params.n, x_lo, x_hi, np.array([x_lo, x_hi])
    )
    # v = low is the x minimum for input_sign = +1 and the x maximum for input_sign = -1
    return float(w_load[0]) if params.input_sign == 1 else float(w_load[1])


def triangle_run(
    params: BoucWenParameters,
    low: float,
    high: float,
    *,
    period: float = 1.0,
    samples_per_branch: int = 2000,
    periods: float = 3.0,
    noise: float = 0.0,
    input_noise: float = 0.0,
    phase: float = 0.0,
    w0: float | None = None,
    rng: np.random.Generator | None = None,
    name: str = "",
) -> Recording:
    """One run: a triangle between ``low`` and ``high`` (rising first), sampled with
    ``samples_per_branch`` samples per rise, for ``periods`` periods, starting ``phase``
    periods into the wave. ``noise``/``input_noise`` are white-noise standard deviations as
    fractions of the output/input span. ``w0`` defaults to the limit-cycle state.
    """
    m = 2 * samples_per_branch
    k0 = int(round(phase * m))
    n = int(round(periods * m)) + 1
    # (numpy's stubs give floating[Any] for an integer array times a float: float64 here)
    t_all = cast(NDArray[np.float64], np.arange(k0 + n) * (period / m))
    v_all = triangle(t_all, period, low, high)
    start = limit_cycle_start(params, low, high) if w0 is None else w0
    y_all = model_output(params, v_all, w0=start)
    t, v, y = t_all[k0:] - t_all[k0], v_all[k0:], y_all[k0:]
    rng = np.random.default_rng(0) if rng is None else rng
    if noise:
        y = y + noise * np.ptp(y) * rng.standard_normal(len(y))
    if input_noise:
        v = v + input_noise * np.ptp(v) * rng.standard_normal(len(v))
    return Recording(t, v, y, name=name or f"triangle {low:g}..{high:g}")


class _RunOptions(TypedDict, total=False):
    """The keyword arguments of :func:`triangle_run` that :func:`triangle_pair` passes on."""

    period: float
    samples_per_branch: int
    periods: float
    noise: float
    input_noise: float
    phase: float
    w0: float | None


def triangle_pair(
    params: BoucWenParameters,
    low: float,
    high: float,
    q: float,
    *,
    rng: np.random.Generator | None = None,
    **kwargs: Unpack[_RunOptions],
) -> tuple[Recording, Recording]:
    """Runs x(t) over [low, high] and x(t)+q (Steps 1-2 of 9.1.3)."""
    rng = rng or np.random.default_rng(0)
    a = triangle_run(params, low, high, rng=rng, name="run A", **kwargs)
    b = triangle_run(params, low + q, high + q, rng=rng, name="run B", **kwargs)
    return a, b


#: thesis reference sets (DESIGN §4)
CH9_EXAMPLE = dict(kappa=(2.0,), kappa_w=2.0, rho=1.0, sigma=3.0, n=1.5)
CH10_PATCH = dict(
    kappa=(1.401e-7, -5.0949e-11),
    kappa_w=9.22e-6,
    rho=0.0047,
    sigma=0.812,
    n=1.12,
    y0=1.7858e-6,
    input_sign=-1,
)
