"""A raster on the simulated XY scanner in the core: both axes' feedforward, learning per
line, the learned tables saved and replayed, bad runs refused."""

import dataclasses

import numpy as np
import pytest

from piezo_stage.config_path import find_config
from piezo_stage.control.errors import ControlError
from piezo_stage.control.learning import FeedforwardTable, LearningConfig, LearningError
from piezo_stage.control.raster import RasterTables, raster_run
from piezo_stage.control.scan import RasterScan
from piezo_stage.control.scan_image import load_sample
from piezo_stage.model.stage_file import load_stage

pytestmark = pytest.mark.unit

RATE = 1000.0


@pytest.fixture(scope="module")
def stages():
    """(model, plant): the shipped XY scanner, and the same with κx 3 % up and κw 5 % down on
    both axes and the coupling 10 % off (a model that is not the plant)."""
    model = load_stage(find_config("xy_scanner.yaml"))
    axes = []
    for axis in model.axes:
        bw = axis.model.bouc_wen
        bw = dataclasses.replace(
            bw, kappa=tuple(1.03 * k for k in bw.kappa), kappa_w=0.95 * bw.kappa_w
        )
        axes.append(dataclasses.replace(axis, model=dataclasses.replace(axis.model, bouc_wen=bw)))
    coupling = model.coupling * np.array([[1.0, 0.9], [1.1, 1.0]])
    return model, dataclasses.replace(model, axes=tuple(axes), coupling=coupling)


def scan(**kw):
    args = dict(lines=8, pixels=16, line_rate=20.0, range=(20e-6, 10e-6), centre=(15e-6, 10e-6))
    return RasterScan(**{**args, **kw})


def test_the_feedforward_takes_the_scan_and_the_coupling_out_and_learning_the_rest(stages):
    model, plant = stages
    s = scan()
    sample = load_sample("grating", s)
    figures = {}
    for label, comp, coupled, learn in (
        ("feedback", "feedback", False, 0),
        ("both", "both", True, 0),
        ("learned", "both", True, 20),
    ):
        run = raster_run(
            s, model, plant, RATE, compensation=comp, compensate_coupling=coupled, learn_lines=learn
        )
        figures[label] = run.figures(sample)
        frames = 2 if learn == 0 else 4  # 20 lines of 9-period frames: a whole one after them
        assert run.desired.shape == run.measured.shape == (2, round(frames * s.frame_time * RATE))
    fb, both, learned = figures["feedback"], figures["both"], figures["learned"]
    # feedback alone lags the 20 Hz line by micrometres; the feedforward removes most of it
    assert fb.rms_error[0] > 1e-6 and both.rms_error[0] < 0.05 * fb.rms_error[0]
    # learning takes the fast axis near its floor, and the slow axis's coupling error down
    assert learned.rms_error[0] < 0.3 * both.rms_error[0]
    assert learned.rms_error[1] < 0.1 * fb.rms_error[1]
    assert learned.distortion_px_max < 0.5 < fb.distortion_px_max


def test_learning_reports_each_line_and_its_tables_replay(stages, tmp_path):
    model, plant = stages
    s = scan()
    learned = raster_run(s, model, plant, RATE, learn_lines=12)
    assert len(learned.learning) == 12
    fast = [x for x, _ in learned.learning if np.isfinite(x)]
    assert fast[-1] < 0.5 * fast[0]
    path = learned.tables.save(tmp_path / "tables.json")
    loaded = RasterTables.load(path)
    np.testing.assert_array_equal(loaded.fast.u, learned.tables.fast.u)
    np.testing.assert_array_equal(loaded.slow.u, learned.tables.slow.u)
    replay = raster_run(s, model, plant, RATE, tables=loaded)
    fresh = raster_run(s, model, plant, RATE)
    sample = load_sample("grating", s)
    assert replay.figures(sample).rms_error[0] < 0.5 * fresh.figures(sample).rms_error[0]


def test_tables_that_do_not_fit_the_scan_are_refused(stages, tmp_path):
    model, plant = stages
    tables = raster_run(scan(), model, plant, RATE, frames=1).tables
    with pytest.raises(ControlError, match="fast axis: the table holds 50 samples"):
        raster_run(scan(line_rate=10.0), model, plant, RATE, tables=tables)
    with pytest.raises(ControlError, match="made at 1000 Hz, the loop runs at 2000 Hz"):
        raster_run(scan(), model, plant, 2 * RATE, tables=tables)
    (tmp_path / "one.json").write_text(tables.fast.save(tmp_path / "x.json").read_text())
    with pytest.raises(LearningError, match="is not a raster's tables"):
        RasterTables.load(tmp_path / "one.json")


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(axes=("x", "x")), "two different axes"),
        (dict(axes=("x", "z")), "two different axes"),
        (dict(rate_hz=999.0), "samples at 999 Hz"),
        (dict(compensation="feedback", learn_lines=2), "learn_lines needs a feedforward"),
    ],
)
def test_bad_runs_are_refused(stages, kw, match):
    model, plant = stages
    args = dict(rate_hz=RATE, frames=1)
    args.update(kw)
    rate = args.pop("rate_hz")
    with pytest.raises(ControlError, match=match):
        raster_run(scan(), model, plant, rate, **args)


def test_a_line_correction_goes_on_the_line_periods_of_the_frame(stages):
    model, _ = stages
    from piezo_stage.control.feedforward import FeedforwardModel
    from piezo_stage.control.learning import LineCorrection, feedforward_response

    s = scan(lines=4, flyback_lines=2)
    n_line, n_frame = round(s.period * RATE), round(s.frame_time * RATE)
    frame = FeedforwardTable(np.linspace(0.0, 1.0, n_frame), RATE)
    base = frame.u.copy()
    ff = FeedforwardModel.from_parameter_set(model.axes[1].model)
    response = feedforward_response(ff, RATE, n_line)
    corr = LineCorrection(frame, n_line, 2, response, LearningConfig(settle_periods=0), ff)
    corr.update(1e-7 * np.sin(2 * np.pi * np.arange(n_line) / n_line))
    delta = (frame.u - base).reshape(-1, n_line)
    assert np.all(delta[:2] == 0.0)  # the fly-back's two periods keep the model's values
    assert np.abs(delta[2:]).max() > 0
    np.testing.assert_allclose(delta[2:], np.tile(corr.correction.u, (4, 1)))
