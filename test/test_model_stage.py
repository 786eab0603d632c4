"""Amplifier, sensor and the simulated stage that chains them with a plant."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from piezo_stage.model import SimulatedStage as FromPackage
from piezo_stage.model.bouc_wen import model_output
from piezo_stage.model.errors import InvalidCommandError, ParameterValueError
from piezo_stage.model.parameter_set import shipped_parameter_set
from piezo_stage.model.plant import DynamicPlant
from piezo_stage.model.stage import AmplifierModel, SensorModel, SensorStatus, SimulatedStage

pytestmark = pytest.mark.unit


def test_amplifier_limits_bandwidth_and_slew():
    ideal = AmplifierModel()
    assert ideal.step(123.4, 1e-4) == 123.4
    clamp = AmplifierModel(v_min=0.0, v_max=100.0)
    assert clamp.step(150.0, 1e-4) == 100.0 and clamp.step(-5.0, 1e-4) == 0.0
    lag = AmplifierModel(bandwidth_hz=1000.0)
    v1 = lag.step(10.0, 1e-4)
    assert v1 == pytest.approx(10.0 * (1.0 - math.exp(-2 * math.pi * 1000.0 * 1e-4)), rel=1e-12)
    slew = AmplifierModel(slew_rate=1e4)  # 1 V per 100 us
    assert [slew.step(3.0, 1e-4) for _ in range(4)] == pytest.approx([1.0, 2.0, 3.0, 3.0])
    with pytest.raises(InvalidCommandError):
        slew.step(math.nan, 1e-4)
    assert slew.voltage == 3.0  # rejected command: state unchanged
    with pytest.raises(ParameterValueError, match="v_min < v_max"):
        AmplifierModel(v_min=1.0, v_max=0.0)
    with pytest.raises(ParameterValueError, match="bandwidth"):
        AmplifierModel(bandwidth_hz=-1.0)


def test_sensor_range_quantisation_and_seeded_noise():
    laser = SensorModel.laser(midpoint=100e-6)
    assert laser.measure(100.04e-6) == (pytest.approx(100.0e-6, abs=1e-15), SensorStatus.OK)
    assert laser.measure(100.06e-6)[0] == pytest.approx(100.1e-6, abs=1e-15)
    value, status = laser.measure(-151e-6)
    assert math.isnan(value) and status == SensorStatus.TOO_CLOSE
    value, status = laser.measure(351e-6)
    assert math.isnan(value) and status == SensorStatus.TOO_FAR
    assert laser.measure(math.nan)[1] == SensorStatus.INVALID
    noisy = [SensorModel(noise_std=1e-8, seed=4).measure(0.0)[0] for _ in range(2)]
    assert noisy[0] == noisy[1] != 0.0  # seeded: reproducible
    samples = np.array(
        [s[0] for s in map(SensorModel(noise_std=1e-8, seed=1).measure, np.zeros(4000))]
    )
    assert np.std(samples) == pytest.approx(1e-8, rel=0.1) and abs(np.mean(samples)) < 1e-9
    assert SensorModel().measure(1.23456789e-7) == (
        1.23456789e-7,
        SensorStatus.OK,
    )  # defaults: ideal
    with pytest.raises(ParameterValueError, match="range_min < range_max"):
        SensorModel(range_min=1.0, range_max=0.0)


def test_static_stage_is_the_model_output_of_the_applied_voltage():
    ps = shipped_parameter_set("ch10_patch")
    stage = SimulatedStage(ps, amplifier=AmplifierModel(v_min=0.0, v_max=250.0))
    commands = np.concatenate([np.linspace(0.0, 300.0, 61), np.linspace(300.0, 50.0, 51)])
    out = [stage.step(c, 0.01) for c in commands]
    applied = np.array([o[0] for o in out])
    assert applied.max() == 250.0
    expected = model_output(ps.bouc_wen, np.concatenate([[0.0], applied]))[1:]
    assert np.allclose([o[1] for o in out], expected, rtol=0, atol=1e-18)
    assert all(o[2] == SensorStatus.OK for o in out) and stage.steps == len(commands)


def test_dynamic_stage_steps_the_plant_and_rejects_non_finite_commands():
    ps = shipped_parameter_set("ch11_rig")
    stage = SimulatedStage(ps, sensor=SensorModel(resolution=1e-7))
    assert stage.output() == (0.0, 0.0, SensorStatus.OK)
    reference = DynamicPlant(ps.bouc_wen, ps.dynamics)
    for _ in range(50):
        applied, y, status = stage.step(100.0, 1e-4)
    x = reference.simulate(np.full(50, 100.0), 1e-4)[0][-1]
    assert applied == 100.0 and status == SensorStatus.OK
    assert y == pytest.approx(round(x / 1e-7) * 1e-7, abs=1e-15) and y > 5e-6  # ~10 um at 100 V
    before = stage.output()
    with pytest.raises(InvalidCommandError, match="finite"):
        stage.step(math.inf, 1e-4)
    assert stage.output() == before and stage.steps == 50
    assert FromPackage is SimulatedStage  # also importable from piezo_stage.model


@given(
    values=st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), max_size=60),
    noise=st.sampled_from([0.0, 1e-3, 2.0]),
    resolution=st.sampled_from([0.0, 1e-2, 0.3]),
    seed=st.integers(0, 2**16),
    span=st.sampled_from([(-1.0, 1.5), (-math.inf, math.inf)]),
)
@example(
    values=[0.5, math.nan, 3.0, -2.0, 0.25], noise=1e-3, resolution=1e-2, seed=1, span=(-1, 1.5)
)
@example(
    values=[1.797693134862316e306], noise=0.0, resolution=0.01, seed=0, span=(-math.inf, math.inf)
)
@example(values=[0.5, 3.0], noise=0.0, resolution=0.0, seed=1, span=(-math.inf, math.inf))
@example(
    values=[0.5, math.nan, -math.inf], noise=0.0, resolution=0.0, seed=1, span=(-math.inf, math.inf)
)
@pytest.mark.hypothesis
def test_measuring_many_is_measuring_each_in_turn(values, noise, resolution, seed, span):
    """The vectorised reading (what a stage steps per chunk) is the per-sample one: the same
    statuses, the same noise draws in the same order, the same quantisation; an ideal sensor
    (no noise, no quantum, no range) too; a reading its quantum or noise takes past the largest
    float is INVALID, never OK."""
    lo, hi = span
    kw = dict(noise_std=noise, resolution=resolution, range_min=lo, range_max=hi, seed=seed)
    one, many = SensorModel(**kw), SensorModel(**kw)
    each = [one.measure(v) for v in values]
    got, status = many.measure_many(np.array(values, dtype=float))
    assert status.tolist() == [s for _, s in each]
    expected = np.array([v for v, _ in each], dtype=float)
    assert np.array_equal(got, expected, equal_nan=True)
    assert np.all(np.isfinite(got[status == SensorStatus.OK]))


@pytest.mark.parametrize("name", ["ch10_patch", "ch11_rig"])
def test_stepping_many_is_stepping_each_in_turn(name):
    """``step_many`` (the emulators' substeps, one plant call per chunk) is ``step`` of each
    command in turn, read after every ``every``-th: the same applied voltages, statuses and
    readings (the static form's too: it was stepped one sample at a time)."""
    ps = shipped_parameter_set(name)
    kw = dict(resolution=1e-9, range_min=-1e-3, range_max=2e-5)  # the top of the sweep: TOO_FAR
    one, many = (
        SimulatedStage(ps, AmplifierModel(v_min=-20.0, v_max=250.0), SensorModel(**kw))
        for _ in range(2)
    )
    volts = 120.0 + 150.0 * np.sin(np.linspace(0.0, 12.0, 1200))
    each = np.array([one.step(v, 1e-4) for v in volts])[4::5]
    got = many.step_many(volts, 1e-4, 5)
    assert got.shape == each.shape and set(got[:, 2]) == {SensorStatus.OK, SensorStatus.TOO_FAR}
    assert np.array_equal(got[:, [0, 2]], each[:, [0, 2]])
    ok = each[:, 2] == SensorStatus.OK
    assert np.allclose(got[ok, 1], each[ok, 1], rtol=0.0, atol=2e-9)  # a quantum, at most
    assert many.steps == one.steps and many.amplifier.voltage == one.amplifier.voltage
