"""TimeVaryingPID: discrete x0/x2 (§11.5), clamp + anti-windup, hold, bumpless transfer, dt
guards."""

import math

import pytest

from piezo_stage.control.controller import ControllerConfig, TimeVaryingPID
from piezo_stage.control.errors import ControllerConfigError, MeasurementError
from piezo_stage.control.laws import Gains

pytestmark = pytest.mark.unit

G = Gains(k0=1e9, k1=5e6, k2=580.0, kA=1.5e9, A=15.0, f=100.0)
DT = 1e-3


def run(ctrl, xs, t0=0.0, yr=0.0):
    return [ctrl.update(t0 + i * DT, x, yr) for i, x in enumerate(xs)]


def test_rectangle_sums_and_euler_differences():
    ctrl = TimeVaryingPID(ControllerConfig(gains=G))
    out = run(ctrl, [1e-6, 2e-6, 4e-6])
    assert out[0].timing == "first" and out[0].x0 == 0.0 and out[0].x2 == 0.0
    assert out[1].x0 == pytest.approx(2e-6 * DT) and out[1].x2 == pytest.approx(1e-3)
    assert out[2].x0 == pytest.approx(6e-6 * DT) and out[2].x2 == pytest.approx(2e-3)
    assert out[2].u == pytest.approx(-1e9 * 6e-9 - 5e6 * 4e-6 - 580 * 2e-3)
    assert out[2].u == out[2].u_pid and out[2].u_excitation == 0.0 and out[2].loop_closed


def test_x2_uses_reference_derivative():
    ctrl = TimeVaryingPID(ControllerConfig(gains=G))
    ctrl.update(0.0, 0.0, yr=0.0)
    tracking = ctrl.update(DT, 1e-6, yr=1e-6)  # ẏr from the Euler difference of yr
    assert tracking.x1 == 0.0 and tracking.x2 == pytest.approx(0.0, abs=1e-15)
    given = ctrl.update(
        2 * DT, 2e-6, yr=2e-6, yr_dot=0.0
    )  # ẏr given: derivative on measurement only
    assert given.x2 == pytest.approx(1e-3)


def test_derivative_filter_first_order():
    tau = 3e-3
    ctrl = TimeVaryingPID(ControllerConfig(gains=G, derivative_tau=tau))
    out = run(ctrl, [0.0, 1e-6, 2e-6, 3e-6])
    alpha = DT / (tau + DT)
    assert out[1].x2 == pytest.approx(alpha * 1e-3)
    assert out[2].x2 == pytest.approx(out[1].x2 + alpha * (1e-3 - out[1].x2))


def test_sine_laws_phase_from_closing_time():
    ctrl = TimeVaryingPID(ControllerConfig(mode="pid_sine", gains=G))
    out = run(ctrl, [0.0, 0.0, 0.0], t0=10.0)  # phase origin: first sample, not t = 0
    assert out[0].u_excitation == pytest.approx(0.0, abs=1e-9)
    assert out[1].u_excitation == pytest.approx(-15.0 * math.sin(2 * math.pi * 100 * DT))
    tv = TimeVaryingPID(ControllerConfig(mode="pid_tv", gains=G))
    out = run(tv, [1e-6, 1e-6, 1e-6])
    assert out[2].u_excitation == pytest.approx(
        -1.5e9 * out[2].x0 * math.sin(2 * math.pi * 100 * 2 * DT)
    )
    assert out[2].u == pytest.approx(out[2].u_pid + out[2].u_excitation)


def _windup_recovery(mode):
    """Saturate against u_min = -10 V for 50 steps, then reverse the error; steps until
    unsaturated."""
    ctrl = TimeVaryingPID(ControllerConfig(gains=G, u_min=-10.0, u_max=10.0, anti_windup=mode))
    out = run(ctrl, [1e-6] * 50)
    assert all(o.saturated and o.u == -10.0 for o in out[10:])
    x0_saturated = ctrl.x0
    out = run(ctrl, [-1e-6] * 200, t0=50 * DT)
    return x0_saturated, next(i for i, o in enumerate(out) if not o.saturated)


def test_anti_windup_modes():
    x0_none, n_none = _windup_recovery("none")
    x0_cond, n_cond = _windup_recovery("conditional")
    x0_back, n_back = _windup_recovery("back_calculation")
    assert x0_none == pytest.approx(49e-6 * DT)  # integrated all along (no Δt at the first sample)
    assert x0_cond < 0.2 * x0_none and x0_back < 0.2 * x0_none
    assert n_none > 20 and n_cond <= 2 and n_back <= 2


def test_conditional_integration_direction():
    cfg = ControllerConfig(gains=G, u_min=-10.0, u_max=10.0, anti_windup="conditional")
    ctrl = TimeVaryingPID(cfg, x0_initial=20e-9)  # u ≈ -20 V: saturated low
    run(ctrl, [1e-6, 1e-6])  # positive error drives u further down: x0 frozen
    assert ctrl.x0 == 20e-9 and ctrl.last_output.saturated
    ctrl = TimeVaryingPID(cfg, x0_initial=20e-9)
    run(ctrl, [-1e-6, -1e-6])  # negative error drives u up, out of the limit: x0 integrates
    assert ctrl.x0 == pytest.approx(19e-9) and ctrl.last_output.saturated


def test_hold_values_while_open():
    ctrl = TimeVaryingPID(ControllerConfig(gains=G, u_min=-450.0, u_max=450.0))
    last = run(ctrl, [1e-6, 2e-6])[-1]
    ctrl.open_loop()  # last output
    out = ctrl.update(2 * DT, 5e-6)
    assert not out.loop_closed and out.u == last.u and out.u_pid == 0.0
    ctrl.open_loop(hold=72.0)
    assert ctrl.update(3 * DT, 5e-6).u == 72.0
    ctrl.open_loop(hold=1000.0)  # clamped to the amplifier
    out = ctrl.update(4 * DT, 5e-6)
    assert out.u == 450.0 and out.saturated
    cfg_hold = TimeVaryingPID(ControllerConfig(gains=G, hold_voltage=200.0), closed=False)
    assert cfg_hold.update(0.0, 0.0).u == 200.0 and not cfg_hold.loop_closed


@pytest.mark.parametrize("mode", ["pid", "pid_sine", "pid_tv"])
def test_bumpless_transfer(mode):
    ctrl = TimeVaryingPID(ControllerConfig(mode=mode, gains=G))
    run(ctrl, [3e-6, 2e-6, 1e-6])
    ctrl.open_loop(hold=72.0)
    run(ctrl, [4e-6, 6e-6], t0=3 * DT)
    ctrl.close_loop()
    assert ctrl.loop_closed
    out = ctrl.update(5 * DT, 7e-6)
    assert out.loop_closed and out.x2 == pytest.approx(1e-3) and out.x1 == 7e-6
    assert out.u == pytest.approx(72.0, abs=1e-9)  # continuous despite x1, x2 != 0
    nxt = ctrl.update(6 * DT, 7e-6)  # then the law moves on from the transferred x0
    assert nxt.x0 == pytest.approx(out.x0 + 7e-6 * DT) and nxt.u != pytest.approx(72.0)


def test_reset_and_keep_on_close():
    reset = TimeVaryingPID(ControllerConfig(gains=G, on_close="reset"), closed=False)
    reset.update(0.0, 1e-6)
    reset.close_loop()
    out = reset.update(DT, 1e-6)
    assert out.x0 == 0.0 and out.u == pytest.approx(-5.0)
    keep = TimeVaryingPID(ControllerConfig(gains=G, on_close="keep"))
    run(keep, [1e-6, 1e-6, 1e-6])
    x0 = keep.x0
    keep.open_loop(hold=0.0)
    run(keep, [9e-6, 9e-6], t0=3 * DT)
    assert keep.x0 == x0  # no integration while open
    keep.close_loop()
    assert keep.update(5 * DT, 9e-6).x0 == x0


def test_dt_guards():
    ctrl = TimeVaryingPID(ControllerConfig(gains=G, dt_max=0.01))
    out = run(ctrl, [1e-6, 2e-6])
    x0 = ctrl.x0
    same = ctrl.update(DT, 9e-6)  # repeated timestamp
    assert same.timing == "nonpositive_dt" and same.u == out[-1].u and ctrl.x0 == x0
    back = ctrl.update(0.0, 9e-6)  # time going backwards
    assert back.timing == "nonpositive_dt" and ctrl.x0 == x0
    gap = ctrl.update(1.0, 3e-6)  # 1 s gap: no integration, x2 re-baselined
    assert gap.timing == "gap" and gap.x0 == x0 and gap.x2 == 0.0
    nxt = ctrl.update(1.0 + DT, 4e-6)
    assert (
        nxt.timing == "ok"
        and nxt.x2 == pytest.approx(1e-3)
        and nxt.x0 == pytest.approx(x0 + 4e-6 * DT)
    )


def test_invalid_inputs_and_config():
    ctrl = TimeVaryingPID(ControllerConfig(gains=G))
    with pytest.raises(MeasurementError, match="open the loop"):
        ctrl.update(0.0, float("nan"))
    with pytest.raises(ControllerConfigError, match="anti_windup"):
        TimeVaryingPID(ControllerConfig(gains=G, anti_windup="clamp"))
    with pytest.raises(ControllerConfigError, match="u_min < u_max"):
        TimeVaryingPID(ControllerConfig(gains=G, u_min=1.0, u_max=-1.0))
    with pytest.raises(ControllerConfigError, match="k0 > 0"):
        TimeVaryingPID(ControllerConfig(gains=Gains(0.0, 1.0, 1.0)))


def test_reconfigure_keeps_u_continuous():
    ctrl = TimeVaryingPID(ControllerConfig(gains=G))
    run(ctrl, [1e-6] * 5)
    before = -G.k0 * ctrl.x0
    ctrl.reconfigure(ControllerConfig(gains=Gains(k0=5e8, k1=5e6, k2=580.0)))
    assert -5e8 * ctrl.x0 == pytest.approx(before)
