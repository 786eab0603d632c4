"""Trajectories for tracking: closed-form derivatives, limits, ranges, CSV input."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.control.trajectory import (
    CsvTrajectory,
    PeriodicTrajectory,
    Shape,
    TrajectoryError,
    make_trajectory,
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


@settings(max_examples=examples(30), deadline=None)
@given(
    shape=st.sampled_from(list(Shape)),
    amplitude=st.floats(1e-7, 5e-5),
    frequency=st.floats(0.5, 500.0),
    rounding=st.floats(0.05, 1.0),
    t=st.lists(st.floats(0.0, 10.0), min_size=1, max_size=20),
)
def test_stays_within_its_range(shape, amplitude, frequency, rounding, t):
    tr = PeriodicTrajectory(shape, amplitude, frequency, offset=0.0, rounding=rounding)
    x, v, a = tr.evaluate(np.array(t))
    assert np.all(np.abs(x) <= amplitude * (1 + 1e-9))
    assert np.all(np.abs(v) <= tr.peak_velocity * (1 + 1e-9))
    assert np.all(np.isfinite(a))


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
