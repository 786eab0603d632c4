"""Normalized Bouc-Wen parameters, (8.10) conversion and the exact path simulation of (9.2)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from piezo_stage.model import _branches
from piezo_stage.model.bouc_wen import (
    BoucWenParameters,
    InitialStateError,
    InputSignalError,
    NotClassIError,
    ParameterValueError,
    from_standard,
    model_output,
    polynomial,
    simulate_w,
)
from piezo_stage.model.signals import triangle

pytestmark = pytest.mark.unit

CH9 = dict(rho=1.0, sigma=3.0, n=1.5)


def integrate_pieces(rate, x: np.ndarray, start: float) -> np.ndarray:
    """Integrate d(state)/dx = rate(x, state, s) with DOP853 (rtol 1e-13) on each monotone piece."""
    out = np.empty_like(x)
    out[0] = start
    direction = np.sign(np.diff(x))
    ends = (
        [0]
        + [i for i in range(1, direction.size) if direction[i] != direction[i - 1]]
        + [x.size - 1]
    )
    for a, b in zip(ends[:-1], ends[1:]):
        s = float(np.sign(x[b] - x[a]))
        sol = solve_ivp(
            rate,
            (x[a], x[b]),
            [out[a]],
            method="DOP853",
            rtol=1e-13,
            atol=1e-15,
            t_eval=x[a : b + 1],
            args=(s,),
        )
        out[a : b + 1] = sol.y[0]
    return out


def reference_w(x: np.ndarray, rho: float, sigma: float, n: float, w0: float = 0.0) -> np.ndarray:
    """(9.2) in the x variable: dw/dx = rho (1 - s sigma |w|^(n-1) w + (sigma - 1) |w|^n)."""

    def rate(_x, w, s):
        a = abs(w[0])
        return [rho * (1.0 - s * sigma * a ** (n - 1.0) * w[0] + (sigma - 1.0) * a**n)]

    return integrate_pieces(rate, x, w0)


def test_parameters_structure_and_kappa_x():
    p = BoucWenParameters(
        kappa=[1.401e-7, -5.0949e-11],
        kappa_w=9.22e-6,
        rho=0.0047,
        sigma=0.812,
        n=1.12,
        y0=1.7858e-6,
        input_sign=-1,
    )
    assert p.kappa == (1.401e-7, -5.0949e-11)
    assert p.kappa_x == 1.401e-7 and p.N == 2
    p.validate()
    with pytest.raises(ParameterValueError, match="at least"):
        BoucWenParameters(kappa=(), kappa_w=1, rho=1, sigma=1, n=1)
    with pytest.raises(ParameterValueError, match="input_sign"):
        BoucWenParameters(kappa=(1.0,), kappa_w=1, rho=1, sigma=1, n=1, input_sign=2)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"sigma": 0.49}, "sigma"),
        ({"rho": 0.0}, "rho"),
        ({"kappa_w": -1.0}, "kappa_w"),
        ({"n": 0.9}, "n must"),
        ({"rho": float("nan")}, "finite"),
        ({"kappa": (float("inf"),)}, "kappa_1"),
    ],
)
def test_validate_names_the_violated_condition(change, message):
    values = dict(kappa=(2.0,), kappa_w=2.0, rho=1.0, sigma=3.0, n=1.5) | change
    with pytest.raises(NotClassIError, match=message):
        BoucWenParameters(**values).validate()


def test_from_standard_matches_standard_model_simulation():
    # (8.1)-(8.2) with A=1.3, beta=0.6, gamma=-0.2 (class I), D=0.7, k=3, alpha=0.4, n=1.7
    A, beta, gamma, D, k, alpha, n = 1.3, 0.6, -0.2, 0.7, 3.0, 0.4, 1.7
    p = from_standard(A, k, alpha, beta, gamma, n, D=D)
    z0 = (A / (beta + gamma)) ** (1 / n)
    assert p.sigma == pytest.approx(beta / (beta + gamma))
    assert p.rho == pytest.approx(A / (D * z0))
    assert p.kappa_x == pytest.approx(alpha * k)
    assert p.kappa_w == pytest.approx((1 - alpha) * D * k * z0)
    x = triangle(np.linspace(0.0, 2.0, 801), 1.0, -0.5, 0.8)

    def zdot(_x, z, s):  # (8.2) in the x variable on a monotone piece, dx/dt sign s
        a = abs(z[0])
        return [(A - beta * s * a ** (n - 1) * z[0] - gamma * a**n) / D]

    z = integrate_pieces(zdot, x, 0.0)
    standard = alpha * k * x + (1 - alpha) * D * k * z  # (8.1)
    assert np.max(np.abs(model_output(p, x) - standard)) < 1e-9


def test_from_standard_rejects_non_class_i():
    with pytest.raises(NotClassIError, match="Table 8.1"):
        from_standard(1.0, 1.0, 0.5, beta=0.2, gamma=0.5, n=1.0)
    with pytest.raises(NotClassIError, match="alpha"):
        from_standard(1.0, 1.0, 1.5, beta=0.5, gamma=0.2, n=1.0)


@pytest.mark.parametrize("w0", [0.0, 0.9, -1.0, 1.0])
def test_simulate_w_matches_converged_reference_ch9(w0):
    t = np.linspace(0.0, 2.0, 2001)
    x = triangle(t, 1.0, -0.2, 0.2)  # ch. 9.2: +-0.2, T = 1
    w = simulate_w(x, **CH9, w0=w0)
    assert np.max(np.abs(w - reference_w(x, **CH9, w0=w0))) <= 1e-9
    assert w[0] == w0


@pytest.mark.parametrize(
    "sigma, n", [(0.9153, 1.176), (0.5, 1.0), (3.0, 1.0), (0.812, 1.12), (2.0, 4.0)]
)
def test_simulate_w_general_n_against_reference(sigma, n):
    x = triangle(np.linspace(0.0, 1.5, 1501), 1.0, -1.5, 1.0)  # rho*span = 5: deep saturation
    w = simulate_w(x, 2.0, sigma, n, w0=0.3)
    assert np.max(np.abs(w - reference_w(x, 2.0, sigma, n, 0.3))) <= 1e-9


def test_n_equal_one_closed_form():
    # n = 1, increasing x, w >= 0 (8.11): dw/dx = rho (1 - w)  =>  w = 1 - (1 - w0) exp(-rho dx)
    x = np.linspace(0.0, 3.0, 301)
    w = simulate_w(x, 1.7, 0.8, 1.0, w0=0.25)
    assert np.max(np.abs(w - (1.0 - 0.75 * np.exp(-1.7 * x)))) < 1e-14


def test_exact_on_monotone_pieces_independent_of_sampling():
    coarse = np.array([0.0, 0.3, -0.1, 0.25])
    fine = np.concatenate(
        [np.linspace(0.0, 0.3, 77), np.linspace(0.3, -0.1, 55)[1:], np.linspace(-0.1, 0.25, 9)[1:]]
    )
    wc = simulate_w(coarse, **CH9)
    wf = simulate_w(fine, **CH9)
    assert np.allclose(wf[[0, 76, 130, -1]], wc, atol=1e-14, rtol=0)


def test_invariance_of_unit_interval_under_random_input():
    rng = np.random.default_rng(1)
    x = np.cumsum(rng.normal(0.0, 0.5, 5000))
    for w0 in (-1.0, 1.0, 0.0):
        w = simulate_w(x, 5.0, 0.6, 1.3, w0=w0)
        assert np.all(np.abs(w) <= 1.0)
        assert np.min(w) < -0.99 and np.max(w) > 0.99  # saturation is reached, never exceeded


def test_pure_python_kernel_equals_compiled():
    x = triangle(np.linspace(0.0, 1.0, 101), 1.0, -0.2, 0.2)
    tab = _branches.tables(3.0, 1.5)
    out = np.empty_like(x)
    walk = getattr(_branches.walk, "py_func", _branches.walk)
    walk(tab, 1.0, x, 0.1, out)
    assert np.max(np.abs(out - simulate_w(x, **CH9, w0=0.1))) < 1e-15


def test_simulate_w_bad_input():
    with pytest.raises(InputSignalError, match="NaN"):
        simulate_w(np.array([0.0, np.nan]), **CH9)
    with pytest.raises(InputSignalError, match="1-D"):
        simulate_w(np.zeros((2, 2)), **CH9)
    with pytest.raises(InitialStateError, match="w0"):
        simulate_w(np.zeros(3), **CH9, w0=1.5)
    with pytest.raises(NotClassIError, match="sigma"):
        simulate_w(np.zeros(3), rho=1.0, sigma=0.2, n=1.0)
    assert simulate_w(np.array([]), **CH9).size == 0


def test_model_output_is_polynomial_plus_hysteresis_with_input_sign():
    p = BoucWenParameters(
        kappa=(1.401e-7, -5.0949e-11),
        kappa_w=9.22e-6,
        rho=0.0047,
        sigma=0.812,
        n=1.12,
        y0=1.7858e-6,
        input_sign=-1,
    )
    v = triangle(np.linspace(0.0, 20.0, 4001), 10.0, 0.0, 300.0)
    y = model_output(p, v, w0=0.05)
    w = simulate_w(-v, p.rho, p.sigma, p.n, 0.05)
    expected = 1.401e-7 * v - 5.0949e-11 * v**2 + 9.22e-6 * w + 1.7858e-6
    assert np.max(np.abs(y - expected)) < 1e-18
    assert np.allclose(polynomial((1.0, 2.0, 3.0), np.array([2.0])), [2 + 8 + 24])
    # the hysteretic loop is clockwise in the (-v, y) plane, as for Bouc-Wen in (x, Phi):
    # the cycle integral of y d(-v) (dissipated energy, Property 2) is positive
    last = slice(2000, 4001)
    energy = np.sum(np.diff(-v[last]) * 0.5 * (y[last][1:] + y[last][:-1]))
    assert energy > 0
