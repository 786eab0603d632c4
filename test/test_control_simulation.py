"""Closed loop against the model's DynamicPlant: sampled-check predictions and §11.4-11.5
behaviour."""

import numpy as np
import pytest

from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT
from piezo_stage.control.controller import ControllerConfig, TimeVaryingPID
from piezo_stage.control.discrete import check_sampled_loop
from piezo_stage.control.errors import SampledLoopError
from piezo_stage.control.laws import THESIS_GAINS
from piezo_stage.control.reference import SecondOrderReference
from piezo_stage.control.simulation import simulate_closed_loop
from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.model.plant import DynamicPlant

pytestmark = pytest.mark.unit

RIG = shipped_parameter_set("ch11_rig")


def plant(x0=20e-6, xdot0=0.2):
    """§11.4.1 initial state: x(0) = 20 µm, ẋ(0) = 0.2 m/s, w(0) = 0."""
    return DynamicPlant(RIG.bouc_wen, RIG.dynamics, x0=x0, xdot0=xdot0, w0=0.0)


def controller(mode="pid", limit=np.inf):
    return TimeVaryingPID(
        ControllerConfig(mode=mode, gains=THESIS_GAINS, u_min=-limit, u_max=limit)
    )


@pytest.mark.parametrize("rate, delay", [(1e3, 0), (20e3, 0), (100e3, 0), (100e3, 1), (200e3, 1)])
def test_simulation_confirms_the_sampled_check(rate, delay):
    predicted = check_sampled_loop(THESIS_NOMINAL_PLANT, THESIS_GAINS, rate, delay).stable
    duration = max(0.01, 200 / rate)
    r = simulate_closed_loop(controller(limit=450.0), plant(), rate, duration, delay_samples=delay)
    half = len(r.t) // 2
    settled = bool(not r.saturated[half:].any() and np.abs(r.x1[half:]).max() < 0.1 * 20e-6)
    diverged = bool(
        r.saturated[half:].mean() > 0.5
    )  # an unstable loop ends up banging the ±450 V limits
    assert settled is predicted and diverged is not predicted


def test_pid_regulates_but_keeps_a_nonzero_control():
    """§11.4.1: x1, x2 -> 0 while u(∞) = κw·w(∞) ≠ 0 (a continuum of equilibria)."""
    p = plant()
    r = simulate_closed_loop(controller("pid"), p, 1e3, 0.3)
    assert abs(r.x1[-1]) < 1e-12 and abs(r.x2[-1]) < 1e-9
    assert abs(r.u[-1]) > 0.1
    assert r.u[-1] == pytest.approx(RIG.bouc_wen.kappa_w * p.w, rel=1e-3)
    assert r.loop_closed.all() and np.isfinite(r.w).all()


def test_pid_tv_restores_the_control_after_a_perturbation():
    """§11.5 experiment: at rest (u = 0), loop opened 10 ms at 72 V, closed again (bumpless)."""
    finals = {}
    for mode in ("pid", "pid_tv"):
        r = simulate_closed_loop(
            controller(mode), plant(0.0, 0.0), 1e3, 1.0, open_windows=[(0.05, 0.06, 72.0)]
        )
        assert np.all(r.u[52:60] == 72.0) and not r.loop_closed[55] and r.loop_closed[60]
        assert abs(r.u[60] - 72.0) < 1e-9  # bumpless re-closing
        assert abs(r.x1[-1]) < 1e-8
        finals[mode] = r.u[-1]
        assert r.u[0] == 0.0
    assert abs(finals["pid"]) > 1.0  # the equilibrium moved
    assert abs(finals["pid_tv"]) < 0.05 * abs(
        finals["pid"]
    )  # (11.18) brings u back towards its value before


class BiasedPlant:
    """The plant driven by u_bias + the controller's u (the perturbation experiment's
    feedforward)."""

    def __init__(self, bias, **state):
        self.bias, self.inner = bias, plant(**state)

    def output(self):
        return self.inner.output()

    def step(self, u, dt):
        return self.inner.step(self.bias + u, dt)


def test_pid_tv_restores_u_slowly_after_the_section_11_5_perturbation():
    """The experiment ``perturbation`` in the core at its rate (100 kHz): at rest at 200 V, open
    10 ms at 72 V, closed with x0 = 0. Under (11.18) u returns within 1 % of 200 V by 0.4 s, and
    the return slows down as it goes (the dither that erases w scales with w: sub-exponential)."""
    rate, bias = 100e3, 200.0
    x_eq = bias / RIG.bouc_wen.kappa[0]
    config = ControllerConfig(
        mode="pid_tv", gains=THESIS_GAINS, u_min=-450 - bias, u_max=450 - bias, on_close="reset"
    )
    r = simulate_closed_loop(
        TimeVaryingPID(config),
        BiasedPlant(bias, x0=x_eq, xdot0=0.0),
        rate,
        0.4,
        reference=lambda t: (x_eq, 0.0),
        open_windows=[(0.005, 0.015, 72.0 - bias)],
    )
    period = int(rate / THESIS_GAINS.f)

    def deviation(t):  # |mean of u − u_before| over the whole period of the sine ending at t
        k = int(round(t * rate))
        return abs(r.u[k - period : k].mean())

    assert np.abs(r.u[:500]).max() < 1e-9  # at rest before the window: u = u_bias
    assert deviation(0.4) <= 0.01 * bias
    ratio_early, ratio_late = deviation(0.2) / deviation(0.1), deviation(0.4) / deviation(0.2)
    assert (
        ratio_late < 1.0 and ratio_late > ratio_early
    )  # exponential decay would give ratio_early²


def test_tracks_the_second_order_reference():
    ref = SecondOrderReference(y0=20e-6, ydot0=0.2)  # yr(0) = x(0), ẏr(0) = ẋ(0)
    r = simulate_closed_loop(controller("pid"), plant(), 1e3, 0.2, reference=ref)
    assert r.reference[0] == pytest.approx(20e-6) and abs(r.reference[-1]) < 1e-15
    assert np.abs(r.x1).max() < 20e-6 and abs(r.measured[-1]) < 1e-9


def test_bad_arguments():
    with pytest.raises(SampledLoopError, match="rate_hz"):
        simulate_closed_loop(controller(), plant(), 0.0, 1.0)
    with pytest.raises(SampledLoopError, match="delay_samples"):
        simulate_closed_loop(controller(), plant(), 1e3, 1.0, delay_samples=-1)
