"""Choice of method: the analytic one (ch. 9-10, two T-wave runs at their limit cycle) or the
fit by simulation error (any runs, see simfit.py), and the fit's result as an
:class:`IdentificationResult`.

auto: the analytic method with its refinement when its preconditions hold (two wave-periodic
runs x(t), x(t)+q whose limit cycle is reached; a bad fit there is refused as such), held
against the fit started from it: when the two disagree beyond their standard errors, the one
with the smaller residual is returned with a warning naming both; the fit otherwise. fit: the
fit, seeded by whatever the analytic method produced. The analytic method assumes no lag
between input and output: a lag the input's corners show (:mod:`.lag`) is taken off the
output first (and reported); the fit starts its delay from it.
"""

from __future__ import annotations

import math
from dataclasses import replace
from enum import StrEnum
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from piezo_stage.model.bouc_wen import BoucWenParameters, model_output

from .analytic import initial_w
from .errors import (
    BadFitError,
    DataFormatError,
    IdentificationError,
    NonFiniteDataError,
    SaturatedOutputError,
)
from .lag import LAG_TOLERANCE, LagEstimate, refine_lag, runs_lag, shift_output
from .pipeline import IdentifyOptions, check_fit, correlation_warning, identify
from .recording import Recording, check_recording
from .refine import HYSTERETIC
from .result import IdentificationResult
from .simfit import (
    FitOptions,
    Seed,
    SimulationFit,
    count_periods,
    holdout_check,
    noise_level,
    predict,
    seed_from,
    seed_of,
    simulation_fit,
)


class Method(StrEnum):
    """Identification method: analytic, fit by simulation error, or auto (module docstring)."""

    ANALYTIC = "analytic"
    FIT = "fit"
    AUTO = "auto"


#: the data are unusable by either method: reported as they are, no fallback
_DATA_ERRORS = (NonFiniteDataError, SaturatedOutputError, DataFormatError)


def identify_runs(
    runs: Sequence[Recording],
    options: IdentifyOptions | None = None,
    method: Method | str = Method.AUTO,
    fit: FitOptions | None = None,
) -> IdentificationResult:
    """Identify from one or more runs with ``method`` (see the module docstring)."""
    options = IdentifyOptions() if options is None else options
    fit = FitOptions() if fit is None else fit
    method = Method(method)
    try:
        return _identify(list(runs), options, method, fit)
    except ArithmeticError as exc:  # overflow or division by zero on extreme data
        raise IdentificationError(
            f"numerical failure ({type(exc).__name__}: {exc}): the data are outside the "
            "range the method handles (check units and scaling)"
        ) from exc


def _analytic(
    runs: list[Recording], options: IdentifyOptions, fit: FitOptions, lag: LagEstimate | None
) -> IdentificationResult:
    """The analytic method (with its refinement), which assumes the output answers the input
    at once: on the runs with the lag the corners show taken off (refined to the model's least
    residual, :func:`~.lag.refine_lag`, its uncertainty added to the standard errors), with the
    lag reported, and the fit's held-out check (:func:`analytic_holdout`).
    """
    given = options.lag_samples is not None
    lagging = lag is not None and (given or abs(lag.samples) >= LAG_TOLERANCE)
    slopes: dict[str, float] = {}
    if lagging:
        assert lag is not None
        if not given:
            lag, slopes = _refined_lag(runs, options, lag)
        runs = [shift_output(r, lag.seconds) for r in runs]
    result = identify(runs[0], runs[1], options)
    warnings, diagnostics = list(result.warnings), dict(result.diagnostics)
    if lagging:
        assert lag is not None
        if not given:
            warnings.append(
                f"the output lags the input by {lag.samples:.2f} ± {lag.spread:.2f} "
                f"samples ({1e3 * lag.seconds:.3g} ms, at the input's {lag.corners} "
                "corners and the model's least residual): the analytic method ran on "
                "the output shifted back by it"
            )
        diagnostics.update(lag_samples=lag.samples, lag_spread=lag.spread)
        std = dict(diagnostics.get("std") or {})
        for key, slope in slopes.items():  # the lag's uncertainty, propagated
            if key in std:
                std[key] = float(np.hypot(std[key], slope * lag.spread))
        diagnostics["std"] = std
    figures = analytic_holdout(runs, options, fit)
    if figures is not None:
        diagnostics.update(figures)
        if figures["holdout_rms"] > 2.0 * figures["train_rms"]:
            warnings.append(
                f"the model predicts the held-out {100 * figures['holdout_fraction']:.0f} % "
                f"worse (RMS {figures['holdout_rms_percent']:.3g} % of span) than it fits the "
                f"rest ({figures['train_rms_percent']:.3g} %): it may not generalise"
            )
    return replace(
        result,
        delay=lag.seconds if lagging and lag is not None else result.delay,
        warnings=tuple(warnings),
        diagnostics=diagnostics,
    )


def _refined_lag(
    runs: list[Recording], options: IdentifyOptions, lag: LagEstimate
) -> tuple[LagEstimate, dict[str, float]]:
    """The lag at the analytic model's least residual (:func:`~.lag.refine_lag`), and each
    hysteretic parameter's slope against it [per sample] (central difference over one standard
    error of the lag, at least 0.02 sample).
    """
    dt = lag.seconds / lag.samples

    def identified(samples: float) -> tuple[list[Recording], IdentificationResult]:
        shifted = [shift_output(r, samples * dt) for r in runs]
        return shifted, identify(shifted[0], shifted[1], options)

    def residual(samples: float) -> tuple[float, int]:
        try:
            shifted, result = identified(samples)
        except IdentificationError:
            return math.inf, 0
        errors = np.concatenate(
            [_model_errors(result.parameters, r)[_settled(r) :] for r in shifted]
        )
        return float(errors @ errors), int(errors.size)

    refined = refine_lag(lag, residual)
    if refined is lag:
        return lag, {}
    h = max(refined.spread, 0.02)
    try:
        up = identified(refined.samples + h)[1].parameters
        down = identified(refined.samples - h)[1].parameters
    except IdentificationError:
        return refined, {}
    return refined, {key: (getattr(up, key) - getattr(down, key)) / (2.0 * h) for key in HYSTERETIC}


def given_lag(runs: Sequence[Recording], samples: float) -> LagEstimate:
    """A lag the caller knows (``IdentifyOptions.lag_samples``), in the runs' sample period."""
    dt = float(np.median(np.diff(runs[0].t))) if len(runs[0].t) > 1 else math.nan
    return LagEstimate(float(samples), 0.0, 0, float(samples) * dt)


def _settled(rec: Recording) -> int:
    """Samples of a run's first period (it settles: the model's w(0) of (10.18) is a guess)."""
    periods = count_periods(rec)
    return len(rec) // (periods + 1) if periods >= 1 else 0


def _model_errors(p: BoucWenParameters, rec: Recording) -> NDArray[np.float64]:
    """The model's output error over ``rec``, run from w(0) of (10.18) at its start."""
    w0 = float(
        np.clip(
            initial_w(p.kappa, p.kappa_w, p.y0, float(rec.input[0]), float(rec.output[0])),
            -1.0,
            1.0,
        )
    )
    return model_output(p, np.asarray(rec.input), w0=w0) - np.asarray(rec.output)


def analytic_holdout(
    runs: Sequence[Recording], options: IdentifyOptions, fit: FitOptions
) -> dict[str, float] | None:
    """The fit's held-out check for the analytic method: identified from the first
    (1 − holdout) of both runs (whole periods of it), the model run over each whole run from
    w(0) of (10.18) at its start; the RMS of its error there (train) and on the rest (held
    out). None when a run holds too few periods or the shorter runs cannot be identified.
    """
    if not fit.holdout > 0 or any(count_periods(r) <= fit.min_holdout_periods for r in runs):
        return None
    cut = [int(round(len(r) * (1.0 - fit.holdout))) for r in runs]
    try:
        p = identify(runs[0].slice(0, cut[0]), runs[1].slice(0, cut[1]), options).parameters
    except IdentificationError:
        return None
    train, held = [], []
    for r, k in zip(runs, cut):
        err = _model_errors(p, r)
        train.append(err[:k])
        held.append(err[k:])
    span = max(float(np.ptp(r.output)) for r in runs)
    rms_train = float(np.sqrt(np.mean(np.concatenate(train) ** 2)))
    rms_held = float(np.sqrt(np.mean(np.concatenate(held) ** 2)))
    return {
        "holdout_fraction": float(fit.holdout),
        "holdout_rms": rms_held,
        "holdout_rms_percent": 100.0 * rms_held / span,
        "train_rms": rms_train,
        "train_rms_percent": 100.0 * rms_train / span,
    }


#: standard errors (combined) beyond which the analytic method and the fit disagree
DISAGREEMENT = 3.0
#: and the relative difference below which they agree anyway (noiseless data have standard
#: errors of 1e-10 that rounding alone exceeds)
AGREEMENT_FLOOR = 1e-3
#: samples per run the cross-checking fit sees (a loop's shape needs far fewer than a 20 kHz
#: data recorder records; the fit's cost grows with them)
CROSS_CHECK_SAMPLES = 20_000


def disagreement(a: IdentificationResult, b: IdentificationResult) -> list[str]:
    """The hysteretic parameters on which ``a`` and ``b`` differ by more than DISAGREEMENT
    combined standard errors and AGREEMENT_FLOOR of the value, as 'name a ± sa vs b ± sb'.
    """
    sa, sb = a.diagnostics.get("std") or {}, b.diagnostics.get("std") or {}
    out = []
    for key in HYSTERETIC:
        va, vb = getattr(a.parameters, key), getattr(b.parameters, key)
        ea, eb = sa.get(key, float("nan")), sb.get(key, float("nan"))
        sigma = float(np.hypot(ea, eb))
        if np.isfinite(sigma) and abs(va - vb) > max(
            DISAGREEMENT * sigma, AGREEMENT_FLOOR * abs(va)
        ):
            out.append(f"{key} {va:.4g} ± {ea:.2g} vs {vb:.4g} ± {eb:.2g}")
    return out


def _cross_checked(
    analytic: IdentificationResult,
    runs: list[Recording],
    options: IdentifyOptions,
    fit: FitOptions,
    lag: LagEstimate | None,
) -> IdentificationResult:
    """For auto: the analytic result held against the fit by simulation error from it (which also
    models a delay and a drift): the analytic result when they agree within their standard
    errors, else the one with the smaller residual, with a warning naming both (never one
    confidently wrong). The fit sees each run thinned to :data:`CROSS_CHECK_SAMPLES`: a check
    needs the shape of the loop, not every sample of a 20 kHz record.
    """
    try:
        thinned = [r.thinned(CROSS_CHECK_SAMPLES) for r in runs]
        fitted = _fit(thinned, options, fit, analytic, "", lag, shown=runs)
    except IdentificationError as exc:  # the fit cannot check it: say so, keep the analytic
        note = f"the fit by simulation error could not cross-check the analytic result: {exc}"
        return replace(analytic, warnings=(*analytic.warnings, note))
    differ = disagreement(analytic, fitted)
    if not differ:
        return replace(
            analytic, diagnostics={**analytic.diagnostics, "cross_check_rms": fitted.rms_error}
        )
    keep = fitted if fitted.rms_error < analytic.rms_error else analytic
    note = (
        f"the analytic method and the fit by simulation error disagree beyond "
        f"{DISAGREEMENT:g} standard errors ({'; '.join(differ)}; analytic vs fit; residual "
        f"RMS {analytic.rms_error:.3g} vs {fitted.rms_error:.3g}): the {keep.method} "
        "result, whose model follows the data closer, is returned"
    )
    return replace(keep, warnings=(*keep.warnings, note))


def _identify(
    runs: list[Recording], options: IdentifyOptions, method: Method, fit: FitOptions
) -> IdentificationResult:
    if not runs:
        raise IdentificationError("no runs to identify from")
    for rec in runs:
        check_recording(rec, clip_fraction=options.cycle.clip_fraction)
    lag = runs_lag(runs) if options.lag_samples is None else given_lag(runs, options.lag_samples)
    if method is Method.ANALYTIC:
        if len(runs) != 2:
            raise IdentificationError(
                f"the analytic method needs exactly two runs (x(t) and x(t)+q), got "
                f"{len(runs)}; --method fit identifies from any runs"
            )
        return _analytic(runs, options, fit, lag)
    analytic: IdentificationResult | None = None
    problem = f"{len(runs)} run(s): the analytic method needs two (x(t) and x(t)+q)"
    if len(runs) == 2:
        try:
            analytic = _analytic(runs, options, fit, lag)
            if method is Method.AUTO:
                return _cross_checked(analytic, runs, options, fit, lag)
            problem = ""
        except _DATA_ERRORS:
            raise
        except BadFitError as exc:
            if method is Method.AUTO:  # its preconditions hold: its verdict stands
                raise
            problem, analytic = str(exc), exc.result
        except IdentificationError as exc:
            problem = str(exc)
    return _fit(runs, options, fit, analytic, problem, lag)


def _fit(
    runs: list[Recording],
    options: IdentifyOptions,
    fit: FitOptions,
    analytic: IdentificationResult | None,
    problem: str,
    lag: LagEstimate | None,
    shown: Sequence[Recording] | None = None,
) -> IdentificationResult:
    """The fit by simulation error, started from the analytic result and the lag if any; its
    model output over ``shown`` (default: the runs fitted).
    """
    fit = replace(fit, degree=options.degree, input_sign=options.input_sign)
    seeds: list[Seed] = []
    if analytic is not None:
        p = analytic.parameters
        seeds.append(
            replace(
                seed_from(
                    p,
                    [
                        initial_w(p.kappa, p.kappa_w, p.y0, float(r.input[0]), float(r.output[0]))
                        for r in runs
                    ],
                ),
                delay=0.0 if lag is None else lag.seconds,
            )
        )
    return fit_runs(
        runs,
        fit,
        seeds,
        analytic=analytic,
        analytic_problem=problem,
        input_name=options.input_name,
        output_name=options.output_name,
        shown=shown,
    )


def _warnings(final: SimulationFit, figures: dict[str, float], fit: FitOptions) -> list[str]:
    out = [correlation_warning(*c) for c in final.correlations]
    loose = [
        f"{k} ±{100 * v:.2g} %"
        for k, v in final.relative_std.items()
        if k in HYSTERETIC and not v <= fit.warn_rel_std
    ]
    if loose:
        out.append(
            f"loosely determined: {', '.join(loose)} (standard errors assume white "
            "noise; model error makes them optimistic)"
        )
    if figures and figures["holdout_rms"] > 2.0 * figures["train_rms"]:
        out.append(
            f"the model predicts the held-out {100 * figures['holdout_fraction']:.0f} % "
            f"worse (RMS {figures['holdout_rms_percent']:.3g} % of span) than it fits "
            f"the rest ({figures['train_rms_percent']:.3g} %): it may not generalise"
        )
    return out


def fit_runs(
    runs: Sequence[Recording],
    fit: FitOptions,
    seeds: Sequence[Seed] = (),
    *,
    analytic: IdentificationResult | None = None,
    analytic_problem: str = "",
    input_name: str = "voltage",
    output_name: str = "displacement",
    shown: Sequence[Recording] | None = None,
) -> IdentificationResult:
    """The fit by simulation error with its held-out check, as an IdentificationResult
    (refused with :class:`BadFitError` when the data do not support it); ``fitted`` holds the
    model's output over ``shown`` (default: ``runs``; the runs a thinned fit was thinned from).
    """
    figures: dict[str, float] = {}
    check = holdout_check(runs, fit, seeds)
    if check is not None:
        partial, figures = check
        seeds = [seed_of(partial), *seeds]
    final = simulation_fit(runs, fit, seeds)
    span = max(float(np.ptp(r.output)) for r in runs)
    diagnostics = {
        "method": "fit",
        "std": final.std,
        "relative_std": final.relative_std,
        "correlations": [list(c) for c in final.correlations],
        "nfev": final.nfev,
        "solver": final.status,
        "noise_output": noise_level(runs),
        "output_span": span,
        "w0_runs": list(final.w0),
        "runs": len(runs),
        **figures,
        "drift_runs": [None if d is None else d.coefficient for d in final.drift],
        #: how far the drift moves each run's output from its start to its end
        "drift_change": [
            None if d is None else float(d.evaluate(np.array([r.t[-1] - r.t[0]]))[0])
            for d, r in zip(final.drift, runs)
        ],
    }
    if analytic_problem:
        diagnostics["analytic_problem"] = analytic_problem
    if analytic is not None:
        diagnostics["q"] = analytic.diagnostics.get("q")
    result = IdentificationResult(
        parameters=final.parameters,
        analytic=None if analytic is None else analytic.parameters,
        rms_error=final.rms_error,
        analytic_rms_error=float("nan") if analytic is None else analytic.rms_error,
        samples=sum(len(r) for r in runs),
        w0=final.w0[0],
        refined=True,
        input_name=input_name,
        output_name=output_name,
        diagnostics=diagnostics,
        method="fit",
        delay=final.delay,
        drift=final.drift[0],
        warnings=tuple(_warnings(final, figures, fit)),
        fitted=final.model if shown is None else tuple(predict(final, shown)),
    )
    check_fit(result, fit)
    return result
