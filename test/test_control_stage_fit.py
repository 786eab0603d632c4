"""A simulated XY stage identified axis by axis: each axis's model and the coupling between them."""

from __future__ import annotations

import numpy as np
import pytest

from piezo_stage.control.model_fit import ModelFitError, perturbed
from piezo_stage.control.stage_fit import fit_stage, stage_recordings
from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.model.stage_file import Stage, StageAxis

pytestmark = pytest.mark.unit

CH11 = shipped_parameter_set("ch11_rig")
#: the scanner of the figures: the ch. 11 rig per axis, Y's parameters 10 % off X's, 2 % of X's
#: motion seen by Y's sensor and 1 % of Y's by X's
XY = Stage(
    "xy",
    (StageAxis("x", CH11, "1"), StageAxis("y", perturbed(CH11, 1.1, "y"), "2")),
    np.array([[1.0, 0.01], [0.02, 1.0]]),
)
NAMES = ("kappa_x", "kappa_w", "rho", "sigma", "n")


def _errors(fitted: Stage) -> dict[str, float]:
    worst = {}
    for true, got in zip(XY.axes, fitted.axes):
        worst[true.name] = max(
            abs(getattr(got.model.bouc_wen, k) / getattr(true.model.bouc_wen, k) - 1.0)
            for k in NAMES
        )
    return worst


def test_noise_free_runs_give_each_axis_and_the_coupling():
    fitted = fit_stage(XY, stage_recordings(XY, hold=50.0))
    assert fitted.names == ("x", "y") and [a.channel for a in fitted.axes] == ["1", "2"]
    np.testing.assert_allclose(fitted.coupling, XY.coupling, rtol=0, atol=1e-9)
    assert max(_errors(fitted).values()) < 0.01


def test_with_sensor_noise_of_a_thousandth_of_the_span_the_figures_hold():
    span = 30e-6  # 0-300 V over kappa_x ~ 1e7 V/m
    fitted = fit_stage(XY, stage_recordings(XY, hold=50.0, noise=1e-3 * span, seed=3))
    errors = _errors(fitted)
    assert max(errors.values()) < 0.02, errors  # every Bouc-Wen parameter within 2 %
    off = ~np.eye(2, dtype=bool)
    relative = np.abs(fitted.coupling[off] / XY.coupling[off] - 1.0)
    assert np.all(relative < 0.05), fitted.coupling  # the coupling within 5 %
    assert np.all(fitted.coupling_standard_errors[off] > 0.0)


def test_an_axis_without_recordings_is_named():
    recordings = stage_recordings(XY)
    del recordings["y"]
    with pytest.raises(ModelFitError, match="no recordings drive axis y"):
        fit_stage(XY, recordings)
