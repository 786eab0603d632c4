"""Identification bench: accuracy and speed of the analytic method and its refinement.

Prints, for the thesis's ch. 9 example (κx=2, κw=2, ρ=1, σ=3, n=1.5; triangle ±0.2, T=1,
q=0.1) the max relative parameter error of the analytic (Table 10.2) estimate and of the
refined fit, at 1000/2000/10000 samples per loading branch, beside the thesis's own result;
the same with white output noise of 1e-4 and 1e-3 of the span (median and worst of 20 seeds,
with the number of fits reported bad); the ch. 10 patch with N = 2; the time per
identification of a 10k-sample cycle pair; and a baseline: plain least squares from a generic
start, run side by side, to show what the analytic start buys.

Fit by simulation error, beside the analytic method and a plain scipy fit of all
parameters from a generic start: one noiseless run from w(0) = 0; two runs before the limit
cycle; the ch. 9 example over 24 periods (steady-state averaging bias); one run with 1e-3 noise
over 20 seeds with the coverage of the standard errors; the real P-885 record (fit on the
first 60 %, held-out RMS on the last 40 %); the time of a fit on a 10k-sample run.

Run:  python bench/identification.py [section ...]   (sections: noiseless patch timing noisy
      one_run one_run_patch two_runs ch9_24 noisy_one_run p885 fit_timing lag threads; default all,
      a few minutes)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
from _targets import check, exit_code

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from piezo_stage.identification.analytic import DerivativeOptions
from piezo_stage.identification.cycles import CycleOptions, smooth_input
from piezo_stage.identification.errors import IdentificationError
from piezo_stage.identification.io import load_csv
from piezo_stage.identification.methods import identify_runs
from piezo_stage.identification.pipeline import IdentifyOptions, identify
from piezo_stage.identification.recording import Recording
from piezo_stage.identification.refine import RefineOptions, cycle_path, refine
from piezo_stage.identification.simfit import FitOptions, holdout_check
from piezo_stage.identification.synthetic import (
    CH9_EXAMPLE,
    CH10_PATCH,
    triangle_pair,
    triangle_run,
)
from piezo_stage.model.bouc_wen import BoucWenParameters, model_output
from piezo_stage.model.parameter_set import DriftKind

P885 = Path(__file__).resolve().parents[1] / "test" / "data" / "p885" / "p885_raised_cosine.csv"

CH9 = BoucWenParameters(**CH9_EXAMPLE)
PATCH = BoucWenParameters(**CH10_PATCH)
THESIS_CH9 = BoucWenParameters(kappa=(2.0,), kappa_w=2.0059, rho=0.9971, sigma=2.9728, n=1.4954)
SEEDS = 20


def max_rel_error(found: BoucWenParameters | None, true: BoucWenParameters) -> float:
    if found is None:
        return float("nan")
    errs = [abs(getattr(found, k) / getattr(true, k) - 1) for k in ("kappa_w", "rho", "sigma", "n")]
    errs += [abs(a / b - 1) for a, b in zip(found.kappa, true.kappa)]
    return max(errs)


def ch9_runs(samples_per_branch: int, noise: float = 0.0, seed: int = 0):
    return triangle_pair(
        CH9,
        -0.2,
        0.2,
        0.1,
        samples_per_branch=samples_per_branch,
        periods=3,
        noise=noise,
        rng=np.random.default_rng(seed),
    )


def generic_start(result) -> BoucWenParameters:
    """What one would start a plain least-squares fit from without the analytic method:
    a straight line through the data, κw a tenth of the output span, ρ = 1/span, σ = 1, n = 2."""
    v = np.concatenate([c.input for c in result.cycles])
    y = np.concatenate([c.output for c in result.cycles])
    slope, icpt = np.polyfit(v, y, 1)
    degree = len(result.parameters.kappa)
    return BoucWenParameters(
        kappa=(slope,) + (0.0,) * (degree - 1),
        y0=icpt,
        kappa_w=0.1 * np.ptp(y),
        rho=1.0 / np.ptp(v),
        sigma=1.0,
        n=2.0,
        input_sign=result.parameters.input_sign,
    )


def baseline(result, true: BoucWenParameters) -> tuple[float, int, float]:
    """(error, evaluations, seconds) of least squares from the generic start."""
    sign = result.parameters.input_sign
    paths = [cycle_path(c, smooth_input(c), sign) for c in result.cycles]
    t0 = time.perf_counter()
    try:
        fit = refine(generic_start(result), paths, RefineOptions())
    except IdentificationError as exc:
        print(f"    (baseline failed: {exc})")
        return float("nan"), 0, time.perf_counter() - t0
    return max_rel_error(fit.parameters, true), fit.nfev, time.perf_counter() - t0


def section(title: str) -> None:
    print(f"\n== {title}")


def noiseless() -> None:
    section("ch. 9 example, noiseless: max relative parameter error")
    print(
        f"{'samples/branch':>14}  {'analytic':>10}  {'refined':>10}  {'baseline LSQ':>12}  "
        f"{'(nfev)':>7}"
    )
    at_2000 = (float("nan"), float("nan"))
    for spb in (1000, 2000, 10000):
        result = identify(*ch9_runs(spb))
        err_b, nfev_b, _ = baseline(result, CH9)
        analytic = max_rel_error(result.analytic, CH9)
        refined = max_rel_error(result.parameters, CH9)
        print(
            f"{spb:>14}  {analytic:10.2e}  {refined:10.2e}  {err_b:12.2e}  {nfev_b:7d}"
            f"   refine nfev {result.diagnostics['nfev']}"
        )
        if spb == 2000:
            at_2000 = (analytic, refined)
    print(
        f"{'thesis (9.2)':>14}  {max_rel_error(THESIS_CH9, CH9):10.2e}  {'-':>10}"
        "   (κw 2.0059, ρ 0.9971, n 1.4954, σ 2.9728)"
    )
    # the thesis's procedure: the cycle over [4T, 5T] from w(0) = 0 (not yet the limit cycle
    # for ρ·span = 0.4) and first differences (9.39) instead of local fits
    thesis_like = IdentifyOptions(
        refine=False,
        cycle=CycleOptions(steady_periods=1, min_steady_periods=1),
        derivative=DerivativeOptions(degree=1, min_samples=2, slope_corrections=0, rel_tol=np.inf),
    )
    runs = triangle_pair(CH9, -0.2, 0.2, 0.1, samples_per_branch=2000, periods=5, w0=0.0)
    r = identify(*runs, thesis_like)
    print(
        f"{'as the thesis':>14}  {max_rel_error(r.parameters, CH9):10.2e}  {'-':>10}"
        "   (2000 samples, cycle [4T,5T] from w(0)=0, first differences (9.39))"
    )
    check("noiseless, 2000 samples/branch: analytic error", at_2000[0], 1e-4)
    check("noiseless, 2000 samples/branch: refined error", at_2000[1], 1e-6)


def noisy() -> None:
    section(f"ch. 9 example with output noise, 2000 samples/branch, {SEEDS} seeds")
    print(
        f"{'noise/span':>10}  {'analytic med/worst':>20}  {'refined med/worst':>20}  "
        f"{'reported bad':>12}  {'silent >target':>14}  {'baseline med/worst (failed)':>28}"
    )
    for noise, target in ((1e-4, 5e-3), (1e-3, 5e-2)):
        ana, ref, base = [], [], []
        bad = silent = base_failed = 0
        for seed in range(SEEDS):
            runs = ch9_runs(2000, noise, seed)
            try:
                result = identify(*runs)
            except IdentificationError:
                bad += 1
                continue
            ana.append(max_rel_error(result.analytic, CH9))
            ref.append(max_rel_error(result.parameters, CH9))
            silent += ref[-1] > target
            err_b = baseline(result, CH9)[0]
            base_failed += not err_b <= target
            base.append(err_b)
        a, r, b = (np.array(x, dtype=float) for x in (ana, ref, base))
        print(
            f"{noise:>10.0e}  {np.nanmedian(a):9.2e}/{np.nanmax(a):9.2e}  "
            f"{np.median(r):9.2e}/{np.max(r):9.2e}  {bad:>12d}  {silent:>14d}  "
            f"{np.nanmedian(b):9.2e}/{np.nanmax(b):9.2e} ({base_failed:2d})"
        )
        # every answer not reported bad within the target: no silent answer above it
        worst = float(np.max(r)) if r.size else float("nan")
        check(f"noise {noise:g}: worst refined error (fits not reported bad)", worst, target)


def patch() -> None:
    section("ch. 10 patch, N = 2, input -v, 0-300 V and 100-400 V triangles at 0.1 Hz")
    runs = triangle_pair(PATCH, 0.0, 300.0, 100.0, period=10.0, samples_per_branch=2000, periods=3)
    result = identify(*runs, IdentifyOptions(degree=2))
    p = result.parameters
    print(
        f"input_sign {p.input_sign:+d}; analytic error "
        f"{max_rel_error(result.analytic, PATCH):.2e}, "
        f"refined {max_rel_error(p, PATCH):.2e}, y0 rel. error {abs(p.y0 / PATCH.y0 - 1):.1e}"
    )
    print(
        f"kappa {p.kappa}, kappa_w {p.kappa_w:.6g}, rho {p.rho:.6g}, sigma {p.sigma:.6g}, "
        f"n {p.n:.6g}"
    )
    err_b, nfev_b, t_b = baseline(result, PATCH)
    print(
        f"baseline LSQ from a generic start: error {err_b:.2e} after {nfev_b} evaluations "
        f"({t_b:.2f} s)"
    )
    try:
        identify(*runs, IdentifyOptions(degree=1))
        print("N = 1 on these data: accepted (unexpected)")
    except IdentificationError as exc:
        print(f"N = 1 on these data: {type(exc).__name__}: {str(exc)[:90]}...")


def timing() -> None:
    section("time per identification, 10k-sample cycle pair (5000 samples/branch, 3 periods)")
    runs = ch9_runs(5000)
    identify(*runs)  # warm up (numba, tables)

    def best(fn, repeat=5):
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return min(times)

    t_ana = best(lambda: identify(*runs, IdentifyOptions(refine=False)))
    t_full = best(lambda: identify(*runs), 3)
    result = identify(*runs)
    _, nfev_b, t_b = baseline(result, CH9)
    print(f"analytic (cycle extraction + Table 10.2): {1e3 * t_ana:7.1f} ms")
    print(f"analytic + refinement:                    {1e3 * t_full:7.1f} ms")
    print(
        f"baseline LSQ from generic start:          {1e3 * t_b:7.1f} ms   ({nfev_b} evaluations, "
        f"refinement from the analytic start: {result.diagnostics['nfev']}); ratio "
        f"{t_b / max(t_full - t_ana, 1e-9):.1f}x"
    )
    check("time of the analytic method", 1e3 * t_ana, 50.0, "ms")
    check("time of the refinement", t_full - t_ana, 5.0, "s")


# ------------------------------------------------------------------ fit by simulation error


def plain_fit(runs, degree: int, true: BoucWenParameters | None = None):
    """What a user writes with scipy: least squares of all parameters (w(0) = 0 in every run)
    from a generic start, both input signs tried. Returns (parameters, RMS, seconds)."""
    from scipy.optimize import least_squares

    t0 = time.perf_counter()
    v = np.concatenate([r.input for r in runs])
    y = np.concatenate([r.output for r in runs])
    slope, icpt = np.polyfit(v, y, 1)
    best = None
    for sign in (1, -1):
        p0 = np.array(
            [slope] + [0.0] * (degree - 1) + [icpt, 0.1 * np.ptp(y), 1.0 / np.ptp(v), 1.0, 2.0]
        )
        scale = np.where(p0 != 0, np.abs(p0), 1.0)
        scale[degree : degree + 1] = max(abs(icpt), np.ptp(y))

        def unpack(z, sign=sign, scale=scale):
            p = z * scale
            return BoucWenParameters(
                kappa=tuple(p[:degree]),
                y0=p[degree],
                kappa_w=p[degree + 1],
                rho=p[degree + 2],
                sigma=p[degree + 3],
                n=p[degree + 4],
                input_sign=sign,
            )

        def fun(z):
            p = unpack(z)
            return np.concatenate([model_output(p, r.input, 0.0) - r.output for r in runs])

        lo = np.full(len(p0), -np.inf)
        hi = np.full(len(p0), np.inf)
        lo[degree + 1 :] = [1e-12, 1e-12, 0.5, 1.0]
        hi[degree + 4] = 50.0
        try:
            res = least_squares(fun, p0 / scale, bounds=(lo / scale, hi / scale), x_scale="jac")
        except Exception as exc:
            print(f"    (plain fit failed: {exc})")
            continue
        if best is None or res.cost < best[1]:
            best = (unpack(res.x), res.cost)
    if best is None:
        return None, float("nan"), time.perf_counter() - t0
    rms = float(np.sqrt(2 * best[1] / len(y)))
    return best[0], rms, time.perf_counter() - t0


def _analytic_or_reason(runs) -> str:
    try:
        r = identify_runs(runs, method="analytic")
    except IdentificationError as exc:
        return f"refused ({str(exc)[:70]}...)"
    return f"{max_rel_error(r.parameters, CH9):.2e}"


def _fit_row(label: str, runs, true: BoucWenParameters, target: float, degree: int = 1) -> None:
    t0 = time.perf_counter()
    r = identify_runs(runs, IdentifyOptions(degree=degree), method="fit")
    t_fit = time.perf_counter() - t0
    base, _, t_base = plain_fit(runs, degree)
    error = max_rel_error(r.parameters, true)
    print(
        f"{label}: fit {error:.2e} ({t_fit:.2f} s)\n    analytic: "
        f"{_analytic_or_reason(runs) if len(runs) == 2 else 'n/a (one run)'}"
        f"\n    plain scipy fit from a generic start: {max_rel_error(base, true):.2e} "
        f"({t_base:.2f} s)"
    )
    check(f"{label}: fit", error, target)


def one_run() -> None:
    section("one noiseless run, 6 periods of a triangle from w(0) = 0 (ch. 9 example)")
    run = triangle_run(CH9, -0.2, 0.2, samples_per_branch=833, periods=6, w0=0.0)
    _fit_row("one run, ch. 9: max relative parameter error", [run], CH9, 1e-6)


def one_run_patch() -> None:
    section(
        "one noiseless run of the ch. 10 patch (N = 2, input -v), a ±150 V 1 Hz sine from "
        "w(0) = 0.5"
    )
    t = np.arange(6000) * 1e-3
    v = 150.0 * np.sin(2 * np.pi * t)
    run = Recording(t, v, model_output(PATCH, v, w0=0.5), name="patch sine")
    _fit_row("one run, ch. 10 patch: max relative parameter error", [run], PATCH, 1e-6, degree=2)


def two_runs() -> None:
    section("two noiseless runs x(t), x(t)+q, 5 periods from w(0) = 0 (limit cycle not reached)")
    runs = triangle_pair(CH9, -0.2, 0.2, 0.1, samples_per_branch=1000, periods=5, w0=0.0)
    _fit_row("two runs, ch. 9: max relative parameter error", list(runs), CH9, 1e-5)
    r = identify_runs(runs)
    print(f"    --method auto: {r.method}, error {max_rel_error(r.parameters, CH9):.2e}")


def ch9_24() -> None:
    section(
        "ch. 9 example, two runs of 24 periods from w(0) = 0 (method auto: analytic + refinement)"
    )
    for spb in (1000, 2000):
        runs = triangle_pair(CH9, -0.2, 0.2, 0.1, samples_per_branch=spb, periods=24, w0=0.0)
        r = identify_runs(runs)
        error = max_rel_error(r.parameters, CH9)
        print(
            f"{spb} samples/branch: {r.method}, steady periods averaged "
            f"{r.diagnostics['steady_periods']}, error {error:.2e}"
            "   (transient periods averaged in: 3.6e-5)"
        )
        check(f"24 periods, {spb} samples/branch: error", error, 1e-8)


def noisy_one_run() -> None:
    section(f"one run (6 periods from w(0) = 0), output noise 1e-3 of span, {SEEDS} seeds")
    names = ("kappa_1", "kappa_w", "rho", "sigma", "n")

    def values(p):
        return np.array([p.kappa[0], p.kappa_w, p.rho, p.sigma, p.n])

    true = values(CH9)
    errs, z, base = [], [], []
    for seed in range(SEEDS):
        run = triangle_run(
            CH9,
            -0.2,
            0.2,
            samples_per_branch=833,
            periods=6,
            w0=0.0,
            noise=1e-3,
            rng=np.random.default_rng(seed),
        )
        r = identify_runs([run])
        v, sd = values(r.parameters), np.array([r.diagnostics["std"][k] for k in names])
        errs.append(float(np.max(np.abs(v / true - 1))))
        z.append(np.abs(v - true) / sd)
        if seed < 5:
            base.append(max_rel_error(plain_fit([run], 1)[0], CH9))
    z = np.array(z)
    print(f"max relative error: median {np.median(errs):.2e}, worst {max(errs):.2e}")
    within3 = 100 * np.mean(np.all(z <= 3, axis=1))
    print(
        f"|error| <= 2 standard errors: {100 * np.mean(z <= 2):.0f} % of parameter estimates "
        f"(Gaussian: 95 %); all five within 2 SE in {100 * np.mean(np.all(z <= 2, axis=1)):.0f} "
        f"% of seeds, within 3 SE in {within3:.0f} %"
    )
    check("one noisy run: worst max relative error", max(errs), 5e-2)
    check("one noisy run: seeds with all five within 3 SE", within3, 90.0, "%", True)
    print(f"plain scipy fit (5 seeds): median {np.median(base):.2e}, worst {np.max(base):.2e}")


def p885() -> None:
    section(
        "real P-885.91 record (test/data/p885, 40 periods of a 1 Hz raised cosine, 100 Hz): "
        "fit on the first 60 %, held-out RMS on the last 40 %"
    )
    rec = load_csv(P885)
    span = float(np.ptp(rec.output))
    for degree in (1, 2):
        for drift in (DriftKind.NONE, DriftKind.LOG):
            t0 = time.perf_counter()
            fit, fig = holdout_check([rec], FitOptions(degree=degree, drift=drift, holdout=0.4))
            print(
                f"N = {degree}, drift {drift.value:<4}: fit RMS "
                f"{fig['train_rms_percent']:.3g} %, "
                f"held-out RMS {fig['holdout_rms_percent']:.3g} % of span, delay "
                f"{1e3 * fit.delay:.2g} ms ({time.perf_counter() - t0:.2f} s)"
            )
            name = f"P-885, N = {degree}, drift {drift.value}: held-out RMS"
            check(name, fig["holdout_rms_percent"], 1.2, "% of span")
    cut = int(round(0.6 * len(rec)))
    train, test = rec.slice(0, cut), rec.slice(cut, len(rec))
    poly = np.polyfit(train.input, train.output, 2)
    static = np.polyval(poly, test.input) - test.output
    print(
        f"static degree-2 polynomial (no hysteresis): held-out RMS "
        f"{100 * np.sqrt(np.mean(static**2)) / span:.3g} %"
    )
    base, _, t_base = plain_fit([train], 2)
    if base is not None:
        pred = model_output(base, rec.input, 0.0)[cut:] - test.output
        print(
            f"plain scipy Bouc-Wen fit (N = 2, w(0) = 0): held-out RMS "
            f"{100 * np.sqrt(np.mean(pred**2)) / span:.3g} % ({t_base:.2f} s)"
        )


def fit_timing() -> None:
    section("time of the fit by simulation error, one 10k-sample run (ch. 9 triangle, 6 periods)")
    run = triangle_run(CH9, -0.2, 0.2, samples_per_branch=833, periods=6, w0=0.0)
    identify_runs([run], method="fit")  # warm up (numba)
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        r = identify_runs([run], method="fit")
        times.append(time.perf_counter() - t0)
    print(
        f"{len(run)} samples: {min(times):.2f} s best of 3 (held-out check + final fit, "
        f"{r.diagnostics['nfev']} evaluations in the final fit)"
    )
    check(f"time of the fit, {len(run)} samples", min(times), 5.0, "s")
    patch_run = triangle_run(
        PATCH, 0.0, 300.0, period=10.0, samples_per_branch=833, periods=6, w0=0.0
    )
    t0 = time.perf_counter()
    r = identify_runs([patch_run], IdentifyOptions(degree=2), method="fit")
    print(
        f"ch. 10 patch, N = 2, 10k samples: {time.perf_counter() - t0:.2f} s, error "
        f"{max_rel_error(r.parameters, PATCH):.2e}"
    )


_THREADS_CHILD = """
import time
from piezo_stage.identification.methods import identify_runs
from piezo_stage.identification.pipeline import IdentifyOptions
from piezo_stage.identification.synthetic import CH10_PATCH, triangle_pair
from piezo_stage.model.bouc_wen import BoucWenParameters
runs = triangle_pair(BoucWenParameters(**CH10_PATCH), 0.0, 300.0, 100.0, period=3.0,
                     samples_per_branch=1500, periods=8, noise=2e-4)
identify_runs(runs, IdentifyOptions(degree=2), "auto")  # warm up (numba)
t0 = time.perf_counter()
identify_runs(runs, IdentifyOptions(degree=2), "auto")
print(time.perf_counter() - t0)
"""


def threads() -> None:
    section(
        "BLAS threads: auto identification of the emulated rig's two runs (ch. 10 patch, "
        "2 x 24k samples), one OpenBLAS thread (the package's default) vs two, idle and "
        "beside a busy process"
    )
    import os
    import subprocess

    def seconds(n: int) -> float:
        env = {**os.environ, "OPENBLAS_NUM_THREADS": str(n), "OMP_NUM_THREADS": str(n)}
        out = subprocess.run(
            [sys.executable, "-c", _THREADS_CHILD], env=env, capture_output=True, text=True
        )
        return float(out.stdout.split()[-1]) if out.returncode == 0 else float("nan")

    for beside in ("idle", "busy"):
        busy = (
            subprocess.Popen([sys.executable, "-c", "while True: pass"])
            if beside == "busy"
            else None
        )
        try:
            one, two = seconds(1), seconds(2)
        finally:
            if busy is not None:
                busy.kill()
                busy.wait()
        print(f"{beside}: 1 thread {one:.2f} s, 2 threads {two:.2f} s, ratio {two / one:.2f}")
        check(f"one BLAS thread vs two, {beside} (ratio 2/1)", two / one, 1.0, "", True)


def lag() -> None:
    section("an output that lags: two ch. 10 T-wave runs, noise 1e-3 of span, 6 seeds each")
    from piezo_stage.identification.lag import estimate_lag
    from piezo_stage.identification.recording import Recording

    keys = ("kappa_w", "rho", "sigma", "n")
    seeds = 6
    print(
        f"{'per period':>10} {'lag':>3}  {'estimated lag':>14}  "
        f"{'auto: worst of kw,rho,sigma,n':>30}  {'fit: worst':>10}  "
        f"{'auto within 3 std errors':>24}"
    )
    for spb in (50, 100):
        for d in range(4):
            est, auto, fit, covered = [], [], [], []
            for seed in range(seeds):
                rng = np.random.default_rng(seed)
                runs = []
                for low, high in ((0.0, 300.0), (100.0, 400.0)):
                    ahead = triangle_run(
                        PATCH, low, high, samples_per_branch=spb, periods=3.0, phase=d / (2 * spb)
                    )
                    now = triangle_run(
                        PATCH, low, high, samples_per_branch=spb, periods=3.0, noise=1e-3, rng=rng
                    )
                    runs.append(Recording(ahead.t, ahead.input, now.output))
                est.append(estimate_lag(runs[0]).samples)
                for method, sink in (("auto", auto), ("fit", fit)):
                    try:
                        p = identify_runs(runs, IdentifyOptions(degree=2), method=method)
                        sink.append(
                            max(abs(getattr(p.parameters, k) / getattr(PATCH, k) - 1) for k in keys)
                        )
                    except Exception:
                        sink.append(float("nan"))
                        continue
                    if method == "auto":
                        std = p.diagnostics.get("std", {})
                        covered += [
                            abs(getattr(p.parameters, k) - getattr(PATCH, k))
                            <= 3 * std.get(k, float("nan"))
                            for k in keys
                        ]
            print(
                f"{2 * spb:>10} {d:>3}  {np.mean(est):8.2f} ±{np.std(est):.2f}  "
                f"{100 * max(auto):29.2f} %  {100 * max(fit):9.2f} %  "
                f"{100 * np.mean(covered):22.0f} %"
            )
            case = f"lag {d}, {2 * spb} per period"
            check(f"{case}: auto, worst parameter", 100 * float(np.max(auto)), 2.0, "%")
            covered_share = 100 * float(np.mean(covered))
            check(f"{case}: auto within 3 std errors", covered_share, 100.0, "%", True)
    print(
        "3 standard errors cover 99.7 % of a normal error: a lower share says the reported "
        "errors are optimistic"
    )


SECTIONS = {
    f.__name__: f
    for f in (
        noiseless,
        patch,
        timing,
        noisy,
        one_run,
        one_run_patch,
        two_runs,
        ch9_24,
        noisy_one_run,
        p885,
        fit_timing,
        lag,
        threads,
    )
}


if __name__ == "__main__":
    t_start = time.perf_counter()
    for name in sys.argv[1:] or SECTIONS:
        SECTIONS[name]()
    print(f"\nbench time {time.perf_counter() - t_start:.0f} s")
    sys.exit(exit_code())
