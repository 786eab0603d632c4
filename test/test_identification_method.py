"""The identification method: G = Q·K, y0, Table 10.2, refinement, honest failures, result."""

from __future__ import annotations

import json
from math import comb

import numpy as np
import pytest

from piezo_stage.identification.analytic import (
    DerivativeOptions,
    DesignPoints,
    hysteretic_estimate,
    initial_w,
    table_10_2,
    theta,
)
from piezo_stage.identification.cycles import extract_cycle, smooth_input, split_branches
from piezo_stage.identification.derivatives import LocalFit
from piezo_stage.identification.errors import (
    AnalyticEstimateError,
    BadFitError,
    DesignPointError,
    IdentificationError,
    InconsistentRunsError,
    OrientationError,
)
from piezo_stage.identification.pipeline import IdentifyOptions, identify
from piezo_stage.identification.polynomial import (
    fit_polynomial,
    kappa_from_g,
    offset_between,
    offset_y0,
    polyval,
    q_matrix,
)
from piezo_stage.identification.recording import Recording
from piezo_stage.identification.refine import RefineOptions, _line_corner
from piezo_stage.identification.synthetic import (
    CH9_EXAMPLE,
    CH10_PATCH,
    limit_cycle_start,
    triangle_pair,
    triangle_run,
)
from piezo_stage.model.bouc_wen import BoucWenParameters, model_output
from piezo_stage.model.parameter_set import load_parameter_set, save_parameter_set
from piezo_stage.model.signals import sine, triangle

pytestmark = pytest.mark.unit

CH9 = BoucWenParameters(**CH9_EXAMPLE)
PATCH = BoucWenParameters(**CH10_PATCH)
HYSTERETIC = ("kappa_w", "rho", "sigma", "n")


def max_rel_error(found: BoucWenParameters, true: BoucWenParameters) -> float:
    errs = [abs(getattr(found, k) / getattr(true, k) - 1) for k in HYSTERETIC]
    errs += [abs(a / b - 1) for a, b in zip(found.kappa, true.kappa)]
    return max(errs)


@pytest.fixture(scope="module")
def ch9_runs():
    return triangle_pair(CH9, -0.2, 0.2, 0.1, samples_per_branch=2000, periods=3)


@pytest.fixture(scope="module")
def patch_runs():
    return triangle_pair(PATCH, 0.0, 300.0, 100.0, period=10.0, samples_per_branch=1000, periods=3)


def branches_of(runs, sign):
    cycles = [extract_cycle(r) for r in runs]
    return cycles, [split_branches(c, sign, smooth_input(c)) for c in cycles]


# ------------------------------------------------------------------ §10.2.2: G = Q·K


def test_q_matrix_n2_is_10_12_and_k_is_10_13():
    q = 0.7
    assert np.allclose(q_matrix(q, 2), [[q, q**2], [0, 2 * q]])
    g = np.array([1.3, -0.4])
    assert np.allclose(kappa_from_g(g, q), [g[0] / q - g[1] / 2, g[1] / (2 * q)])


@pytest.mark.parametrize("degree", [1, 3, 5])
def test_q_matrix_reproduces_the_difference_polynomial(degree):
    rng = np.random.default_rng(degree)
    kappa, q = rng.standard_normal(degree), 0.37
    x = np.linspace(-2, 2, 7)
    diff = polyval(kappa, x + q) - polyval(kappa, x)  # (10.7) left side
    g = q_matrix(q, degree) @ kappa  # (10.9)
    assert np.allclose(diff, sum(g[j] * x**j for j in range(degree)))  # (10.7) right side
    assert np.allclose(kappa_from_g(g, q), kappa)  # (10.11)
    assert q_matrix(q, degree)[0, degree - 1] == pytest.approx(comb(degree, degree) * q**degree)


def test_q_must_be_nonzero():
    with pytest.raises(InconsistentRunsError, match="q = 0"):
        kappa_from_g(np.array([1.0]), 0.0)


def test_polynomial_part_and_y0_of_the_patch(patch_runs):
    _, br = branches_of(patch_runs, -1)
    q = offset_between(br[0], br[1])
    assert q == pytest.approx(100.0, rel=1e-12)
    fit = fit_polynomial(br[0], br[1], 2, q)
    assert np.allclose(fit.kappa, PATCH.kappa, rtol=1e-9)
    assert fit.residual_rms < 1e-15
    assert offset_y0(br, fit.kappa) == pytest.approx(PATCH.y0, rel=1e-9)  # (10.17)


def test_y0_for_an_asymmetric_t_wave():
    """(10.17) assumes ∫w̄dτ = 0, true for symmetric triangles only; the branch average in x
    holds for every T-wave."""
    t = np.arange(10 * 4000 + 1) / 4000
    runs = []
    for lo in (0.0, 100.0):
        v = triangle(t, 1.0, lo, lo + 300.0, rise_fraction=0.25)
        y = model_output(PATCH, v, w0=0.0)
        runs.append(Recording(t, v, y))
    # start from w0=0 converges fast for the patch (ρ·span = 1.41): keep the last periods
    _, br = branches_of(runs, -1)
    fit = fit_polynomial(br[0], br[1], 2, offset_between(br[0], br[1]))
    assert offset_y0(br, fit.kappa) == pytest.approx(PATCH.y0, rel=1e-4)
    cycle = extract_cycle(runs[0])
    naive = np.mean(cycle.output - polyval(fit.kappa, cycle.input))  # (10.17) in time
    assert abs(naive - PATCH.y0) > 100 * abs(offset_y0(br, fit.kappa) - PATCH.y0)


def test_runs_must_be_a_t_wave_pair(ch9_runs):
    a, _ = ch9_runs
    with pytest.raises(InconsistentRunsError, match="clearly non-zero"):
        identify(a, a)
    wider = triangle_run(CH9, -0.15, 0.3, samples_per_branch=500)
    with pytest.raises(InconsistentRunsError, match="spans differ"):
        identify(a, wider)


# ------------------------------------------------------------------ Table 10.2


def test_analytic_estimate_of_the_ch9_example(ch9_runs):
    """Thesis: 2.0059, 0.9971, 1.4954, 2.9728 (9e-3); target here 1e-4 at 2000 samples."""
    result = identify(*ch9_runs, IdentifyOptions(refine=False))
    assert result.analytic == result.parameters and not result.refined
    assert max_rel_error(result.analytic, CH9) < 1e-4
    assert abs(result.parameters.y0) < 1e-12
    d = result.diagnostics
    assert d["a"] == pytest.approx(CH9.rho * CH9.kappa_w, rel=1e-5)  # a = ρκw
    assert d["b"] == pytest.approx(CH9.rho * CH9.kappa_w ** (1 - CH9.n), rel=1e-4)
    assert d["x_star3"] < d["x_star"] < d["x_star1"] < d["x_star2"]


def test_plain_table_10_2_without_slope_correction(ch9_runs):
    _, br = branches_of(ch9_runs, 1)
    plain = hysteretic_estimate(
        br[0][0], np.array([2.0]), 0.0, 0.0, derivative=DerivativeOptions(slope_corrections=0)
    )
    corrected = hysteretic_estimate(br[0][0], np.array([2.0]), 0.0, 0.0)

    def err(h):
        return max(abs(getattr(h, k) / getattr(CH9, k) - 1) for k in HYSTERETIC)

    assert err(corrected) < err(plain) < 1e-4


def test_table_10_2_rejects_a_non_bouc_wen_shape():
    def fit(value, slope):
        return LocalFit(0.0, value, slope, 0.0, 0.0, 8, 0.01)

    with pytest.raises(AnalyticEstimateError, match="both must be negative"):
        table_10_2(2.0, fit(0.1, 2.5), fit(0.3, 1.0), fit(-0.3, 3.0))
    with pytest.raises(AnalyticEstimateError, match="w̄ < 0"):
        table_10_2(2.0, fit(0.1, 1.9), fit(0.3, 1.0), fit(0.05, 3.0))


def test_design_points(ch9_runs):
    _, br = branches_of(ch9_runs, 1)
    with pytest.raises(DesignPointError, match="outside the loading branch"):
        hysteretic_estimate(br[0][0], np.array([2.0]), 0.0, 0.0, DesignPoints(x2=0.5))
    with pytest.raises(DesignPointError, match="x\\*3 < x\\* < x\\*1 < x\\*2"):
        hysteretic_estimate(br[0][0], np.array([2.0]), 0.0, 0.0, DesignPoints(x3=0.1))
    with pytest.raises(DesignPointError, match="f1 < f2"):
        DesignPoints(f1=0.9, f2=0.5)
    # a wrong offset moves θ off zero everywhere: x* lies outside the data
    with pytest.raises(DesignPointError, match="x\\* lies outside the data"):
        hysteretic_estimate(br[0][0], np.array([2.0]), -5.0, 0.0)
    # other design points give the same parameters on exact data
    other = hysteretic_estimate(br[0][0], np.array([2.0]), 0.0, 0.0, DesignPoints(0.4, 0.8, 0.2))
    assert other.n == pytest.approx(1.5, rel=1e-4) and other.sigma == pytest.approx(3.0, rel=1e-4)


def test_theta_is_kappa_w_times_w_on_the_loading_branch(ch9_runs):
    _, br = branches_of(ch9_runs, 1)
    b = br[0][0]
    w = (b.y - 2.0 * b.x) / 2.0
    assert np.allclose(theta(b, np.array([2.0]), 0.0), 2.0 * w)  # (9.21)


# ------------------------------------------------------------------ refinement and targets


def test_refined_ch9_example(ch9_runs):
    result = identify(*ch9_runs)
    assert result.refined and max_rel_error(result.parameters, CH9) < 1e-6
    assert result.rms_error < 1e-10 < result.analytic_rms_error
    assert result.samples == 2 * 3 * 4000


def test_ch10_patch_with_n2_and_input_minus_v(patch_runs):
    result = identify(*patch_runs, IdentifyOptions(degree=2))
    p = result.parameters
    assert p.input_sign == -1 and len(p.kappa) == 2
    assert max_rel_error(p, PATCH) < 1e-6 and p.y0 == pytest.approx(PATCH.y0, rel=1e-6)
    assert max_rel_error(result.analytic, PATCH) < 1e-4


def test_plain_bouc_wen_on_patch_data_is_a_bad_fit(patch_runs):
    with pytest.raises(BadFitError, match="does not describe") as info:
        identify(*patch_runs, IdentifyOptions(degree=1))
    rejected = info.value.result
    assert rejected.rms_error > 0.01 * rejected.diagnostics["output_span"]
    # the analytic N = 1 estimate is worse still; it passes only when the user allows 5 %
    lax = RefineOptions(max_rms_fraction=0.05)
    ok = identify(*patch_runs, IdentifyOptions(degree=1, refine=False, refinement=lax))
    assert ok.rms_error > rejected.rms_error
    with pytest.raises(BadFitError):
        identify(*patch_runs, IdentifyOptions(degree=1, refine=False))


@pytest.mark.parametrize("seed", [0, 1])
def test_noise_1e_4_of_span(seed):
    runs = triangle_pair(
        CH9,
        -0.2,
        0.2,
        0.1,
        samples_per_branch=2000,
        periods=3,
        noise=1e-4,
        rng=np.random.default_rng(seed),
    )
    result = identify(*runs)
    assert max_rel_error(result.parameters, CH9) < 5e-3
    assert result.rms_error < 3 * result.diagnostics["noise_output"]


def test_noise_1e_3_of_span():
    runs = triangle_pair(
        CH9,
        -0.2,
        0.2,
        0.1,
        samples_per_branch=2000,
        periods=3,
        noise=1e-3,
        rng=np.random.default_rng(11),
    )
    result = identify(*runs)
    assert max_rel_error(result.parameters, CH9) < 5e-2
    std = result.diagnostics["relative_std"]
    for k in HYSTERETIC:  # the reported standard errors cover the actual error
        assert abs(getattr(result.parameters, k) / getattr(CH9, k) - 1) < 4 * std[k]


def test_undetermined_parameters_are_reported():
    runs = triangle_pair(
        CH9,
        -0.2,
        0.2,
        0.1,
        samples_per_branch=2000,
        periods=3,
        noise=1e-3,
        rng=np.random.default_rng(11),
    )
    with pytest.raises(BadFitError, match="not determined by the data"):
        identify(*runs, IdentifyOptions(refinement=RefineOptions(max_rel_std=1e-3)))


def test_rate_independence_runs_may_differ_in_period_and_rate():
    a = triangle_run(CH9, -0.2, 0.2, period=1.0, samples_per_branch=2000, periods=3)
    b = triangle_run(CH9, -0.1, 0.3, period=3.7, samples_per_branch=1500, periods=2.5, phase=0.3)
    result = identify(a, b)
    assert max_rel_error(result.parameters, CH9) < 1e-6


def test_w0_by_10_18():
    v0_w = 0.3
    t = np.arange(12 * 2000 + 1) / 2000
    runs = []
    for lo in (0.0, 100.0):
        v = triangle(t, 1.0, lo, lo + 300.0, phase=0.3)
        runs.append(Recording(t, v, model_output(PATCH, v, w0=v0_w)))
    result = identify(*runs, IdentifyOptions(degree=2))
    assert result.w0 == pytest.approx(v0_w, abs=1e-5)
    assert initial_w(
        PATCH.kappa, PATCH.kappa_w, PATCH.y0, runs[0].input[0], runs[0].output[0]
    ) == pytest.approx(v0_w, abs=1e-12)


def test_options_are_checked(ch9_runs):
    with pytest.raises(IdentificationError, match="degree"):
        identify(*ch9_runs, IdentifyOptions(degree=0))
    with pytest.raises(OrientationError, match="requires input_sign=\\+1"):
        identify(*ch9_runs, IdentifyOptions(input_sign=-1))


# ------------------------------------------------------------------ result


def test_result_dict_and_parameter_set(patch_runs, tmp_path):
    result = identify(*patch_runs, IdentifyOptions(degree=2))
    d = json.loads(json.dumps(result.to_dict()))
    for key in (
        "kappa",
        "y0",
        "kappa_w",
        "rho",
        "sigma",
        "n",
        "input_sign",
        "rms_error",
        "samples",
    ):
        assert key in d and key in d["analytic"]
    assert d["kappa"] == list(result.parameters.kappa) and d["input_sign"] == -1
    assert d["analytic"]["rms_error"] > d["rms_error"]
    path = tmp_path / "p.yaml"
    save_parameter_set(result.to_parameter_set(name="patch"), path)
    loaded = load_parameter_set(path)
    assert loaded.name == "patch" and loaded.form == "static" and loaded.dynamics is None
    assert loaded.bouc_wen == result.parameters


# ------------------------------------------------------------------ other T-waves, sampling


def test_sine_is_a_t_wave_too():
    t = np.arange(3 * 4000 + 1) / 4000
    runs = []
    for lo in (-0.2, -0.1):
        v = sine(t, 1.0, 0.2, lo + 0.2, phase=-np.pi / 2)  # starts at its minimum
        runs.append(Recording(t, v, model_output(CH9, v, w0=limit_cycle_start(CH9, lo, lo + 0.4))))
    result = identify(*runs)
    assert max_rel_error(result.analytic, CH9) < 1e-4
    assert max_rel_error(result.parameters, CH9) < 1e-6


def test_turning_points_between_samples():
    """4001.3 samples per period: the corners fall between samples. The data are simulated on
    the continuous triangle (corners included) and then sampled, as a real rig would be."""
    t = np.arange(0.0, 3.3, 1 / 4001.3)
    fine = np.union1d(t, np.arange(0.0, 3.31, 0.5))
    on_sample = np.isin(fine, t)
    runs = []
    for lo in (-0.2, -0.1):
        v = triangle(fine, 1.0, lo, lo + 0.4)
        y = model_output(CH9, v, w0=limit_cycle_start(CH9, lo, lo + 0.4))
        runs.append(Recording(fine[on_sample], v[on_sample], y[on_sample]))
    result = identify(*runs)
    assert max_rel_error(result.analytic, CH9) < 1e-3
    assert max_rel_error(result.parameters, CH9) < 1e-4


def test_corner_reconstruction():
    k = np.arange(1000)
    corner = _line_corner(-np.abs(k - 500.3), 500, 10)
    assert corner[0] == pytest.approx(500.3) and corner[1] == pytest.approx(0.0, abs=1e-12)
    assert _line_corner(np.cos(2 * np.pi * (k - 500.3) / 1000), 500, 10) is None  # smooth top


def test_analytic_outside_class_i_is_projected_then_refined():
    """σ = ½ lies on the class-I boundary: Table 10.2 lands a hair below it."""
    true = BoucWenParameters(kappa=(2.0,), kappa_w=2.0, rho=1.0, sigma=0.5, n=1.5)
    runs = triangle_pair(true, -0.2, 0.2, 0.1, samples_per_branch=1000, periods=3)
    result = identify(*runs)
    assert result.analytic is None and "sigma" in result.diagnostics["analytic_problem"]
    assert max_rel_error(result.parameters, true) < 1e-6
    d = json.loads(json.dumps(result.to_dict(), allow_nan=False))
    assert d["analytic"]["class_i"] is False and d["analytic"]["sigma"] < 0.5
    assert d["analytic"]["rms_error"] is None
    with pytest.raises(AnalyticEstimateError, match="outside class I"):
        identify(*runs, IdentifyOptions(refine=False))
