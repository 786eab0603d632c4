"""Excitation schedules: the identification pair, settling/steady windows, clamps, presets."""

import math

import numpy as np
import pytest

from piezo_stage.model.errors import ParameterValueError
from piezo_stage.model.excitation import PRESETS, ExcitationPlan, plan_from

pytestmark = pytest.mark.unit


def test_ch10_preset_is_the_thesis_experiment():
    plan = PRESETS["ch10_patch"]
    t = np.linspace(0, plan.run_duration, 3001, endpoint=False)
    v0 = plan.values(t)
    v1 = plan.values(t + plan.run_duration)
    assert v0.min() == pytest.approx(0.0) and v0.max() == pytest.approx(300.0, abs=0.5)
    assert v1.min() == pytest.approx(100.0) and v1.max() == pytest.approx(400.0, abs=0.5)
    np.testing.assert_allclose(v1 - v0, 100.0, atol=1e-9)  # x(t) and x(t) + q
    assert (
        plan.period == 10.0 and plan.duration == 2 * (8 + 2) * 10.0
    )  # 8 settling + 2 recorded periods per run


def test_triangle_starts_rising_from_its_minimum_and_is_periodic():
    plan = ExcitationPlan(period=2.0, low=-1.0, amplitude=2.0)
    assert plan.values(0.0) == pytest.approx(-1.0)
    assert plan.values(0.5) == pytest.approx(0.0)
    assert plan.values(1.0) == pytest.approx(1.0)
    t = np.linspace(0, 2, 101)
    np.testing.assert_allclose(plan.values(t), plan.values(t + 2.0), atol=1e-12)


def test_steady_flag_run_index_and_done():
    plan = ExcitationPlan(period=1.0, offsets=(0.0, 5.0), settle_periods=2, record_periods=3)
    assert plan.steady_window(1) == (7.0, 10.0)
    s = plan.sample(1.5)
    assert (s.run, s.steady, s.done) == (0, False, False)
    s = plan.sample(2.5)
    assert (s.run, s.steady, s.offset) == (0, True, 0.0)
    s = plan.sample(7.25)
    assert (s.run, s.steady, s.offset) == (1, True, 5.0)
    s = plan.sample(10.5)
    assert s.done and not s.steady and s.voltage == pytest.approx(plan.hold_value())


def test_clamp_never_exceeds_limits():
    plan = ExcitationPlan(period=1.0, low=-10, amplitude=100, v_min=0.0, v_max=50.0)
    v = plan.values(np.linspace(0, 3, 1000))
    assert v.min() >= 0.0 and v.max() <= 50.0 and v.max() == 50.0


def test_random_waveform_is_seeded_bounded_and_periodic():
    a = ExcitationPlan(waveform="random", period=4.0, low=0, amplitude=10, bandwidth=5.0, seed=3)
    b = ExcitationPlan(waveform="random", period=4.0, low=0, amplitude=10, bandwidth=5.0, seed=3)
    c = ExcitationPlan(waveform="random", period=4.0, low=0, amplitude=10, bandwidth=5.0, seed=4)
    t = np.linspace(0, 4, 4001)
    np.testing.assert_array_equal(a.values(t), b.values(t))
    assert not np.allclose(a.values(t), c.values(t))
    assert a.values(t).min() >= 0 and a.values(t).max() <= 10
    np.testing.assert_allclose(a.values(t[:-1]), a.values(t[:-1] + 4.0), atol=1e-9)


@pytest.mark.parametrize(
    "bad",
    [
        dict(waveform="saw"),
        dict(period=0.0),
        dict(offsets=()),
        dict(low=math.nan),
        dict(v_min=1.0, v_max=0.0),
        dict(record_periods=0),
    ],
)
def test_bad_plans_are_refused(bad):
    with pytest.raises(ParameterValueError):
        ExcitationPlan(**bad)


def test_plan_from_preset_with_overrides():
    plan = plan_from("ch9_example", period=2.0, offsets=[0.0, 0.05], seed=None)
    assert plan.period == 2.0 and plan.offsets == (0.0, 0.05) and plan.amplitude == 0.4
    with pytest.raises(ParameterValueError):
        plan_from("nope")
