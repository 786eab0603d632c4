"""The whole method: two runs x(t), x(t)+q in, identified (modified) Bouc-Wen model out.

Steps 1-2 (9.1.3): steady cycles of both runs (cycles.py); orientation (input_sign, §10.3.2);
polynomial part by G = Q·K (10.7-10.13); y0 (10.17); Steps 4-10 by Table 10.2 (analytic.py);
refinement on the whole cycles (refine.py); w(0) by (10.18).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np
from numpy.typing import NDArray

from piezo_stage.model.bouc_wen import BoucWenParameters
from piezo_stage.model.errors import ModelError

from .analytic import (
    DerivativeOptions,
    DesignPoints,
    HystereticEstimate,
    hysteretic_estimate,
    initial_w,
)
from .cycles import CycleOptions, SteadyCycle, extract_cycle, smooth_input, split_branches
from .errors import AnalyticEstimateError, BadFitError, IdentificationError, RefinementError
from .orientation import Orientation, detect_orientation, resolve_orientation
from .polynomial import PolynomialFit, fit_polynomial, offset_between, offset_y0
from .recording import Recording
from .refine import (
    HYSTERETIC,
    CyclePath,
    RefinedFit,
    RefineOptions,
    cycle_path,
    feasible_start,
    refine,
    residuals,
)
from .result import IdentificationResult

if TYPE_CHECKING:
    from .simfit import FitOptions


@dataclass(frozen=True)
class IdentifyOptions:
    """Options of the analytic method (:func:`identify`, :func:`identify_cycles`), step by step."""

    degree: int = 1  #: N of (10.4); 1 is the plain Bouc-Wen κx·x
    refine: bool = True
    input_sign: int | None = None  #: None: detect from the loop orientation
    cycle: CycleOptions = field(default_factory=CycleOptions)
    design: DesignPoints = field(default_factory=DesignPoints)
    derivative: DerivativeOptions = field(default_factory=DerivativeOptions)
    refinement: RefineOptions = field(default_factory=RefineOptions)
    min_loop_width: float = 1e-3  #: least mean loop width, fraction of output span
    span_tolerance: float = 0.02  #: the runs' input spans must agree this well
    input_name: str = "voltage"
    output_name: str = "displacement"
    #: the output's lag behind the input [samples], given: the runs are identified with the
    #: input delayed by it (None: timed at the input's corners when it is clean, :mod:`.lag`)
    lag_samples: float | None = None


def identify(
    run_a: Recording, run_b: Recording, options: IdentifyOptions = IdentifyOptions()
) -> IdentificationResult:
    """Identify from two recorded runs (any phase, transients included)."""
    cycles = (extract_cycle(run_a, options.cycle), extract_cycle(run_b, options.cycle))
    result = identify_cycles(cycles[0], cycles[1], options)
    w0 = initial_w(
        result.parameters.kappa,
        result.parameters.kappa_w,
        result.parameters.y0,
        float(run_a.input[0]),
        float(run_a.output[0]),
    )
    return replace(result, w0=w0)


def _check_options(options: IdentifyOptions) -> None:
    if int(options.degree) != options.degree or options.degree < 1:
        raise IdentificationError(
            f"polynomial degree N must be an integer >= 1, got {options.degree!r}"
        )
    if options.input_sign not in (None, 1, -1):
        raise IdentificationError(f"input_sign must be +1, -1 or None, got {options.input_sign!r}")


def identify_cycles(
    cycle_a: SteadyCycle, cycle_b: SteadyCycle, options: IdentifyOptions = IdentifyOptions()
) -> IdentificationResult:
    """Identify from the two steady cycles (run B = run A's input + q)."""
    _check_options(options)
    cycles = (cycle_a, cycle_b)
    smooth = [smooth_input(c) for c in cycles]
    orientations = [
        detect_orientation(
            c, v, min_loop_width=options.min_loop_width, noise_factor=options.cycle.noise_factor
        )
        for c, v in zip(cycles, smooth)
    ]
    sign = resolve_orientation(orientations, options.input_sign)
    branches = [split_branches(c, sign, v) for c, v in zip(cycles, smooth)]
    # §10.2.2: polynomial part from the difference of the two cycles, then y0 (10.17)
    q = offset_between(branches[0], branches[1], span_tolerance=options.span_tolerance)
    poly = fit_polynomial(branches[0], branches[1], options.degree, q)
    y0 = offset_y0(branches, poly.kappa)
    # §10.2.3 / 9.1.3 Steps 4-10 on run A's loading branch
    hyst = hysteretic_estimate(
        branches[0][0], poly.kappa, y0, cycle_a.noise_output, options.design, options.derivative
    )
    paths = [cycle_path(c, v, sign) for c, v in zip(cycles, smooth)]
    analytic, analytic_problem = _analytic_parameters(poly.kappa, y0, hyst, sign)
    diagnostics = _diagnostics(cycles, orientations, poly, y0, hyst, sign)
    analytic_rms, analytic_problem = _analytic_rms(
        analytic, paths, analytic_problem, options.refine
    )
    correlations: tuple[tuple[str, str, float], ...] = ()
    if options.refine:
        start = (
            analytic
            if analytic is not None
            else _feasible_start(poly.kappa, y0, hyst, sign, options.refinement.n_max)
        )
        fit = refine(start, paths, options.refinement)
        final, rms, correlations = fit.parameters, fit.rms_error, fit.correlations
        diagnostics.update(_refinement_diagnostics(fit))
    else:
        if analytic is None:
            raise AnalyticEstimateError(
                f"the analytic estimate is outside class I ({analytic_problem}); "
                "run with refinement to fit the data within the class-I bounds"
            )
        final, rms = analytic, analytic_rms
    if analytic_problem:
        diagnostics["analytic_problem"] = analytic_problem
    result = IdentificationResult(
        parameters=final,
        analytic=analytic,
        rms_error=rms,
        analytic_rms_error=analytic_rms,
        samples=cycle_a.raw_samples + cycle_b.raw_samples,
        w0=initial_w(
            final.kappa, final.kappa_w, final.y0, float(cycle_a.input[0]), float(cycle_a.output[0])
        ),
        refined=options.refine,
        input_name=options.input_name,
        output_name=options.output_name,
        diagnostics=diagnostics,
        cycles=cycles,
        warnings=tuple(correlation_warning(*c) for c in correlations),
    )
    check_fit(result, options.refinement)
    return result


def _diagnostics(
    cycles: tuple[SteadyCycle, SteadyCycle],
    orientations: list[Orientation],
    poly: PolynomialFit,
    y0: float,
    h: HystereticEstimate,
    sign: int,
) -> dict[str, Any]:
    """What the analytic steps saw: cycles, polynomial part (10.7), Table 10.2 raw values."""
    return {
        "q": poly.q,
        "g": [float(v) for v in poly.g],
        "difference_residual_rms": poly.residual_rms,
        "periods": [c.period for c in cycles],
        "steady_periods": [c.periods for c in cycles],
        "noise_output": float(np.sqrt(np.mean([c.noise_output**2 for c in cycles]))),
        "output_span": max(c.output_span for c in cycles),
        "loop_width": [o.mean_gap for o in orientations],
        "a": h.a,
        "b": h.b,
        "a_uncorrected": h.a_uncorrected,
        "x_star": h.x_star,
        "x_star1": h.x1,
        "x_star2": h.x2,
        "x_star3": h.x3,
        "analytic_raw": {
            "kappa": [float(k) for k in poly.kappa],
            "y0": y0,
            "kappa_w": h.kappa_w,
            "rho": h.rho,
            "sigma": h.sigma,
            "n": h.n,
            "input_sign": sign,
        },
    }


def _analytic_rms(
    analytic: BoucWenParameters | None, paths: list[CyclePath], problem: str, refining: bool
) -> tuple[float, str]:
    """RMS residual of the analytic estimate on the cycles (NaN without one) and the problem.

    A simulation failure becomes the problem when the refinement follows, else it is raised.
    """
    if analytic is None:
        return float("nan"), problem
    try:
        return float(np.sqrt(np.mean(residuals(analytic, paths) ** 2))), problem
    except RefinementError as exc:
        if not refining:
            raise
        return float("nan"), str(exc)


def _feasible_start(
    kappa: NDArray[np.float64], y0: float, h: HystereticEstimate, sign: int, n_max: float
) -> BoucWenParameters:
    """The refinement's start when the analytic estimate is outside class I."""
    return feasible_start(kappa, y0, h.kappa_w, h.rho, h.sigma, h.n, sign, n_max)


def _refinement_diagnostics(fit: RefinedFit) -> dict[str, Any]:
    """What the refinement reports: standard errors (relative and absolute), solver figures."""
    return {
        "relative_std": fit.relative_std,
        "nfev": fit.nfev,
        "solver": fit.status,
        "rejected_trials": fit.rejected_trials,
        "std": _absolute_std(fit.parameters, fit.relative_std),
        "correlations": [list(c) for c in fit.correlations],
    }


def _absolute_std(params: BoucWenParameters, relative_std: Mapping[str, float]) -> dict[str, float]:
    """Standard errors in the parameters' units from relative ones (finite ones only)."""
    values = dict(
        zip([f"kappa_{i + 1}" for i in range(len(params.kappa))], params.kappa),
        y0=params.y0,
        kappa_w=params.kappa_w,
        rho=params.rho,
        sigma=params.sigma,
        n=params.n,
    )
    return {
        k: rel * abs(values[k])
        for k, rel in relative_std.items()
        if k in values and np.isfinite(rel)
    }


def correlation_warning(a: str, b: str, c: float) -> str:
    """The warning for two strongly correlated parameters (both methods)."""
    return (
        f"{a} and {b} are strongly correlated ({c:+.5f}): this record separates them "
        "poorly (see their standard errors)"
    )


def _analytic_parameters(
    kappa: NDArray[np.float64], y0: float, h: HystereticEstimate, sign: int
) -> tuple[BoucWenParameters | None, str]:
    """The analytic estimate as validated parameters, or (None, reason) outside class I."""
    if not (h.kappa_w > 0 and h.rho > 0):
        raise AnalyticEstimateError(
            f"Table 10.2 gives κw = {h.kappa_w:.3g}, ρ = {h.rho:.3g}; both must be positive"
        )
    try:
        params = BoucWenParameters(
            kappa=tuple(float(k) for k in kappa),
            kappa_w=h.kappa_w,
            rho=h.rho,
            sigma=h.sigma,
            n=h.n,
            y0=float(y0),
            input_sign=sign,
        )
        params.validate()
    except ModelError as exc:
        return None, str(exc)
    return params, ""


def check_fit(result: IdentificationResult, options: RefineOptions | FitOptions) -> None:
    """Reject a fit the data do not support: residual above both the noise allowance and the
    span allowance, or a hysteretic parameter with a large relative standard error (the limits
    of either method's options; the figures from ``result.diagnostics``).
    """
    d = result.diagnostics
    span, noise = d["output_span"], d["noise_output"]
    allowed = max(options.noise_factor * noise, options.max_rms_fraction * span)
    if result.rms_error > allowed:
        raise BadFitError(
            f"bad fit: residual RMS {result.rms_error:.4g} "
            f"({100 * result.rms_error / span:.3g} % of "
            f"the output span) exceeds both {options.noise_factor:g}x the noise level "
            f"({noise:.3g}) and {100 * options.max_rms_fraction:g} % of the span: the model "
            "(degree N, Bouc-Wen structure) does not describe these data",
            result,
        )
    rel = d.get("relative_std", {})
    loose = {k: v for k, v in rel.items() if k in HYSTERETIC and not v <= options.max_rel_std}
    if loose:
        text = ", ".join(f"{k} ±{100 * v:.2g} %" for k, v in loose.items())
        raise BadFitError(
            f"bad fit: parameters not determined by the data ({text}, limit "
            f"{100 * options.max_rel_std:g} %): excite a wider loop or reduce the noise",
            result,
        )
