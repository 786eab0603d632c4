"""Loop orientation: which sign of the recorded input drives w (input_sign, §10.3.2).

With ρ, κw > 0 and σ ≥ ½, w̄ runs ahead of x towards ±1 (9.13-9.14): along x the loading
branch lies *above* the unloading branch, a clockwise loop in the (x, Φ) plane. The thesis's
patch shows the opposite in (v, y), so it identifies with −v ("so that the loading and
unloading lead to a clockwise limit cycle"). Here the side on which the v-rising branch lies
decides: above → input_sign = +1, below → −1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .cycles import SteadyCycle
from .errors import OrientationError


@dataclass(frozen=True)
class Orientation:
    """Outcome of :func:`detect_orientation` on one cycle: input_sign and the loop gap behind it."""

    input_sign: int
    mean_gap: float  #: mean over v of y_rising − y_falling [output unit]
    gap_noise: float  #: noise level of one gap sample
    reversed_fraction: float  #: share of the input range where the gap has the other sign


def loop_gap(
    cycle: SteadyCycle, v_smooth: NDArray[np.float64], samples: int = 400
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Output y on the v-rising branch minus y on the v-falling one, on a grid inside the span."""
    i = cycle.i_max
    vr, yr = v_smooth[: i + 1], cycle.output[: i + 1]
    vf = np.concatenate((v_smooth[i:], v_smooth[:1]))[::-1]
    yf = np.concatenate((cycle.output[i:], cycle.output[:1]))[::-1]
    lo, hi = max(vr.min(), vf.min()), min(vr.max(), vf.max())
    grid = np.linspace(lo, hi, samples)[1:-1]
    rise = np.interp(grid, *_sorted(vr, yr))
    fall = np.interp(grid, *_sorted(vf, yf))
    return grid, rise - fall


def _sorted(
    x: NDArray[np.float64], y: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    order = np.argsort(x, kind="stable")
    return x[order], y[order]


def detect_orientation(
    cycle: SteadyCycle,
    v_smooth: NDArray[np.float64],
    *,
    min_loop_width: float = 1e-3,
    noise_factor: float = 3.0,
) -> Orientation:
    """Orientation of one cycle; raises :class:`OrientationError` when the loop has no
    detectable hysteresis (mean width below ``min_loop_width`` of the output span and below
    the noise) or crosses itself (a figure-eight is not a Bouc-Wen loop).
    """
    grid, gap = loop_gap(cycle, v_smooth)
    span = cycle.output_span
    gap_noise = float(np.sqrt(2.0) * cycle.noise_output)
    mean_gap = float(np.mean(gap))
    needed = max(min_loop_width * span, noise_factor * gap_noise / np.sqrt(len(gap)))
    if abs(mean_gap) <= needed:
        raise OrientationError(
            f"{cycle.name or 'cycle'}: no detectable hysteresis (mean loop width "
            f"{abs(mean_gap) / span:.2g} of the output span, need > {needed / span:.2g}); the "
            "Bouc-Wen parameters cannot be identified from a loop without area"
        )
    sign = 1 if mean_gap > 0 else -1
    # the gap vanishes at the turning points: judge crossings away from them
    inner = (grid - grid[0] > 0.05 * (grid[-1] - grid[0])) & (
        grid[-1] - grid > 0.05 * (grid[-1] - grid[0])
    )
    against = np.sign(gap[inner]) == np.sign(-mean_gap)
    significant = np.abs(gap[inner]) > noise_factor * gap_noise
    reversed_fraction = float(np.mean(against & significant))
    if reversed_fraction > 0.05:
        raise OrientationError(
            f"{cycle.name or 'cycle'}: the loop crosses itself ({100 * reversed_fraction:.0f} % "
            "of the input range has the other orientation): not a Bouc-Wen limit cycle"
        )
    return Orientation(sign, mean_gap, gap_noise, reversed_fraction)


def resolve_orientation(orientations: list[Orientation], requested: int | None) -> int:
    """Common input_sign of all runs, checked against a requested one (None: automatic)."""
    signs = {o.input_sign for o in orientations}
    if len(signs) > 1:
        raise OrientationError(
            "the runs have loops of opposite orientation; they cannot come from one Bouc-Wen system"
        )
    detected = signs.pop()
    if requested is not None and requested != detected:
        raise OrientationError(
            f"input_sign={requested:+d} was requested but the loop orientation requires "
            f"input_sign={detected:+d} (w driven by {'-' if detected < 0 else ''}v): "
            "with ρ, κw > 0 "
            "the requested orientation cannot fit these data"
        )
    return detected
