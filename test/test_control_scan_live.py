"""A scan's image as its samples arrive: fed in any chunks, a frame's image and line errors are
the ones the whole frame gives (scan_image, scan_figures), each line replacing the previous
frame's; the scan's origin found among the recorded stamps."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.control.scan import RasterScan, ScanAxis, ScanError
from piezo_stage.control.scan_image import load_sample, scan_figures, scan_image
from piezo_stage.control.scan_live import ScanAccumulator, scan_origin

pytestmark = pytest.mark.unit

SCAN = RasterScan(6, 32, 20.0, (20e-6, 10e-6), (20e-6, 10e-6))
RATE = 2000.0


def _samples(frames: float, seed: int = 0):
    t = np.arange(int(frames * SCAN.frame_time * RATE)) / RATE
    (x, _, _), (y, _, _) = SCAN.evaluate(t)
    noise = np.random.default_rng(seed).normal(0.0, 30e-9, (2, t.size))
    return t, np.vstack([x, y]) + noise


@settings(max_examples=40, deadline=None)
@given(cuts=st.lists(st.integers(1, 2 * int(SCAN.frame_time * RATE)), max_size=12))
def test_chunks_in_any_sizes_give_the_whole_frames_image(cuts):
    sample = load_sample("grating", SCAN)
    t, pos = _samples(2.0)
    live = ScanAccumulator(SCAN, sample)
    for part in np.split(np.arange(t.size), sorted(set(cuts))):
        live.add(t[part], pos[:, part])
    last = t >= SCAN.frame_time  # the second frame replaced every line of the first
    whole = scan_image(SCAN, sample, t[last], pos[:, last])
    np.testing.assert_allclose(live.image(), whole.image, rtol=1e-12, atol=1e-18)
    figures = scan_figures(SCAN, sample, t[last], pos[:, last])
    np.testing.assert_allclose(live.line_rms(), figures.line_rms, rtol=1e-9)
    assert live.last_line == SCAN.lines - 1


def test_a_line_scanned_again_replaces_the_last_frames():
    sample = load_sample("grating", SCAN)
    t, pos = _samples(1.5)
    live = ScanAccumulator(SCAN, sample)
    first = t < SCAN.frame_time
    live.add(t[first], pos[:, first])
    before = live.image().copy()
    assert np.isfinite(before).all()
    shifted = pos.copy()
    shifted[0] += 1e-6  # the second frame 1 µm off: its lines image another part
    live.add(t[~first], shifted[:, ~first])
    line, _ = SCAN.line_index(t[~first])
    done = np.unique(line[line >= 0])
    assert 0 < done.size < SCAN.lines
    again = ~np.isclose(live.image(), before)
    assert again[done].any() and not again[np.setdiff1d(np.arange(SCAN.lines), done)].any()
    assert live.line_rms()[done, 0] == pytest.approx(1e-6, rel=0.05)


def test_the_origin_is_the_stamp_the_set_points_follow_from():
    t0 = 1_700_000_000_000_000_000
    columns = []
    for index, offset in ((0, 0), (1, 300_000)):
        stamp = t0 + offset + np.arange(3000, dtype=np.int64) * 1_000_000
        reference = ScanAxis(SCAN, index).evaluate(stamp * 1e-9 - t0 * 1e-9)[0]
        columns.append({"stamp": stamp, "reference": reference})
    columns[0]["reference"][:2] = np.nan  # the fast axis stepped from its third sample
    assert scan_origin(SCAN, columns) == t0
    late = [{k: v[5:] for k, v in c.items()} for c in columns]  # the start missed
    with pytest.raises(ScanError, match="missed the start"):
        scan_origin(SCAN, late)
