"""Branch integrals of the normalized Bouc-Wen model, their inverses, and the exact path walker.

On a piece where x increases, (9.2) reads dw/dx = rho*g+(w) with
g+(w) = 1 - w^n (w >= 0, (8.11)) and 1 + (2 sigma - 1)(-w)^n (w <= 0, (8.12)); on a decreasing
piece dw/dx = rho*g-(w) = rho*g+(-w) ((8.13)-(8.14)). The equation is autonomous, so

    phi+(w) = phi+(w_a) + rho (x - x_a)        (increasing piece)
    phi-(w) = phi-(w_a) + rho (x - x_a)        (decreasing piece)

with phi+/- the integrals (9.3)-(9.4) and phi-(w) = -phi+(-w). With c = 2 sigma - 1 >= 0,

    phi+(w) = P(w) = -log(1 - w)/n + H(w)     for w in [0, 1)      ((9.7))
    phi+(w) = -E(-w)                          for w in [-1, 0]     ((9.9))

    H(a) = int_0^a [1/(1 - v^n) - 1/(n (1 - v))] dv   (bounded, smooth up to a = 1)
    E(a) = int_0^a dv / (1 + c v^n)

H and E are tabulated once per (sigma, n) as piecewise Chebyshev antiderivatives (geometric
grading toward v = 0 where v^n is not smooth); the inverse psi+ is solved by safeguarded Newton
in t = -log(1 - w) (well conditioned up to w -> 1) and also tabulated for speed.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

from ._cheb import fit_antiderivative, fit_interpolant, flat_eval, graded_breaks, pack
from ._jit import njit

Array: TypeAlias = NDArray[np.float64]
_GRADING_LEVELS = 52
_T_MAX = 40.0  # beyond t = -log(1-w) = 40, w == 1.0 in double precision

# Layout of the flat table array T (see tables()): scalars, then the 4-number headers of the
# packed piecewise tables H, E (antiderivatives), t(y) and w(y) (inverse of phi+).
N_, C_, H1_, E1_, YMAX_ = 0, 1, 2, 3, 4
TAB_H, TAB_E, TAB_T, TAB_W = 5, 9, 13, 17
HEADER = 21


def _h_integrand(v: Array, n: float) -> Array:
    """1/(1 - v^n) - 1/(n (1 - v)) on [0, 1], without cancellation near v = 1."""
    v = np.asarray(v, dtype=float)
    eps = 1.0 - v
    out = np.empty_like(v)
    far = eps >= 0.1
    out[far] = 1.0 / (1.0 - v[far] ** n) - 1.0 / (n * eps[far])
    near = ~far
    e = eps[near]
    log_term = np.log1p(-e)  # log v
    z = n * log_term
    # eps + log1p(-eps) = -sum_{k>=2} eps^k / k ;  expm1(z) - z = sum_{k>=2} z^k / k!
    s1 = np.zeros_like(e)
    s2 = np.zeros_like(e)
    e_pow = e.copy()
    z_pow = z.copy()
    fact = 1.0
    for k in range(2, 60):
        e_pow = e_pow * e
        z_pow = z_pow * z
        fact *= k
        s1 -= e_pow / k
        s2 += z_pow / fact
    numerator = n * s1 + s2
    denominator = n * e * (-np.expm1(z))
    with np.errstate(invalid="ignore", divide="ignore"):
        values = numerator / denominator
    values[e == 0.0] = (n - 1.0) / (2.0 * n)
    out[near] = values
    return out


@njit(inline=True, nrt=False)
def _newton_step(
    x: float, f: float, df: float, lo: float, hi: float
) -> tuple[float, float, float, bool]:
    """One safeguarded Newton step for an increasing f with f(x) = ``f``, f'(x) = ``df`` and the
    root in [lo, hi]: narrows the bracket, bisects when Newton leaves it. Returns
    (x_new, lo, hi, converged).
    """
    if f > 0.0:
        hi = x
    else:
        lo = x
    x_new = x - f / df
    if abs(x_new - x) <= 1e-15 * x:
        return x_new, lo, hi, True
    if not (lo < x_new < hi):
        x_new = 0.5 * (lo + hi)
        if hi - lo <= 1e-15 * hi:
            return x_new, lo, hi, True
    return x_new, lo, hi, False


@njit
def _t_solve(tab: Array, y: float, with_e: bool) -> float:
    """Solve t/n + H(a) (+ E(a)) = y for t >= 0, a = 1 - exp(-t): safeguarded Newton.

    Inverts P (phi+ for w >= 0) or, with ``with_e``, P + E (phi of (9.5) for w >= 0).
    """
    n: float = tab[0]
    h1: float = tab[2]
    e1: float = tab[3]
    if y <= 0.0:
        return 0.0
    if y == math.inf:
        return math.inf
    if with_e:
        lo = 0.5 * y
        guess = n * (y - h1 - e1)
    else:
        lo = y
        guess = n * (y - h1)
    hi = n * y
    t = min(max(guess, lo), hi)
    for _ in range(100):
        ea = math.exp(-t)
        a = -math.expm1(-t)
        f = t / n + flat_eval(tab, TAB_H, a) - y
        if ea == 0.0:
            df = 1.0 / n
        elif ea == 1.0:
            df = 1.0
        else:
            df = ea / -math.expm1(n * math.log1p(-ea))
        if with_e:
            f += flat_eval(tab, TAB_E, a)
            df += ea / (1.0 + tab[1] * a**n)
        t, lo, hi, done = _newton_step(t, f, df, lo, hi)
        if done:
            return t
    return t


@njit
def _e_solve(tab: Array, y: float, with_p: bool) -> float:
    """Solve E(a) (+ P(a)) = y for a in [0, 1], for the w <= 0 side: safeguarded Newton."""
    n: float = tab[0]
    c: float = tab[1]
    if y <= 0.0:
        return 0.0
    if not with_p and y >= tab[3]:
        return 1.0
    lo = 0.0
    hi = 1.0
    a = min(y, 1.0)
    for _ in range(100):
        an = a**n
        f = flat_eval(tab, TAB_E, a) - y
        df = 1.0 / (1.0 + c * an)
        if with_p:
            f += -math.log1p(-a) / n + flat_eval(tab, TAB_H, a)
            df += 1.0 / (1.0 - an)
        a, lo, hi, done = _newton_step(a, f, df, lo, hi)
        if done:
            return a
    return a


@njit(inline=True)
def phi_plus_k(tab: Array, w: float) -> float:
    """phi+(w) (9.4): +inf at w = 1, -E(1) at w = -1 (inputs clipped to [-1, 1])."""
    if w >= 1.0:
        return math.inf
    if w >= 0.0:
        value: float = -math.log1p(-w) / tab[0] + flat_eval(tab, TAB_H, w)
        return value
    if w <= -1.0:
        e1: float = tab[3]
        return -e1
    return -flat_eval(tab, TAB_E, -w)


@njit
def psi_plus_exact(tab: Array, y: float) -> float:
    """Inverse of phi+ by Newton on the H/E tables (clipped to [-1, 1])."""
    if y >= 0.0:
        return -math.expm1(-_t_solve(tab, y, False))
    if y <= -tab[3]:
        return -1.0
    return -_e_solve(tab, -y, False)


@njit(inline=True)
def psi_plus_k(tab: Array, y: float) -> float:
    """Inverse of phi+ from its tables (fast path; agrees with psi_plus_exact to ~1e-15)."""
    if y >= 0.0:
        if y >= tab[4]:
            return 1.0
        return -math.expm1(-flat_eval(tab, TAB_T, y))
    if y <= -tab[3]:
        return -1.0
    return flat_eval(tab, TAB_W, y)


@njit
def phi_total_k(tab: Array, w: float) -> float:
    """phi(w) = phi+(w) + phi-(w) (9.5), odd in w; +-inf at w = +-1."""
    a = abs(w)
    if a >= 1.0:
        value = math.inf
    else:
        value = -math.log1p(-a) / tab[0] + flat_eval(tab, TAB_H, a) + flat_eval(tab, TAB_E, a)
    return value if w >= 0.0 else -value


@njit
def psi_total_k(tab: Array, y: float) -> float:
    """psi, inverse of phi (9.5), by Newton (in t = -log(1 - |w|))."""
    magnitude = -math.expm1(-_t_solve(tab, abs(y), True))
    return magnitude if y >= 0.0 else -magnitude


@njit
def walk(tab: Array, rho: float, x: Array, w0: float, out: Array) -> None:
    """Write w at every sample of the path x (linear between samples) into ``out``, exact on
    monotone pieces.

    A monotone piece starting at (x_a, w_a) in direction s = +-1 gives
    w(x) = s * psi+(phi+(s w_a) + rho |x - x_a|) ((9.3)-(9.4) with phi-(w) = -phi+(-w)).
    """
    w = w0
    s = 0.0
    x_anchor = x[0]
    y_anchor = 0.0
    x_prev = x[0]
    out[0] = w
    for k in range(1, x.size):
        dx = x[k] - x_prev
        if dx != 0.0:
            d = 1.0 if dx > 0.0 else -1.0
            if d != s:
                s = d
                x_anchor = x_prev
                y_anchor = phi_plus_k(tab, s * w)
            w = s * psi_plus_k(tab, y_anchor + rho * s * (x[k] - x_anchor))
            x_prev = x[k]
        out[k] = w


@njit
def _map(kernel_id: int, tab: Array, values: Array, out: Array) -> None:
    for i in range(values.size):
        v = values.flat[i]
        if kernel_id == 0:
            out.flat[i] = phi_plus_k(tab, v)
        elif kernel_id == 1:
            out.flat[i] = psi_plus_k(tab, v)
        elif kernel_id == 2:
            out.flat[i] = psi_plus_exact(tab, v)
        elif kernel_id == 3:
            out.flat[i] = phi_total_k(tab, v)
        elif kernel_id == 4:
            out.flat[i] = psi_total_k(tab, v)
        else:
            out.flat[i] = _t_solve(tab, v, False)


KERNELS = {"phi_plus": 0, "psi_plus": 1, "psi_plus_exact": 2, "phi": 3, "psi": 4, "t_of_y": 5}


def apply(name: str, tab: Array, values: Array) -> Array:
    """Apply a scalar kernel (see KERNELS) elementwise to an array."""
    values = np.ascontiguousarray(values, dtype=float)
    out = np.empty_like(values)
    _map(KERNELS[name], tab, values, out)
    return out


def _assemble(
    n: float, c: float, h1: float, e1: float, y_max: float, parts: list[tuple[Array, Array]]
) -> Array:
    data, headers = pack(parts)
    headers = [h + HEADER if i % 4 in (0, 2) else h for i, h in enumerate(headers)]
    return np.concatenate([[n, c, h1, e1, y_max], np.array(headers, dtype=float), data])


@lru_cache(maxsize=64)
def tables(sigma: float, n: float) -> Array:
    """Flat float array of the tables the kernels take, for sigma >= 1/2, n >= 1 (cached).

    Layout: n, c = 2 sigma - 1, H(1), E(1), Ymax, then headers of the packed tables
    H, E (antiderivatives on [0, 1]), t(y) = -log(1 - psi+(y)) on [0, Ymax] and
    w(y) = psi+(y) on [-E(1), 0] (see :func:`piezo_stage.model._cheb.pack`).
    """
    n = float(n)
    c = 2.0 * float(sigma) - 1.0
    grading = graded_breaks(0.0, 1.0, _GRADING_LEVELS)
    # H's integrand is a difference of O(1/(1 - v)) terms whose value is O(n - 1): for n near 1
    # its rounding noise (~1e-16 absolute) is large relative to it, so the fit stops at an
    # absolute 1e-14 (an error of that order in H, far below the model's 1e-9 target)
    h_table = fit_antiderivative(lambda v: _h_integrand(v, n), grading, abs_tol=1e-14)
    e_table = fit_antiderivative(lambda v: 1.0 / (1.0 + c * v**n), grading)
    dummy = (np.array([0.0, 1.0]), np.zeros((1, 2)))
    partial = _assemble(n, c, 0.0, 0.0, 0.0, [h_table, e_table, dummy, dummy])
    h1 = float(flat_eval(partial, TAB_H, 1.0))
    e1 = float(flat_eval(partial, TAB_E, 1.0))
    y_max = _T_MAX / n + h1
    partial[H1_], partial[E1_], partial[YMAX_] = h1, e1, y_max

    first = min(1.0, y_max)
    positive = graded_breaks(0.0, first, _GRADING_LEVELS)
    if y_max > first:
        positive = np.concatenate(
            [positive[:-1], np.linspace(first, y_max, int(math.ceil(y_max)) + 1)]
        )
    t_table = fit_interpolant(lambda y: apply("t_of_y", partial, y), positive)
    negative = graded_breaks(-e1, 0.0, _GRADING_LEVELS, toward_low=False)
    w_table = fit_interpolant(lambda y: apply("psi_plus_exact", partial, y), negative)
    out = _assemble(n, c, h1, e1, y_max, [h_table, e_table, t_table, w_table])
    out.flags.writeable = False
    return out
