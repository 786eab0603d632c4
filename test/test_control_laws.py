"""The three laws (11.5, 11.17, 11.18) and the §11.4.1 second-order reference."""

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.control.errors import ControlError, GainError
from piezo_stage.control.laws import (
    THESIS_GAINS,
    Gains,
    control_law,
    excitation_term,
    pid_term,
    x0_coefficient,
)
from piezo_stage.control.reference import SecondOrderReference

from property_support import examples

pytestmark = pytest.mark.unit

G = Gains(k0=1e9, k1=5e6, k2=580.0, kA=1.5e9, A=15.0, f=100.0)


def test_pid_formula():
    assert pid_term(G, 2e-9, 3e-6, 0.01) == pytest.approx(-1e9 * 2e-9 - 5e6 * 3e-6 - 580 * 0.01)
    assert control_law("pid", G, 0.0025, 2e-9, 3e-6, 0.01) == pytest.approx(-2 - 15 - 5.8)


def test_pid_sine_formula():
    t = 0.0025  # sin(2π·100·0.0025) = 1
    assert control_law("pid_sine", G, t, 2e-9, 3e-6, 0.01) == pytest.approx(-22.8 - 15.0)


def test_pid_tv_formula_and_x0_coefficient():
    t = np.array([0.0, 0.0025, 0.0075])  # sin = 0, 1, -1
    u = control_law("pid_tv", G, t, 2e-9, 0.0, 0.0)
    np.testing.assert_allclose(u, [-2.0, -2.0 - 3.0, -2.0 + 3.0])
    assert x0_coefficient("pid_tv", G, 0.0025) == pytest.approx(-2.5e9)
    assert x0_coefficient("pid", G, 0.0025) == -1e9


def test_laws_vectorise_and_reject_unknown_names():
    x = np.linspace(0, 1e-5, 7)
    assert np.shape(control_law("pid_tv", G, x, x, x, x)) == (7,)
    assert np.all(excitation_term("pid", G, x, x) == 0)
    with pytest.raises(GainError, match="unknown control law"):
        control_law("pi", G, 0, 0, 0, 0)


def test_gains_validation():
    THESIS_GAINS.validate("pid_tv")
    with pytest.raises(GainError, match="k2 must be >= 0"):
        Gains(1, 1, -1).validate()
    with pytest.raises(GainError, match="f > 0"):
        Gains(1, 1, 1, f=0.0).validate("pid_sine")


def test_reference_obeys_its_ode_and_initial_conditions():
    ref = SecondOrderReference(y0=20e-6, ydot0=0.2)
    assert ref.xi == 0.7 and ref.omega0 == pytest.approx(2 * math.pi * 500)
    y, yd, ydd = ref.evaluate(np.array([0.0]))
    assert y[0] == pytest.approx(20e-6) and yd[0] == pytest.approx(0.2)
    t = np.linspace(0.0, 0.01, 20001)
    y, yd, ydd = ref.evaluate(t)
    w0 = ref.omega0
    np.testing.assert_allclose(ydd + 2 * 0.7 * w0 * yd + w0**2 * y, 0.0, atol=1e-9 * w0**2 * 20e-6)
    np.testing.assert_allclose(np.gradient(y, t)[1:-1], yd[1:-1], atol=1e-3 * np.max(np.abs(yd)))
    assert abs(y[-1]) < 1e-12  # decays (e^{-0.7·2π·500·0.01} ≈ 3e-10 of the start)


@pytest.mark.parametrize("xi", [1.0, 2.0])
def test_reference_other_damping_and_target(xi):
    ref = SecondOrderReference(y0=0.0, ydot0=0.0, xi=xi, target=5e-6, t_start=0.1)
    y, yd, _ = ref.evaluate(np.array([0.05, 0.1, 0.2]))
    assert y[0] == 0.0 and yd[0] == 0.0 and y[1] == pytest.approx(0.0)
    assert y[2] == pytest.approx(5e-6, rel=1e-6)
    assert ref(0.1001)[1] > 0  # moving up towards the target


@settings(max_examples=examples(60), deadline=None)
@given(
    y0=st.floats(-1e-4, 1e-4),
    ydot0=st.floats(-1.0, 1.0),
    xi=st.floats(0.05, 3.0),
    omega0=st.floats(10.0, 1e4),
    target=st.floats(-1e-4, 1e-4),
    t_start=st.floats(-1.0, 1.0),
    times=st.lists(st.floats(-2.0, 2.0), min_size=1, max_size=20),
)
@example(0.0, 0.0, 1.0, 3000.0, 5e-6, 0.1, [0.05, 0.1, 0.2])  # critically damped: its own form
def test_the_reference_at_one_time_is_its_evaluation_there(
    y0, ydot0, xi, omega0, target, t_start, times
):
    """``at(t)`` (a controller's per-sample call, in scalar arithmetic) gives what
    ``evaluate`` gives at t, to rounding, for any damping, before and after t_start."""
    ref = SecondOrderReference(y0, ydot0, xi, omega0, target, t_start)
    t = np.array(times + [t_start])
    want = ref.evaluate(t)
    got = np.array([ref.at(float(tk)) for tk in t]).T
    e0 = abs(y0 - target) + abs(ydot0) / omega0 + 1e-30  # the motion's scale [m]
    for g, w, scale in zip(got, want, (e0 + abs(target), e0 * omega0, e0 * omega0**2)):
        np.testing.assert_allclose(g, w, rtol=0.0, atol=1e-9 * scale)


def test_reference_rejects_bad_parameters():
    with pytest.raises(ControlError, match="xi > 0"):
        SecondOrderReference(y0=0.0, xi=0.0)
