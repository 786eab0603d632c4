"""The pieces TimeVaryingPID.update composes (control/controller.py), each against its equation:
Δt classes, the filtered Euler x2, the bumpless x0, back-calculation and conditional
anti-windup."""

import math

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.control.controller import (
    AntiWindup,
    ControllerConfig,
    OnClose,
    Timing,
    back_calculation,
    bumpless_x0,
    check_sample,
    integration_winds_up,
    sample_timing,
    x2_filtered,
)
from piezo_stage.control.errors import ControllerConfigError, GainError, MeasurementError
from piezo_stage.control.laws import PID_TV, Gains, check_law, pid_term

from property_support import examples

pytestmark = pytest.mark.unit

G = Gains(k0=1e9, k1=5e6, k2=580.0)
finite = st.floats(-1e3, 1e3, allow_nan=False)
positive = st.floats(1e-7, 1.0)


@given(t_prev=st.none() | finite, t=finite, dt_max=positive)
@settings(max_examples=examples(200))
@example(t_prev=0.0, t=0.1, dt_max=0.1)  # Δt = dt_max is still a sample, not a gap
@example(t_prev=1.0, t=1.0, dt_max=0.1)
def test_every_step_falls_in_exactly_one_timing_class(t_prev, t, dt_max):
    timing, dt = sample_timing(t_prev, t, dt_max)
    if t_prev is None:
        assert (timing, dt) == (Timing.FIRST, 0.0)
        return
    assert dt == t - t_prev
    expected = Timing.NONPOSITIVE if dt <= 0 else Timing.OK if dt <= dt_max else Timing.GAP
    assert timing is expected


@given(x2f=finite, x=finite, x_prev=finite, yr_dot=finite, dt=positive)
@settings(max_examples=examples(200))
@example(x2f=1.0, x=0.0, x_prev=0.0, yr_dot=4.36135908851211e-181, dt=1.0)
def test_unfiltered_x2_is_the_euler_difference_and_a_filter_lies_between(
    x2f, x, x_prev, yr_dot, dt
):
    raw = (x - x_prev) / dt - yr_dot
    scale = 1e-12 * max(abs(raw), abs(x2f))  # rounding of x2f + α·(raw − x2f)
    assert x2_filtered(x2f, x, x_prev, yr_dot, dt, 0.0) == pytest.approx(raw, rel=0, abs=scale)
    filtered = x2_filtered(x2f, x, x_prev, yr_dot, dt, 10 * dt)
    assert min(raw, x2f) - scale <= filtered <= max(raw, x2f) + scale
    # α = Δt/(τ+Δt) = 1/11: one eleventh of the way from x2f to the raw value
    assert filtered == pytest.approx(x2f + (raw - x2f) / 11, rel=1e-9, abs=scale)


@given(u=finite, u_ff=finite, x1=st.floats(-1e-4, 1e-4), x2=st.floats(-1.0, 1.0))
@settings(max_examples=examples(200))
def test_the_bumpless_x0_reproduces_the_applied_output(u, u_ff, x1, x2):
    x0 = bumpless_x0(G, u, u_ff, x1, x2)
    assert pid_term(G, x0, x1, x2) + u_ff == pytest.approx(u, abs=1e-6)


@given(x0=st.floats(-1e-5, 1e-5), u=finite, u_raw=finite, dt=positive, tt=positive)
@settings(max_examples=examples(200))
def test_back_calculation_moves_the_law_towards_the_clamped_output(x0, u, u_raw, dt, tt):
    x0_new = back_calculation(x0, u, u_raw, dt, tt, G.k0)
    u_raw_new = u_raw - G.k0 * (x0_new - x0)  # the law's u at the same x1, x2
    share = min(dt / tt, 1.0)
    assert u_raw_new == pytest.approx(u_raw + share * (u - u_raw), abs=1e-6)
    assert back_calculation(x0, u, u_raw, 0.0, tt, G.k0) == x0  # no time, no bleed


@pytest.mark.parametrize(
    ("excess", "coefficient", "step", "winds_up"),
    [
        (5.0, -1e9, -1e-9, True),  # above u_max, x0 falling raises u further
        (5.0, -1e9, 1e-9, False),  # above u_max, x0 rising lowers u: integrate
        (-5.0, -1e9, 1e-9, True),  # below u_min, x0 rising lowers u further
        (-5.0, -1e9, -1e-9, False),
        (0.0, -1e9, 1e-9, False),  # within the limits: always integrate
    ],
)
def test_conditional_anti_windup_skips_only_increments_that_push_further_out(
    excess, coefficient, step, winds_up
):
    assert integration_winds_up(excess, coefficient, step) is winds_up


def test_choices_are_enums_and_a_wrong_name_lists_them():
    cfg = ControllerConfig(mode="pid_tv", anti_windup="back_calculation", on_close="reset")
    assert (
        cfg.mode == "pid_tv"
        and cfg.law is PID_TV
        and cfg.anti_windup is AntiWindup.BACK_CALCULATION
    )
    assert cfg.on_close is OnClose.RESET and f"{cfg.on_close}" == "reset"
    with pytest.raises(ControllerConfigError, match="on_close must be one of bumpless, reset"):
        ControllerConfig(on_close="smooth")
    with pytest.raises(GainError, match="expected one of pid, pid_sine, pid_tv"):
        check_law("pdi")


@pytest.mark.parametrize("bad", ["t", "x_measured", "yr", "yr_dot", "yr_ddot"])
def test_a_non_finite_sample_value_is_named(bad):
    values = dict(t=0.0, x_measured=0.0, yr=0.0, yr_dot=None, yr_ddot=0.0)
    check_sample(**values)
    values[bad] = math.nan
    with pytest.raises(MeasurementError, match=f"^{bad} must be finite"):
        check_sample(**values)
