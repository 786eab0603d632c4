"""Regression: n just above 1 (the ch. 10 patch has n = 1.12) must simulate accurately.

The branch integral H of (9.7) is a small difference of large terms when n -> 1; its table once
failed to converge for 1 < n < ~1.11, which made identification refuse data near the patch."""

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from piezo_stage.model.bouc_wen import simulate_w

pytestmark = pytest.mark.unit


def _reference(x_up: float, x_down: float, rho: float, sigma: float, n: float, xs_up, xs_down):
    def g(w: float, sign: int) -> float:  # (8.9) with dx/dt of sign `sign`
        return 1 - sigma * abs(w) ** (n - 1) * w * sign + (sigma - 1) * abs(w) ** n

    up = solve_ivp(
        lambda x, w: [rho * g(w[0], 1)], (0, x_up), [0.0], rtol=1e-13, atol=1e-15, dense_output=True
    )
    down = solve_ivp(
        lambda x, w: [rho * g(w[0], -1)],
        (x_up, x_down),
        [up.sol(x_up)[0]],
        rtol=1e-13,
        atol=1e-15,
        dense_output=True,
    )
    return np.concatenate([up.sol(xs_up)[0], down.sol(xs_down)[0]])


@pytest.mark.parametrize("n", [1.0001, 1.01, 1.05, 1.1, 1.12, 1.176])
@pytest.mark.parametrize("sigma", [0.5, 0.812, 3.0])
def test_w_near_n_equal_one_matches_a_converged_reference(n, sigma):
    xs_up = np.linspace(0, 2, 200)
    xs_down = np.linspace(2, -1, 300)[1:]
    w = simulate_w(np.concatenate([xs_up, xs_down]), 1.0, sigma, n, 0.0)
    ref = _reference(2.0, -1.0, 1.0, sigma, n, xs_up, xs_down)
    assert np.max(np.abs(w - ref)) < 1e-9
