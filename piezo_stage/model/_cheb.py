"""Piecewise Chebyshev tables: build (numpy) and evaluate (jit kernel).

Used to tabulate the branch integrals of the normalized Bouc-Wen model (9.3-9.9) and their
inverses to near machine precision. A function is sampled at the Chebyshev points of each
piece; a piece whose trailing coefficients do not fall below the tolerance is bisected. The
antiderivative of a fitted integrand is integrated exactly term by term, so a table of
``F(x) = integral_a^x f`` is as accurate as the Chebyshev fit of the (smooth) integrand ``f``.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Callable, TypeAlias

import numpy as np
from numpy.typing import NDArray

from ._jit import njit

Array: TypeAlias = NDArray[np.float64]
VectorFunction = Callable[[Array], Array]

DEGREE = 20  # polynomial degree per piece
_TAIL_TOL = 4e-15  # trailing coefficients relative to the piece's largest (rounding floor ~1e-15)
_ABS_TOL = 1e-16  # absolute floor: the tabulated functions are O(1)
_MAX_PIECES = 20000
_MIN_WIDTH = 1e-13  # never bisect below this width (relative to the domain)


def _points(degree: int) -> Array:
    """Chebyshev points of the second kind on [-1, 1], ordered from -1 to 1."""
    return -np.cos(np.pi * np.arange(degree + 1) / degree)


@lru_cache(maxsize=8)
def _coefficient_matrix(degree: int) -> Array:
    """Matrix M with c = M @ values (values at ``_points(degree)``), the DCT-I of the samples."""
    j = np.arange(degree + 1)
    weights = np.ones(degree + 1)
    weights[0] = weights[-1] = 0.5
    # points ordered from -1: x_j = -cos(pi j / D) = cos(pi (D - j) / D)
    matrix = (2.0 / degree) * np.cos(np.pi * np.outer(j, degree - j) / degree) * weights
    matrix[0] *= 0.5
    matrix[-1] *= 0.5
    return matrix


def _antiderivative_coefficients(c: Array, half_width: float) -> Array:
    """Coefficients of F with F' = f (on the mapped piece) and F(left end) = 0."""
    degree = c.size - 1
    padded = np.concatenate([c, [0.0, 0.0]])
    big = np.zeros(degree + 2)
    big[1] = padded[0] - padded[2] / 2.0
    for k in range(2, degree + 2):
        big[k] = (padded[k - 1] - padded[k + 1]) / (2.0 * k)
    signs = (-1.0) ** np.arange(degree + 2)
    big[0] = -np.sum(big[1:] * signs[1:])
    return big * half_width


def _fit_pieces(
    func: VectorFunction, breaks: Array, degree: int, abs_tol: float = _ABS_TOL
) -> tuple[Array, Array]:
    """Bisect the pieces of ``breaks`` until each fit's tail is below tolerance (batched).

    ``abs_tol`` is the absolute floor of the tail: a function computed as a small difference
    of O(1) terms carries rounding noise of that size, which no bisection removes.
    """
    domain = breaks[-1] - breaks[0]
    nodes = _points(degree)
    matrix = _coefficient_matrix(degree)
    lefts, rights = breaks[:-1], breaks[1:]
    done_left: list[Array] = []
    done_right: list[Array] = []
    done_rows: list[Array] = []
    while lefts.size:
        x = 0.5 * (lefts + rights)[:, None] + 0.5 * (rights - lefts)[:, None] * nodes
        rows = func(x.ravel()).reshape(x.shape) @ matrix.T
        scale = np.max(np.abs(rows), axis=1)
        tail = np.max(np.abs(rows[:, -3:]), axis=1)
        split = (tail > np.maximum(_TAIL_TOL * scale, abs_tol)) & (
            rights - lefts > _MIN_WIDTH * domain
        )
        keep = ~split
        done_left.append(lefts[keep])
        done_right.append(rights[keep])
        done_rows.append(rows[keep])
        mids = 0.5 * (lefts[split] + rights[split])
        lefts, rights = np.concatenate([lefts[split], mids]), np.concatenate([mids, rights[split]])
        if sum(part.size for part in done_left) + lefts.size > _MAX_PIECES:
            raise RuntimeError("Chebyshev table did not converge (function not smooth enough)")
    left = np.concatenate(done_left)
    order = np.argsort(left)
    right = np.concatenate(done_right)[order]
    return np.append(left[order], right[-1]), np.concatenate(done_rows)[order]


def fit_interpolant(
    func: VectorFunction, breaks: Array, degree: int = DEGREE
) -> tuple[Array, Array]:
    """Piecewise Chebyshev interpolant of ``func``: (breaks, coefficients[piece, k])."""
    return _fit_pieces(func, np.asarray(breaks, dtype=float), degree)


def fit_antiderivative(
    func: VectorFunction, breaks: Array, degree: int = DEGREE, abs_tol: float = _ABS_TOL
) -> tuple[Array, Array]:
    """Piecewise Chebyshev table of ``F(x) = integral_{breaks[0]}^x func``."""
    new_breaks, rows = _fit_pieces(func, np.asarray(breaks, dtype=float), degree, abs_tol)
    out = np.zeros((rows.shape[0], degree + 2))
    offset = 0.0
    for i, c in enumerate(rows):
        big = _antiderivative_coefficients(c, 0.5 * (new_breaks[i + 1] - new_breaks[i]))
        big[0] += offset
        out[i] = big
        offset = float(np.sum(big))  # value at the right end (T_k(1) = 1)
    return new_breaks, out


def graded_breaks(low: float, high: float, levels: int, toward_low: bool = True) -> Array:
    """Breaks on [low, high] refined geometrically (ratio 2) toward ``low`` (or ``high``)."""
    fractions = np.concatenate([[0.0], 2.0 ** -np.arange(levels, -1, -1.0)])
    if not toward_low:
        fractions = 1.0 - fractions[::-1]
    return low + (high - low) * fractions


def pack(tables: list[tuple[Array, Array]]) -> tuple[Array, list[int]]:
    """Concatenate piecewise tables into one flat array; returns it and each table's header.

    Header of a table (4 numbers): offset of its breaks, number of breaks, offset of its
    coefficients, coefficients per piece. (One flat array is much cheaper to pass to compiled
    kernels than a tuple of arrays.)
    """
    parts: list[Array] = []
    headers: list[int] = []
    offset = 0
    for breaks, coefs in tables:
        headers += [offset, breaks.size, offset + breaks.size, coefs.shape[1]]
        parts += [breaks, coefs.ravel()]
        offset += breaks.size + coefs.size
    return np.concatenate(parts), headers


@njit(inline=True)
def flat_eval(T: Array, header: int, x: float) -> float:
    """Value at ``x`` of the packed table whose 4-number header starts at T[header]."""
    off_b = int(T[header])
    nb = int(T[header + 1])
    off_c = int(T[header + 2])
    ncoef = int(T[header + 3])
    lo = 0
    hi = nb - 1
    while hi - lo > 1:
        mid = (lo + hi) >> 1
        if T[off_b + mid] <= x:
            lo = mid
        else:
            hi = mid
    a = T[off_b + lo]
    b = T[off_b + lo + 1]
    t = (2.0 * x - a - b) / (b - a)
    if t > 1.0:
        t = 1.0
    elif t < -1.0:
        t = -1.0
    two_t = 2.0 * t
    base = off_c + lo * ncoef
    b1 = 0.0
    b2 = 0.0
    for j in range(ncoef - 1, 0, -1):
        b0 = T[base + j] + two_t * b1 - b2
        b2 = b1
        b1 = b0
    value: float = T[base] + t * b1 - b2
    return value
