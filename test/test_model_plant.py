"""Simulated plants: static (10.15) and dynamic (11.1)-(11.3) with ZOH input, against references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import expm

from piezo_stage.model import _plant_kernels as K
from piezo_stage.model.bouc_wen import BoucWenParameters, model_output
from piezo_stage.model.errors import (
    InitialStateError,
    InputSignalError,
    InvalidCommandError,
    ParameterValueError,
)
from piezo_stage.model.limit_cycle import limit_cycle
from piezo_stage.model.parameter_set import Dynamics, shipped_parameter_set
from piezo_stage.model.plant import DynamicPlant, StaticPlant, simulate_reference
from piezo_stage.model.signals import band_limited_noise, triangle

pytestmark = pytest.mark.unit

RIG = shipped_parameter_set("ch11_rig")
M, C = RIG.dynamics.m, RIG.dynamics.c
KX = RIG.bouc_wen.kappa_x


def test_static_plant_equals_model_output():
    p = shipped_parameter_set("ch10_patch").bouc_wen
    v = triangle(np.linspace(0.0, 25.0, 2501), 10.0, 0.0, 300.0) + 7.0
    plant = StaticPlant(p, w0=0.1, v0=v[0])
    assert np.max(np.abs(plant.simulate(v) - model_output(p, v, w0=0.1))) < 1e-18
    stepper = StaticPlant(p, w0=0.1, v0=v[0])
    assert np.allclose(
        [stepper.step(x) for x in v[:300]], model_output(p, v[:300], w0=0.1), rtol=0, atol=1e-18
    )
    assert stepper.output() == pytest.approx(model_output(p, v[:300], w0=0.1)[-1], abs=1e-18)
    with pytest.raises(InvalidCommandError):
        stepper.step(math.nan)
    with pytest.raises(InitialStateError):
        StaticPlant(p, w0=1.2)


def _linear_rig() -> DynamicPlant:
    # kappa_w -> 0: the plant is the linear oscillator m x'' + c x' + kappa_x x = u
    bw = BoucWenParameters(kappa=(KX,), kappa_w=1e-12, rho=RIG.bouc_wen.rho, sigma=0.9153, n=1.176)
    return DynamicPlant(bw, RIG.dynamics)


def test_linear_step_response_is_exact_with_thesis_frequency_and_damping():
    plant = _linear_rig()
    dt = 2e-6
    u = 100.0
    x, xdot, _ = plant.simulate(np.full(1000, u), dt)
    t = dt * np.arange(1, 1001)
    wn = math.sqrt(KX / M)  # ~ 2 pi 7 kHz
    zeta = C / (2.0 * math.sqrt(KX * M))  # ~ 2.8 %
    wd = wn * math.sqrt(1.0 - zeta**2)
    exact = (
        u
        / KX
        * (
            1.0
            - np.exp(-zeta * wn * t)
            * (np.cos(wd * t) + zeta / math.sqrt(1 - zeta**2) * np.sin(wd * t))
        )
    )
    assert np.max(np.abs(x - exact)) <= 1e-9 * u / KX
    # the simulated response itself: the damped frequency from the zero crossings of x', the
    # damping from successive peaks (log decrement), the static gain from the mean level; the
    # natural frequency and damping they give are those of the ch. 11 rig (~7.03 kHz, ~2.78 %)
    crossings = t[1:][np.diff(np.sign(xdot)) != 0]
    wd_measured = 2 * math.pi / (2 * np.mean(np.diff(crossings)))
    peaks = x[1:-1][(x[1:-1] > x[:-2]) & (x[1:-1] > x[2:])] - u / KX
    decrement = np.log(peaks[0] / peaks[1])
    zeta_measured = decrement / math.sqrt(4 * math.pi**2 + decrement**2)
    wn_measured = wd_measured / math.sqrt(1.0 - zeta_measured**2)
    assert wd_measured == pytest.approx(wd, rel=2e-3)
    assert zeta_measured == pytest.approx(zeta, rel=2e-2)
    assert wn_measured / (2 * math.pi) == pytest.approx(7.03e3, rel=1e-2)
    assert zeta_measured == pytest.approx(0.0278, rel=1e-2)
    assert np.mean(x[t > t[-1] - 2 * math.pi / wd]) == pytest.approx(u / KX, rel=1e-2)


def test_rig_rings_between_the_elastic_and_the_hysteretic_stiffness():
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics)
    x, xdot, w = plant.simulate(np.full(400, 50.0), 2.5e-6)
    crossings = np.flatnonzero(np.diff(np.sign(xdot)) != 0)
    period = 2 * np.mean(np.diff(crossings[:6])) * 2.5e-6
    b = RIG.bouc_wen
    low = math.sqrt(b.kappa_x / M) / (2 * math.pi)
    high = math.sqrt((b.kappa_x + 2 * b.sigma * b.kappa_w * b.rho) / M) / (2 * math.pi)
    assert low < 1.0 / period < high
    assert np.all(np.abs(w) <= 1.0)


@pytest.mark.parametrize("case, nodes", [("noise", 4), ("step", 4), ("noise", 5)])
def test_dynamic_plant_matches_converged_reference(case, nodes):
    dt = 1e-4
    t = dt * np.arange(120)
    if case == "noise":
        u = 150.0 + band_limited_noise(t, 100.0, 50.0, seed=3)
    else:
        u = np.where(t < 0.005, 0.0, 200.0)
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics, w0=0.2, tol=1e-8, nodes=nodes)
    x, xdot, w = plant.simulate(u, dt)
    xr, vr, wr = simulate_reference(RIG.bouc_wen, RIG.dynamics, u, dt, w0=0.2, rtol=1e-12)
    assert np.max(np.abs(x - xr)) <= 1e-6 * np.ptp(xr)
    assert np.max(np.abs(w - wr)) <= 1e-5


@pytest.mark.parametrize("nodes", [4, 5])
def test_piece_exponentials_from_the_group_plan_equal_expm(nodes):
    # exp(L t) at the piece's points from two or three sin/cos/exp evaluations (double angle,
    # angle difference) equals the matrix exponential, under-, critically and over-damped
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics, nodes=nodes)
    points, Ez = plant._work[0], plant._work[1]
    fractions, ops, index, parts = plant._work[13][:4]
    assert np.count_nonzero(ops[:, 0] == 0) < points.size  # fewer direct evaluations than points
    assert np.allclose(fractions[index], points, rtol=0, atol=1e-15)
    for a, b in ((2.3e9, 2453.0), (4.0e6, 4.0e3), (1.0e6, 5.0e3)):  # b^2/4 <, =, > a
        for tau in (3e-6, 4e-5, 1.5e-4):
            K._exp_points(a, b, tau, fractions, ops, index, parts, Ez)
            L = np.array([[0.0, 1.0], [-a, -b]])
            scale = np.array([[1.0, 1.0 / math.sqrt(a)], [math.sqrt(a), 1.0]])  # of each entry
            for p, xi in enumerate(points):
                assert np.max(np.abs(Ez[p] - expm(L * tau * xi)) / scale) <= 1e-13


def test_quasi_static_limit_is_the_theorem_2_cycle():
    # a slow T-wave drive: the x path is monotone between its extremes, and w(x) is rate
    # independent, so the steady w vs x is the closed-form limit cycle (9.13)-(9.14)
    dt = 1e-5
    period = 0.05
    t = dt * np.arange(1, int(8 * period / dt) + 1)  # 8 periods: converged to 1e-9 (Theorem 2)
    u = 150.0 - 150.0 * np.cos(2 * np.pi * t / period)
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics)
    x, xdot, w = plant.simulate(u, dt)
    last = slice(len(t) - int(period / dt) - 1, len(t))
    xs, ws, vs = x[last], w[last], xdot[last]
    assert (
        np.count_nonzero(np.diff(np.sign(vs[np.abs(vs) > 0])) != 0) <= 2
    )  # T-wave: one turn each way
    b = RIG.bouc_wen
    loading, unloading = limit_cycle(b.rho, b.sigma, b.n, xs.min(), xs.max(), xs)
    expected = np.where(vs > 0, loading, unloading)
    assert np.max(np.abs(ws - expected)) < 1e-6
    assert np.ptp(ws) > 1.0  # a real loop, not a trivial one


def test_step_by_step_equals_batch_and_state_accessors():
    u = 100.0 + band_limited_noise(1e-4 * np.arange(200), 100.0, 30.0, seed=5)
    batch = DynamicPlant(RIG.bouc_wen, RIG.dynamics, x0=1e-6, xdot0=1e-3, w0=-0.3)
    x, xdot, w = batch.simulate(u, 1e-4)
    stepped = DynamicPlant(RIG.bouc_wen, RIG.dynamics, x0=1e-6, xdot0=1e-3, w0=-0.3)
    ys = [stepped.step(uk, 1e-4) for uk in u]
    assert np.array_equal(ys, x)
    assert (stepped.x, stepped.xdot, stepped.w) == (x[-1], xdot[-1], w[-1])
    stepped.reset(2e-6, 0.0, 0.5)
    assert (stepped.x, stepped.xdot, stepped.w, stepped.output()) == (2e-6, 0.0, 0.5, 2e-6)


def test_dynamic_plant_bad_inputs():
    plant = DynamicPlant(RIG.bouc_wen, RIG.dynamics)
    with pytest.raises(InputSignalError, match="finite"):
        plant.simulate(np.array([1.0, np.inf]), 1e-4)
    with pytest.raises(InputSignalError, match="dt"):
        plant.simulate(np.ones(2), 0.0)
    with pytest.raises(InvalidCommandError):
        plant.step(math.nan, 1e-4)
    with pytest.raises(ParameterValueError, match="tol"):
        DynamicPlant(RIG.bouc_wen, RIG.dynamics, tol=1.0)
    with pytest.raises(ParameterValueError, match="Dynamics"):
        DynamicPlant(RIG.bouc_wen, (5e-3, 13.0))  # type: ignore[arg-type]
    with pytest.raises(ParameterValueError, match="dynamics.m"):
        Dynamics(m=0.0, c=1.0)
