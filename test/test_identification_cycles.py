"""Cycle extraction, data filter, orientation and local derivatives (identification Steps 1-2)."""

from __future__ import annotations

import numpy as np
import pytest

from piezo_stage.identification.cycles import (
    CycleOptions,
    SteadyCycle,
    estimate_period,
    extract_cycle,
    smooth_input,
    split_branches,
    upward_crossings,
)
from piezo_stage.identification.derivatives import adaptive_fit, local_fit, local_root, noise_std
from piezo_stage.identification.errors import (
    DataFormatError,
    NonFiniteDataError,
    NonMonotoneBranchError,
    NoSteadyStateError,
    NotPeriodicError,
    OrientationError,
    SaturatedOutputError,
    TooFewSamplesError,
)
from piezo_stage.identification.filtering import filter_gain, zero_phase_periodic
from piezo_stage.identification.orientation import detect_orientation, resolve_orientation
from piezo_stage.identification.recording import Recording
from piezo_stage.identification.synthetic import CH9_EXAMPLE, CH10_PATCH, triangle_run
from piezo_stage.model.bouc_wen import BoucWenParameters, model_output
from piezo_stage.model.limit_cycle import limit_cycle
from piezo_stage.model.signals import triangle

pytestmark = pytest.mark.unit

CH9 = BoucWenParameters(**CH9_EXAMPLE)
PATCH = BoucWenParameters(**CH10_PATCH)


def ch9_run(**kw) -> Recording:
    kw.setdefault("samples_per_branch", 500)
    return triangle_run(CH9, -0.2, 0.2, **kw)


# ------------------------------------------------------------------ period, steady state


def test_period_and_crossings_of_a_triangle():
    rec = ch9_run(period=2.5, periods=4.3, phase=0.4)
    period, crossings = estimate_period(rec)
    assert period == pytest.approx(2.5, rel=1e-9)
    # every crossing at the same phase, near the mid level a quarter period after the minimum
    phases = np.mod(crossings + 0.4 * 2.5, 2.5)
    assert np.ptp(phases) < 1e-9 and phases[0] == pytest.approx(0.25 * 2.5, rel=0.01)


def test_crossings_robust_to_noise():
    t = np.linspace(0, 10, 20001)
    x = triangle(t, 1.0, 0.0, 1.0) + 0.02 * np.random.default_rng(3).standard_normal(len(t))
    assert len(upward_crossings(t, x)) == 10  # no chatter around the mid level


def test_steady_cycle_matches_theorem_2():
    rec = ch9_run(periods=3)
    cycle = extract_cycle(rec)
    assert cycle.periods == 3 and cycle.period == pytest.approx(1.0)
    assert cycle.input[0] == pytest.approx(-0.2) and cycle.i_max == 500
    assert cycle.input[cycle.i_max] == pytest.approx(0.2)
    x = cycle.input[: cycle.i_max + 1]
    w_load, _ = limit_cycle(CH9.rho, CH9.sigma, CH9.n, -0.2, 0.2, x)
    assert np.allclose(cycle.output[: cycle.i_max + 1], 2 * x + 2 * w_load, atol=1e-12)
    assert cycle.raw_samples == 3000


def test_recording_phase_does_not_matter():
    a = extract_cycle(ch9_run(periods=3.2))
    b = extract_cycle(ch9_run(periods=3.6, phase=0.37))
    assert np.allclose(a.output, b.output, atol=1e-9)


def test_transient_periods_are_left_out():
    rec = ch9_run(periods=20, w0=0.0)  # ch. 9 converges by a factor ~0.37 per period
    cycle = extract_cycle(rec)
    # noiseless: every earlier period still differs from the last (by ~1e-10 of the span,
    # above the noise level): only the last one is the cycle, not an average carrying the
    # transient (averaging 24 periods gave 3.6e-5 parameter error instead of 1e-9)
    assert cycle.periods == 1
    assert cycle.start_time > 18.0
    assert cycle.period_rms[0] > 1e-3 and cycle.period_rms[-2] < 1e-5


def test_noisy_transient_periods_average_only_at_the_noise_level():
    rec = ch9_run(periods=20, w0=0.0, noise=1e-4, rng=np.random.default_rng(5))
    cycle = extract_cycle(rec)
    # periods differing from the last by less than the noise are averaged, settling ones not
    assert 2 <= cycle.periods < 19
    assert cycle.start_time > (20 - cycle.periods - 1) * 1.0
    noise = 1e-4 * np.ptp(rec.output)
    used = np.asarray(cycle.period_rms[-cycle.periods :])
    assert np.all(used < 3 * np.sqrt(2) * noise * 1.2)


def test_no_steady_state_when_still_converging():
    with pytest.raises(NoSteadyStateError, match="limit cycle is not reached"):
        extract_cycle(ch9_run(periods=4, w0=0.0))


def test_one_period_cannot_show_a_steady_state():
    with pytest.raises(NoSteadyStateError, match="at least 2"):
        extract_cycle(ch9_run(periods=1.9))


def test_forced_steady_periods():
    cycle = extract_cycle(ch9_run(periods=5), CycleOptions(steady_periods=2))
    assert cycle.periods == 2
    with pytest.raises(NoSteadyStateError, match="requested"):
        extract_cycle(ch9_run(periods=3), CycleOptions(steady_periods=7))


def test_forced_steady_periods_ignore_a_disturbed_settling_period():
    """A stall of the amplifier in the first (settling) period holds the input for 40 ms: the
    run is not periodic as a whole, but the K periods it is asked to use are."""
    rec = ch9_run(period=1.0, periods=6)
    v = rec.input.copy()
    first = estimate_period(rec)[1][0]  # the first rising mid-level crossing
    held = (rec.t > first - 0.03) & (rec.t < first + 0.01)
    v[held] = v[np.argmax(held)]
    disturbed = Recording(rec.t, v, rec.output, rec.name)
    with pytest.raises((NotPeriodicError, NoSteadyStateError)):  # the whole run's period is off
        extract_cycle(disturbed)
    cycle = extract_cycle(disturbed, CycleOptions(steady_periods=3))
    reference = extract_cycle(rec, CycleOptions(steady_periods=3))
    assert cycle.periods == 3 and cycle.period == pytest.approx(1.0, rel=1e-6)
    np.testing.assert_allclose(cycle.output, reference.output, rtol=0, atol=1e-9)


def test_averaging_reduces_noise_and_noise_is_estimated():
    rec = ch9_run(periods=8, noise=1e-3, rng=np.random.default_rng(1))
    sigma = 1e-3 * np.ptp(ch9_run(periods=8).output)
    assert noise_std(rec.output) == pytest.approx(sigma, rel=0.1)
    cycle = extract_cycle(rec)
    assert cycle.periods == 8
    assert cycle.noise_output == pytest.approx(sigma / np.sqrt(8), rel=0.15)


def test_random_input_is_not_periodic():
    rng = np.random.default_rng(0)
    t = np.linspace(0, 10, 5000)
    v = np.cumsum(rng.standard_normal(len(t)))
    rec = Recording(t, v, 2 * v, name="random")
    with pytest.raises(NotPeriodicError):
        extract_cycle(rec)


def test_chirp_is_not_periodic():
    t = np.linspace(0, 10, 20000)
    v = np.sin(2 * np.pi * (0.5 * t + 0.05 * t**2))
    with pytest.raises(NotPeriodicError, match="periods differ"):
        extract_cycle(Recording(t, v, v + 0.1 * v**2))


def test_input_with_a_minor_loop_is_rejected():
    t = np.arange(4 * 2000 + 1) / 2000
    v = triangle(t, 1.0, -0.2, 0.2)
    phase = np.mod(t, 1.0)
    v = v - 0.05 * np.exp(-(((phase - 0.3) / 0.01) ** 2))  # a dip inside the rise
    rec = Recording(t, v, model_output(CH9, v, w0=-0.2))
    with pytest.raises(NonMonotoneBranchError, match="loading"):
        smooth_input(extract_cycle(rec, CycleOptions(steady_periods=2)))


def _noisy_cycle(peak_late: int, dip: float = 0.0) -> SteadyCycle:
    """One averaged period of a measured T-wave input (2000 samples, span 1, noise 1e-4): the
    turning point taken ``peak_late`` samples after the true peak (the raw maximum of a noisy
    record can sit there), ``dip`` a minor reversal at 30 % of the period."""
    m = 2000
    phase = np.arange(m) / m
    v = 1.0 - np.abs(1.0 - 2.0 * phase)
    v = v - dip * np.exp(-(((phase - 0.3) / 0.01) ** 2))
    v = v + np.random.default_rng(3).normal(0.0, 1e-4, m)
    return SteadyCycle(1.0, v, v.copy(), 0.0, 6, 6 * m, 1e-4, 1e-4, m // 2 + peak_late)


def test_a_measured_input_split_a_few_samples_past_its_peak_is_a_t_wave():
    """The noisy record's maximum 5 samples into the fall (within the extremes' search of 1 %
    of the period): the smoothed rise bends down at its end by 0.005 of the span, the
    split's doing, not a minor loop (this refused one good servo record in sixteen)."""
    cycle = _noisy_cycle(peak_late=5)
    v = smooth_input(cycle)
    assert np.max(np.abs(v[50:950] - cycle.input[50:950])) < 1e-3


def test_a_measured_input_with_a_minor_loop_is_still_rejected():
    with pytest.raises(NonMonotoneBranchError, match="loading"):
        smooth_input(_noisy_cycle(peak_late=0, dip=0.05))


def test_clipped_output_is_rejected():
    rec = ch9_run(periods=3)
    y = np.minimum(rec.output, np.percentile(rec.output, 90))
    with pytest.raises(SaturatedOutputError, match="maximum"):
        extract_cycle(Recording(rec.t, rec.input, y))


def test_nan_and_short_and_unordered_runs_are_rejected():
    rec = ch9_run(periods=3)
    y = rec.output.copy()
    y[17] = np.nan
    with pytest.raises(NonFiniteDataError, match="sample 17"):
        extract_cycle(Recording(rec.t, rec.input, y))
    with pytest.raises(TooFewSamplesError):
        extract_cycle(rec.slice(0, 150))
    t = rec.t.copy()
    t[50] = t[49]
    with pytest.raises(DataFormatError, match="strictly increasing"):
        extract_cycle(Recording(t, rec.input, rec.output))


def test_too_few_samples_per_branch():
    rec = triangle_run(CH9, -0.2, 0.2, samples_per_branch=30, periods=10)
    with pytest.raises(TooFewSamplesError, match="branch"):
        extract_cycle(rec)


# ------------------------------------------------------------------ branches


def test_branches_in_model_input_orientation():
    cycle = extract_cycle(triangle_run(PATCH, 0.0, 300.0, period=10, samples_per_branch=400))
    v = smooth_input(cycle)
    loading, unloading = split_branches(cycle, -1, v)
    assert loading.loading and not unloading.loading
    assert np.all(np.diff(loading.x) >= 0) and loading.x[0] == pytest.approx(-300.0)
    # loading in x = -v is the falling voltage: its y lies on the v-falling part of the cycle
    falling = np.concatenate((cycle.output[cycle.i_max :], cycle.output[:1]))
    assert np.allclose(np.sort(loading.y), np.sort(falling))


def test_noisy_input_is_smoothed_branchwise():
    rec = ch9_run(periods=4, input_noise=1e-3, rng=np.random.default_rng(5))
    cycle = extract_cycle(rec)
    v = smooth_input(cycle)
    exact = triangle(cycle.t, 1.0, -0.2, 0.2)
    assert np.max(np.abs(v - exact)) < 0.3 * np.max(np.abs(cycle.input - exact))


# ------------------------------------------------------------------ data filter (§10.3.2)


def test_filter_gain_is_the_thesis_second_order_filter():
    assert filter_gain(np.array([0.0]))[0] == pytest.approx(1.0)
    assert filter_gain(np.array([50.0]))[0] == pytest.approx(1 / (2 * 0.7))  # at ω_n
    assert filter_gain(np.array([500.0]))[0] < 0.011


def test_zero_phase_filter_keeps_the_timing():
    m = 2000
    tau = np.arange(m) / m
    x = triangle(tau, 1.0, -1.0, 1.0)
    noisy = x + 0.05 * np.random.default_rng(2).standard_normal(m)
    filtered = zero_phase_periodic(noisy)
    assert np.std(filtered - x) < 0.25 * np.std(noisy - x)
    assert int(np.argmax(zero_phase_periodic(x))) == m // 2  # no delay


def test_filtered_cycle_option():
    rec = ch9_run(periods=3, noise=1e-3, rng=np.random.default_rng(4))
    clean = extract_cycle(ch9_run(periods=3)).output
    raw = extract_cycle(rec)
    filt = extract_cycle(rec, CycleOptions(data_filter=True))
    inner = slice(50, raw.i_max - 50)  # away from the rounded corners
    assert np.std((filt.output - clean)[inner]) < 0.5 * np.std((raw.output - clean)[inner])
    assert filt.noise_output == raw.noise_output  # the fits still see the white-noise level


# ------------------------------------------------------------------ orientation


def test_orientation_of_thesis_sets():
    c9 = extract_cycle(ch9_run(periods=3))
    assert detect_orientation(c9, smooth_input(c9)).input_sign == 1
    cp = extract_cycle(triangle_run(PATCH, 0.0, 300.0, period=10, samples_per_branch=400))
    assert detect_orientation(cp, smooth_input(cp)).input_sign == -1


def test_requested_orientation_must_fit_the_data():
    c9 = extract_cycle(ch9_run(periods=3))
    o = detect_orientation(c9, smooth_input(c9))
    assert resolve_orientation([o, o], None) == 1
    with pytest.raises(OrientationError, match="requires input_sign=\\+1"):
        resolve_orientation([o], -1)
    flipped = type(o)(-1, -o.mean_gap, o.gap_noise, 0.0)
    with pytest.raises(OrientationError, match="opposite"):
        resolve_orientation([o, flipped], None)


def test_loop_without_hysteresis_is_rejected():
    t = np.arange(3 * 1000 + 1) / 1000
    v = triangle(t, 1.0, 0.0, 1.0)
    rec = Recording(t, v, 2 * v + 0.3 * v**2)
    cycle = extract_cycle(rec)
    with pytest.raises(OrientationError, match="no detectable hysteresis"):
        detect_orientation(cycle, smooth_input(cycle))


def test_figure_eight_is_rejected():
    t = np.arange(3 * 2000 + 1) / 2000
    v = triangle(t, 1.0, -1.0, 1.0)
    rising = np.mod(t, 1.0) < 0.5
    # gap proportional to v: positive on one half of the range, negative on the other
    y = (
        v
        + np.where(rising, 0.05, -0.05) * v * (1 - v**2)
        + 0.01 * np.where(rising, 1, -1) * (1 - v**2)
    )
    cycle = extract_cycle(Recording(t, v, y))
    with pytest.raises(OrientationError, match="crosses itself"):
        detect_orientation(cycle, smooth_input(cycle))


# ------------------------------------------------------------------ local derivatives


def test_local_fit_is_exact_on_cubics_and_one_sided_at_ends():
    x = np.linspace(0, 1, 201)
    y = 1 - 2 * x + 3 * x**2 - 0.5 * x**3
    f = local_fit(x, y, 0.4, 9)
    assert f.value == pytest.approx(1 - 0.8 + 0.48 - 0.032, abs=1e-12)
    assert f.slope == pytest.approx(-2 + 2.4 - 0.24, abs=1e-10)
    end = local_fit(x, y, 1.0, 9)
    assert end.slope == pytest.approx(-2 + 6 - 1.5, abs=1e-9) and end.samples == 9


def test_adaptive_window_widens_with_noise_and_beats_differences():
    rng = np.random.default_rng(7)
    x = np.linspace(0, 1, 4001)
    clean = np.sin(2 * x)
    noisy = clean + 1e-4 * rng.standard_normal(len(x))
    sharp = adaptive_fit(x, clean, 0.5, noise=noise_std(clean), slope_scale=1.0)
    wide = adaptive_fit(x, noisy, 0.5, noise=noise_std(noisy), slope_scale=1.0)
    assert sharp.samples == 8 and wide.samples > 100
    exact = 2 * np.cos(1.0)
    raw_difference = (noisy[2001] - noisy[2000]) / (x[2001] - x[2000])  # (9.39)
    assert abs(wide.slope - exact) < 1e-3 < abs(raw_difference - exact)
    assert abs(wide.slope - exact) < 4 * wide.slope_std


def test_local_root():
    x = np.linspace(-1, 1, 1001)
    f = local_root(x, np.tanh(3 * (x - 0.123)), 0.0, noise=0.0, slope_scale=1.0)
    assert f.x0 == pytest.approx(0.123, abs=1e-9) and f.slope == pytest.approx(3.0, rel=1e-6)
