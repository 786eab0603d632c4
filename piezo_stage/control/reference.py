"""The thesis's reference yr(t) (§11.4.1): a second-order linear system driven by initial
conditions.

yr is the output of ω0/(s² + 2ξω0 s + ω0²) with zero input, i.e.
ÿr + 2ξω0·ẏr + ω0²·(yr − target) = 0, with yr(0) = y0, ẏr(0) = ydot0; the thesis uses
ξ = 0.7, ω0 = 2π·500 rad/s and target = 0.
A non-zero ``target`` makes the same system a smooth set-point transition (yr → target),
whose derivatives all vanish exponentially as the Theorem 4 setting requires.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import ControlError


@dataclass(frozen=True)
class SecondOrderReference:
    """yr(t), ẏr(t), ÿr(t) in closed form; ``t`` is measured from ``t_start`` (before it,
    yr = y0).
    """

    y0: float
    ydot0: float = 0.0
    xi: float = 0.7
    omega0: float = 2.0 * math.pi * 500.0
    target: float = 0.0
    t_start: float = 0.0

    def __post_init__(self) -> None:
        for key in ("y0", "ydot0", "xi", "omega0", "target", "t_start"):
            if not math.isfinite(getattr(self, key)):
                raise ControlError(f"reference {key} must be finite, got {getattr(self, key)}")
        if self.xi <= 0 or self.omega0 <= 0:
            raise ControlError(
                f"reference needs xi > 0 and omega0 > 0, got xi={self.xi}, omega0={self.omega0}"
            )

    def evaluate(
        self, t: ArrayLike
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(yr, ẏr, ÿr) at times t [s] (vectorised)."""
        tau = np.maximum(np.asarray(t, dtype=float) - self.t_start, 0.0)
        xi, w0 = self.xi, self.omega0
        e0, v0 = self.y0 - self.target, self.ydot0
        a = xi * w0
        decay = np.exp(-a * tau)
        if xi < 1.0:
            wd = w0 * math.sqrt(1.0 - xi * xi)
            b = (v0 + a * e0) / wd
            cos, sin = np.cos(wd * tau), np.sin(wd * tau)
            e = decay * (e0 * cos + b * sin)
            edot = decay * ((b * wd - a * e0) * cos - (e0 * wd + a * b) * sin)
        elif xi == 1.0:
            b = v0 + a * e0
            e = decay * (e0 + b * tau)
            edot = decay * (b - a * (e0 + b * tau))
        else:
            r = w0 * math.sqrt(xi * xi - 1.0)
            l1, l2 = -a + r, -a - r
            c1 = (v0 - l2 * e0) / (l1 - l2)
            c2 = e0 - c1
            e1, e2 = np.exp(l1 * tau), np.exp(l2 * tau)
            e = c1 * e1 + c2 * e2
            edot = c1 * l1 * e1 + c2 * l2 * e2
        eddot = -2.0 * a * edot - w0 * w0 * e
        before = np.asarray(t, dtype=float) < self.t_start
        edot = np.where(before, 0.0, edot)
        eddot = np.where(before, 0.0, eddot)
        return self.target + e, edot, eddot

    def __call__(self, t: float) -> tuple[float, float]:
        """(yr, ẏr) at one time t, the pair :meth:`TimeVaryingPID.update` takes."""
        yr, yr_dot, _ = self.evaluate(t)
        return float(yr), float(yr_dot)
