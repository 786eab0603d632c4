"""Compiled kernels of the simulated stage: hysteresis walker and the dynamic-plant integrator.

Dynamic plant (11.1)-(11.3), (10.4):  m x'' + c x' + sum_i kappa_i x^i + kappa_w w = u,
w driven by input_sign * x through (9.2), u constant over each output step (zero-order hold).

Integrator: the step is cut into *pieces* on which x is monotone. On a piece of direction s,
w is a smooth function of x given exactly by the branch solution (9.3)-(9.4), so the piece is
smooth. On it

    m x'' + c x' + k x = F(t),   F = u - sum_i kappa_i x^i - kappa_w w + k x,

with k = dPhi/dx at the piece start (the local stiffness, so F varies only at second order in
the motion). The linear left side is solved exactly for a polynomial F (closed-form 2x2
exponential plus a polynomial particular solution, or for short pieces, where that cancels,
a Taylor series), F being the polynomial through its values at the q Lobatto nodes.
exp(L t) at the piece's points comes from two sin/cos/exp evaluations (group property, see
:func:`exp_plan`).

- small motions: F from the quadratic Taylor model F0 - Phi''/2 (x - x0)^2 on the linear
  prediction (no iteration, the solution for that one F, one exact walk to the end); accepted
  when the neglected cubic term and the interpolation defect are below the tolerance;
- otherwise: collocation, nodal F solved by a chord-Newton iteration with w at every node from
  the exact walk (piece matrices: response at the points to each nodal forcing), error =
  forcing defect at a check point (actual F minus the interpolant).

Pieces end at output times (u changes there), at velocity reversals (predicted from the
linearized motion, then located on x'(t) and polished so that x'(end) ~ 0: a small correction
of the end moves it along the piece's own solution, without a new solve), or where the error
control (tol_x on the displacement) puts them.

State vector layout (float64 array): [x, v, s, x_anchor, y_anchor, x_cur, w_cur, h_pref]
where (s, x_anchor, y_anchor, x_cur, w_cur) is the walker state in the hysteresis input and
h_pref the preferred piece length.
"""

from __future__ import annotations

import math
from typing import TypeAlias

import numpy as np
from numpy.typing import NDArray

from ._branches import phi_plus_k, psi_plus_k
from ._jit import njit

Array: TypeAlias = NDArray[np.float64]
IntArray: TypeAlias = NDArray[np.int64]
#: (rho, kappa_w, kappa_x, -, m, c, input_sign): see :func:`integrate`
Model: TypeAlias = tuple[float, float, float, float, float, float, float]
#: the walker state (s, x_anchor, y_anchor, x_cur, w_cur): see :func:`advance`
Walker: TypeAlias = tuple[float, float, float, float, float]
#: :func:`exp_plan`'s (fractions, ops, index), then the work arrays of :func:`workspace`
Plan: TypeAlias = tuple[Array, IntArray, IntArray, Array, Array, Array, Array, Array]
#: :func:`workspace`: (points, Ez, Gz, pcoef, tmp, invfact, F, zs, wst, Dn, dwdx, res, jac, plan)
Workspace: TypeAlias = tuple[
    Array, Array, Array, Array, Array, Array, Array, Array, Array, Array, Array, Array, Array, Plan
]

# indices in the state vector
X, V, S, XA, YA, XC, WC, HPREF = range(8)
STATE_SIZE = 8
# indices in the statistics vector
PIECES, REJECTED, NEWTON, REVERSALS, SOLVES, ROOT_EVALS, MOVED_ENDS = range(7)
STATS_SIZE = 7


@njit(inline=True)
def advance(
    tab: Array, rho: float, s: float, xa: float, ya: float, xc: float, wc: float, x_new: float
) -> Walker:
    """Move the hysteresis input from xc to x_new (monotone), exact branch solution.

    A new monotone piece starts at the current point when the direction changes:
    w = s psi+(phi+(s w_anchor) + rho s (x - x_anchor))  ((9.3)-(9.4), phi-(w) = -phi+(-w)).
    """
    dx = x_new - xc
    if dx == 0.0:
        return s, xa, ya, xc, wc
    d = 1.0 if dx > 0.0 else -1.0
    if d != s:
        s = d
        xa = xc
        ya = phi_plus_k(tab, s * wc)
    w = s * psi_plus_k(tab, ya + rho * s * (x_new - xa))
    return s, xa, ya, x_new, w


@njit(inline=True)
def g_plus(tab: Array, w: float) -> float:
    """g+(w) with dw/dx = rho g+(w) on an increasing piece ((8.11)-(8.12))."""
    if w >= 0.0:
        g: float = 1.0 - w ** tab[0]
    else:
        g = 1.0 + tab[1] * (-w) ** tab[0]
    return g


@njit(nrt=False)
def static_walk(tab: Array, rho: float, state: Array, x_in: Array, out: Array) -> None:
    """Advance the walker state [s, xa, ya, xc, wc] (in place) through the samples x_in."""
    s, xa, ya, xc, wc = state[0], state[1], state[2], state[3], state[4]
    for k in range(x_in.size):
        s, xa, ya, xc, wc = advance(tab, rho, s, xa, ya, xc, wc, x_in[k])
        out[k] = wc
    state[0], state[1], state[2], state[3], state[4] = s, xa, ya, xc, wc


@njit(inline=True)
def _poly_hi(kpoly: Array, x: float) -> tuple[float, float]:
    """sum_{i>=2} kappa_i x^i and its derivative (kpoly = kappa_2..kappa_N)."""
    p = 0.0
    dp = 0.0
    for j in range(kpoly.size - 1, -1, -1):
        dp = dp * x + p
        p = p * x + kpoly[j]
    return x * x * p, 2.0 * x * p + x * x * dp


@njit(inline=True)
def _lu_factor(a: Array, size: int) -> None:
    """In-place LU factorization without pivoting of a[:size, :size] (I minus a small matrix)."""
    for col in range(size):
        for r in range(col + 1, size):
            f = a[r, col] / a[col, col]
            a[r, col] = f
            for cc in range(col + 1, size):
                a[r, cc] -= f * a[col, cc]


@njit(inline=True)
def _lu_solve(a: Array, b: Array, size: int) -> None:
    """Solve with the factors of :func:`_lu_factor`, b[:size] in place."""
    for r in range(size):
        for cc in range(r):
            b[r] -= a[r, cc] * b[cc]
    for r in range(size - 1, -1, -1):
        acc = b[r]
        for cc in range(r + 1, size):
            acc -= a[r, cc] * b[cc]
        b[r] = acc / a[r, r]


@njit(inline=True)
def _exp_parts(a: float, b: float, t: float) -> tuple[float, float, float]:
    """(cos(beta t), sin(beta t)/beta, exp(-b t/2)), beta^2 = a - b^2/4 (cosh/sinh if negative):
    the three numbers exp(L t) is built from, L = [[0, 1], [-a, -b]].
    """
    al = 0.5 * b
    beta2 = a - al * al
    if beta2 > 0.0:
        be = math.sqrt(beta2)
        cc = math.cos(be * t)
        ss = math.sin(be * t) / be
    elif beta2 < 0.0:
        ga = math.sqrt(-beta2)
        cc = math.cosh(ga * t)
        ss = math.sinh(ga * t) / ga
    else:
        cc = 1.0
        ss = t
    return cc, ss, math.exp(-al * t)


@njit(inline=True)
def _exp_matrix(
    a: float, b: float, cc: float, ss: float, ex: float
) -> tuple[float, float, float, float]:
    """exp(L t) from its parts (:func:`_exp_parts`)."""
    al = 0.5 * b
    return ex * (cc + ss * al), ex * ss, -ex * ss * a, ex * (cc - ss * al)


@njit(inline=True)
def _exp_l(a: float, b: float, t: float) -> tuple[float, float, float, float]:
    """exp(L t) for L = [[0, 1], [-a, -b]] (closed form; under-, over- and critically damped)."""
    cc, ss, ex = _exp_parts(a, b, t)
    return _exp_matrix(a, b, cc, ss, ex)


# exponential plan (see exp_plan): how the parts at each fraction of the piece are obtained
_DIRECT, _DOUBLE, _DIFFERENCE = 0, 1, 2


def exp_plan(points: Array) -> tuple[Array, IntArray, IntArray]:
    """A recipe for exp(L tau xi) at all the ``points`` xi with few sin/cos/exp evaluations.

    exp(L t) is a one-parameter group, so its parts (cos(beta t), sin(beta t)/beta, e^(-b t/2))
    at t1 - t2 and 2 t follow from those at t1, t2 by the angle-difference and double-angle
    formulas (exact up to rounding). Fraction 1 is evaluated; a point xi < 1/2 directly, or as
    the double of xi/2 (evaluated) when 1 - xi/2 is wanted too; every other point as 1 minus a
    fraction already there, else directly. Lobatto nodes with the check point between the last
    two (q = 4: 0.276, 0.724, 1, 0.862) need two evaluations instead of four. Returns
    (fractions, ops[i] = (kind, j, k): direct, double of fraction j, or fraction j minus
    fraction k; index, fractions[index[p]] = points[p]).
    """
    fractions: list[float] = [1.0]  # 1.0 first: the other fractions may refer to it
    ops: list[tuple[int, int, int]] = [(_DIRECT, 0, 0)]

    def find(value: float) -> int:
        for i, f in enumerate(fractions):
            if abs(f - value) <= 1e-14:
                return i
        return -1

    def add(value: float, op: tuple[int, int, int]) -> int:
        fractions.append(value)
        ops.append(op)
        return len(fractions) - 1

    wanted = sorted(set(float(p) for p in points))
    for p in (p for p in wanted if p < 0.5):
        if any(abs((1.0 - h) - 0.5 * p) <= 1e-14 for h in wanted):  # 1 - p/2 wanted: p from p/2
            add(p, (_DOUBLE, add(0.5 * p, (_DIRECT, 0, 0)), 0))
        else:
            add(p, (_DIRECT, 0, 0))
    for p in wanted:
        if find(p) >= 0:
            continue
        j = find(1.0 - p)
        add(p, (_DIFFERENCE, 0, j) if j >= 0 else (_DIRECT, 0, 0))
    index = np.array([find(float(p)) for p in points], dtype=np.int64)
    return np.array(fractions), np.array(ops, dtype=np.int64), index


@njit(inline=True)
def _exp_points(
    a: float,
    b: float,
    tau: float,
    fractions: Array,
    ops: IntArray,
    index: IntArray,
    parts: Array,
    Ez: Array,
) -> None:
    """Ez[p] = exp(L tau points[p]) following the plan of :func:`exp_plan` (parts: work array)."""
    al = 0.5 * b
    beta2 = a - al * al
    for i in range(fractions.size):
        kind = ops[i, 0]
        if kind == _DIRECT:
            cc, ss, ex = _exp_parts(a, b, tau * fractions[i])
        elif kind == _DOUBLE:
            j = ops[i, 1]
            c1, s1, e1 = parts[j, 0], parts[j, 1], parts[j, 2]
            cc = c1 * c1 - beta2 * s1 * s1
            ss = 2.0 * c1 * s1
            ex = e1 * e1
        else:  # fraction j minus fraction k
            j = ops[i, 1]
            k = ops[i, 2]
            c1, s1, e1 = parts[j, 0], parts[j, 1], parts[j, 2]
            c2, s2, e2 = parts[k, 0], parts[k, 1], parts[k, 2]
            cc = c1 * c2 + beta2 * s1 * s2
            ss = s1 * c2 - c1 * s2
            ex = e1 / e2
        parts[i, 0] = cc
        parts[i, 1] = ss
        parts[i, 2] = ex
    for p in range(index.size):
        i = index[p]
        e00, e01, e10, e11 = _exp_matrix(a, b, parts[i, 0], parts[i, 1], parts[i, 2])
        Ez[p, 0, 0] = e00
        Ez[p, 0, 1] = e01
        Ez[p, 1, 0] = e10
        Ez[p, 1, 1] = e11


# the next controlled piece grows by 0.9 err^-0.2, at most by _MAX_GROWTH (3 made the ringing inputs
# reject a piece in ten: 2 halves that, and the rejections' solves, for a few more pieces)
_MAX_GROWTH = 2.0
_FULL_GROWTH = (
    0.9 / _MAX_GROWTH
) ** 5  # errors below which it grows by _MAX_GROWTH (no power needed)
_MOVE_LIMIT = (
    0.1  # a reversal piece's end moves along its solution by up to this fraction of it in all
)
_SERIES_TERMS = 24  # Taylor terms of phi_j(L t) when |L| t <= _SERIES_LIMIT
_SERIES_LIMIT = 0.3
_TAYLOR_TERMS = 40  # at most, in the Taylor series of a short piece's solution (|L| tau <= 0.3)


@njit(inline=True)
def _piece_matrices(
    a: float,
    b: float,
    m: float,
    tau: float,
    points: Array,
    vinv: Array,
    invfact: Array,
    Ez: Array,
    Gz: Array,
    pcoef: Array,
    tmp: Array,
    plan: Plan,
) -> None:
    """z(tau xi_p) = Ez[p] z(0) + Gz[p] F for the points xi_p, F the nodal forcing values.

    Forcing sum_k beta_k xi^k, beta = vinv F, xi = t/tau. Long pieces (|L| tau > 1): the
    polynomial particular solution P of m x'' + c x' + k x = F (back substitution from the top
    degree), z(t) = exp(L t)(z(0) - (P(0), P'(0))) + (P(t), P'(t)). Short pieces (where that
    cancels badly): z(t) = exp(L t) z(0) + sum_k beta_k k! t^(k+1) / tau^k phi_{k+1}(L t) B,
    phi_j(Z) = sum_i Z^i / (i + j)! by its Taylor series.
    """
    q = vinv.shape[0]
    inv_tau = 1.0 / tau
    _exp_points(a, b, tau, plan[0], plan[1], plan[2], plan[3], Ez)
    if max(math.sqrt(a), b) * tau <= _SERIES_LIMIT:
        for p in range(points.size):
            t = tau * points[p]
            for j in range(q):
                Gz[p, 0, j] = 0.0
                Gz[p, 1, j] = 0.0
            # phi_j(L t) B = sum_i (L t)^i B / (i + j)!, j = 1..q; y = (L t)^i B
            y0 = 0.0
            y1 = 1.0 / m
            for i in range(_SERIES_TERMS):
                for j in range(q):
                    f = invfact[i + j + 1]
                    Gz[p, 0, j] += y0 * f
                    Gz[p, 1, j] += y1 * f
                n0 = t * y1
                y1 = t * (-a * y0 - b * y1)
                y0 = n0
                if abs(y0) + abs(y1) * t < 1e-18 / m * t:
                    break
            # column k of the monomial basis xi^k: k! t^(k+1) / tau^k phi_{k+1}(L t) B
            scale = t
            for k in range(q):
                tmp[0, k] = Gz[p, 0, k] * scale
                tmp[1, k] = Gz[p, 1, k] * scale
                scale *= (k + 1) * t * inv_tau
            for j in range(q):
                acc0 = 0.0
                acc1 = 0.0
                for k in range(q):
                    acc0 += vinv[k, j] * tmp[0, k]
                    acc1 += vinv[k, j] * tmp[1, k]
                Gz[p, 0, j] = acc0
                Gz[p, 1, j] = acc1
        return
    # particular solutions of all the nodal unit forcings at once: row k of P holds the xi^k
    # coefficients (back substitution from the top degree, rows of q numbers), then the values
    # and derivatives at the points through the constant tables xi_p^k and k xi_p^(k-1)
    vpow, dpow, P = plan[4], plan[5], plan[6]
    inv_a = 1.0 / a
    inv_ma = inv_a / m
    for k in range(q - 1, -1, -1):
        c1 = b * inv_tau * (k + 1) * inv_a
        c2 = inv_tau * inv_tau * (k + 2) * (k + 1) * inv_a
        for j in range(q):
            acc = vinv[k, j] * inv_ma
            if k + 1 < q:
                acc -= c1 * P[k + 1, j]
            if k + 2 < q:
                acc -= c2 * P[k + 2, j]
            P[k, j] = acc
    for p in range(points.size):
        e00, e01 = Ez[p, 0, 0], Ez[p, 0, 1] * inv_tau
        e10, e11 = Ez[p, 1, 0], Ez[p, 1, 1] * inv_tau
        for j in range(q):
            val = 0.0
            der = 0.0
            for k in range(q):
                val += vpow[p, k] * P[k, j]
                der += dpow[p, k] * P[k, j]
            Gz[p, 0, j] = val - (e00 * P[0, j] + e01 * P[1, j])
            Gz[p, 1, j] = der * inv_tau - (e10 * P[0, j] + e11 * P[1, j])


@njit(inline=True)
def _forcing(model: Model, kpoly: Array, u: float, k_loc: float, x: float, w: float) -> float:
    """F = u - sum_i kappa_i x^i - kappa_w w + k_loc x."""
    hi_val, _ = _poly_hi(kpoly, x)
    return u - model[2] * x - hi_val - model[1] * w + k_loc * x


@njit(inline=True)
def _piece(
    tab: Array,
    model: Model,
    kpoly: Array,
    st: Array,
    u: float,
    k_loc: float,
    tau: float,
    points: Array,
    vinv: Array,
    invfact: Array,
    Ez: Array,
    Gz: Array,
    pcoef: Array,
    tmp: Array,
    F: Array,
    zs: Array,
    wst: Array,
    Dn: Array,
    dwdx: Array,
    res: Array,
    jac: Array,
    tol_x: float,
    tol_force: float,
    stats: Array,
) -> None:
    """Solve the collocation equations of one piece (Newton on the nodal forcing F_1..F_{q-1}).

    Uses the piece matrices Ez, Gz already computed for (tau, k_loc) and F as initial guess.

    On return zs[p] = (x, v) at the points (nodes 1..q-1, then the check points), wst[i] the
    walker state at node i (wst[0]: the start) and res[q:] unused.
    """
    rho, sgn = model[0], model[6]
    q = vinv.shape[0]
    x0 = st[X]
    v0 = st[V]
    for j in range(5):
        wst[0, j] = st[S + j]
    for it in range(30):
        stats[NEWTON] += 1
        worst = 0.0
        for i in range(1, q):
            xi = Ez[i - 1, 0, 0] * x0 + Ez[i - 1, 0, 1] * v0
            vi = Ez[i - 1, 1, 0] * x0 + Ez[i - 1, 1, 1] * v0
            for j in range(q):
                xi += Gz[i - 1, 0, j] * F[j]
                vi += Gz[i - 1, 1, j] * F[j]
            zs[i - 1, 0] = xi
            zs[i - 1, 1] = vi
            s, xa, ya, xc, wc = advance(
                tab,
                rho,
                wst[i - 1, 0],
                wst[i - 1, 1],
                wst[i - 1, 2],
                wst[i - 1, 3],
                wst[i - 1, 4],
                sgn * xi,
            )
            wst[i, 0], wst[i, 1], wst[i, 2], wst[i, 3], wst[i, 4] = s, xa, ya, xc, wc
            if it == 0:
                _, hi_slope = _poly_hi(kpoly, xi)
                dwdx[i] = sgn * rho * g_plus(tab, s * wc)
                Dn[i] = k_loc - (model[2] + hi_slope + model[1] * dwdx[i])
            res[i] = _forcing(model, kpoly, u, k_loc, xi, wc) - F[i]
            worst = max(worst, abs(res[i]))
        if worst <= tol_force:
            break
        if it == 0:
            # chord method: J = I - diag(D) dX/dF over F_1..F_{q-1}, factorized once
            for i in range(1, q):
                for j in range(1, q):
                    jac[i - 1, j - 1] = (1.0 if i == j else 0.0) - Dn[i] * Gz[i - 1, 0, j]
            _lu_factor(jac, q - 1)
        for i in range(1, q):
            res[i - 1] = res[i]
        _lu_solve(jac, res, q - 1)
        # node displacement change caused by the update; when negligible, update the nodes to
        # first order (w along its branch slope) instead of evaluating again
        small = True
        for i in range(1, q):
            dx = 0.0
            for j in range(1, q):
                dx += Gz[i - 1, 0, j] * res[j - 1]
            if abs(dx) > tol_x:
                small = False
        for i in range(1, q):
            F[i] += res[i - 1]
        if small:
            for i in range(1, q):
                dx = 0.0
                dv = 0.0
                for j in range(1, q):
                    dx += Gz[i - 1, 0, j] * res[j - 1]
                    dv += Gz[i - 1, 1, j] * res[j - 1]
                zs[i - 1, 0] += dx
                zs[i - 1, 1] += dv
                wst[i, 3] += sgn * dx
                wst[i, 4] += dwdx[i] * dx
            break
    # states at the check points
    for p in range(q - 1, points.size):
        xc_ = Ez[p, 0, 0] * x0 + Ez[p, 0, 1] * v0
        vc_ = Ez[p, 1, 0] * x0 + Ez[p, 1, 1] * v0
        for j in range(q):
            xc_ += Gz[p, 0, j] * F[j]
            vc_ += Gz[p, 1, j] * F[j]
        zs[p, 0] = xc_
        zs[p, 1] = vc_


@njit(inline=True)
def _branch_derivatives(
    tab: Array, model: Model, kpoly: Array, x: float, s_in: float, w: float
) -> tuple[float, float, float]:
    """First, second and third derivatives of Phi at x along the branch of direction s_in.

    One power evaluation. With wt = s_in w and dw/dx_in = rho g+(wt): w_x = sgn rho g,
    w_xx = s_in rho^2 g g1, w_xxx = sgn rho^3 (g g1^2 + g^2 g2), with g1, g2 the derivatives
    of g+ ((8.11)-(8.12)) at wt. The third is infinite at wt = 0 for n < 2 (|w|^n not smooth).
    """
    rho, kw, sgn = model[0], model[1], model[6]
    n = tab[0]
    c = tab[1]
    wt = s_in * w
    a = abs(wt)
    an1 = a ** (n - 1.0)  # |wt|^(n-1)
    an = an1 * a
    if a > 0.0:
        an2 = an1 / a
    elif n < 2.0:
        an2 = math.inf
    else:
        an2 = 0.0 if n > 2.0 else 1.0
    if wt >= 0.0:
        g = 1.0 - an
        g1 = -n * an1
        g2 = -n * (n - 1.0) * an2
    else:
        g = 1.0 + c * an
        g1 = -n * c * an1
        g2 = n * (n - 1.0) * c * an2
    d1 = model[2]
    d2 = 0.0
    d3 = 0.0
    for j in range(kpoly.size):  # sum_{i>=2} kappa_i x^i, kpoly = kappa_2..kappa_N
        i = j + 2
        d1 += kpoly[j] * i * x ** (i - 1)
        d2 += kpoly[j] * i * (i - 1) * x ** (i - 2)
        if i >= 3:
            d3 += kpoly[j] * i * (i - 1) * (i - 2) * x ** (i - 3)
    d1 += kw * sgn * rho * g
    d2 += kw * s_in * rho * rho * g * g1
    rho3 = rho * rho * rho
    if n == 1.0:
        d3 += kw * sgn * rho3 * g * g1 * g1
    else:
        d3 += kw * sgn * rho3 * (g * g1 * g1 + g * g * g2)
    return d1, d2, d3


@njit(inline=True)
def _monomial_forcing(vinv: Array, F: Array, pcoef: Array) -> None:
    """Write into ``pcoef`` the coefficients beta_k of the forcing interpolant sum_k beta_k xi^k
    (nodal values F).
    """
    q = vinv.shape[0]
    for k in range(q):
        beta = 0.0
        for j in range(q):
            beta += vinv[k, j] * F[j]
        pcoef[k] = beta


@njit(inline=True)
def _particular(a: float, b: float, m: float, inv_tau: float, pcoef: Array) -> None:
    """In place: forcing coefficients beta_k -> those of the polynomial particular solution P(xi)
    of m x'' + c x' + k x = sum beta_k xi^k (a = k/m, b = c/m, xi = t/tau), from the top degree.
    """
    q = pcoef.size
    inv_a = 1.0 / a
    for k in range(q - 1, -1, -1):
        acc = pcoef[k] / m
        if k + 1 < q:
            acc -= b * inv_tau * (k + 1) * pcoef[k + 1]
        if k + 2 < q:
            acc -= inv_tau * inv_tau * (k + 2) * (k + 1) * pcoef[k + 2]
        pcoef[k] = acc * inv_a


@njit(inline=True)
def _states_at_points(
    a: float,
    b: float,
    m: float,
    tau: float,
    vinv: Array,
    F: Array,
    plan: Plan,
    Ez: Array,
    pcoef: Array,
    x0: float,
    v0: float,
    zs: Array,
) -> None:
    """zs[p] = (x, x') at the points for the nodal forcing F (exp(L t) at the points in Ez).

    Long pieces: as :func:`_piece_matrices`'s long form for one forcing, the polynomial
    particular solution (pcoef, in xi = t/tau) plus exp(L t) applied to the start offset.
    Short pieces (|L| tau <= _SERIES_LIMIT, where that cancels): the Taylor series of x in
    xi, y_n = x^(n)(0) tau^n / n!, from the recursion of m x'' + c x' + k x = sum beta_n xi^n:
    y_{n+2} = (beta_n - c/tau (n+1) y_{n+1} - k y_n) tau^2 / (m (n+1)(n+2)), k = a m, c = b m.
    """
    vpow, dpow, ys = plan[4], plan[5], plan[7]
    q = vinv.shape[0]
    inv_tau = 1.0 / tau
    _monomial_forcing(vinv, F, pcoef)
    if max(math.sqrt(a), b) * tau <= _SERIES_LIMIT:
        ys[0] = x0
        ys[1] = v0 * tau
        h2 = tau * tau
        size = ys.size
        floor = 1e-19 * (abs(x0) + abs(ys[1]))
        for n in range(size - 2):
            beta = pcoef[n] * h2 / m if n < q else 0.0
            ys[n + 2] = (beta - b * tau * (n + 1) * ys[n + 1] - a * h2 * ys[n]) / (
                (n + 1) * (n + 2)
            )
            if n + 2 >= q and abs(ys[n + 1]) + abs(ys[n + 2]) <= floor:
                size = n + 3
                break
        for p in range(zs.shape[0]):
            xi = vpow[p, 1]
            val = 0.0
            der = 0.0
            for n in range(size - 1, -1, -1):
                der = der * xi + val
                val = val * xi + ys[n]
            zs[p, 0] = val
            zs[p, 1] = der * inv_tau
        return
    _particular(a, b, m, inv_tau, pcoef)
    dx = x0 - pcoef[0]
    dv = v0 - pcoef[1] * inv_tau
    for p in range(zs.shape[0]):
        val = 0.0
        der = 0.0
        for k in range(q):
            val += vpow[p, k] * pcoef[k]
            der += dpow[p, k] * pcoef[k]
        zs[p, 0] = Ez[p, 0, 0] * dx + Ez[p, 0, 1] * dv + val
        zs[p, 1] = Ez[p, 1, 0] * dx + Ez[p, 1, 1] * dv + der * inv_tau


@njit(inline=True)
def _piece_small(
    tab: Array,
    model: Model,
    st: Array,
    k_loc: float,
    tau: float,
    points: Array,
    vinv: Array,
    invfact: Array,
    lagrange: Array,
    Ez: Array,
    Gz: Array,
    pcoef: Array,
    tmp: Array,
    plan: Plan,
    F: Array,
    zs: Array,
    wst: Array,
    phi2: float,
    phi3: float,
    tol_x: float,
    stats: Array,
) -> float:
    """Small-amplitude piece: forcing from the quadratic Taylor model of Phi along the branch.

    F(t) = F0 - phi2/2 (x(t) - x0)^2 on the linear prediction of x (a one-shot collocation, no
    Newton); only the end point is walked exactly. Returns the error estimate in units of
    tol_x (neglected cubic term, prediction mismatch at the nodes, interpolation defect at the
    check point). F[0] must hold F0; F, zs, Ez and wst[q-1] are filled (not Gz).
    """
    rho, m, sgn = model[0], model[4], model[6]
    q = vinv.shape[0]
    stats[SOLVES] += 1
    a = k_loc / m
    b = model[5] / m
    # the solution for this one F only, not the piece matrices (built by the caller if a
    # collocation follows)
    _exp_points(a, b, tau, plan[0], plan[1], plan[2], plan[3], Ez)
    x0 = st[X]
    v0 = st[V]
    for i in range(1, q):
        # response to the unit constant forcing: (1 - exp(L t)_00) / k
        d = (
            Ez[i - 1, 0, 0] * x0
            + Ez[i - 1, 0, 1] * v0
            + (1.0 - Ez[i - 1, 0, 0]) / k_loc * F[0]
            - x0
        )
        F[i] = F[0] - 0.5 * phi2 * d * d
    _states_at_points(a, b, m, tau, vinv, F, plan, Ez, pcoef, x0, v0, zs)
    reach = 0.0
    mismatch = 0.0
    for p in range(points.size):
        xp = zs[p, 0]
        d = xp - x0
        reach = max(reach, abs(d))
        model_force = F[0] - 0.5 * phi2 * d * d
        if p < q - 1:
            mismatch = max(mismatch, abs(F[p + 1] - model_force))
        else:
            interp = 0.0
            for j in range(q):
                interp += lagrange[p - (q - 1), j] * F[j]
            mismatch = max(mismatch, abs(model_force - interp))
    cubic = abs(phi3) * reach * reach * reach / 6.0
    for j in range(5):
        wst[0, j] = st[S + j]
    s, xa, ya, xc, wc = advance(
        tab, rho, wst[0, 0], wst[0, 1], wst[0, 2], wst[0, 3], wst[0, 4], sgn * zs[q - 2, 0]
    )
    wst[q - 1, 0], wst[q - 1, 1], wst[q - 1, 2], wst[q - 1, 3], wst[q - 1, 4] = s, xa, ya, xc, wc
    return (cubic + mismatch) * min(tau * tau / (8.0 * m), 1.0 / k_loc) / tol_x


@njit(inline=True)
def _defect(
    tab: Array,
    model: Model,
    kpoly: Array,
    u: float,
    k_loc: float,
    points: Array,
    nodes: Array,
    lagrange: Array,
    F: Array,
    zs: Array,
    wst: Array,
) -> float:
    """Largest |F(actual state) - F(interpolated)| at the check points."""
    rho, sgn = model[0], model[6]
    q = nodes.size
    worst = 0.0
    for p in range(q - 1, points.size):
        # the node before the check point
        i = 0
        while i + 1 < q and nodes[i + 1] <= points[p]:
            i += 1
        walker = advance(
            tab, rho, wst[i, 0], wst[i, 1], wst[i, 2], wst[i, 3], wst[i, 4], sgn * zs[p, 0]
        )
        actual = _forcing(model, kpoly, u, k_loc, zs[p, 0], walker[4])
        interp = 0.0
        for j in range(q):
            interp += lagrange[p - (q - 1), j] * F[j]
        worst = max(worst, abs(actual - interp))
    return worst


@njit(inline=True)
def _state_at(
    model: Model,
    k_loc: float,
    tau: float,
    vinv: Array,
    F: Array,
    pcoef: Array,
    x0: float,
    v0: float,
    t: float,
) -> tuple[float, float]:
    """(x(t), x'(t)) on the piece for the nodal forcing F (exact for the interpolated forcing)."""
    m, c = model[4], model[5]
    a = k_loc / m
    b = c / m
    q = vinv.shape[0]
    inv_tau = 1.0 / tau
    _monomial_forcing(vinv, F, pcoef)
    _particular(a, b, m, inv_tau, pcoef)
    xi = t * inv_tau
    val = 0.0
    der = 0.0
    for k in range(q - 1, -1, -1):
        der = der * xi + val
        val = val * xi + pcoef[k]
    e00, e01, e10, e11 = _exp_l(a, b, t)
    d0 = pcoef[1] * inv_tau if q > 1 else 0.0
    return (
        e00 * (x0 - pcoef[0]) + e01 * (v0 - d0) + val,
        e10 * (x0 - pcoef[0]) + e11 * (v0 - d0) + der * inv_tau,
    )


@njit(inline=True)
def _reversal_time(
    model: Model,
    k_loc: float,
    tau: float,
    vinv: Array,
    F: Array,
    pcoef: Array,
    x0: float,
    v0: float,
    direction: float,
    t_hi: float,
    stats: Array,
) -> float:
    """Root of x'(t) in (0, t_hi] (x' has the sign of ``direction`` at 0, the other at t_hi)."""
    lo = 0.0
    hi = t_hi
    f_lo = v0 * direction
    f_hi = _state_at(model, k_loc, tau, vinv, F, pcoef, x0, v0, hi)[1] * direction
    t = hi
    for _ in range(60):
        if f_lo > 0.0 and f_hi < 0.0:
            t = hi - f_hi * (hi - lo) / (f_hi - f_lo)  # regula falsi step
            if not (lo < t < hi):
                t = 0.5 * (lo + hi)
        else:
            t = 0.5 * (lo + hi)
        f = _state_at(model, k_loc, tau, vinv, F, pcoef, x0, v0, t)[1] * direction
        stats[ROOT_EVALS] += 1
        if f > 0.0:
            lo = t
            f_lo = f
            f_hi *= 0.5  # Illinois
        else:
            hi = t
            f_hi = f
            f_lo *= 0.5
        if hi - lo <= 1e-14 * t_hi:
            break
    return hi


@njit(inline=True)
def _predicted_reversal(a: float, b: float, dx: float, v0: float, direction: float) -> float:
    """First t > 0 with x'(t) = 0 for x'' + b x' + a (x - x_eq) = 0, x - x_eq = dx (inf if none).

    Under-damped: x'(t) = e^(-b t/2) (cos(beta t) v0 - sin(beta t)/beta (a dx + b v0/2)).
    """
    al = 0.5 * b
    beta2 = a - al * al
    if beta2 <= 0.0:
        return math.inf
    be = math.sqrt(beta2)
    # direction * x'(t) = e^(-al t) (cos(beta t) vd - sin(beta t)/beta rd), vd >= 0
    vd = max(direction * v0, 0.0) + 0.0
    rd = direction * (a * dx + al * v0)
    theta = math.atan2(be * vd, rd)
    if theta <= 0.0:
        return math.inf
    return theta / be


def workspace(nodes: Array, checks: Array) -> Workspace:
    """The arrays :func:`integrate` works in, allocated once per plant (it allocates nothing):
    (points, Ez, Gz, pcoef, tmp, invfact, F, zs, wst, Dn, dwdx, res, jac, plan), plan the
    :func:`exp_plan` of the points, its work array of parts, the tables xi_p^k and
    k xi_p^(k-1), a q x q work array (:func:`_piece_matrices`) and the Taylor coefficients of
    :func:`_states_at_points`.
    """
    q = nodes.size
    npts = q - 1 + checks.size
    points: Array = np.concatenate([nodes[1:], checks])
    invfact = np.empty(_SERIES_TERMS + q + 2)
    invfact[0] = 1.0
    for i in range(1, invfact.size):
        invfact[i] = invfact[i - 1] / i
    fractions, ops, index = exp_plan(points)
    powers = np.arange(q)
    vpow = points[:, None] ** powers  # xi_p^k
    dpow = powers * points[:, None] ** np.maximum(powers - 1, 0)  # d/dxi xi^k at xi_p
    plan = (
        fractions,
        ops,
        index,
        np.empty((fractions.size, 3)),
        vpow,
        dpow,
        np.empty((q, q)),
        np.empty(_TAYLOR_TERMS),
    )
    return (
        points,
        np.empty((npts, 2, 2)),
        np.empty((npts, 2, q)),
        np.empty(q),
        np.empty((2, q)),
        invfact,
        np.empty(q),
        np.empty((npts, 2)),
        np.empty((q, 5)),
        np.empty(q),
        np.empty(q),
        np.empty(q),
        np.empty((q, q)),
        plan,
    )


@njit(nrt=False)
def integrate(
    tab: Array,
    model: Model,
    kpoly: Array,
    nodes: Array,
    checks: Array,
    vinv: Array,
    lagrange: Array,
    dt: float,
    tol_x: float,
    h_min: float,
    st: Array,
    u: Array,
    x_out: Array,
    v_out: Array,
    w_out: Array,
    stats: Array,
    work: Workspace,
) -> None:
    """Advance the plant over len(u) output steps of length dt with u held on each.

    ``model`` = (rho, kappa_w, kappa_x, -, m, c, input_sign). Outputs are the states at the end
    of each step; ``st`` is updated in place; ``stats`` counts pieces, rejected pieces, Newton
    evaluations, velocity reversals, piece solves, x'(t) evaluations locating a reversal and
    reversal ends moved without a solve (indices PIECES..MOVED_ENDS); ``work`` is
    :func:`workspace` (nodes, checks).
    Compiled without reference counting (``nrt=False``): the kernels it inlines work on the
    caller's arrays only.
    """
    q = nodes.size
    m, c = model[4], model[5]
    points, Ez, Gz, pcoef, tmp, invfact, F, zs, wst, Dn, dwdx, res, jac, plan = work
    npts = points.size
    for k in range(u.size):
        uk = u[k]
        t = 0.0
        while dt - t > 1e-12 * dt:
            x0 = st[X]
            v0 = st[V]
            hi_val, _ = _poly_hi(kpoly, x0)
            a0 = (uk - c * v0 - model[2] * x0 - hi_val - model[1] * st[WC]) / m
            remaining = dt - t
            tau = min(st[HPREF], remaining)
            if remaining - tau < 1e-9 * dt:
                tau = remaining
            controlled = (
                tau == st[HPREF]
            )  # length chosen by the error control (not cut by an event)
            # direction of the piece: the velocity's, unless it is about to reverse anyway (the
            # excursion v0^2 / 2|a0| left before the reversal is far below the tolerance)
            v_pred = v0
            if v0 * a0 < 0.0 and v0 * v0 < 2e-3 * tol_x * abs(a0):
                direction = 1.0 if a0 > 0.0 else -1.0
                v_pred = 0.0
            else:
                direction = (
                    1.0 if v0 > 0.0 else (-1.0 if v0 < 0.0 else (1.0 if a0 >= 0.0 else -1.0))
                )
            s_in = direction * model[6]
            k_loc, phi2, phi3 = _branch_derivatives(tab, model, kpoly, x0, s_in, st[WC])
            if k_loc < 0.05 * model[2]:
                k_loc = model[2]
            tol_force = 1e-3 * tol_x * k_loc
            # predicted reversal: first zero of x' for the linearized motion (forcing held at F0)
            dx_eq = x0 - _forcing(model, kpoly, uk, k_loc, x0, st[WC]) / k_loc
            t_pred = _predicted_reversal(k_loc / m, c / m, dx_eq, v_pred, direction)
            # an oscillation far below the tolerance is not worth a piece boundary
            amplitude = abs(dx_eq) + abs(v_pred) * math.sqrt(m / k_loc)
            ends_reversal = False
            if t_pred < tau and amplitude > tol_x:
                tau = max(h_min, t_pred)
                ends_reversal = True  # aim the piece at the reversal
            rooted = False
            polish = 0
            err = 0.0
            while True:
                F[0] = _forcing(model, kpoly, uk, k_loc, x0, st[WC])
                small_err = _piece_small(
                    tab,
                    model,
                    st,
                    k_loc,
                    tau,
                    points,
                    vinv,
                    invfact,
                    lagrange,
                    Ez,
                    Gz,
                    pcoef,
                    tmp,
                    plan,
                    F,
                    zs,
                    wst,
                    phi2,
                    phi3,
                    tol_x,
                    stats,
                )
                small = small_err <= 1.0
                if not small:  # full collocation, started from the quadratic prediction in F
                    _piece_matrices(
                        k_loc / m, c / m, m, tau, points, vinv, invfact, Ez, Gz, pcoef, tmp, plan
                    )
                    _piece(
                        tab,
                        model,
                        kpoly,
                        st,
                        uk,
                        k_loc,
                        tau,
                        points,
                        vinv,
                        invfact,
                        Ez,
                        Gz,
                        pcoef,
                        tmp,
                        F,
                        zs,
                        wst,
                        Dn,
                        dwdx,
                        res,
                        jac,
                        tol_x,
                        tol_force,
                        stats,
                    )
                # first point (in time) whose velocity has the wrong sign; a backward excursion
                # far below the tolerance is left to the walker (no piece boundary)
                t_bad = -1.0
                backward = 0.0
                for p in range(npts):
                    if zs[p, 1] * direction < 0.0:
                        backward = max(backward, -zs[p, 1] * direction)
                        if t_bad < 0.0 or points[p] * tau < t_bad:
                            t_bad = points[p] * tau
                if t_bad > 0.0 and not rooted and backward * tau > 1e-3 * tol_x:
                    t_rev = _reversal_time(
                        model, k_loc, tau, vinv, F, pcoef, x0, v0, direction, t_bad, stats
                    )
                    if t_rev > h_min:
                        tau = t_rev
                        ends_reversal = True
                        rooted = True
                        continue
                if ends_reversal and polish < 4:
                    # Newton on the piece length until the velocity at its end is negligible
                    # (the excursion v^2 / 2|a| it would still make is below the tolerance);
                    # an aimed piece that ends far from a reversal is kept as an ordinary one.
                    # A small shift moves the end along this piece's solution (same forcing
                    # polynomial, w walked exactly from the start): no new solve
                    v_peak = abs(v0)
                    for p in range(npts):
                        v_peak = max(v_peak, abs(zs[p, 1]))
                    f_end = F[q - 1]
                    tau_solved = tau  # the length F was solved for
                    # (moves only on long pieces: the polynomial form of _state_at cancels on
                    # short ones)
                    movable = max(math.sqrt(k_loc / m), c / m) * tau > _SERIES_LIMIT
                    resolve = False
                    while polish < 4:
                        v_end = zs[q - 2, 1]
                        a_end = (f_end - c * v_end - k_loc * zs[q - 2, 0]) / m
                        if not rooted and abs(v_end) > 0.05 * v_peak:
                            ends_reversal = False
                            break
                        if not (
                            a_end * direction < 0.0 and v_end * v_end > 2e-3 * tol_x * abs(a_end)
                        ):
                            break
                        shift = -v_end / a_end
                        polish += 1
                        if (
                            movable
                            and abs(tau + shift - tau_solved) <= _MOVE_LIMIT * tau_solved
                            and h_min < tau + shift <= remaining
                        ):
                            tau += shift
                            x_e, v_e = _state_at(
                                model, k_loc, tau_solved, vinv, F, pcoef, x0, v0, tau
                            )
                            walker = advance(
                                tab,
                                model[0],
                                wst[0, 0],
                                wst[0, 1],
                                wst[0, 2],
                                wst[0, 3],
                                wst[0, 4],
                                model[6] * x_e,
                            )
                            zs[q - 2, 0] = x_e
                            zs[q - 2, 1] = v_e
                            for j in range(5):
                                wst[q - 1, j] = walker[j]
                            f_end = _forcing(model, kpoly, uk, k_loc, x_e, walker[4])
                            stats[MOVED_ENDS] += 1
                        else:
                            tau = max(h_min, tau + shift)
                            resolve = True
                            break
                    if resolve:
                        continue
                if small:
                    err = small_err
                else:
                    err = _defect(tab, model, kpoly, uk, k_loc, points, nodes, lagrange, F, zs, wst)
                    err *= min(tau * tau / (8.0 * m), 1.0 / k_loc) / tol_x
                if err > 1.0 and tau > h_min:
                    tau = max(h_min, tau * max(0.2, 0.9 * err**-0.2))
                    controlled = True
                    ends_reversal = False
                    rooted = False
                    polish = 0
                    stats[REJECTED] += 1
                    continue
                break
            stats[PIECES] += 1
            st[X] = zs[q - 2, 0]
            st[V] = zs[q - 2, 1]
            for j in range(5):
                st[S + j] = wst[q - 1, j]
            if ends_reversal:
                stats[REVERSALS] += 1
            if controlled:  # the next piece may grow by up to _MAX_GROWTH
                st[HPREF] = min(dt, tau * (_MAX_GROWTH if err <= _FULL_GROWTH else 0.9 * err**-0.2))
            t += tau
        x_out[k] = st[X]
        v_out[k] = st[V]
        w_out[k] = st[WC]
