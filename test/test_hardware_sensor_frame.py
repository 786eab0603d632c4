"""A sensor's published frame (hardware/sensor_frame.py): what laser_reader publishes and the
composed loops step on are one conversion."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from piezo_stage.hardware.optoncdt import Status
from piezo_stage.hardware.sensor_frame import SensorFrame

pytestmark = pytest.mark.unit

finite = st.floats(-1.0, 1.0, allow_nan=False)


@given(
    zero=finite,
    sign=st.sampled_from([-1.0, 1.0]),
    latency=st.floats(0.0, 0.01),
    readings=st.lists(st.tuples(finite, st.sampled_from(list(Status))), max_size=20),
    arrival=st.integers(0, 2**62),
)
def test_one_reading_and_a_block_are_the_same_conversion(zero, sign, latency, readings, arrival):
    frame = SensorFrame(zero, sign, latency)
    d = [x for x, _ in readings]
    status = [int(s) for _, s in readings]
    block = frame.values(d, status)
    for x, s, v in zip(d, status, block):
        one = frame.value(x, s == Status.OK)
        assert (math.isnan(one) and math.isnan(v)) if s != Status.OK else one == v
        if s == Status.OK:
            assert v == sign * (x - zero)
    assert frame.stamp(arrival) == arrival - round(latency * 1e9)
    assert list(frame.stamps([arrival, arrival + 1])) == [
        frame.stamp(arrival),
        frame.stamp(arrival + 1),
    ]
