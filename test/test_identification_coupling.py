"""The coupling of a simulated XY stage, identified from runs that move one axis at a time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from piezo_stage.identification.coupling import coupling_slope, identify_coupling
from piezo_stage.identification.errors import (
    InputDataError,
    NonFiniteDataError,
    TooFewSamplesError,
)
from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.model.stage import CoupledStage, SensorModel
from piezo_stage.model.stage_file import Stage, StageAxis

pytestmark = pytest.mark.unit

CH11 = shipped_parameter_set("ch11_rig")
C = np.array([[1.0, 0.01], [0.02, 1.0]])


def _runs(noise_std: float, seed: int = 1) -> dict[str, np.ndarray]:
    """One run per axis: a 0-100 V raised cosine on it, the other held (and settled) at 30 V,
    10 kHz."""
    stage = Stage("xy", (StageAxis("x", CH11, "1"), StageAxis("y", CH11, "2")), C)
    runs = {}
    for j, name in enumerate(stage.names):
        sensors = [SensorModel(noise_std=noise_std, seed=seed + k) for k in range(2)]
        plant = CoupledStage(stage, sensors=sensors)
        for _ in range(500):  # the held axis settles at 30 V before the run
            plant.step([30.0 if k != j else 0.0 for k in range(2)], 1e-4)
        t = np.arange(5000) * 1e-4
        drive = 50.0 * (1.0 - np.cos(2.0 * math.pi * 4.0 * t))
        rows = []
        for v in drive:
            commands = [30.0, 30.0]
            commands[j] = float(v)
            rows.append(plant.step(commands, 1e-4).readings)
        runs[name] = np.array(rows)
    return runs


def test_noise_free_runs_give_the_coupling_exactly():
    estimate = identify_coupling(("x", "y"), _runs(0.0))
    np.testing.assert_allclose(estimate.coupling, C, rtol=1e-9, atol=1e-12)
    assert estimate.standard_errors.max() < 1e-9


def test_with_sensor_noise_the_estimate_is_within_its_standard_errors():
    runs = _runs(0.0)
    span = np.ptp(runs["x"][:, 0])
    estimate = identify_coupling(("x", "y"), _runs(1e-3 * span))
    off = ~np.eye(2, dtype=bool)
    error = np.abs(estimate.coupling - C)[off]
    assert np.all(error < 0.05 * np.abs(C[off]))  # the 5 % the scanner figures ask for
    assert np.all(error < 5.0 * estimate.standard_errors[off])
    assert np.all(estimate.standard_errors[off] > 0.0)


def test_a_run_that_does_not_move_its_axis_is_refused_naming_it():
    runs = _runs(0.0)
    runs["y"] = np.tile(runs["y"][:1], (100, 1))
    with pytest.raises(InputDataError, match="run driving y: the driven axis did not move"):
        identify_coupling(("x", "y"), runs)


def test_missing_short_and_non_finite_runs_say_why():
    runs = _runs(0.0)
    with pytest.raises(InputDataError, match=r"no run drives axis/axes \['y'\]"):
        identify_coupling(("x", "y"), {"x": runs["x"]})
    with pytest.raises(TooFewSamplesError, match="run driving x: 5 samples"):
        identify_coupling(("x", "y"), {**runs, "x": runs["x"][:5]})
    bad = runs["x"].copy()
    bad[7, 1] = math.nan
    with pytest.raises(NonFiniteDataError, match="run driving x"):
        identify_coupling(("x", "y"), {**runs, "x": bad})
    with pytest.raises(InputDataError, match=r"samples x 2 axes, got shape \(5000,\)"):
        identify_coupling(("x", "y"), {**runs, "x": runs["x"][:, 0]})


def test_the_slope_is_least_squares():
    x = np.linspace(0.0, 1.0, 50)
    y = 3.0 + 0.25 * x + 0.01 * np.sin(17.0 * x)
    slope, error = coupling_slope(x, y)
    expected = np.polyfit(x, y, 1)[0]
    assert slope == pytest.approx(expected, rel=1e-12)
    assert 0.0 < error < 0.01
