"""Raster scans: both axes in closed form, the image windows, rows and pixels, bad scans."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.control.scan import (
    FastShape,
    Order,
    RasterScan,
    ScanAxis,
    ScanError,
    SlowMotion,
    make_trajectory,
    quintic_transition,
)

from property_support import examples

pytestmark = pytest.mark.unit

R, C = (20e-6, 10e-6), (12e-6, 6e-6)


def scan(**kw):
    args = dict(lines=8, pixels=32, line_rate=10.0, range=R, centre=C)
    return RasterScan(**{**args, **kw})


def _derivatives_agree(s: RasterScan, t):
    """ẋ and ẍ of both axes are the derivatives of x and ẋ (so x and ẋ are continuous)."""
    dt = t[1] - t[0]
    for x, v, a in s.evaluate(t):
        peak_v, peak_a = max(np.abs(v).max(), 1e-12), max(np.abs(a).max(), 1e-9)
        assert np.abs(np.gradient(x, dt) - v)[2:-2].max() <= 1e-3 * peak_v
        assert np.abs(np.gradient(v, dt) - a)[2:-2].max() <= 2e-2 * peak_a


def test_quintic_transition_meets_its_end_conditions():
    x, v, a = quintic_transition(np.array([0.0, 2.0]), 2.0, 1.0, 0.3, -4.0, -0.7)
    np.testing.assert_allclose(x, [1.0, -4.0], atol=1e-12)
    np.testing.assert_allclose(v, [0.3, -0.7], atol=1e-12)
    np.testing.assert_allclose(a, [0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("order", list(Order))
@pytest.mark.parametrize("motion", list(SlowMotion))
@pytest.mark.parametrize("shape", list(FastShape))
def test_both_axes_are_smooth_over_two_frames(shape, motion, order):
    s = scan(fast_shape=shape, slow_motion=motion, order=order)
    t = np.linspace(0.0, 2 * s.frame_time, 400_001)
    _derivatives_agree(s, t)
    (x, vx, _), (y, vy, _) = s.evaluate(t)
    pitch = R[1] / s.lines  # a ramp's fly-back and lead-in over-travel by less than a row
    assert y.min() >= C[1] - R[1] / 2 - pitch and y.max() <= C[1] + R[1] / 2 + pitch
    # the second frame repeats the first after its lead-in
    later = t > s.window_start(0)
    shifted = s.evaluate(t[later] + s.frame_time)
    np.testing.assert_allclose(shifted[1][0], y[later], atol=1e-15)
    np.testing.assert_allclose(shifted[0][0], x[later], atol=1e-15)
    assert vx[0] == 0.0 and vy[0] == pytest.approx(0.0, abs=1e-18)  # it starts at rest
    assert x[0] == pytest.approx(x.min())


@pytest.mark.parametrize("order", list(Order))
@pytest.mark.parametrize("shape", list(FastShape))
def test_image_windows_sweep_the_range_on_their_row(shape, order):
    s = scan(fast_shape=shape, order=order)
    rows = s.row_positions()
    np.testing.assert_allclose(np.diff(rows), R[1] / 8)
    assert rows.mean() == pytest.approx(C[1])
    for k in range(s.lines):
        a = float(s.window_start(k))
        t = np.linspace(a, a + s.window, 201)
        (x, vx, _), (y, vy, _) = s.evaluate(t)
        lo, hi = C[0] - R[0] / 2, C[0] + R[0] / 2
        forwards = order is Order.RASTER or k % 2 == 0
        assert (x[0], x[-1]) == pytest.approx((lo, hi) if forwards else (hi, lo), abs=1e-12)
        assert np.all(np.sign(vx) == (1 if forwards else -1))
        np.testing.assert_allclose(y, rows[k], atol=1e-15)  # staircase: held on its row
        assert np.abs(vy).max() <= 1e-9 * R[1] / s.window  # (its ends: rounding)
        line, direction = s.line_index(t[1:-1])  # (its ends: rounding either way)
        assert np.all(line == k) and np.all(direction == (1 if forwards else -1))
    if shape is FastShape.TRIANGLE:  # the whole window is the constant-velocity ramp
        a = float(s.window_start(0))
        _, vx, ax = s.evaluate(np.linspace(a, a + s.window, 101))[0]
        assert np.ptp(vx) <= 1e-12 * vx.max()
        assert np.abs(ax).max() <= 1e-9 * s.fast.peak_acceleration


def test_ramp_passes_each_row_in_the_middle_of_its_window():
    s = scan(slow_motion=SlowMotion.RAMP)
    mids = s.window_start(np.arange(s.lines)) + s.window / 2
    (_, _, _), (y, vy, ay) = s.evaluate(mids)
    np.testing.assert_allclose(y, s.row_positions(), atol=1e-15)
    np.testing.assert_allclose(vy, s.slow_velocity())
    assert s.slow_velocity() == pytest.approx(R[1] / 8 / 0.1)


def test_turnarounds_and_flyback_are_outside_the_image():
    s = scan()
    t = np.linspace(0.0, 2 * s.frame_time, 20_001)
    line, direction = s.line_index(t)
    assert np.all((line == -1) == (direction == 0))
    assert np.all(t[line >= 0] >= s.window_start(0) - 1e-12)
    # the image share of a frame: lines × window over the frame
    share = np.mean(line >= 0)
    assert share == pytest.approx(8 * s.window / s.frame_time, abs=2e-3)
    assert set(np.unique(line[line >= 0])) == set(range(8))


def test_pixels_cover_the_image_and_nothing_else():
    s = scan()
    lo, w = C[0] - R[0] / 2, R[0] / 32
    x = lo + (np.arange(32) + 0.5) * w
    np.testing.assert_array_equal(s.pixel_of(x), np.arange(32))
    assert list(s.pixel_of([lo - 1e-9, lo + R[0] + 1e-9])) == [-1, -1]


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(lines=0), "lines"),
        (dict(pixels=2.5), "pixels"),
        (dict(line_rate=float("nan")), "line_rate"),
        (dict(range=(1e-6, -1e-6)), "range"),
        (dict(range=(1e-6,)), "two values"),
        (dict(centre=(0.0, float("inf"))), "centre"),
        (dict(order="zigzag"), "order must be one of raster, serpentine"),
        (dict(order="serpentine", lines=7), "even number of lines"),
        (dict(rounding=1.0), "rounding"),
    ],
)
def test_bad_scans_are_refused_with_the_key(kw, match):
    with pytest.raises(ScanError, match=match):
        scan(**kw)


def test_the_loop_rate_must_sample_lines_and_fill_pixels():
    s = scan(pixels=256, line_rate=10.0)  # window 40 ms
    s.check_rate(10_000.0)  # 400 samples per window
    with pytest.raises(ScanError, match="256 pixels per line .* 40.0 samples"):
        s.check_rate(1000.0)
    with pytest.raises(ScanError, match="samples per image line"):
        scan(pixels=4, line_rate=100.0).check_rate(1000.0)


#: every kind of scan (an even number of lines: a serpentine needs one)
SCANS = dict(
    lines=st.integers(1, 6).map(lambda n: 2 * n),
    rate=st.floats(0.5, 200.0),
    shape=st.sampled_from(list(FastShape)),
    motion=st.sampled_from(list(SlowMotion)),
    order=st.sampled_from(list(Order)),
    rounding=st.floats(0.05, 0.95),
    flyback=st.integers(0, 3),
)


@settings(max_examples=examples(40), deadline=None)
@given(**SCANS, share=st.floats(0.05, 0.95))
def test_every_scan_is_smooth_and_images_on_its_rows(
    lines, rate, shape, motion, order, rounding, share, flyback
):
    """For every scan: x and ẋ of both axes continuous (ẋ, ẍ the derivatives), the slow axis
    inside the image's range, every window on its row at the image's edges."""
    s = RasterScan(
        lines, 16, rate, R, C, shape, motion, order, rounding, share, flyback_lines=flyback
    )
    t = np.linspace(0.0, 1.5 * s.frame_time, 300_001)
    _derivatives_agree(s, t)
    mids = s.window_start(np.arange(lines)) + s.window / 2
    (xm, _, _), (ym, _, _) = s.evaluate(mids)
    np.testing.assert_allclose(ym, s.row_positions(), atol=1e-12 * R[1])
    np.testing.assert_allclose(xm, C[0], atol=1e-12 * R[0])
    line, _ = s.line_index(mids)
    np.testing.assert_array_equal(line, np.arange(lines))


@settings(max_examples=examples(30), deadline=None)
@given(**SCANS, index=st.sampled_from([0, 1]))
def test_a_scan_axis_saved_is_read_back_as_the_same_trajectory(
    tmp_path_factory, lines, rate, shape, motion, order, rounding, flyback, index
):
    """A scan axis's file (a controller's ``trajectory``) gives back the same scan and the
    same x_d, ẋ_d, ẍ_d; its period is the line's (fast) or the frame's (slow)."""
    s = RasterScan(lines, 16, rate, R, C, shape, motion, order, rounding, flyback_lines=flyback)
    path = ScanAxis(s, index).save(tmp_path_factory.mktemp("scan") / "axis.json")
    axis = make_trajectory(str(path))
    assert isinstance(axis, ScanAxis) and axis.scan == s and axis.index == index
    assert axis.period == (s.period if index == 0 else s.frame_time) and axis.periodic
    t = np.linspace(-0.1, 2.5 * s.frame_time, 2001)
    for got, want in zip(axis.evaluate(t), s.evaluate(t)[index]):
        np.testing.assert_array_equal(got, want)
    # as a controller evaluates it: one sample at a time
    assert (
        axis.evaluate(0.3 * s.frame_time)[0]
        == s.evaluate(np.array([0.3 * s.frame_time]))[index][0][0]
    )


@pytest.mark.parametrize(
    "text, match",
    [
        ("not json", "is not JSON"),
        ('{"format": "other"}', "is not a scan axis"),
        ('{"format": "piezo_stage raster scan axis 1", "axis": 2, "scan": {}}', "scan"),
        (
            '{"format": "piezo_stage raster scan axis 1", "axis": 0, "scan": {"lines": 4, '
            '"pixels": 8, "line_rate": 10, "range": [1e-6, 1e-6], "spin": 1}}',
            "spin",
        ),
        (
            '{"format": "piezo_stage raster scan axis 1", "axis": 0, "scan": {"lines": 4, '
            '"pixels": 8, "line_rate": -1, "range": [1e-6, 1e-6]}}',
            "line_rate must be > 0",
        ),
    ],
)
def test_a_scan_axis_file_it_cannot_use_names_itself_and_why(tmp_path, text, match):
    path = tmp_path / "axis.json"
    path.write_text(text)
    with pytest.raises(ScanError, match=match) as info:
        ScanAxis.read(path)
    assert str(path) in str(info.value)
    with pytest.raises(ScanError, match="cannot read scan"):
        ScanAxis.read(tmp_path / "missing.json")


@settings(max_examples=examples(40), deadline=None)
@given(
    **SCANS,
    index=st.sampled_from([0, 1]),
    share=st.floats(0.05, 0.95),
    times=st.lists(st.floats(-1.0, 4.0), min_size=1, max_size=30),
)
def test_a_scan_axis_at_one_time_is_its_evaluation_there(
    lines, rate, shape, motion, order, rounding, share, flyback, index, times
):
    """``at(t)`` (a controller's per-sample call, in scalar arithmetic) gives what ``evaluate``
    gives at t, to rounding: at any time in frames (times drawn in frames, plus every window's
    edges and the frame's ends, where the pieces meet)."""
    s = RasterScan(
        lines, 16, rate, R, C, shape, motion, order, rounding, share, flyback_lines=flyback
    )
    axis = ScanAxis(s, index)
    starts = s.window_start(np.arange(lines))
    edges = np.concatenate([starts, starts + s.window, [0.0, s.frame_time]])
    t = np.concatenate([np.array(times) * s.frame_time, edges, edges + s.frame_time])
    want = axis.evaluate(t)
    got = np.array([axis.at(float(tk)) for tk in t]).T
    for g, w in zip(got, want):
        scale = max(np.abs(w).max(), 1e-30)
        np.testing.assert_allclose(g, w, rtol=0.0, atol=1e-9 * scale)
    assert all(type(v) is float for v in axis.at(float(t[0])))
