"""Feedforward for a sampled loop and its learning (piezo_stage.control.learning): the model's
response against the plant it describes, one exact update against a linear loop, the limits
every table keeps, the stop rule, tables on disk, and the ch. 11 rig tracked at 1 kHz."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.control.controller import ControllerConfig, TimeVaryingPID
from piezo_stage.control.feedforward import Compensation, FeedforwardModel
from piezo_stage.control.learning import (
    MAX_MISSING,
    MAX_MISSING_RUN,
    FeedforwardTable,
    IterativeLearning,
    LearningConfig,
    LearningError,
    PeriodicLearner,
    at_limits,
    feedforward_response,
    fill_gaps,
    harmonics,
    incremental_stiffness,
    limit,
    sampled_feedforward,
)
from piezo_stage.control.model_fit import perturbed
from piezo_stage.control.scan import make_trajectory
from piezo_stage.control.tracking import simulate_tracking
from piezo_stage.model.parameter_set import Dynamics, shipped_parameter_set
from piezo_stage.model.plant import DynamicPlant

pytestmark = pytest.mark.unit

RIG = shipped_parameter_set("ch11_rig")
RATE = 1000.0


def nearly_linear(ps):
    """The rig with its hysteresis made negligible (κw·ρ 1e-6 of κx): a linear plant."""
    bw = replace(ps.bouc_wen, kappa_w=ps.bouc_wen.kappa_w * 1e-6)
    return replace(ps, bouc_wen=bw)


def test_the_response_is_what_the_plant_does_at_each_harmonic():
    """G without feedback against the model's own DynamicPlant (collocation, not the ZOH
    formula), driven by a periodic staircase with every harmonic: x/u per harmonic within
    1e-3 in steady state, for the rig's 7 kHz resonance sampled at 1 kHz and at 20 kHz."""
    ps = nearly_linear(RIG)
    model = FeedforwardModel.from_parameter_set(ps)
    for rate, n in ((RATE, 64), (20e3, 128)):
        rng = np.random.default_rng(3)
        u = 100.0 + rng.normal(0.0, 10.0, n)
        stage = DynamicPlant(ps.bouc_wen, ps.dynamics, x0=100.0 / ps.bouc_wen.kappa_x)
        x = []
        for _ in range(30):  # the resonance's ringing decays within a few periods
            x = []
            for value in u:
                x.append(stage.output())
                stage.step(float(value), 1.0 / rate)
        U, X = np.fft.rfft(u), np.fft.rfft(np.array(x))
        G = feedforward_response(model, rate, n)
        k = incremental_stiffness(model)
        assert np.max(np.abs(X[1:] / U[1:] - G[1:])) * k < 1e-3


def test_with_the_law_no_mean_passes_and_the_loop_is_the_plant_over_one_plus_cp():
    model = FeedforwardModel.from_parameter_set(RIG)
    from piezo_stage.control.laws import THESIS_GAINS

    open_loop = feedforward_response(model, RATE, 100)
    closed = feedforward_response(model, RATE, 100, gains=THESIS_GAINS)
    assert closed[0] == 0.0
    z = np.exp(2j * math.pi * harmonics(100, RATE)[1:] / RATE)
    g = THESIS_GAINS
    c = g.k1 + g.k0 / RATE / (1 - 1 / z) + g.k2 * (1 - 1 / z) * RATE
    assert np.allclose(closed[1:], open_loop[1:] / (1 + c * open_loop[1:]), rtol=1e-12)


def circulant_loop(g: np.ndarray, x_d: np.ndarray):
    """A linear loop whose error is exactly e = G·u − x_d (per harmonic)."""
    return lambda u: np.fft.irfft(g * np.fft.rfft(u), x_d.size) - x_d


def test_one_update_with_the_exact_response_leaves_only_what_q_removes():
    model = FeedforwardModel.from_parameter_set(RIG)
    n = 100
    g = feedforward_response(model, RATE, n)
    x_d = 10e-6 * np.sin(2 * math.pi * np.arange(n) / n) + 20e-6
    error = circulant_loop(g, x_d)
    table = FeedforwardTable(np.zeros(n), RATE)
    learning = IterativeLearning(
        table, g, LearningConfig(gain=1.0, cutoff_hz=RATE / 2, settle_periods=0)
    )
    before = np.sqrt(np.mean(error(table.u) ** 2))
    learning.update(error(table.u))
    assert np.sqrt(np.mean(error(table.u) ** 2)) < 1e-9 * before
    # a half gain halves the error each period
    table2 = FeedforwardTable(np.zeros(n), RATE)
    half = IterativeLearning(
        table2, g, LearningConfig(gain=0.5, cutoff_hz=RATE / 2, settle_periods=0)
    )
    for _ in range(3):
        half.update(error(table2.u))
    assert np.sqrt(np.mean(error(table2.u) ** 2)) == pytest.approx(before / 8, rel=1e-6)


def test_settling_periods_are_not_learned_from_and_learning_stops_when_the_error_stalls():
    model = FeedforwardModel.from_parameter_set(RIG)
    n = 50
    g = feedforward_response(model, RATE, n)
    x_d = 5e-6 * np.cos(2 * math.pi * np.arange(n) / n)
    error = circulant_loop(g, x_d)
    table = FeedforwardTable(np.zeros(n), RATE)
    learning = IterativeLearning(
        table, g, LearningConfig(gain=1.0, cutoff_hz=RATE / 2, settle_periods=1, patience=2)
    )
    learning.update(np.full(n, 1.0))  # the start settles: ignored, whatever it holds
    assert not table.u.any()
    learning.update(error(table.u))  # learned: the table changes
    changed = table.u.copy()
    assert changed.any()
    learning.update(np.full(n, 1.0))  # a settling period after the change: ignored
    assert np.array_equal(table.u, changed)
    periods = 0
    while not learning.done:
        learning.update(error(table.u))
        periods += 1
        assert periods < 20
    # the first update converged (second entry), then two learned periods without
    # improvement stop it
    assert len(learning.history) == 4 and learning.periods == 3 + periods
    assert learning.history[1] < 1e-12 * learning.history[0]
    frozen = table.u.copy()
    learning.update(error(table.u) + 1e-6)
    assert np.array_equal(table.u, frozen)


def test_errors_at_the_rounding_floor_are_no_improvement():
    """Once the error is at the floating-point floor, its size there is rounding (it varies with
    the CPU and the BLAS kernel): a 'fall' by half from 1e-21 to 5e-22 does not keep learning
    going; two such periods stop it as any stall does."""
    model = FeedforwardModel.from_parameter_set(RIG)
    n = 50
    g = feedforward_response(model, RATE, n)
    learning = IterativeLearning(
        FeedforwardTable(np.zeros(n), RATE),
        g,
        LearningConfig(gain=1.0, cutoff_hz=RATE / 2, settle_periods=0, patience=2),
    )
    for rms in (3.5e-6, 1.2e-21, 6e-22, 3e-22):
        learning.update(np.full(n, rms))
    assert learning.done and len(learning.history) == 4


@settings(max_examples=200, deadline=None)
@given(
    u=st.lists(st.floats(-1e3, 1e3), min_size=2, max_size=40),
    lo=st.floats(-500, 0),
    span=st.floats(1, 1000),
    slew=st.floats(1.0, 1e6),
    periodic=st.booleans(),
)
@example(u=[0.0, 1000.0, -1000.0, 1000.0], lo=-10.0, span=20.0, slew=1.0, periodic=True)
@example(u=[-1.0, 0.0, 0.0, 0.0, 0.0], lo=-1.0, span=1.0, slew=1.0, periodic=True)
def test_every_table_value_keeps_the_limits_and_the_slew(u, lo, span, slew, periodic):
    config = LearningConfig(u_min=lo, u_max=lo + span, slew_rate=slew)
    out = limit(np.array(u), config, RATE, periodic)
    cap = slew / RATE
    assert np.all(out >= lo) and np.all(out <= lo + span)
    steps = np.diff(np.concatenate([out, out[:1]]) if periodic else out)
    assert np.all(np.abs(steps) <= cap * (1 + 1e-9) + 1e-12)


@settings(max_examples=200, deadline=None)
@given(
    u=st.lists(st.floats(-1e3, 1e3), min_size=2, max_size=40),
    lo=st.floats(-500, 0),
    span=st.floats(1, 1000),
)
@example(u=[-1e3, 1e3], lo=-10.0, span=20.0)
@example(u=[0.0, 4.141999409885948e-282], lo=0.0, span=1.0)
def test_every_clipped_value_is_counted_and_no_other(u, lo, span):
    """A value the clip moved sits at a limit and is counted, as is one within 1e-9 of the
    range of it (already there); one 1e-6 of the range inside is not."""
    hi = lo + span
    x = np.array(u)
    out = np.clip(x, lo, hi)
    outside = int(np.count_nonzero((x < lo) | (x > hi)))
    tol = 1e-9 * (hi - lo)
    near = (x >= lo) & (x <= hi) & ((x <= lo + tol) | (x >= hi - tol))
    assert outside <= at_limits(out, lo, hi) <= outside + int(np.count_nonzero(near))
    inside = np.clip(x, lo + 1e-6 * span, hi - 1e-6 * span)
    assert at_limits(inside, lo, hi) == 0


def test_bad_configurations_and_errors_are_refused():
    for kwargs in (
        {"gain": 0.0},
        {"gain": 1.5},
        {"cutoff_hz": 0.0},
        {"u_min": 1, "u_max": 0},
        {"slew_rate": 0.0},
        {"patience": 0},
        {"settle_periods": -1},
    ):
        with pytest.raises(LearningError):
            LearningConfig(**kwargs)
    table = FeedforwardTable(np.zeros(10), RATE)
    g = feedforward_response(FeedforwardModel.from_parameter_set(RIG), RATE, 10)
    learning = IterativeLearning(table, g)
    with pytest.raises(LearningError):
        learning.update(np.zeros(9))
    with pytest.raises(LearningError):
        learning.update(np.full(10, math.nan))
    with pytest.raises(LearningError):
        IterativeLearning(FeedforwardTable(np.zeros(12), RATE), g)
    with pytest.raises(LearningError):
        FeedforwardTable(np.array([1.0, math.inf]), RATE)


def test_a_table_saved_is_the_table_loaded_and_a_foreign_file_is_refused(tmp_path):
    table = FeedforwardTable(np.linspace(-3, 3, 7), 2000.0, meta={"trajectory": "triangle"})
    path = table.save(tmp_path / "ff.json")
    back = FeedforwardTable.load(path)
    assert np.array_equal(back.u, table.u) and back.rate_hz == 2000.0
    assert back.meta == {"trajectory": "triangle"} and back.periodic
    assert back.matches(2000.0, 7) == ""
    assert "1000" in back.matches(1000.0, 7) and "7 samples" in back.matches(2000.0, 8)
    (tmp_path / "other.json").write_text(json.dumps({"u": [1, 2]}))
    for bad in (tmp_path / "other.json", tmp_path / "missing.json"):
        with pytest.raises(LearningError):
            FeedforwardTable.load(bad)


def test_a_table_is_read_at_the_time_since_the_first_update():
    """The controller takes u_ff from the table at t − t_first (periodic), the model unused."""
    table = FeedforwardTable(np.array([1.0, 2.0, 3.0, 4.0]), RATE)
    config = ControllerConfig(compensation=Compensation.FEEDFORWARD, feedforward_table=table)
    pid = TimeVaryingPID(config, closed=True)
    t0 = 12.345
    got = [pid.update(t0 + k / RATE, 0.0, 0.0).u_ff for k in range(9)]
    assert got == [1.0, 2.0, 3.0, 4.0, 1.0, 2.0, 3.0, 4.0, 1.0]


def rig_triangle():
    trajectory = make_trajectory("triangle", amplitude=10e-6, frequency=10.0)
    n = int(round(trajectory.period * RATE))
    return trajectory, np.asarray(trajectory.evaluate(np.arange(n) / RATE)[0])


def test_the_sampled_feedforward_beats_the_sampled_continuous_one_tenfold_at_1_khz():
    """The ch. 11 rig at 1 kHz, its own model, 10 Hz triangle over 20 um: the continuous u_ff
    sampled leaves ~4 % of the range (the staircase rings the 7 kHz resonance, which wears w
    down); the staircase computed for the sampled loop leaves < 0.4 %."""
    model = FeedforwardModel.from_parameter_set(RIG)
    trajectory, x_d = rig_triangle()
    _, continuous = simulate_tracking(trajectory, RIG, "both", model, rate_hz=RATE)
    table = sampled_feedforward(model, x_d, RATE)
    _, sampled = simulate_tracking(trajectory, RIG, "both", model, rate_hz=RATE, table=table)
    assert continuous.relative > 0.02
    assert sampled.relative < 0.1 * continuous.relative and sampled.relative < 0.004


@pytest.mark.parametrize("factor", [1.05, 0.95])
def test_learning_on_a_rig_5_percent_off_its_model_reaches_a_tenth_of_the_target(factor):
    """The plant 5 % off the model in every parameter: at most 20 learning periods (one
    settling period after each change) bring the frozen table under 0.03 % of the range
    (the figure asked is 0.3 %)."""
    model = FeedforwardModel.from_parameter_set(perturbed(RIG, factor))
    trajectory, x_d = rig_triangle()
    table = sampled_feedforward(model, x_d, RATE)
    _, errors = simulate_tracking(
        trajectory,
        RIG,
        "both",
        model,
        rate_hz=RATE,
        table=table,
        learn_periods=20,
        learning=LearningConfig(u_min=-450.0, u_max=450.0),
    )
    assert errors.relative < 3e-4
    assert errors.learning[-1] < 0.1 * errors.learning[0]


def test_learning_stops_itself_once_the_error_stops_falling():
    """The rig's own model: the error falls to what Q leaves within a few updates, then two
    learned periods without a 5 % gain end the learning before the 20 periods allowed."""
    model = FeedforwardModel.from_parameter_set(RIG)
    trajectory, x_d = rig_triangle()
    table = sampled_feedforward(model, x_d, RATE)
    _, errors = simulate_tracking(
        trajectory, RIG, "both", model, rate_hz=RATE, table=table, learn_periods=20
    )
    assert 4 <= len(errors.learning) < 20 and errors.relative < 3e-4


def test_learning_refuses_what_it_cannot_learn():
    trajectory, x_d = rig_triangle()
    model = FeedforwardModel.from_parameter_set(RIG)
    with pytest.raises(Exception, match="learning needs"):
        simulate_tracking(trajectory, RIG, "both", model, rate_hz=RATE, learn_periods=3)
    static = FeedforwardModel(RIG.bouc_wen, 0.0, 0.0)
    g = feedforward_response(static, RATE, 4)
    z = np.exp(2j * math.pi * harmonics(4, RATE) / RATE)
    assert np.allclose(g, 1.0 / (incremental_stiffness(static) * z))
    assert Dynamics(RIG.dynamics.m, RIG.dynamics.c) == RIG.dynamics


@settings(max_examples=100, deadline=None)
@given(
    n=st.integers(20, 600),
    holes=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(1, 20)), max_size=60),
)
@example(n=100, holes=[(0.995, 3)])  # a run across the period's end
def test_a_few_missing_samples_are_filled_and_too_many_refuse_the_period(n, holes):
    """What is there is kept, what is missing is interpolated between its periodic neighbours
    (a chord's error), and a period missing more than half its samples, or a run longer than
    3 % of it (3 at least), is refused."""
    error = np.sin(2 * math.pi * np.arange(n) / n)
    holed = error.copy()
    for at, length in holes:
        start = int(at * n)
        holed[np.arange(start, start + length) % n] = np.nan
    missing = np.isnan(holed)
    filled = fill_gaps(holed)
    runs = [0]
    for k in range(2 * n):  # around the end too
        runs.append(runs[-1] + 1 if missing[k % n] else 0)
    longest = max(runs)
    refuse = (
        missing.all() or missing.sum() > MAX_MISSING * n or longest > max(3, MAX_MISSING_RUN * n)
    )
    if refuse:
        assert filled is None
        return
    assert filled is not None and np.all(np.isfinite(filled))
    np.testing.assert_array_equal(filled[~missing], error[~missing])
    # a unit sine's chord across a run of r missing samples (r + 1 intervals of 2π/n) is off
    # by at most h²/8, h = 2π(r + 1)/n
    assert np.abs(filled - error).max() <= (2 * math.pi * (longest + 1) / n) ** 2 / 8 + 1e-12


def test_a_period_a_loaded_loop_superseded_a_few_samples_of_is_still_learned():
    model = FeedforwardModel.from_parameter_set(RIG)
    n = 100
    g = feedforward_response(model, RATE, n)
    table = FeedforwardTable(np.zeros(n), RATE)
    learning = IterativeLearning(table, g, LearningConfig(settle_periods=0))
    learner = PeriodicLearner(learning, periods=10)
    error = 1e-7 * np.sin(2 * math.pi * np.arange(n) / n)
    ends = []
    for period in range(3):
        for k in range(n):
            # period 0: two samples missing (learned); period 1: a 10-sample gap (skipped);
            # period 2: its last sample missing (it ends when the index wraps)
            gone = (
                (period == 0 and k in (40, 41))
                or (period == 1 and 30 <= k < 40)
                or (period == 2 and k == n - 1)
            )
            if not gone and learner.record(k, float(error[k])):
                ends.append((period, k))
    assert ends == [(0, n - 1), (1, n - 1)]  # at its last sample: the next plays the new table
    assert learner.record(0, 0.0)  # the third period ends
    assert learner.completed == 3 and learner.skipped == 1 and len(learning.history) == 2


def test_a_frame_learns_its_correction_from_each_line_past_the_fly_back():
    """A raster's slow axis: the learner's periods are the frame's lines (6 a frame, 1 of
    fly-back); the correction learns from the lines past the fly-back's settling only, every
    line counts toward ``periods``, and the frame's table is its base plus the correction on
    the lines past the fly-back."""
    from piezo_stage.control.learning import SETTLE_LINES, LineCorrection

    model = FeedforwardModel.from_parameter_set(RIG)
    n, lines, first = 50, 6, 1
    frame = FeedforwardTable(np.linspace(0.0, 5.0, n * lines), RATE)
    base = frame.u.copy()
    config = LearningConfig(settle_periods=0, patience=100)
    correction = LineCorrection(
        frame, n, first, feedforward_response(model, RATE, n), config, model
    )
    done = []
    learner = PeriodicLearner(correction, periods=2 * lines, on_done=done.append)
    error = 1e-7 * np.sin(2 * math.pi * np.arange(n) / n)
    for k in range(2 * lines * n + 1):  # two frames, and the first sample of a third
        learner.record(k % (lines * n), float(error[k % n]))
    assert learner.completed == 2 * lines and learner.frozen and done == [learner]
    # of each frame's lines, those from first + SETTLE_LINES on
    assert len(correction.history) == 2 * (lines - first - SETTLE_LINES)
    delta = (frame.u - base).reshape(lines, n)
    assert np.all(delta[:first] == 0.0) and np.abs(delta[first:]).max() > 0
    np.testing.assert_allclose(
        delta[first:], np.tile(correction.correction.u, (lines - 1, 1)), atol=1e-12
    )
    with pytest.raises(LearningError, match="not whole lines of 70"):
        LineCorrection(frame, 70, first, feedforward_response(model, RATE, 70), config, model)
