"""The realtime plant's timer with no commander (:func:`piezo_stage.nodes.plant.hold_period`):
whole samples, a burst a SensorDataQoS reader keeps, never slower than HOLD_TICK unless one
sample is."""

from __future__ import annotations

import math

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from piezo_stage.nodes.plant import HOLD_TICK, hold_period
from piezo_stage.nodes.qos import SENSOR_QOS

pytestmark = pytest.mark.unit


@given(st.floats(min_value=1.0, max_value=1e7))
@example(1000.0)
@example(1.0 / HOLD_TICK)
@example(3000.0)
def test_a_burst_is_whole_samples_a_sensor_reader_keeps(rate_hz: float) -> None:
    period = hold_period(rate_hz)
    samples = period * rate_hz
    assert samples == pytest.approx(round(samples), rel=1e-9)
    assert 1 <= round(samples) <= SENSOR_QOS.depth
    assert period <= max(HOLD_TICK, 1.0 / rate_hz) * (1 + 1e-12)


def test_at_1_khz_the_plant_wakes_every_5_ms() -> None:
    assert hold_period(1000.0) == pytest.approx(5e-3)
    assert math.isclose(hold_period(100.0), 1e-2)
