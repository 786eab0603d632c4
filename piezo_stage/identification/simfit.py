"""Fit by simulation error: the modified model (10.15) simulated over whole records.

For any input (triangle, sine, raised cosine, random, steps), one run or several, transients
included: the output ``y = Σ κ_i v^i + κw·w + y0 (+ drift)`` is simulated over every record
from a fitted initial state w(0), with w from (9.2) driven by the (optionally delayed) input,
and the squared output error is minimised.

The parameters that enter linearly (κ_1..κ_N, y0, κw, drift coefficients) are eliminated by
linear least squares at every trial point (variable projection), so the nonlinear search runs
over ρ, σ, n, w(0) of each run and the delay only. κw may come out negative: the model is odd
(w driven by −v from −w(0) is −w), so that is input_sign = −1 with κw > 0 (the orientation
is detected, §10.3.2). Seeds: given ones (the analytic method, ch. 9-10) and a small
deterministic grid. Standard errors come from the Jacobian of all parameters at the optimum,
scaled by the residual.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from piezo_stage.model.bouc_wen import BoucWenParameters, polynomial, simulate_w
from piezo_stage.model.errors import ModelError
from piezo_stage.model.parameter_set import Drift, DriftKind, drift_basis

from .cycles import upward_crossings
from .derivatives import noise_std
from .errors import IdentificationError, OrientationError
from .recording import Recording
from .refine import strong_correlations

if TYPE_CHECKING:  # the stubs' type of least_squares' result, with its fields typed
    from scipy.optimize._lsq.least_squares import OptimizeResult as LeastSquaresResult

#: multi-start grid: ρ·(input span), σ, n
_GRID_RHO = (0.3, 1.0, 3.0, 10.0)
_GRID_SIGMA = (0.6, 1.5, 4.0)
_GRID_N = (1.2, 2.5)
_GRID_W0 = (-0.6, 0.0, 0.6)
#: the multi-start runs on every k-th sample when the runs hold more samples than this
GRID_SAMPLES = 12000
#: upper bounds of σ and n: beyond, w is a step function of x and the branch tables of the
#: model (piezo_stage.model._branches) no longer converge
SIGMA_MAX = 100.0
N_MAX = 50.0


@dataclass(frozen=True)
class FitOptions:
    """Options of the fit by simulation error (:func:`simulation_fit`) and of its checks."""

    degree: int = 1  #: N of (10.4)
    input_sign: int | None = None  #: None: from the sign of κw (loop orientation)
    drift: DriftKind = DriftKind.NONE  #: slow additive output drift per run
    fit_delay: bool = True  #: estimate a constant input-to-output delay
    max_delay_samples: float = 10.0  #: |delay| bound, in sampling intervals
    holdout: float = 0.25  #: share of each run held out for the check ...
    min_holdout_periods: float = 3.0  #: ... when every run holds more periods than this
    starts: int = 3  #: grid points refined when no seed is given
    max_nfev: int = 200
    tolerance: float = 1e-14  #: ftol = xtol = gtol of scipy's least_squares
    correlation_limit: float = 0.999  #: |correlation| above this draws a warning
    noise_factor: float = 3.0  #: a fit is bad if RMS > noise_factor·noise ...
    max_rms_fraction: float = 0.02  #: ... and RMS > this fraction of the output span
    max_rel_std: float = 0.25  #: a hysteretic parameter whose relative standard
    #: error exceeds this is not determined by the data
    warn_rel_std: float = 0.05  #: ... above this, a warning


@dataclass(frozen=True)
class Seed:
    """A starting point of the nonlinear search (w0 per run; None: 0)."""

    rho: float
    sigma: float
    n: float
    w0: tuple[float, ...] | None = None
    delay: float = 0.0


@dataclass(frozen=True)
class SimulationFit:
    """The optimum: parameters, per-run initial states, delay, drift, and their quality."""

    parameters: BoucWenParameters
    w0: tuple[float, ...]
    delay: float
    drift: tuple[Drift | None, ...]
    rms_error: float
    std: dict[str, float]
    relative_std: dict[str, float]
    correlations: list[tuple[str, str, float]]
    model: tuple[NDArray[np.float64], ...]  #: simulated output of each run
    nfev: int
    status: str
    diagnostics: dict[str, Any] = field(default_factory=dict)


class _Problem:
    """The runs, with the design matrix of the linear parameters at a nonlinear point.

    θ = (ρ·span_v, σ, n, w0_1..w0_R[, delay/dt]); columns: v^1..v^N, 1, w, drift of each run.
    """

    def __init__(
        self,
        runs: Sequence[Recording],
        options: FitOptions,
        time_constant: Sequence[float] | None = None,
    ) -> None:
        self.runs = list(runs)
        self.options = options
        self.degree = int(options.degree)
        v_all = np.concatenate([r.input for r in runs])
        self.span_v = float(np.ptp(v_all))
        self.dt = float(np.median(np.concatenate([np.diff(r.t) for r in runs])))
        self.y = np.concatenate([r.output for r in runs])
        #: residuals are minimised in units of the output span: the solver's tolerances are
        #: then relative to the data (outputs in metres made gtol stop early)
        self.y_scale = float(np.ptp(self.y)) or 1.0
        self.sizes = [len(r) for r in runs]
        self.drift = DriftKind(options.drift)
        if time_constant is None:
            time_constant = [max(10.0 * self.dt, (r.t[-1] - r.t[0]) / 100.0) for r in runs]
        self.time_constant = list(time_constant)
        self.basis = (
            [drift_basis(self.drift, r.t - r.t[0], tc) for r, tc in zip(runs, self.time_constant)]
            if self.drift is not DriftKind.NONE
            else []
        )

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        r = len(self.runs)
        lo = [1e-6, 0.5, 1.0] + [-1.0] * r
        hi = [np.inf, SIGMA_MAX, N_MAX] + [1.0] * r
        if self.options.fit_delay:
            lo.append(-self.options.max_delay_samples)
            hi.append(self.options.max_delay_samples)
        return np.array(lo), np.array(hi)

    def theta(self, seed: Seed) -> NDArray[np.float64]:
        w0 = seed.w0 if seed.w0 is not None else (0.0,) * len(self.runs)
        th = [seed.rho * self.span_v, seed.sigma, seed.n, *w0]
        if self.options.fit_delay:
            th.append(seed.delay / self.dt)
        lo, hi = self.bounds()
        return np.clip(np.array(th, dtype=np.float64), lo, hi)

    def seed(self, th: NDArray[np.float64]) -> Seed:
        rho, sigma, n, w0, delay = self.split(th)
        return Seed(rho, sigma, n, tuple(float(w) for w in w0), delay)

    def split(
        self, th: NDArray[np.float64]
    ) -> tuple[float, float, float, NDArray[np.float64], float]:
        r = len(self.runs)
        delay = float(th[3 + r]) * self.dt if self.options.fit_delay else 0.0
        return float(th[0]) / self.span_v, float(th[1]), float(th[2]), th[3 : 3 + r], delay

    def inputs(self, delay: float) -> list[NDArray[np.float64]]:
        """Each run's input as it acts on the output: v(t − delay), held before the start."""
        if delay == 0.0:
            return [r.input for r in self.runs]
        return [np.interp(r.t - delay, r.t, r.input) for r in self.runs]

    def states(
        self, th: NDArray[np.float64]
    ) -> tuple[list[NDArray[np.float64]], list[NDArray[np.float64]]]:
        rho, sigma, n, w0, delay = self.split(th)
        vs = self.inputs(delay)
        ws = [simulate_w(v, rho, sigma, n, float(np.clip(w, -1.0, 1.0))) for v, w in zip(vs, w0)]
        return vs, ws

    def matrix(
        self, vs: list[NDArray[np.float64]], ws: list[NDArray[np.float64]]
    ) -> NDArray[np.float64]:
        v, w = np.concatenate(vs), np.concatenate(ws)
        cols = [v ** (i + 1) for i in range(self.degree)] + [np.ones_like(v), w]
        offsets = np.cumsum([0] + self.sizes)
        for k, b in enumerate(self.basis):
            col = np.zeros_like(v)
            col[offsets[k] : offsets[k + 1]] = b
            cols.append(col)
        return np.column_stack(cols)

    def linear(
        self, th: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """(coefficients, design matrix, residual model − data) at θ."""
        A = self.matrix(*self.states(th))
        norms = np.linalg.norm(A, axis=0)
        norms[norms == 0] = 1.0
        c = np.linalg.lstsq(A / norms, self.y, rcond=None)[0] / norms
        return c, A, A @ c - self.y

    def residual(self, th: NDArray[np.float64]) -> NDArray[np.float64]:
        """Model minus data at θ, in units of the output span."""
        try:
            return self.linear(th)[2] / self.y_scale
        except (RuntimeError, ModelError):
            # a trial point the model cannot simulate: a large residual turns the step down
            return np.full_like(self.y, 1e3)


def _seeds(given: Sequence[Seed], span_v: float, runs: int) -> list[Seed]:
    """The given seeds, or the grid (ρ as ρ·span_v, σ, n, the same w(0) in every run)."""
    if given:
        return list(given)
    return [
        Seed(rho / span_v, sigma, n, (w0,) * runs)
        for rho in _GRID_RHO
        for sigma in _GRID_SIGMA
        for n in _GRID_N
        for w0 in _GRID_W0
    ]


def _solve(
    problem: _Problem, th0: NDArray[np.float64], max_nfev: int, tol: float
) -> LeastSquaresResult:
    lo, hi = problem.bounds()
    return least_squares(
        problem.residual,
        th0,
        jac="2-point",
        bounds=(lo, hi),
        method="trf",
        x_scale="jac",
        ftol=tol,
        xtol=tol,
        gtol=tol,
        max_nfev=max_nfev,
    )


#: tolerance and evaluations of the first pass from each start (the best is then polished)
_FIRST_PASS_TOL = 1e-8
_FIRST_PASS_NFEV = 40


def _optimum(
    problem: _Problem, seeds: Sequence[Seed], options: FitOptions, polish: bool = True
) -> tuple[LeastSquaresResult, int]:
    """Best least-squares optimum over the seeds: seeds are ranked by their cost, the best
    ``options.starts`` get a first pass (on every k-th sample of long runs), the best of those
    is polished on all samples to ``options.tolerance``.
    """
    total = sum(problem.sizes)
    if len(seeds) == 1:
        res = _solve(problem, problem.theta(seeds[0]), options.max_nfev, options.tolerance)
        return res, int(res.nfev)
    if total > GRID_SAMPLES:
        k = int(np.ceil(total / GRID_SAMPLES))
        coarse = _Problem(
            [Recording(r.t[::k], r.input[::k], r.output[::k], r.name) for r in problem.runs],
            options,
            problem.time_constant,
        )
        res, nfev = _optimum(coarse, seeds, options, polish=False)
        fine = _solve(
            problem, problem.theta(coarse.seed(res.x)), options.max_nfev, options.tolerance
        )
        return fine, nfev + int(fine.nfev)
    th_grid = [problem.theta(s) for s in seeds]
    costs = [float(np.sum(problem.residual(th) ** 2)) for th in th_grid]
    best: LeastSquaresResult | None = None
    nfev = 0
    for i in np.argsort(costs)[: max(1, options.starts)]:
        res = _solve(
            problem,
            th_grid[i],
            min(options.max_nfev, _FIRST_PASS_NFEV),
            max(options.tolerance, _FIRST_PASS_TOL),
        )
        nfev += int(res.nfev)
        if best is None or res.cost < best.cost:
            best = res
    assert best is not None  # max(1, starts) starts were solved
    if polish:
        best = _solve(problem, best.x, options.max_nfev, options.tolerance)
        nfev += int(best.nfev)
    return best, nfev


def _param_names(problem: _Problem) -> list[str]:
    names = [f"kappa_{i + 1}" for i in range(problem.degree)] + ["y0", "kappa_w"]
    names += [f"drift_{k}" for k in range(len(problem.basis))]
    names += ["rho", "sigma", "n"] + [f"w0_{k}" for k in range(len(problem.runs))]
    if problem.options.fit_delay:
        names.append("delay")
    return names


def _uncertainty(
    problem: _Problem,
    th: NDArray[np.float64],
    c: NDArray[np.float64],
    A: NDArray[np.float64],
    r: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Standard errors and covariance (of the column-normalised problem: for correlations) of
    all parameters (linear ones, then θ in physical units) from the full Jacobian at the
    optimum, scaled by the residual variance.
    """
    lo, hi = problem.bounds()
    cols = []
    for j in range(len(th)):
        h = 1e-6 * max(1.0, abs(th[j]))
        step = h if th[j] + h <= hi[j] else -h
        tj = th.copy()
        tj[j] += step
        cols.append((problem.matrix(*problem.states(tj)) @ c - A @ c) / step)
    J = np.column_stack([A] + cols)
    scale = np.ones(J.shape[1])
    scale[A.shape[1]] = 1.0 / problem.span_v  # ρ from ρ·span_v
    if problem.options.fit_delay:
        scale[-1] = problem.dt  # delay from delay/dt
    norms = np.linalg.norm(J, axis=0)
    norms[norms == 0] = 1.0
    Jn = J / norms
    dof = max(1, len(r) - J.shape[1])
    s2 = float(r @ r) / dof
    cov_n = np.linalg.pinv(Jn.T @ Jn) * s2
    std = np.sqrt(np.clip(np.diag(cov_n), 0.0, None)) / norms * scale
    return std, cov_n


def _values(
    problem: _Problem, th: NDArray[np.float64], c: NDArray[np.float64]
) -> NDArray[np.float64]:
    rho, sigma, n, w0, delay = problem.split(th)
    vals = [*c, rho, sigma, n, *w0]
    if problem.options.fit_delay:
        vals.append(delay)
    return np.array(vals)


def count_periods(rec: Recording) -> int:
    """Periods of the input: its rising mid-level crossings (any waveform)."""
    return len(upward_crossings(rec.t, rec.input))


def simulation_fit(
    runs: Sequence[Recording],
    options: FitOptions = FitOptions(),
    seeds: Sequence[Seed] = (),
    time_constant: Sequence[float] | None = None,
) -> SimulationFit:
    """Least-squares fit of (10.15) with w from (9.2) over the whole runs (no checks of
    fit quality; see :func:`check_simulation_fit`).
    """
    if int(options.degree) != options.degree or options.degree < 1:
        raise IdentificationError(
            f"polynomial degree N must be an integer >= 1, got {options.degree!r}"
        )
    problem = _Problem(runs, options, time_constant)
    if problem.span_v <= 0:
        raise IdentificationError("the input is constant: no excitation to identify from")
    res, nfev = _optimum(problem, _seeds(seeds, problem.span_v, len(runs)), options)
    th = res.x
    c, A, r = problem.linear(th)
    std, cov = _uncertainty(problem, th, c, A, r)
    names = _param_names(problem)
    values = _values(problem, th, c)
    rho, sigma, n, w0, delay = problem.split(th)
    deg = problem.degree
    kappa, y0, kappa_w = tuple(float(k) for k in c[:deg]), float(c[deg]), float(c[deg + 1])
    sign = 1
    if kappa_w < 0:  # odd model: w(−v; −w0) = −w(v; w0)
        sign, kappa_w, w0 = -1, -kappa_w, -w0
        values[deg + 1] = kappa_w
        values[names.index("w0_0") : names.index("w0_0") + len(w0)] = w0
        flip = np.array([-1.0 if k == "kappa_w" or k.startswith("w0_") else 1.0 for k in names])
        cov = cov * np.outer(flip, flip)
    if options.input_sign is not None and sign != options.input_sign:
        raise OrientationError(
            f"the loop orientation gives input_sign {sign:+d}, but {options.input_sign:+d} was "
            "requested: the loops run the other way"
        )
    params = BoucWenParameters(
        kappa=kappa, kappa_w=kappa_w, rho=rho, sigma=sigma, n=n, y0=y0, input_sign=sign
    )
    drifts = tuple(
        Drift(problem.drift, float(c[deg + 2 + k]), problem.time_constant[k])
        for k in range(len(problem.basis))
    ) or (None,) * len(runs)
    offsets = np.cumsum([0] + problem.sizes)
    model = tuple((A @ c)[offsets[k] : offsets[k + 1]] for k in range(len(runs)))
    std_d = {k: float(s) for k, s in zip(names, std)}
    rel = {k: float(s / abs(v)) if v != 0 else float("inf") for k, s, v in zip(names, std, values)}
    pairs = list(strong_correlations(names, cov, options.correlation_limit))
    return SimulationFit(
        parameters=params,
        w0=tuple(float(w) for w in w0),
        delay=delay,
        drift=drifts,
        rms_error=float(np.sqrt(np.mean(r**2))),
        std=std_d,
        relative_std=rel,
        correlations=pairs,
        model=model,
        nfev=nfev,
        status=str(res.message),
        diagnostics={"time_constant": problem.time_constant},
    )


def predict(fit: SimulationFit, runs: Sequence[Recording]) -> list[NDArray[np.float64]]:
    """The fitted model's output over ``runs`` (same w0, delay and drift as fitted)."""
    p = fit.parameters
    out = []
    for rec, w0, drift in zip(runs, fit.w0, fit.drift):
        v = rec.input if fit.delay == 0.0 else np.interp(rec.t - fit.delay, rec.t, rec.input)
        y = (
            polynomial(p.kappa, v)
            + p.kappa_w * simulate_w(p.input_sign * v, p.rho, p.sigma, p.n, w0)
            + p.y0
        )
        if drift is not None:
            y = y + drift.evaluate(rec.t - rec.t[0])
        out.append(y)
    return out


def holdout_check(
    runs: Sequence[Recording], options: FitOptions, seeds: Sequence[Seed] = ()
) -> tuple[SimulationFit, dict[str, float]] | None:
    """Fit on the first (1 − holdout) of every run, predict the rest: (fit, figures), or
    None when a run holds too few periods (or holdout is 0).
    """
    if not options.holdout > 0 or any(
        count_periods(r) <= options.min_holdout_periods for r in runs
    ):
        return None
    cut = [int(round(len(r) * (1.0 - options.holdout))) for r in runs]
    train = [r.slice(0, k) for r, k in zip(runs, cut)]
    time_constant = [
        max(10.0 * float(np.median(np.diff(r.t))), (r.t[-1] - r.t[0]) / 100.0) for r in runs
    ]
    fit = simulation_fit(train, options, seeds, time_constant)
    pred = predict(fit, runs)
    err = np.concatenate([p[k:] - r.output[k:] for p, r, k in zip(pred, runs, cut)])
    span = max(float(np.ptp(r.output)) for r in runs)
    rms = float(np.sqrt(np.mean(err**2)))
    return fit, {
        "holdout_fraction": float(options.holdout),
        "holdout_rms": rms,
        "holdout_rms_percent": 100.0 * rms / span,
        "train_rms": fit.rms_error,
        "train_rms_percent": 100.0 * fit.rms_error / span,
    }


def seed_of(fit: SimulationFit) -> Seed:
    """A seed from an earlier fit (e.g. the held-out one), in the κw > 0 orientation."""
    p = fit.parameters
    return Seed(
        rho=p.rho, sigma=p.sigma, n=p.n, w0=tuple(p.input_sign * w for w in fit.w0), delay=fit.delay
    )


def seed_from(params: BoucWenParameters, w0: Sequence[float]) -> Seed:
    """A seed from known parameters (the analytic method) with w(0) of each run."""
    return Seed(
        rho=params.rho,
        sigma=params.sigma,
        n=params.n,
        w0=tuple(params.input_sign * float(np.clip(w, -1, 1)) for w in w0),
    )


def noise_level(runs: Sequence[Recording]) -> float:
    """White-noise std of the outputs (third differences, pooled)."""
    return float(np.sqrt(np.mean([noise_std(r.output) ** 2 for r in runs])))
