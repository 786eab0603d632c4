"""Trajectories for tracking: closed-form derivatives, limits, ranges, CSV input."""

import math

import numpy as np
import pytest
from hypothesis import event, example, given, settings
from hypothesis import strategies as st

from piezo_stage.control.scan import make_trajectory
from piezo_stage.control.trajectory import (
    CsvTrajectory,
    PeriodicTrajectory,
    SetPoint,
    Shape,
    TrajectoryError,
)

from property_support import examples

pytestmark = pytest.mark.unit


def _numeric_derivatives(tr, t):
    x, v, a = tr.evaluate(t)
    dt = t[1] - t[0]
    return x, v, a, np.gradient(x, dt), np.gradient(v, dt)


@pytest.mark.parametrize("shape", list(Shape))
def test_velocity_and_acceleration_are_the_derivatives(shape):
    tr = PeriodicTrajectory(shape, amplitude=10e-6, frequency=10.0)
    t = np.linspace(0.0, 0.25, 250_001)
    x, v, a, dx, dv = _numeric_derivatives(tr, t)
    inner = slice(2, -2)
    assert np.abs(dx - v)[inner].max() <= 1e-6 * tr.peak_velocity
    assert np.abs(dv - a)[inner].max() <= 1e-3 * tr.peak_acceleration  # a is continuous
    assert x.min() == pytest.approx(0.0, abs=1e-15) and x.max() == pytest.approx(20e-6)
    assert np.abs(v).max() == pytest.approx(tr.peak_velocity, rel=1e-3)
    assert np.abs(a).max() == pytest.approx(tr.peak_acceleration, rel=1e-3)


def test_triangle_is_a_constant_velocity_scan_between_rounded_corners():
    tr = PeriodicTrajectory(Shape.TRIANGLE, amplitude=10e-6, frequency=10.0, rounding=0.2)
    t = np.linspace(0.0, 0.1, 100_001)
    _, v, a = tr.evaluate(t)
    ramp = (t > 0.5 * tr.blend_time + 1e-4) & (t < 0.05 - 0.5 * tr.blend_time - 1e-4)
    assert np.all(v[ramp] == pytest.approx(tr.peak_velocity)) and np.all(a[ramp] == 0.0)
    # the corners cost 2 T_c (1 - 2/pi) of ramp time: v just above range / half period
    assert tr.peak_velocity > 20e-6 / 0.05


def test_acceleration_limit_lengthens_the_corners_and_impossible_limits_are_refused():
    free = PeriodicTrajectory(Shape.TRIANGLE, amplitude=10e-6, frequency=10.0)
    limited = PeriodicTrajectory(Shape.TRIANGLE, amplitude=10e-6, frequency=10.0, a_max=0.05)
    assert limited.blend_time > free.blend_time and limited.peak_acceleration <= 0.05 * (1 + 1e-9)
    with pytest.raises(TrajectoryError, match="acceleration .* a_max"):
        PeriodicTrajectory(Shape.SINE, amplitude=5e-6, frequency=100.0, a_max=1.0)
    with pytest.raises(TrajectoryError, match="velocity .* v_max"):
        PeriodicTrajectory(Shape.STEPS, amplitude=5e-6, frequency=100.0, v_max=1e-4)
    with pytest.raises(TrajectoryError, match="frequency"):
        make_trajectory("sine", frequency=math.nan)
    with pytest.raises(TrajectoryError, match="unknown trajectory"):
        make_trajectory("square")


#: every periodic trajectory's arguments
SHAPES = dict(
    shape=st.sampled_from(list(Shape)),
    amplitude=st.floats(1e-7, 5e-5),
    frequency=st.floats(0.5, 500.0),
    offset=st.floats(-1e-4, 1e-4),
    rounding=st.floats(0.05, 1.0),
)


def _unlimited(tr: PeriodicTrajectory, rounding: float) -> PeriodicTrajectory:
    """``tr``'s shape without limits, its blend rounding·P/2 (what the shape needs there)."""
    return PeriodicTrajectory(tr.shape, tr.amplitude, tr.frequency, tr.offset, rounding=rounding)


@settings(max_examples=examples(60), deadline=None)
@given(
    **SHAPES,
    v_factor=st.one_of(st.none(), st.floats(0.3, 1.5)),
    a_factor=st.one_of(st.none(), st.floats(0.1, 1.5)),
    t=st.lists(st.floats(0.0, 10.0), min_size=1, max_size=20),
)
# a triangle whose a_max asks a longer corner that its v_max still allows (was refused)
@example(Shape.TRIANGLE, 3.576094819522429e-05, 1.0, 0.0, 0.0625, 1.5, 0.5, [0.0])
def test_stays_within_its_range_and_its_limits(
    shape, amplitude, frequency, offset, rounding, v_factor, a_factor, t
):
    """v_max and a_max drawn around what the shape needs without them (a factor of its free
    peaks, or none). Built: it stays within offset ± amplitude and under its peaks, which are
    within the limits; a triangle's corner or a step's transition is no shorter than
    rounding·P/2 and no longer than P/2, and the shortest there within the limits (a
    millionth shorter breaks one). Refused: the message names the limit, and the shape breaks
    a limit at rounding·P/2, at P/2 (the longest blend there is; the shortest for a sine,
    which has none) and at every blend between."""
    free = PeriodicTrajectory(shape, amplitude, frequency, offset=offset, rounding=rounding)
    v_max = math.inf if v_factor is None else v_factor * free.peak_velocity
    a_max = math.inf if a_factor is None else a_factor * free.peak_acceleration

    def breaks_a_limit(tr: PeriodicTrajectory, margin: float = 0.0) -> bool:
        return tr.peak_velocity > v_max * (1 + margin) or tr.peak_acceleration > a_max * (
            1 + margin
        )

    try:
        tr = PeriodicTrajectory(shape, amplitude, frequency, offset, rounding, v_max, a_max)
    except TrajectoryError as exc:
        event("refused")
        assert "v_max" in str(exc) or "a_max" in str(exc)
        assert breaks_a_limit(free) and breaks_a_limit(_unlimited(free, 1.0), 1e-9)
        # and no blend between: a triangle's v rises as its a falls
        assert all(breaks_a_limit(_unlimited(free, r)) for r in np.linspace(rounding, 1.0, 25))
        return
    x, v, a = tr.evaluate(np.array(t))
    assert np.all(np.abs(x - offset) <= amplitude * (1 + 1e-9))
    assert np.all(np.abs(v) <= tr.peak_velocity * (1 + 1e-9))
    assert np.all(np.abs(a) <= tr.peak_acceleration * (1 + 1e-9))
    assert tr.peak_velocity <= v_max * (1 + 1e-9) and tr.peak_acceleration <= a_max * (1 + 1e-9)
    half = 0.5 * tr.period
    if shape is Shape.SINE:
        event("built: sine")
        assert tr.blend_time == 0.0
        return
    assert rounding * half * (1 - 1e-12) <= tr.blend_time <= half * (1 + 1e-12)
    if tr.blend_time > rounding * half * (1 + 1e-9):  # lengthened to meet a limit
        event("built: blend lengthened")
        assert breaks_a_limit(_unlimited(tr, (1 - 1e-6) * tr.blend_time / half))
    else:
        event("built: blend as rounded")
        assert tr.blend_time == pytest.approx(free.blend_time, rel=1e-12)


def test_a_triangle_that_meets_both_limits_is_built():
    """A longer corner lowers a triangle's acceleration but raises its ramp velocity: the corner
    lengthens for a_max only, to the shortest that meets it, then v_max is checked there."""
    at_20_ms = PeriodicTrajectory(Shape.TRIANGLE, 10e-6, 10.0, rounding=0.4)  # corner P/2 · 0.4
    assert at_20_ms.blend_time == pytest.approx(0.02)
    v_max, a_max = 1.01 * at_20_ms.peak_velocity, 1.01 * at_20_ms.peak_acceleration
    tr = PeriodicTrajectory(Shape.TRIANGLE, 10e-6, 10.0, rounding=0.2, v_max=v_max, a_max=a_max)
    assert tr.peak_velocity <= v_max and tr.peak_acceleration <= a_max
    assert 0.01 < tr.blend_time < at_20_ms.blend_time  # the shortest corner within a_max


def test_csv_spline_holds_its_ends_and_reports_bad_files(tmp_path):
    path = tmp_path / "scan.csv"
    t = np.linspace(0.0, 0.02, 21)
    x = 5e-6 * (1 - np.cos(2 * np.pi * 50 * t))
    rows = "".join(f"{a:.17g},{b:.17g}\n" for a, b in zip(t, x))
    path.write_text("t [s], x [m]\n# a comment\n" + rows)
    tr = make_trajectory(str(path))
    assert isinstance(tr, CsvTrajectory) and tr.range == pytest.approx(10e-6)
    xs, vs, accel = tr.evaluate(np.array([-1.0, 0.01, 1.0]))
    assert xs[1] == pytest.approx(10e-6, rel=1e-3) and vs[0] == vs[2] == 0.0 and accel[2] == 0.0
    bad = tmp_path / "bad.csv"
    bad.write_text("0,0\n0.1,1e-6\n0.05,2e-6\n")
    with pytest.raises(TrajectoryError, match="increase"):
        make_trajectory(str(bad))
    bad.write_text("0,0\n0.1,oops\n")
    with pytest.raises(TrajectoryError, match="bad.csv:2"):
        make_trajectory(str(bad))
    with pytest.raises(TrajectoryError, match="cannot read"):
        make_trajectory(str(tmp_path / "missing.csv"))


@settings(max_examples=examples(60), deadline=None)
@given(
    **SHAPES,
    periods=st.lists(st.floats(-2.0, 1e4), min_size=1, max_size=30),
)
def test_a_trajectory_at_one_time_is_its_evaluation_there(
    shape, amplitude, frequency, offset, rounding, periods
):
    """``at(t)`` (a controller's per-sample call, in scalar arithmetic) gives what
    ``evaluate`` gives at t, to rounding, for any shape at any time (drawn in periods, plus
    the corners' and transitions' edges, where the pieces meet)."""
    tr = PeriodicTrajectory(shape, amplitude, frequency, offset=offset, rounding=rounding)
    half, blend = 0.5 * tr.period, tr.blend_time
    edges = np.array([0.0, 0.5 * blend, blend, half - 0.5 * blend, half, tr.period])
    t = np.concatenate([np.array(periods) * tr.period, edges, edges + 3 * tr.period])
    want = tr.evaluate(t)
    got = np.array([tr.at(float(tk)) for tk in t]).T
    scales = (amplitude + abs(offset), tr.peak_velocity, tr.peak_acceleration)
    for g, w, scale in zip(got, want, scales):
        np.testing.assert_allclose(g, w, rtol=0.0, atol=1e-9 * scale)


def test_a_csv_trajectory_and_a_set_point_at_one_time_are_their_evaluation(tmp_path):
    path = tmp_path / "x.csv"
    path.write_text("t,x\n0,0\n0.1,1e-6\n0.3,-2e-6\n0.4,0\n", encoding="utf-8")
    for tr in (CsvTrajectory.read(path), SetPoint(3e-6)):
        for t in (-0.1, 0.0, 0.05, 0.1, 0.25, 0.4, 1.0):
            assert tr.at(t) == tuple(float(v) for v in tr.evaluate(t))
