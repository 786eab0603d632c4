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
from typing import Any

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
        t = np.asarray(t, dtype=float)
        tau = np.maximum(t - self.t_start, 0.0)
        e, edot, eddot = self._error(tau, np.exp, np.cos, np.sin)
        before = t < self.t_start
        return self.target + e, np.where(before, 0.0, edot), np.where(before, 0.0, eddot)

    def at(self, t: float) -> tuple[float, float, float]:
        """:meth:`evaluate` at one time, in scalar arithmetic (a controller's per-sample call)."""
        before = t < self.t_start
        e, edot, eddot = self._error(max(t - self.t_start, 0.0), math.exp, math.cos, math.sin)
        return self.target + e, 0.0 if before else edot, 0.0 if before else eddot

    def _error(self, tau: Any, exp: Any, cos: Any, sin: Any) -> tuple[Any, Any, Any]:
        """E = yr − target and its two derivatives at ``tau`` ≥ 0 after t_start, in the
        arithmetic ``exp``, ``cos``, ``sin`` give (numpy's or math's).
        """
        xi, w0 = self.xi, self.omega0
        e0, v0 = self.y0 - self.target, self.ydot0
        a = xi * w0
        decay = exp(-a * tau)
        if xi < 1.0:
            wd = w0 * math.sqrt(1.0 - xi * xi)
            b = (v0 + a * e0) / wd
            c, s = cos(wd * tau), sin(wd * tau)
            e = decay * (e0 * c + b * s)
            edot = decay * ((b * wd - a * e0) * c - (e0 * wd + a * b) * s)
        elif xi == 1.0:
            b = v0 + a * e0
            e = decay * (e0 + b * tau)
            edot = decay * (b - a * (e0 + b * tau))
        else:
            r = w0 * math.sqrt(xi * xi - 1.0)
            l1, l2 = -a + r, -a - r
            c1 = (v0 - l2 * e0) / (l1 - l2)
            c2 = e0 - c1
            e1, e2 = exp(l1 * tau), exp(l2 * tau)
            e = c1 * e1 + c2 * e2
            edot = c1 * l1 * e1 + c2 * l2 * e2
        return e, edot, -2.0 * a * edot - w0 * w0 * e

    def __call__(self, t: float) -> tuple[float, float]:
        """(yr, ẏr) at one time t, the pair :meth:`TimeVaryingPID.update` takes."""
        yr, yr_dot, _ = self.at(t)
        return yr, yr_dot
