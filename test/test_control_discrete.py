"""Sampled-loop check (ZOH plant, rectangle-sum x0, Euler-difference x2, output delay)."""

import numpy as np
import pytest

from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT as PLANT
from piezo_stage.control.controller import ControllerConfig, TimeVaryingPID
from piezo_stage.control.discrete import (
    check_sampled_loop,
    closed_loop_matrices,
    continuous_poles,
    zoh_plant,
)
from piezo_stage.control.errors import SampledLoopError
from piezo_stage.control.laws import THESIS_GAINS as G

pytestmark = pytest.mark.unit

# docs/design.md §7: stable at 1 kHz and >= 100 kHz, unstable at 5-50 kHz; >= 200 kHz with one
# sample of delay.
CASES = [
    (1e3, 0, True),
    (5e3, 0, False),
    (20e3, 0, False),
    (50e3, 0, False),
    (100e3, 0, True),
    (1e3, 1, True),
    (100e3, 1, False),
    (200e3, 1, True),
]


def test_continuous_loop_of_the_linear_part_is_stable():
    poles = continuous_poles(PLANT, G)
    assert np.all(poles.real < 0)
    # m s^3 + (c+k2) s^2 + (kx+k1) s + k0 evaluated at its roots
    np.testing.assert_allclose(
        np.polyval([PLANT.m, PLANT.c + G.k2, PLANT.kappa_x + G.k1, G.k0], poles),
        0,
        atol=1e-6 * G.k0,
    )


@pytest.mark.parametrize("rate, delay, stable", CASES)
def test_rate_and_delay_decide_stability(rate, delay, stable):
    report = check_sampled_loop(PLANT, G, rate, delay)
    print(
        f"{rate:>9.0f} Hz delay {delay}: rho = {report.spectral_radius:.6f} "
        f"margin {report.margin:+.3e}"
    )
    assert report.stable is stable
    assert report.margin == pytest.approx(1 - report.spectral_radius)
    assert report.continuous_stable


def test_matrix_reproduces_the_controller_and_zoh_plant():
    """One step of the check's matrix equals TimeVaryingPID + exact ZOH propagation."""
    rate, delay = 20e3, 1
    period = 1 / rate
    phi = closed_loop_matrices(PLANT, G, rate, delay)[0]
    ad, bd = zoh_plant(PLANT, period)
    ctrl = TimeVaryingPID(ControllerConfig(gains=G, anti_windup="none"))
    z = np.array([2e-6, 0.0])
    # the controller's first sample neither integrates nor differentiates: x0[-1] = -T·x[0],
    # x[-1] = x[0]
    s = np.array([z[0], z[1], -period * z[0], z[0], 0.0, 0.0])
    pending = 0.0
    for k in range(12):
        out = ctrl.update(k * period, z[0])
        z = ad @ z + bd * pending  # one sample of delay
        pending = out.u
        s = phi @ s
        np.testing.assert_allclose(s[:2], z, rtol=1e-9, atol=1e-18)
        assert s[2] == pytest.approx(out.x0, rel=1e-9, abs=1e-20)


def test_pid_tv_floquet_and_derivative_filter():
    tv = check_sampled_loop(PLANT, G, 1e3, 0, law="pid_tv")
    assert tv.stable and tv.spectral_radius != check_sampled_loop(PLANT, G, 1e3).spectral_radius
    assert not check_sampled_loop(PLANT, G, 20e3, 0, law="pid_tv").stable
    filt = check_sampled_loop(PLANT, G, 1e3, derivative_tau=1e-3)
    assert filt.spectral_radius != check_sampled_loop(PLANT, G, 1e3).spectral_radius


def test_initial_slope_linearisation_changes_the_answer():
    assert not check_sampled_loop(PLANT, G, 2e3).stable
    assert check_sampled_loop(PLANT, G, 2e3, hysteresis="initial_slope").stable


def test_bad_arguments():
    with pytest.raises(SampledLoopError, match="rate_hz"):
        check_sampled_loop(PLANT, G, 0.0)
    with pytest.raises(SampledLoopError, match="delay_samples"):
        check_sampled_loop(PLANT, G, 1e3, -1)
    with pytest.raises(SampledLoopError, match="integer"):
        check_sampled_loop(PLANT, G, 1234.5, law="pid_tv")
    with pytest.raises(SampledLoopError, match="hysteresis"):
        check_sampled_loop(PLANT, G, 1e3, hysteresis="bogus")


@pytest.mark.unit
def test_a_loop_without_an_integral_is_judged_without_its_x0_mode():
    """k0 = 0: x0 feeds nothing back, so the full matrix has an eigenvalue 1 that is not the
    loop's; the check's radius is the largest of the others, and the loop counts as stable."""
    from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT
    from piezo_stage.control.discrete import _step_matrix, zoh_plant
    from piezo_stage.control.laws import Gains

    pd = Gains(k0=0.0, k1=5e6, k2=600.0)
    report = check_sampled_loop(THESIS_NOMINAL_PLANT, pd, 100e3, 0, "pid")
    ad, bd = zoh_plant(THESIS_NOMINAL_PLANT, 1 / 100e3, "disturbance")
    full = _step_matrix(ad, bd, 1 / 100e3, (0.0, 5e6, 600.0), 0, 1.0)
    eig = np.linalg.eigvals(full)
    x0_mode = np.argmin(np.abs(eig - 1.0))
    assert abs(eig[x0_mode] - 1.0) < 1e-12  # x0 integrates and feeds nothing back
    others = np.abs(np.delete(eig, x0_mode))
    assert report.spectral_radius == pytest.approx(others.max(), rel=1e-9)
    assert report.stable and report.continuous_stable
