"""The voltage a trajectory needs by the ch. 11 inverse model, against an amplifier's range
(control/voltage_range.py), and the saturation figures of the loop's supervision."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.control.controller import ControllerConfig, TimeVaryingPID
from piezo_stage.control.feedforward import FeedforwardModel, feedforward
from piezo_stage.control.laws import Gains
from piezo_stage.control.scan import make_trajectory
from piezo_stage.control.supervision import (
    Health,
    LoopSupervisor,
    SaturationWindow,
    SupervisionConfig,
)
from piezo_stage.control.voltage_range import (
    AMPLITUDE_TOLERANCE,
    PID_MARGIN,
    AmplifierRange,
    VoltageNeed,
    VoltageRangeError,
    largest_amplitude,
    voltage_need,
)
from piezo_stage.model.parameter_set import shipped_parameter_set

from property_support import examples

pytestmark = pytest.mark.unit

RIG = FeedforwardModel.from_parameter_set(shipped_parameter_set("ch11_rig"))
KX, KW = RIG.bouc_wen.kappa[0], RIG.bouc_wen.kappa_w
AMPLIFIER = AmplifierRange(0.0, 400.0)


def triangle(amplitude: float, offset: float, frequency: float = 10.0):
    return make_trajectory("triangle", amplitude=amplitude, frequency=frequency, offset=offset)


def test_the_need_is_the_inverse_model_along_x_d_and_brackets_its_static_part():
    """6-46 µm at 10 Hz on the ch. 11 rig: κx·46 µm = 476 V plus κw·w near +1 at the top,
    κx·6 µm = 62 V less κw near the bottom; the figure is the model's own along a finer grid."""
    tr = triangle(20e-6, 26e-6)
    need = voltage_need(RIG, tr)
    t = np.linspace(0.0, 3 * tr.period, 60001)
    u, w = feedforward(RIG, *tr.evaluate(t), 0.0)
    assert need.low == pytest.approx(u.min(), abs=0.05) and need.high == pytest.approx(
        u.max(), abs=0.05
    )
    assert KX * 46e-6 < need.high < KX * 46e-6 + KW
    assert KX * 6e-6 - KW < need.low < KX * 6e-6
    assert w.max() > 0.9 and w.min() < -0.9  # the hysteresis swings through its range


def test_the_range_keeps_a_margin_for_the_pid_and_refuses_bad_limits():
    assert AMPLIFIER.margin == pytest.approx(PID_MARGIN * 400.0)
    assert AMPLIFIER.usable == (8.0, 392.0)
    assert AMPLIFIER.admits(VoltageNeed(8.0, 392.0))
    assert not AMPLIFIER.admits(VoltageNeed(7.9, 100.0))
    assert not AMPLIFIER.admits(VoltageNeed(100.0, 392.1))
    unbounded = AmplifierRange(-math.inf, math.inf)
    assert unbounded.margin == 0.0 and unbounded.admits(VoltageNeed(-1e6, 1e6))
    for bad in ((400.0, 0.0), (math.nan, 1.0), (0.0, 0.0)):
        with pytest.raises(VoltageRangeError, match="u_min < u_max"):
            AmplifierRange(*bad)
    with pytest.raises(VoltageRangeError, match="margin_share"):
        AmplifierRange(0.0, 1.0, 0.5)


def test_the_largest_amplitude_of_the_refused_rig_request():
    """The emulated rig's 20 µm at offset 26 µm needs 524 V; at that offset 400 V less the
    margin allows ~8.2 µm (κx·(26 + 8.2) µm + κw·w ≈ 392 V)."""
    best = largest_amplitude(RIG, lambda a: triangle(a, 26e-6), AMPLIFIER, 20e-6)
    assert 7e-6 < best < 9.5e-6
    assert AMPLIFIER.admits(voltage_need(RIG, triangle(best, 26e-6)))
    assert not AMPLIFIER.admits(voltage_need(RIG, triangle(1.01 * best, 26e-6)))
    # an admitted request is its own answer; an offset that alone needs too much has none
    assert largest_amplitude(RIG, lambda a: triangle(a, 16e-6), AMPLIFIER, 10e-6) == 10e-6
    assert largest_amplitude(RIG, lambda a: triangle(a, 60e-6), AMPLIFIER, 10e-6) == 0.0
    with pytest.raises(VoltageRangeError, match="upper"):
        largest_amplitude(RIG, lambda a: triangle(a, 26e-6), AMPLIFIER, 0.0)


@settings(max_examples=examples(25), deadline=None)
@given(
    offset=st.floats(5e-6, 40e-6),
    amplitude=st.floats(0.5e-6, 30e-6),
    u_min=st.floats(-100.0, 60.0),
    span=st.floats(150.0, 600.0),
    shape=st.sampled_from(["triangle", "sine", "steps"]),
)
# the offset alone nearly leaves the range: the answer (1.5 nm) is within the bisection's
# tolerance of the exact one, and 1 % more of it is still admitted
@example(offset=5e-6, amplitude=9.12508397408557e-06, u_min=48.734375, span=150.0, shape="triangle")
def test_largest_amplitude_is_admitted_and_one_percent_more_is_not(
    offset, amplitude, u_min, span, shape
):
    """The answer is admitted; 1 % more is not, or the tolerance more where that is larger
    (the answer is exact to the tolerance times the ask)."""
    amplifier = AmplifierRange(u_min, u_min + span)

    def at(a: float):
        return make_trajectory(shape, amplitude=a, frequency=10.0, offset=offset)

    best = largest_amplitude(RIG, at, amplifier, amplitude)
    need = voltage_need(RIG, at(amplitude))
    low, high = amplifier.usable
    # the refusal fires iff the need leaves the usable range; then the answer is below the ask
    assert amplifier.admits(need) == (low <= need.low and need.high <= high)
    assert (best == amplitude) == amplifier.admits(need)
    if 0.0 < best < amplitude / 1.01:
        assert amplifier.admits(voltage_need(RIG, at(best)))
        more = max(1.01 * best, best + AMPLITUDE_TOLERANCE * amplitude)
        assert not amplifier.admits(voltage_need(RIG, at(more)))


@settings(max_examples=examples(25), deadline=None)
@given(
    offset=st.floats(0.0, 40e-6),
    a=st.floats(0.5e-6, 20e-6),
    more=st.floats(1.01, 3.0),
    shape=st.sampled_from(["triangle", "sine", "steps"]),
)
def test_the_need_grows_with_the_amplitude(offset, a, more, shape):
    """What bisection relies on: at a fixed offset a larger amplitude needs a wider range."""
    small = voltage_need(RIG, make_trajectory(shape, amplitude=a, offset=offset))
    large = voltage_need(RIG, make_trajectory(shape, amplitude=a * more, offset=offset))
    assert large.low <= small.low + 1e-9 and large.high >= small.high - 1e-9


def test_a_model_1_percent_stiffer_needs_about_1_percent_more():
    stiff = replace(
        RIG,
        bouc_wen=replace(RIG.bouc_wen, kappa=(1.01 * KX,), kappa_w=1.01 * KW),
    )
    tr = triangle(20e-6, 26e-6)
    ratio = voltage_need(stiff, tr).high / voltage_need(RIG, tr).high
    assert ratio == pytest.approx(1.01, rel=1e-3)


# ---------------------------------------------------------------------------- saturation
def test_the_window_reports_what_was_counted_since_the_previous_report():
    window = SaturationWindow()
    assert window.report(0, 0) == (0, 0)
    assert window.report(3, 10) == (3, 10)
    assert window.report(3, 30) == (0, 20)
    assert window.report(9, 35) == (5, 5)  # one saturated step counted before its step: capped


def _saturating_supervisor() -> LoopSupervisor:
    pid = TimeVaryingPID(
        ControllerConfig(
            gains=Gains(k0=1e9, k1=5e6, k2=580.0, kA=1.5e9, A=15.0, f=100.0),
            u_min=0.0,
            u_max=100.0,
        ),
        closed=False,
    )
    return LoopSupervisor(
        pid, SupervisionConfig(rate_hz=1000.0, u_min=0.0, u_max=100.0, start_closed=True)
    )


def test_diagnose_warns_with_the_share_of_the_steps_saturated_since_the_last_report():
    """100 steps 1 mm below the set point (after the bumpless first step at 0 V the law asks for
    thousands of volts: saturated), then 50 with the loop open, held at 100 V: the share
    is per report."""
    sup = _saturating_supervisor()
    for k in range(100):
        sup.sample(k * 1e-3, 0.0, True)
        sup.step(k * 1e-3, 1e-3)
    level, message, values = sup.diagnose()
    assert level is Health.WARN and values["saturated_share"] == 0.99
    assert "saturated on 99 % of the 100 steps" in message and "0 to 100 V" in message
    assert sup.diagnose()[0] is Health.OK  # no step since: nothing saturated in this window
    sup.open()  # held at the hold voltage (the last output, 100 V): within the limits
    for k in range(100, 150):
        sup.sample(k * 1e-3, 0.0, True)
        sup.step(k * 1e-3, 1e-3)
    level, message, values = sup.diagnose()
    assert sup.saturated_steps == 99 and sup.steps == 150
    assert level is Health.OK and values["saturated_share"] == 0.0
