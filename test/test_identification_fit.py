"""Fit by simulation error: one run, any input, transients, delay, drift, standard
errors, held-out check, --method analytic|fit|auto, and the real P-885 record."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.cli import main
from piezo_stage.identification.errors import (
    BadFitError,
    IdentificationError,
    NoSteadyStateError,
    OrientationError,
)
from piezo_stage.identification.io import load_csv
from piezo_stage.identification.methods import identify_runs
from piezo_stage.identification.pipeline import IdentifyOptions
from piezo_stage.identification.recording import Recording
from piezo_stage.identification.simfit import FitOptions, holdout_check, simulation_fit
from piezo_stage.identification.synthetic import (
    CH9_EXAMPLE,
    CH10_PATCH,
    triangle_pair,
    triangle_run,
)
from piezo_stage.identification.validation import validate_model
from piezo_stage.model.bouc_wen import BoucWenParameters, model_output
from piezo_stage.model.parameter_set import (
    Drift,
    DriftKind,
    load_parameter_set,
    parameter_set_from_dict,
    parameter_set_to_dict,
    shipped_parameter_set,
)
from piezo_stage.model.signals import sine

from property_support import examples

pytestmark = pytest.mark.unit

CH9 = BoucWenParameters(**CH9_EXAMPLE)
PATCH = BoucWenParameters(**CH10_PATCH)
P885 = Path(__file__).parent / "data" / "p885" / "p885_raised_cosine.csv"


def max_rel_error(found: BoucWenParameters, true: BoucWenParameters) -> float:
    errs = [abs(getattr(found, k) / getattr(true, k) - 1) for k in ("kappa_w", "rho", "sigma", "n")]
    return max(errs + [abs(a / b - 1) for a, b in zip(found.kappa, true.kappa)])


def write_csv(path: Path, rec: Recording) -> Path:
    rows = np.column_stack((rec.t, rec.input, rec.output))
    path.write_text(
        "time,input,output\n" + "\n".join(",".join(f"{v:.17g}" for v in r) for r in rows) + "\n"
    )
    return path


@pytest.fixture(scope="module")
def one_run() -> Recording:
    """6 periods of a triangle from w(0) = 0: the transient is part of the record."""
    return triangle_run(CH9, -0.2, 0.2, samples_per_branch=300, periods=6, w0=0.0)


# ------------------------------------------------------------------ synthetic accuracy


def test_one_noiseless_run_from_rest_gives_the_parameters(one_run):
    result = identify_runs([one_run])
    assert result.method == "fit"
    assert max_rel_error(result.parameters, CH9) <= 1e-6
    assert abs(result.w0) < 1e-6 and abs(result.delay) < 1e-9
    assert result.parameters.input_sign == 1
    assert result.diagnostics["holdout_rms"] < 1e-9 * np.ptp(one_run.output)


def test_two_runs_before_the_limit_cycle():
    runs = triangle_pair(CH9, -0.2, 0.2, 0.1, samples_per_branch=300, periods=5, w0=0.0)
    with pytest.raises(NoSteadyStateError, match="limit cycle is not reached"):
        identify_runs(runs, method="analytic")
    result = identify_runs(runs)  # auto falls back to the fit
    assert result.method == "fit" and "limit cycle" in result.diagnostics["analytic_problem"]
    assert max_rel_error(result.parameters, CH9) <= 1e-5


def test_ch9_24_periods_without_averaging_bias():
    runs = triangle_pair(CH9, -0.2, 0.2, 0.1, samples_per_branch=500, periods=24, w0=0.0)
    result = identify_runs(runs)
    assert result.method == "analytic"
    assert max_rel_error(result.parameters, CH9) <= 1e-8  # was 3.6e-5 (13 periods averaged)


def test_auto_uses_the_analytic_method_on_steady_pairs_and_fit_seeds_from_it():
    runs = triangle_pair(PATCH, 0.0, 300.0, 100.0, period=10.0, samples_per_branch=300, periods=3)
    auto = identify_runs(runs, IdentifyOptions(degree=2))
    assert auto.method == "analytic" and "q" in auto.diagnostics
    fit = identify_runs(runs, IdentifyOptions(degree=2), method="fit")
    assert fit.method == "fit" and fit.analytic is not None
    assert fit.parameters.input_sign == -1
    assert max_rel_error(fit.parameters, PATCH) <= 1e-6


def test_sine_input_with_delay_and_drift():
    t = np.arange(6000) * 1e-3
    v = sine(t, 1.0, 0.2)
    delay = 2.5e-3
    vd = np.interp(t - delay, t, v)
    drift = Drift(DriftKind.LOG, 0.01, 0.06)
    y = model_output(CH9, vd, w0=0.3) + drift.evaluate(t)
    rec = Recording(t, v, y, name="sine")
    fit = simulation_fit([rec], FitOptions(drift=DriftKind.LOG), time_constant=[0.06])
    assert max_rel_error(fit.parameters, CH9) <= 1e-6
    assert fit.delay == pytest.approx(delay, abs=1e-8)
    assert fit.drift[0].coefficient == pytest.approx(0.01, rel=1e-6)
    assert fit.w0[0] == pytest.approx(0.3, abs=1e-6)


def _filtered_noise(n: int, rng: np.random.Generator) -> np.ndarray:
    b = np.convolve(rng.standard_normal(n), np.ones(50) / 50, mode="same")
    return 0.2 * b / np.max(np.abs(b))


@pytest.mark.parametrize(
    "name, make_input",
    [
        ("random", lambda t, rng: _filtered_noise(len(t), rng)),
        ("steps", lambda t, rng: np.repeat(rng.uniform(-0.2, 0.2, 20), len(t) // 20)),
        ("abrupt start", lambda t, rng: np.where(t < 0.5, 0.0, 0.2 * np.sin(2 * np.pi * t))),
        ("decaying sine", lambda t, rng: 0.2 * np.exp(-t / 3) * np.sin(4 * np.pi * t)),
    ],
)
def test_any_input_one_run(name, make_input):
    t = np.arange(4000) * 1e-3
    v = make_input(t, np.random.default_rng(3))
    rec = Recording(t, v, model_output(CH9, v, w0=-0.2), name=name)
    result = identify_runs([rec])
    assert result.method == "fit"
    assert max_rel_error(result.parameters, CH9) <= 1e-6, name
    assert result.w0 == pytest.approx(-0.2, abs=1e-6)


def test_validate_applies_delay_and_drift():
    t = np.arange(3000) * 1e-3
    v = sine(t, 1.0, 150.0)
    delay, drift = 3e-3, Drift(DriftKind.LINEAR, 2e-7, 1.0)
    y = model_output(PATCH, np.interp(t - delay, t, v), w0=0.0) + drift.evaluate(t)
    rec = Recording(t, v, y, name="bipolar")
    exact = validate_model(PATCH, rec, w0=0.0, delay=delay, drift=drift)
    assert exact.rms < 1e-12 * np.ptp(y)
    assert validate_model(PATCH, rec, w0=0.0).rms > 1e-3 * np.ptp(y)  # the terms matter


def test_input_sign_detected_and_a_contradicting_request_refused():
    rec = triangle_run(PATCH, 0.0, 300.0, period=10.0, samples_per_branch=300, periods=3, w0=0.0)
    fit = simulation_fit([rec], FitOptions(degree=2, fit_delay=False))
    assert fit.parameters.input_sign == -1 and fit.parameters.kappa_w > 0
    with pytest.raises(OrientationError, match="other way"):
        simulation_fit([rec], FitOptions(degree=2, fit_delay=False, input_sign=1))


def test_noise_standard_errors_cover_the_error():
    rec = triangle_run(
        CH9,
        -0.2,
        0.2,
        samples_per_branch=400,
        periods=6,
        w0=0.0,
        noise=1e-3,
        rng=np.random.default_rng(7),
    )
    result = identify_runs([rec])
    p, std = result.parameters, result.diagnostics["std"]
    assert max_rel_error(p, CH9) <= 0.05
    for name, true in (("kappa_w", 2.0), ("rho", 1.0), ("sigma", 3.0), ("n", 1.5)):
        assert 0 < std[name] < 0.05 * true
        assert abs(getattr(p, name) - true) <= 4 * std[name], name


def test_a_loop_too_small_to_separate_the_parameters_is_refused():
    tiny = BoucWenParameters(kappa=(2.0,), kappa_w=2.0, rho=0.05, sigma=3.0, n=1.5)
    rec = triangle_run(
        tiny,
        -0.2,
        0.2,
        samples_per_branch=300,
        periods=4,
        w0=0.0,
        noise=1e-3,
        rng=np.random.default_rng(1),
    )
    with pytest.raises(BadFitError, match="not determined"):
        identify_runs([rec])


def test_no_excitation_is_refused():
    t = np.arange(400) * 1e-3
    rec = Recording(t, np.full(400, 1.0), np.sin(t))
    with pytest.raises(IdentificationError, match="constant"):
        identify_runs([rec], method="fit")


# ------------------------------------------------------------------ real data


def test_p885_held_out_prediction():
    rec = load_csv(P885)
    fit, figures = holdout_check([rec], FitOptions(degree=2, holdout=0.4))
    assert figures["holdout_rms_percent"] <= 1.2
    assert fit.parameters.input_sign == -1
    assert 0 < fit.delay < 0.02  # about one 200 Hz sample


def test_cli_identify_one_real_run_then_validate_another(tmp_path, capsys):
    rec = load_csv(P885)
    cut = int(0.6 * len(rec))
    first = write_csv(tmp_path / "first.csv", rec.slice(0, cut))
    last = write_csv(tmp_path / "last.csv", rec.slice(cut, len(rec)))
    params = tmp_path / "p.yaml"
    assert (
        main(
            [
                "identify",
                str(first),
                "--degree",
                "2",
                "--output",
                str(params),
                "--drift",
                "log",
                "--json",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    assert out["method"] == "fit" and out["drift"]["kind"] == "log"
    assert set(out["std"]) >= {"kappa_1", "kappa_2", "rho", "sigma", "n", "delay"}
    assert out["holdout"]["holdout_rms_percent"] < 1.2
    assert (tmp_path / "p_timeseries.png").stat().st_size > 0
    pset = load_parameter_set(params)
    assert pset.delay == pytest.approx(out["delay"]) and pset.drift is not None
    assert main(["validate", str(params), str(last), "--json", "--no-plot"]) == 0
    assert json.loads(capsys.readouterr().out)["rms_percent"] < 1.2


# ------------------------------------------------------------------ CLI input errors


@pytest.mark.parametrize(
    "args, reason",
    [
        (["--steady-periods", "0"], "--steady-periods must be >= 1"),
        (["--max-rms", "-1"], "--max-rms must be in"),
        (["--max-rms", "nan"], "--max-rms must be in"),
        (["--holdout", "2"], "--holdout must be in"),
        (["--degree", "0"], "--degree must be"),
    ],
)
def test_cli_option_errors_exit_2_with_one_line(tmp_path, one_run, capsys, args, reason):
    path = write_csv(tmp_path / "a.csv", one_run)
    assert main(["identify", str(path), *args]) == 2
    err = capsys.readouterr().err
    assert reason in err and err.count("\n") == 1


@pytest.mark.parametrize("scale", [1e300, 1e-300])
def test_cli_extreme_values_give_a_reason_not_a_traceback(tmp_path, capsys, scale):
    runs = triangle_pair(CH9, -0.2, 0.2, 0.1, samples_per_branch=300, periods=3)
    paths = [
        write_csv(tmp_path / f"{i}.csv", Recording(r.t, r.input * scale, r.output * scale))
        for i, r in enumerate(runs)
    ]
    assert main(["identify", *map(str, paths)]) == 2
    err = capsys.readouterr().err
    assert "out of range" in err and err.count("\n") == 1


# ------------------------------------------------------------------ parameter sets


@settings(max_examples=examples(30), deadline=None)
@given(
    delay=st.floats(-1.0, 1.0),
    kind=st.sampled_from([DriftKind.LINEAR, DriftKind.LOG]),
    coefficient=st.floats(-1e-3, 1e-3),
    time_constant=st.floats(1e-3, 1e3),
)
def test_parameter_set_drift_and_delay_round_trip(delay, kind, coefficient, time_constant):
    base = shipped_parameter_set("ch10_patch")
    data = parameter_set_to_dict(base)
    data.update(
        delay=delay,
        drift={"kind": kind.value, "coefficient": coefficient, "time_constant": time_constant},
    )
    pset = parameter_set_from_dict(data)
    assert pset.delay == delay and pset.drift == Drift(kind, coefficient, time_constant)
    assert parameter_set_from_dict(parameter_set_to_dict(pset)) == pset
    t = np.linspace(0.0, 10.0, 11)
    values = pset.drift.evaluate(t)
    assert values[0] == 0.0 and np.all(np.diff(values) * np.sign(coefficient) >= 0)


def test_a_thinned_cross_check_that_wins_shows_its_model_over_the_whole_runs(monkeypatch, tmp_path):
    """auto's cross-checking fit sees thinned runs; when its result is returned, its model
    output (``fitted``: what ``identify --output`` plots against the data) covers the runs as
    given, sample for sample, and follows them."""
    from dataclasses import replace

    from piezo_stage.identification import methods
    from piezo_stage.identification.pipeline import identify

    monkeypatch.setattr(methods, "CROSS_CHECK_SAMPLES", 1500)
    options = IdentifyOptions(degree=2)
    runs = list(
        triangle_pair(PATCH, 0.0, 300.0, 100.0, samples_per_branch=1000, periods=2.0, noise=1e-4)
    )
    analytic = identify(runs[0], runs[1], options)
    off = replace(analytic.parameters, kappa_w=1.3 * analytic.parameters.kappa_w)
    wrong = replace(analytic, parameters=off, rms_error=1.0)  # far off, and said to fit badly
    result = methods._cross_checked(wrong, runs, options, FitOptions(), None)
    assert result.method == "fit" and "disagree" in result.warnings[-1]
    assert [len(f) for f in result.fitted] == [len(r) for r in runs]
    span = np.ptp(runs[0].output)
    for model, rec in zip(result.fitted, runs):
        assert np.sqrt(np.mean((model - rec.output) ** 2)) < 2e-3 * span
