"""phi+/-, psi+/- (9.3)-(9.9) and the closed-form limit cycle of Theorem 2 (9.12)-(9.15)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from piezo_stage.model.bouc_wen import simulate_w
from piezo_stage.model.errors import InputSignalError, NotClassIError
from piezo_stage.model.limit_cycle import (
    limit_cycle,
    limit_cycle_bounds,
    phi,
    phi_minus,
    phi_plus,
    psi,
    psi_minus,
    psi_plus,
)
from piezo_stage.model.signals import triangle

pytestmark = pytest.mark.unit

SETS = [(3.0, 1.5), (0.9153, 1.176), (0.812, 1.12), (0.5, 1.0), (7.0, 3.3)]


def quad_phi(w: float, sigma: float, n: float, sign: float) -> float:
    """Direct quadrature of (9.3) (sign=-1) / (9.4) (sign=+1)."""

    def f(u):
        return 1.0 / (1.0 + sign * (-sigma * abs(u) ** (n - 1) * u) + (sigma - 1.0) * abs(u) ** n)

    return quad(f, 0.0, w, epsabs=1e-14, epsrel=1e-13, limit=200)[0]


@pytest.mark.parametrize("sigma, n", SETS)
def test_phi_plus_minus_against_quadrature(sigma, n):
    ws = np.array([-0.999, -0.7, -0.2, -1e-3, 0.0, 1e-3, 0.3, 0.8, 0.99])
    ref_plus = [quad_phi(w, sigma, n, +1.0) for w in ws]
    ref_minus = [quad_phi(w, sigma, n, -1.0) for w in ws]
    assert np.allclose(phi_plus(ws, sigma, n), ref_plus, rtol=1e-11, atol=1e-13)
    assert np.allclose(phi_minus(ws, sigma, n), ref_minus, rtol=1e-11, atol=1e-13)
    assert np.allclose(phi(ws, sigma, n), np.add(ref_plus, ref_minus), rtol=1e-11, atol=1e-13)


def test_closed_forms_n1_and_n2():
    w = np.linspace(0.0, 0.999, 50)
    # n = 1: (9.7) -> -log(1 - w); (9.6) -> log(1 + (2 sigma - 1) w) / (2 sigma - 1)
    assert np.allclose(phi_plus(w, 3.0, 1.0), -np.log1p(-w), rtol=1e-14, atol=1e-15)
    assert np.allclose(phi_minus(w, 3.0, 1.0), np.log1p(5.0 * w) / 5.0, rtol=1e-14, atol=1e-15)
    # n = 2: (9.7) -> artanh(w); (9.6) -> arctan(sqrt(c) w) / sqrt(c)
    assert np.allclose(phi_plus(w, 2.0, 2.0), np.arctanh(w), rtol=1e-14, atol=1e-15)
    assert np.allclose(
        phi_minus(w, 2.0, 2.0), np.arctan(np.sqrt(3.0) * w) / np.sqrt(3.0), rtol=1e-14, atol=1e-15
    )


@pytest.mark.parametrize("sigma, n", SETS)
def test_inverses_and_symmetry(sigma, n):
    w = np.linspace(-0.9999, 0.9999, 301)
    assert np.max(np.abs(psi_plus(phi_plus(w, sigma, n), sigma, n) - w)) < 1e-13
    assert np.max(np.abs(psi_minus(phi_minus(w, sigma, n), sigma, n) - w)) < 1e-13
    assert np.max(np.abs(psi(phi(w, sigma, n), sigma, n) - w)) < 1e-13
    assert np.allclose(phi_minus(w, sigma, n), -phi_plus(-w, sigma, n), rtol=0, atol=1e-15)
    assert np.all(np.diff(phi(w, sigma, n)) > 0)  # strictly increasing (9.1.2)
    assert phi_plus(np.array([1.0]), sigma, n)[0] == np.inf
    assert psi_plus(np.array([np.inf]), sigma, n)[0] == 1.0


@pytest.mark.parametrize(
    "rho, sigma, n, low, high",
    [
        (1.0, 3.0, 1.5, -0.2, 0.2),
        (8.566e4, 0.9153, 1.176, 0.0, 3e-5),
        (0.0047, 0.812, 1.12, -300.0, 0.0),
    ],
)
def test_simulation_converges_to_theorem_2(rho, sigma, n, low, high):
    samples = 400
    periods = 40
    x = triangle(np.arange(periods * samples + 1) / samples, 1.0, low, high)
    w = simulate_w(x, rho, sigma, n)
    last = slice((periods - 1) * samples, periods * samples + 1)
    loading, unloading = limit_cycle(rho, sigma, n, low, high, x[last])
    tau = np.arange(samples + 1)
    expected = np.where(tau <= samples // 2, loading, unloading)
    assert np.max(np.abs(w[last] - expected)) < 1e-12
    w_low, w_high = limit_cycle_bounds(rho, sigma, n, low, high)  # (9.15), at tau = 0 and T+
    assert w[last][0] == pytest.approx(w_low, abs=1e-12)
    assert w[last][samples // 2] == pytest.approx(w_high, abs=1e-12)
    assert -1.0 < w_low == -w_high < 1.0


def test_theorem_2_offset_invariance_used_by_identification():
    # x and x + q give the same w-bar as a function of tau (9.20): w1(x + q) = w(x)
    x = np.linspace(-0.2, 0.2, 41)
    a = limit_cycle(1.0, 3.0, 1.5, -0.2, 0.2, x)
    b = limit_cycle(1.0, 3.0, 1.5, -0.1, 0.3, x + 0.1)
    assert np.allclose(a, b, rtol=0, atol=1e-15)


def test_limit_cycle_errors():
    with pytest.raises(InputSignalError, match="X_max > X_min"):
        limit_cycle(1.0, 3.0, 1.5, 0.2, -0.2, np.zeros(2))
    with pytest.raises(InputSignalError, match=r"\[x_min, x_max\]"):
        limit_cycle(1.0, 3.0, 1.5, -0.2, 0.2, np.array([0.5]))
    with pytest.raises(NotClassIError):
        phi_plus(np.zeros(2), 0.3, 1.5)
