"""Tracking in pure core: the model fitted from the simulated rig's recordings, and
the tracking figures against their targets with that model (bench/tracking.py prints them all)."""

import numpy as np
import pytest

from piezo_stage.control.errors import ControlError
from piezo_stage.control.feedforward import FeedforwardModel
from piezo_stage.control.model_fit import fit_feedforward_model, perturbed, rig_recordings
from piezo_stage.control.scan import make_trajectory
from piezo_stage.control.tracking import simulate_tracking, tracking_errors
from piezo_stage.model.parameter_set import shipped_parameter_set

pytestmark = pytest.mark.unit

RIG = shipped_parameter_set("ch11_rig")


@pytest.fixture(scope="module")
def fitted():
    return fit_feedforward_model(rig_recordings(RIG))


def test_model_from_the_rigs_recordings(fitted):
    bw, true = fitted.bouc_wen, RIG.bouc_wen
    for got, want in (
        (bw.kappa_x, true.kappa_x),
        (bw.kappa_w, true.kappa_w),
        (bw.rho, true.rho),
        (bw.sigma, true.sigma),
        (bw.n, true.n),
        (fitted.dynamics.m, RIG.dynamics.m),
        (fitted.dynamics.c, RIG.dynamics.c),
    ):
        assert got == pytest.approx(want, rel=0.015)
    assert abs(bw.y0) < 1e-9  # [m]: the rig has no offset


def test_tracking_errors_over_the_steady_part():
    t = np.linspace(0.0, 1.0, 11)
    x_d = np.linspace(0.0, 1e-5, 11)
    e = tracking_errors(t, x_d + np.where(t < 0.5, 1e-6, 1e-8), x_d, t_from=0.5)
    assert e.rms_error == pytest.approx(1e-8) and e.max_error == pytest.approx(1e-8)
    assert e.range == pytest.approx(5e-6) and e.samples == 6 and e.relative == pytest.approx(2e-3)
    with pytest.raises(ControlError, match="no samples"):
        tracking_errors(t, x_d, x_d, t_from=2.0)


@pytest.mark.slow
def test_triangle_targets_and_model_mismatch(fitted):
    model = FeedforwardModel.from_parameter_set(fitted)
    tri = make_trajectory("triangle", amplitude=10e-6, frequency=10.0)
    _, fb = simulate_tracking(tri, RIG, "feedback", model)
    rec, both = simulate_tracking(tri, RIG, "both", model)
    assert both.range == pytest.approx(20e-6)
    assert both.relative <= 0.005 and both.rms_error <= 0.2 * fb.rms_error
    assert np.all(np.abs(rec.u) <= 450.0) and np.abs(rec.u_ff).max() > 200.0
    off = perturbed(RIG, 1.05)
    _, fb_off = simulate_tracking(tri, off, "feedback", model)
    _, both_off = simulate_tracking(tri, off, "both", model)
    assert both_off.rms_error <= 0.5 * fb_off.rms_error
    assert both_off.rms_error > both.rms_error  # the mismatch is felt


def test_sine_at_100_hz(fitted):
    model = FeedforwardModel.from_parameter_set(fitted)
    sine = make_trajectory("sine", amplitude=5e-6, frequency=100.0)
    _, both = simulate_tracking(sine, RIG, "both", model)
    assert both.range == pytest.approx(10e-6, rel=1e-3) and both.relative <= 0.02
