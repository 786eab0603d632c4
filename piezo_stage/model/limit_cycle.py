"""The functions phi+/-, psi+/- of (9.3)-(9.9) and the closed-form limit cycle of Theorem 2.

phi-(w) = int_0^w du / (1 + sigma |u|^(n-1) u + (sigma - 1) |u|^n)      (9.3)
phi+(w) = int_0^w du / (1 - sigma |u|^(n-1) u + (sigma - 1) |u|^n)      (9.4)
phi(w)  = phi+(w) + phi-(w)                                                (9.5)
psi+/-, psi are their inverses. All are evaluated to ~1e-15 from tables built once per
(sigma, n) (see :mod:`piezo_stage.model._branches`); arrays in, arrays out.
"""

from __future__ import annotations

from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

from . import _branches
from .bouc_wen import _as_path, check_class_i
from .errors import InputSignalError

Array: TypeAlias = NDArray[np.float64]

__all__ = [
    "phi_plus",
    "phi_minus",
    "phi",
    "psi_plus",
    "psi_minus",
    "psi",
    "limit_cycle",
    "limit_cycle_bounds",
]


def _tables(sigma: float, n: float) -> Array:
    check_class_i(1.0, sigma, n)
    return _branches.tables(float(sigma), float(n))


def _apply(name: str, sigma: float, n: float, values: Array) -> Array:
    return _branches.apply(name, _tables(sigma, n), np.asarray(values, dtype=float))


def phi_plus(w: Array, sigma: float, n: float) -> Array:
    """phi+_{sigma,n}(w) (9.4), (9.7), (9.9) for w in [-1, 1]; +inf at w = 1."""
    return _apply("phi_plus", sigma, n, w)


def phi_minus(w: Array, sigma: float, n: float) -> Array:
    """phi-_{sigma,n}(w) (9.3), (9.6), (9.8); phi-(w) = -phi+(-w); -inf at w = -1."""
    return -_apply("phi_plus", sigma, n, -np.asarray(w, dtype=float))


def phi(w: Array, sigma: float, n: float) -> Array:
    """phi_{sigma,n}(w) = phi+(w) + phi-(w) (9.5), odd and strictly increasing on (-1, 1)."""
    return _apply("phi", sigma, n, w)


def psi_plus(y: Array, sigma: float, n: float) -> Array:
    """psi+ = inverse of phi+ on [phi+(-1), +inf) (-1 below, 1 at +inf)."""
    return _apply("psi_plus_exact", sigma, n, y)


def psi_minus(y: Array, sigma: float, n: float) -> Array:
    """psi- = inverse of phi-: psi-(y) = -psi+(-y)."""
    return -_apply("psi_plus_exact", sigma, n, -np.asarray(y, dtype=float))


def psi(y: Array, sigma: float, n: float) -> Array:
    """Inverse psi of phi (9.5) on the whole real line, values in (-1, 1)."""
    return _apply("psi", sigma, n, y)


def limit_cycle_bounds(
    rho: float, sigma: float, n: float, x_min: float, x_max: float
) -> tuple[float, float]:
    """(w at tau = 0, w at tau = T+) = (-psi(rho (X_max - X_min)), +psi(...)) (9.15)."""
    check_class_i(rho, sigma, n)
    if not x_max > x_min:
        raise InputSignalError(
            f"a T-wave needs X_max > X_min, got X_min={x_min!r}, X_max={x_max!r}"
        )
    top = float(psi(np.array([rho * (x_max - x_min)]), sigma, n)[0])
    return -top, top


def limit_cycle(
    rho: float, sigma: float, n: float, x_min: float, x_max: float, x: Array
) -> tuple[Array, Array]:
    """Steady-state w on loading and on unloading at input values ``x`` (Theorem 2).

    Loading (9.13):   w = psi+( phi+(-psi(rho (X_max - X_min))) + rho (x - X_min) )
    Unloading (9.14): w = -psi+( phi+(-psi(rho (X_max - X_min))) - rho (x - X_max) )
    for x in [X_min, X_max] (values outside raise :class:`InputSignalError`).
    """
    w_low, _ = limit_cycle_bounds(rho, sigma, n, x_min, x_max)
    x = _as_path(np.atleast_1d(np.asarray(x, dtype=float)).ravel(), "x").reshape(np.shape(x))
    span = x_max - x_min
    if np.any(x < x_min - 1e-12 * span) or np.any(x > x_max + 1e-12 * span):
        raise InputSignalError("limit_cycle: x must lie in [x_min, x_max]")
    start = float(phi_plus(np.array([w_low]), sigma, n)[0])
    loading = psi_plus(start + rho * (x - x_min), sigma, n)
    unloading = -psi_plus(start - rho * (x - x_max), sigma, n)
    return loading, unloading
