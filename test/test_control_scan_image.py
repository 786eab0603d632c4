"""The scanned image of a sample: pixels from desired positions, heights at measured ones,
errors over the image windows and the distortion of the sample's edges, in pixels."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.control.scan import Order, RasterScan, ScanError, SlowMotion
from piezo_stage.control.scan_image import (
    Grating,
    HeightMap,
    load_sample,
    scan_figures,
    scan_image,
)

from property_support import examples

pytestmark = pytest.mark.unit

RATE = 20_000.0


def setup(order=Order.RASTER, motion=SlowMotion.STAIRCASE):
    scan = RasterScan(16, 32, 20.0, (16e-6, 8e-6), (10e-6, 5e-6), order=order, slow_motion=motion)
    t = np.arange(int(scan.frame_time * RATE)) / RATE
    (xd, _, _), (yd, _, _) = scan.evaluate(t)
    return scan, load_sample("grating", scan), t, np.vstack([xd, yd])


@pytest.mark.parametrize("order", list(Order))
def test_a_stage_on_its_path_images_the_sample_as_it_is(order):
    scan, grating, t, desired = setup(order)
    img = scan_image(scan, grating, t, desired)
    assert img.image.shape == (16, 32) and np.all(img.counts > 0)
    # pits aligned with the pixels: each pixel reads its pit or plateau (a sample exactly on a
    # wall may round to either side: at most one per pixel)
    assert np.all(np.abs(img.image - img.ideal) <= 100e-9 / img.counts + 1e-20)
    assert np.mean(np.abs(img.image - img.ideal) < 1e-20) > 0.8
    assert set(np.unique(img.ideal)) == {-100e-9, 0.0}
    fig = scan_figures(scan, grating, t, desired)
    assert fig.rms_error == (0.0, 0.0) and fig.distortion_px_max == pytest.approx(0.0, abs=1e-9)
    assert fig.edges > 16 * 8  # every line crosses the 8 walls of its pits (2 µm pitch, 16 µm)


@pytest.mark.parametrize("axis, shift_px", [(0, 0.3), (1, 0.2), (0, -0.45)])
def test_an_offset_moves_the_edges_by_that_many_pixels(axis, shift_px):
    scan, grating, t, desired = setup()
    pixel = scan.range[0] / scan.pixels if axis == 0 else scan.range[1] / scan.lines
    measured = desired.copy()
    measured[axis] += shift_px * pixel
    fig = scan_figures(scan, grating, t, measured)
    assert fig.distortion_px_max == pytest.approx(abs(shift_px), rel=1e-6)
    assert fig.rms_error[axis] == pytest.approx(abs(shift_px) * pixel)
    assert fig.rms_error[1 - axis] == 0.0
    np.testing.assert_allclose(fig.line_rms[:, axis], abs(shift_px) * pixel)
    img = scan_image(scan, grating, t, measured)
    assert np.isfinite(img.difference).all() and np.abs(img.difference).max() > 0


def test_errors_outside_the_image_windows_do_not_count():
    scan, grating, t, desired = setup()
    line, _ = scan.line_index(t)
    measured = desired.copy()
    measured[:, line < 0] += 1e-6  # turnarounds and fly-back far off
    fig = scan_figures(scan, grating, t, measured)
    assert fig.rms_error == (0.0, 0.0) and fig.distortion_px_max == pytest.approx(0.0, abs=1e-9)


def test_grating_edges_are_the_walls_of_its_pits():
    g = Grating(pitch=2e-6, duty=0.5, origin=(1e-6, 0.0))
    np.testing.assert_allclose(g.edges(0, 0.0, 6e-6), [0.0, 1e-6, 2e-6, 3e-6, 4e-6, 5e-6, 6e-6])
    assert g.height(np.array([1.5e-6]), np.array([0.5e-6]))[0] == -g.depth
    assert g.height(np.array([0.5e-6]), np.array([0.5e-6]))[0] == 0.0


def test_samples_from_files_stretch_over_the_image(tmp_path):
    import matplotlib.image

    scan, _, _, _ = setup()
    grid = np.zeros((4, 8))
    grid[:, 4:] = 1.0
    matplotlib.image.imsave(tmp_path / "half.png", grid, cmap="gray", vmin=0, vmax=1)
    np.savetxt(tmp_path / "half.csv", grid * 50e-9, delimiter=",")
    for name, depth in (("half.png", 100e-9), ("half.csv", 50e-9)):
        sample = load_sample(str(tmp_path / name), scan)
        assert isinstance(sample, HeightMap)
        x = np.array([4e-6, 12e-6])
        np.testing.assert_allclose(sample.height(x, np.full(2, 5e-6)), [0.0, depth], atol=1e-12)
        np.testing.assert_allclose(sample.edges(0, 2e-6, 18e-6), [10e-6])
        assert sample.edges(1, 1e-6, 9e-6).size == 0


@pytest.mark.parametrize(
    "content, name, match",
    [
        (None, "missing.csv", "cannot read"),
        ("1,2\n3,x\n", "bad.csv", "cannot read"),
        ("1,2,3\n", "row.csv", "2-D grid"),
        ("", "sample.tiff", "expected 'grating'"),
    ],
)
def test_a_sample_that_does_not_load_is_refused(tmp_path, content, name, match):
    scan, _, _, _ = setup()
    if content is not None:
        (tmp_path / name).write_text(content)
    with pytest.raises(ScanError, match=match):
        load_sample(str(tmp_path / name), scan)


@settings(max_examples=examples(30), deadline=None)
@given(
    order=st.sampled_from(list(Order)),
    motion=st.sampled_from(list(SlowMotion)),
    dx=st.floats(-0.45, 0.45),
    dy=st.floats(-0.45, 0.45),
)
def test_distortion_is_the_offset_in_pixels_for_every_scan(order, motion, dx, dy):
    """A stage offset by (dx, dy) pixels from its path shows every edge moved by that much."""
    scan, grating, t, desired = setup(order, motion)
    px = np.array([[scan.range[0] / scan.pixels], [scan.range[1] / scan.lines]])
    fig = scan_figures(scan, grating, t, desired + np.array([[dx], [dy]]) * px)
    assert fig.distortion_px_max == pytest.approx(max(abs(dx), abs(dy)), rel=1e-6, abs=1e-9)
