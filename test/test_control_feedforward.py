"""Bouc-Wen feedforward: u_ff along x_d, the compensation modes in the controller,
the re-seeding of w when the loop closes, and tracking against the ch. 11 rig."""

import math
from dataclasses import replace

import numpy as np
import pytest

from piezo_stage.control.controller import ControllerConfig, TimeVaryingPID
from piezo_stage.control.errors import ControllerConfigError
from piezo_stage.control.feedforward import (
    Compensation,
    Feedforward,
    FeedforwardError,
    FeedforwardModel,
    feedforward,
)
from piezo_stage.control.laws import THESIS_GAINS
from piezo_stage.control.scan import make_trajectory
from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.model.plant import DynamicPlant

pytestmark = pytest.mark.unit

RIG = shipped_parameter_set("ch11_rig")
#: the rig's own file as the model: these tests check the algebra, not the identification
MODEL = FeedforwardModel.from_parameter_set(RIG)
RATE = 100e3


def test_path_and_steps_agree_and_the_terms_are_those_of_11_1():
    tr = make_trajectory("triangle", amplitude=10e-6, frequency=10.0)
    t = np.arange(20_000) / RATE
    x, v, a = tr.evaluate(t)
    u_path, w = feedforward(MODEL, x, v, a)
    ff = Feedforward(MODEL)
    ff.seed(x[0], 0.0)  # at rest at 0 V and x = 0: w = 0
    u_steps = np.array([ff.step(*p) for p in zip(x, v, a)])
    assert np.allclose(u_steps, u_path, rtol=0, atol=1e-9)
    bw = RIG.bouc_wen
    expected = RIG.dynamics.m * a + RIG.dynamics.c * v + bw.kappa_x * x + bw.kappa_w * w
    assert np.allclose(u_path, expected, rtol=0, atol=1e-9)
    assert 0.0 < np.abs(bw.kappa_w * w).max() < 0.5 * np.abs(u_path).max()  # hysteresis is there


def test_feedforward_alone_drives_the_rig_along_x_d():
    tr = make_trajectory("sine", amplitude=5e-6, frequency=100.0)
    t = np.arange(3000) / RATE
    u, _ = feedforward(MODEL, *tr.evaluate(t + 0.5 / RATE))  # the mid-interval value, held
    x, _, _ = DynamicPlant(RIG.bouc_wen, RIG.dynamics).simulate(u, 1.0 / RATE)
    x_d = tr.evaluate(t + 1.0 / RATE)[0]
    # without the model the error would be the hysteresis, ~kappa_w/kappa_x = 4 um
    assert np.sqrt(np.mean((x - x_d) ** 2)) < 0.005 * tr.range


def _controller(compensation, **kw):
    cfg = ControllerConfig(
        gains=THESIS_GAINS,
        u_min=-450.0,
        u_max=450.0,
        compensation=compensation,
        feedforward=MODEL,
        **kw,
    )
    return TimeVaryingPID(cfg, closed=True)


def test_modes_combine_the_terms():
    outs = {}
    for mode in Compensation:
        ctrl = _controller(mode)
        ctrl.update(0.0, 0.0, 0.0, 0.0, 0.0)
        outs[mode] = ctrl.update(1e-5, 1e-7, 2e-7, 0.02, 1.0)
    fb, ffo, both = (
        outs[c] for c in (Compensation.FEEDBACK, Compensation.FEEDFORWARD, Compensation.BOTH)
    )
    assert fb.u_ff == 0.0 and fb.u == pytest.approx(fb.u_pid)
    assert ffo.u_pid == 0.0 and ffo.u == pytest.approx(ffo.u_ff) and ffo.x0 == 0.0
    assert both.u_ff == pytest.approx(ffo.u_ff) and both.u == pytest.approx(both.u_pid + both.u_ff)
    assert both.u_ff > RIG.bouc_wen.kappa_x * 2e-7  # the c·ẋ_d and the hysteresis terms add


def test_compensation_needs_a_model_and_a_known_name():
    with pytest.raises(ControllerConfigError, match="needs a feedforward model"):
        ControllerConfig(compensation="both").validate()
    with pytest.raises(ControllerConfigError, match="compensation must be one of"):
        ControllerConfig(compensation="inverse")
    static = shipped_parameter_set("ch10_patch")
    with pytest.raises(FeedforwardError, match="dynamic form"):
        FeedforwardModel.from_parameter_set(static)
    with pytest.raises(FeedforwardError, match="kappa_w"):
        FeedforwardModel(replace(RIG.bouc_wen, kappa_w=-1.0), 1e-3, 1.0)
    ff = Feedforward(MODEL)
    with pytest.raises(FeedforwardError, match="seeded"):
        ff.step(0.0, 0.0, 0.0)
    ff.seed(0.0, 0.0)
    with pytest.raises(FeedforwardError, match="finite"):
        ff.step(math.nan, 0.0, 0.0)


def test_feedforward_beyond_the_amplifier_is_clamped():
    ctrl = _controller(Compensation.FEEDFORWARD)
    ctrl.update(0.0, 0.0, 0.0)
    out = ctrl.update(1e-5, 0.0, 60e-6)  # kappa_x * 60 um = 621 V > 450 V
    assert out.u == 450.0 and out.saturated and out.u_ff > 450.0


def test_closing_reseeds_w_from_the_stage_and_transfers_bumplessly():
    """Open the loop while tracking, let the stage settle at the hold voltage, close again: the
    feedforward's w restarts at the stage's own w, and u is continuous at the closing."""
    ctrl = _controller(Compensation.BOTH, on_close="bumpless")
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics)
    tr = make_trajectory("triangle", amplitude=10e-6, frequency=10.0)
    t_open, t_close = 0.03, 0.045  # on the rising ramp: w far from 0
    x, u_prev, closing = plant.output(), None, None
    for k in range(int(0.1 * RATE)):
        t = k / RATE
        if abs(t - t_open) < 0.5 / RATE:
            ctrl.open_loop()  # hold the last output: no step (a step's ringing would erase w)
            hold = ctrl.u
        if abs(t - t_close) < 0.5 / RATE:
            ctrl.close_loop()
            w_stage, x_stage = plant.w, x
        out = ctrl.update(t, x, *map(float, tr.evaluate(t)))
        if abs(t - t_close) < 0.5 / RATE:
            closing = (u_prev, out.u, ctrl._ff.w)
        u_prev = out.u
        x = plant.step(out.u, 1.0 / RATE)
    u_before, u_at, _ = closing
    assert u_at == pytest.approx(u_before, abs=1e-6)  # bumpless with the feedforward inside
    # the seed from the measured x and the held voltage is the stage's own w (at rest, 15 ms)
    ff = Feedforward(MODEL)
    ff.seed(x_stage, hold)
    assert abs(w_stage) > 0.3 and ff.w == pytest.approx(w_stage, abs=1e-4)
    # and the controller then drove it one step along x_d from there
    ff.step(*map(float, tr.evaluate(t_close)))
    assert closing[2] == pytest.approx(ff.w, abs=1e-9)
