"""Refinement: least squares of all parameters on the whole steady cycles of both runs.

The analytic estimate (Table 10.2) uses a handful of points of one branch; the refinement
simulates the model on both cycles (both branches, both runs) and minimises the output
residual, starting from the analytic values, within the class-I bounds σ ≥ ½, ρ, κw > 0,
n ≥ 1 (Table 8.2). Each cycle is simulated from its input minimum, where Theorem 2 fixes the
state: w = −ψ_{σ,n}(ρ(Xmax − Xmin)) (9.15).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from piezo_stage.model.bouc_wen import BoucWenParameters, model_output
from piezo_stage.model.errors import ModelError
from piezo_stage.model.limit_cycle import limit_cycle_bounds

from .cycles import SteadyCycle
from .errors import RefinementError

#: parameters after κ_1..κ_N in the optimisation vector
_TAIL = ("y0", "kappa_w", "rho", "sigma", "n")
#: the hysteretic parameters whose standard errors decide whether the data determine them
HYSTERETIC = ("kappa_w", "rho", "sigma", "n")
_FD_STEP = 1.5e-8  #: relative finite-difference step of the Jacobian (√eps)
#: |correlation| of two parameters above which the result warns (as the fit by simulation)
CORRELATION_LIMIT = 0.999


@dataclass(frozen=True)
class RefineOptions:
    """Options of :func:`refine` and of its bad-fit and determinacy checks."""

    enabled: bool = True
    max_nfev: int = 200
    tolerance: float = 1e-13  #: ftol = xtol = gtol of scipy's least_squares
    noise_factor: float = 3.0  #: a fit is bad if RMS > noise_factor·noise ...
    max_rms_fraction: float = 0.005  #: ... and RMS > this fraction of the output span
    max_rel_std: float = 0.05  #: a hysteretic parameter whose relative standard error
    #: exceeds this is not determined by the data
    n_max: float = 50.0  #: upper bound of n (keeps |w|^n finite)


@dataclass(frozen=True)
class CyclePath:
    """A cycle laid out for simulation: the input path (in v) from the x minimum over one
    period, with the turning points reconstructed between samples, and the measured output
    at the path positions that are real samples (except those at the turning points).
    """

    v: NDArray[np.float64]
    sample_positions: NDArray[np.int_]
    y: NDArray[np.float64]
    x_min: float
    x_max: float


def _line_corner(x: NDArray[np.float64], i: int, m: int) -> tuple[float, float] | None:
    """Turning point near sample i as the intersection of lines fitted to the m samples on
    either side (exact for triangles); None when the lines do not meet within one sample of
    i, or overshoot x[i] by more than one sample's worth of slope (a smooth turning point,
    e.g. a sine, where tangent lines meet above the curve).
    """
    n = len(x)
    left = np.arange(i - m, i) % n
    right = np.arange(i + 1, i + m + 1) % n
    pl = np.arange(i - m, i, dtype=float)
    pr = np.arange(i + 1, i + m + 1, dtype=float)
    sl, cl = np.polyfit(pl, x[left], 1)
    sr, cr = np.polyfit(pr, x[right], 1)
    if sl == sr or np.sign(sl) == np.sign(sr):
        return None
    pc = (cr - cl) / (sl - sr)
    xc = cl + sl * pc
    if abs(pc - i) >= 1.0 or abs(xc - x[i]) > min(abs(sl), abs(sr)):
        return None
    return float(pc), float(xc)


def cycle_path(cycle: SteadyCycle, v_smooth: NDArray[np.float64], input_sign: int) -> CyclePath:
    """Lay out ``cycle`` for :func:`model_output`, starting at the x = input_sign·v minimum."""
    x = input_sign * v_smooth
    m_samples = len(x)
    m_fit = max(3, m_samples // 100)
    corners = []
    for i, extreme in ((int(np.argmin(x)), -1.0), (int(np.argmax(x)), 1.0)):
        c = _line_corner(x, i, m_fit)
        if c is None or extreme * (c[1] - x[i]) < 0:
            c = (float(i), float(x[i]))  # smooth turning point: the sample itself
        corners.append(c)
    (p_min, x_lo), (p_max, x_hi) = corners
    # rotate so the path starts at the minimum; phases measured from it in [0, M)
    start = int(np.ceil(p_min - 1e-9))
    order = (start + np.arange(m_samples)) % m_samples
    # (numpy's stubs give floating[Any] for an integer array minus a float: float64 here)
    phases = cast(NDArray[np.float64], (order - p_min) % m_samples)
    path_x = list(x[order])
    positions = list(range(m_samples))
    inserted = 0
    if phases[0] > 1e-9:  # minimum lies between samples: prepend it
        path_x.insert(0, x_lo)
        positions = [p + 1 for p in positions]
        inserted = 1
    else:  # on a sample: use the reconstructed value
        path_x[0] = x_lo
    ph_max = (p_max - p_min) % m_samples
    if abs(ph_max - round(ph_max)) > 1e-9:  # maximum between samples: insert it
        k = int(np.searchsorted(phases, ph_max)) + inserted
        path_x.insert(k, x_hi)
        positions = [p + (1 if p >= k else 0) for p in positions]
    else:
        path_x[int(round(ph_max)) % m_samples + inserted] = x_hi

    # samples within one sampling interval of a turning point were interpolated across the
    # kink when the periods were averaged (unless the grid hit the corner): leave them out
    def distance(ph: NDArray[np.float64], corner: float) -> NDArray[np.float64]:
        d: NDArray[np.float64] = np.abs(ph - corner) % m_samples
        return np.minimum(d, m_samples - d)

    keep = (distance(phases, 0.0) >= 1.0 - 1e-9) & (distance(phases, ph_max) >= 1.0 - 1e-9)
    return CyclePath(
        v=input_sign * np.asarray(path_x),
        sample_positions=np.asarray(positions)[keep],
        y=cycle.output[order][keep],
        x_min=min(x_lo, float(x.min())),
        x_max=max(x_hi, float(x.max())),
    )


def pack(params: BoucWenParameters) -> NDArray[np.float64]:
    """Optimisation vector (κ_1..κ_N, y0, κw, ρ, σ, n) of ``params``."""
    return np.array([*params.kappa, params.y0, params.kappa_w, params.rho, params.sigma, params.n])


def unpack(p: NDArray[np.float64], degree: int, input_sign: int) -> BoucWenParameters:
    """Parameters of an optimisation vector of :func:`pack` with ``degree`` κ's."""
    kw = dict(zip(_TAIL, (float(v) for v in p[degree:])))
    return BoucWenParameters(kappa=tuple(float(v) for v in p[:degree]), input_sign=input_sign, **kw)


def start_w(params: BoucWenParameters, path: CyclePath) -> float:
    """Hysteretic state w at the x minimum on the limit cycle: −ψ_{σ,n}(ρ(Xmax − Xmin)) (9.15)."""
    return limit_cycle_bounds(params.rho, params.sigma, params.n, path.x_min, path.x_max)[0]


def residuals(params: BoucWenParameters, paths: list[CyclePath]) -> NDArray[np.float64]:
    """Model minus measured output on all samples of all cycles; a model that cannot be
    simulated at these parameters raises :class:`RefinementError`.
    """
    out = []
    try:
        for path in paths:
            sim = model_output(params, path.v, w0=start_w(params, path))
            out.append(sim[path.sample_positions] - path.y)
    except (RuntimeError, ModelError) as exc:
        raise RefinementError(
            f"the model cannot be simulated at sigma={params.sigma:.6g}, n={params.n:.6g}, "
            f"rho={params.rho:.6g} ({type(exc).__name__}: {exc})"
        ) from exc
    return np.concatenate(out)


@dataclass(frozen=True)
class RefinedFit:
    """Outcome of :func:`refine`: parameters, residual, relative standard errors, solver report."""

    parameters: BoucWenParameters
    rms_error: float
    relative_std: dict[str, float]
    nfev: int
    status: str
    rejected_trials: int = 0  #: trial points the model could not simulate
    #: parameter pairs whose correlation exceeds CORRELATION_LIMIT: (name, name, correlation)
    correlations: tuple[tuple[str, str, float], ...] = ()


def _bounds(
    p0: NDArray[np.float64], degree: int, n_max: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    lo = np.full_like(p0, -np.inf)
    hi = np.full_like(p0, np.inf)
    i = degree + 1  # κw, ρ, σ, n
    lo[i] = p0[i] * 1e-6
    lo[i + 1] = p0[i + 1] * 1e-6
    lo[i + 2] = 0.5
    lo[i + 3], hi[i + 3] = 1.0, n_max
    return lo, hi


def feasible_start(
    kappa: NDArray[np.float64],
    y0: float,
    kappa_w: float,
    rho: float,
    sigma: float,
    n: float,
    input_sign: int,
    n_max: float = 50.0,
) -> BoucWenParameters:
    """Project an analytic estimate into class I (σ ≥ ½, 1 ≤ n ≤ n_max) to start the
    refinement (κw, ρ > 0 are checked before).
    """
    return BoucWenParameters(
        kappa=tuple(float(k) for k in kappa),
        kappa_w=float(kappa_w),
        rho=float(rho),
        sigma=max(float(sigma), 0.5),
        n=min(max(float(n), 1.0), n_max),
        y0=float(y0),
        input_sign=input_sign,
    )


def strong_correlations(
    names: list[str], cov: NDArray[np.float64], limit: float
) -> tuple[tuple[str, str, float], ...]:
    """Parameter pairs whose correlation (from the covariance ``cov``) exceeds ``limit`` in
    magnitude; κ_i with y0 left out (the polynomial's offset when the input is not centred).
    """
    d = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    d[d == 0] = 1.0
    corr = cov / np.outer(d, d)
    return tuple(
        (names[i], names[j], float(corr[i, j]))
        for i in range(len(names))
        for j in range(i + 1, len(names))
        if not (names[j] == "y0" and names[i].startswith("kappa_")) and abs(corr[i, j]) > limit
    )


def refine(
    start: BoucWenParameters, paths: list[CyclePath], options: RefineOptions = RefineOptions()
) -> RefinedFit:
    """Least squares (scipy, trust-region reflective, bounded) from ``start``."""
    degree = len(start.kappa)
    sign = start.input_sign
    p0 = pack(start)
    lo, hi = _bounds(p0, degree, options.n_max)
    p0 = np.clip(p0, lo, hi)
    scale = np.where(np.abs(p0) > 0, np.abs(p0), 1.0)
    # y0 may be 0: scale it like the output
    y_span = max(float(np.ptp(np.concatenate([p.y for p in paths]))), np.finfo(float).tiny)
    scale[degree] = max(abs(p0[degree]), 1e-3 * y_span)

    first = residuals(start, paths)  # raises RefinementError if the start fails
    failures: list[str] = []

    def fun(z: NDArray[np.float64]) -> NDArray[np.float64]:
        try:
            # in units of the output span: the tolerances are then relative to the data
            return residuals(unpack(z * scale, degree, sign), paths) / y_span
        except RefinementError as exc:
            # a trial point the model cannot simulate: non-finite residuals make the
            # trust-region method reject the step and shrink the region
            failures.append(str(exc))
            return np.full(first.shape, np.nan)

    lo_z, hi_z = lo / scale, hi / scale
    cache: dict[bytes, NDArray[np.float64]] = {}

    def cached(z: NDArray[np.float64]) -> NDArray[np.float64]:
        key = z.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = fun(z)
        return cache[key]

    def jac(z: NDArray[np.float64]) -> NDArray[np.float64]:
        """Forward differences, backward where the forward point is out of bounds or cannot
        be simulated.
        """
        f0 = cached(z)
        J = np.empty((len(f0), len(z)))
        for j in range(len(z)):
            h = _FD_STEP * max(1.0, abs(z[j]))
            for step in (h, -h) if z[j] + h <= hi_z[j] else (-h,):
                zj = z.copy()
                zj[j] += step
                col = (fun(zj) - f0) / step
                if np.all(np.isfinite(col)):
                    break
            J[:, j] = col
        return J

    try:
        res = least_squares(
            cached,
            p0 / scale,
            jac=jac,
            bounds=(lo_z, hi_z),
            method="trf",
            ftol=options.tolerance,
            xtol=options.tolerance,
            gtol=options.tolerance,
            max_nfev=options.max_nfev,
            x_scale=1.0,
        )
    except (ValueError, np.linalg.LinAlgError) as exc:
        detail = f"; last model failure: {failures[-1]}" if failures else ""
        raise RefinementError(f"refinement failed: {exc}{detail}") from exc
    # dense (the stubs also allow a sparse or operator Jacobian: ``jac`` returns an array)
    jacobian = cast(NDArray[np.float64], res.jac)
    if not np.all(np.isfinite(res.fun)) or not np.all(np.isfinite(jacobian)):
        raise RefinementError(
            f"refinement ended on a point the model cannot simulate: "
            f"{failures[-1] if failures else 'non-finite residuals'}"
        )
    p = res.x * scale
    params = unpack(p, degree, sign)
    r = res.fun * y_span
    dof = max(1, len(r) - len(p))
    s2 = float(r @ r) / dof
    J = jacobian * y_span
    jtj = J.T @ J
    # (numpy's stubs give floating[Any] for pinv: float64 for a float64 matrix)
    cov = cast(NDArray[np.float64], np.linalg.pinv(jtj) * s2)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None)) * scale
    names = [f"kappa_{i + 1}" for i in range(degree)] + list(_TAIL)
    rel = {
        name: float(sd / abs(v)) if v != 0 else float("inf") for name, sd, v in zip(names, std, p)
    }
    pairs = strong_correlations(names, cov, CORRELATION_LIMIT)
    return RefinedFit(
        parameters=params,
        rms_error=float(np.sqrt(np.mean(r**2))),
        relative_std=rel,
        nfev=int(res.nfev),
        status=str(res.message),
        correlations=pairs,
        rejected_trials=len(failures),
    )
