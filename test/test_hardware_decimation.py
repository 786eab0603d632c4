"""Decimation of the sensor stream (piezo_stage.hardware.decimation): means of N OK samples,
the first bad status of a group, stamps at the group's mean time, groups across blocks."""

from __future__ import annotations

import math

import numpy as np
import pytest

from piezo_stage.hardware import ConfigError, Decimator, Status

pytestmark = pytest.mark.unit

PERIOD = 1_000_000  # ns: a 1 kHz sensor


def block(values, status=None) -> tuple[list[float], list[int]]:
    """Displacement (NaN unless OK, as the parser gives it) and status of a block."""
    s = [0] * len(values) if status is None else [int(x) for x in status]
    return [float(v) if st == Status.OK else math.nan for v, st in zip(values, s)], s


def stamps(first: int, n: int) -> list[int]:
    return [first * PERIOD + PERIOD * k for k in range(n)]


def test_groups_are_means_stamped_at_their_middle_and_carry_over_blocks():
    dec = Decimator(4)
    a = dec.feed(*block([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]), stamps(0, 6))
    assert list(a.displacement) == [2.5] and list(a.status) == [Status.OK]
    assert list(a.stamp) == [PERIOD * 3 // 2]  # samples 0..3: mean time 1.5 ms
    b = dec.feed(*block([7.0, 8.0, 9.0]), stamps(6, 3))  # completes samples 4..7
    assert list(b.displacement) == [6.5] and list(b.stamp) == [PERIOD * 11 // 2]
    dec.reset()  # a reconnect: sample 8 is dropped, the next group starts afresh
    c = dec.feed(*block([0.0] * 4), stamps(100, 4))
    assert list(c.displacement) == [0.0] and list(c.stamp) == [100 * PERIOD + PERIOD * 3 // 2]


def test_a_group_with_a_bad_sample_takes_its_first_bad_status_and_nan():
    status = [0, Status.TOO_FAR, Status.NO_TARGET, 0, 0, 0, 0, 0]
    out = Decimator(4).feed(*block(np.arange(8.0), status), stamps(0, 8))
    assert list(out.status) == [Status.TOO_FAR, Status.OK]
    assert math.isnan(out.displacement[0]) and out.displacement[1] == pytest.approx(5.5)


def test_one_passes_every_sample_and_less_than_one_is_refused():
    out = Decimator(1).feed(*block([1.0, 2.0], [0, Status.INVALID]), stamps(0, 2))
    assert out.displacement[0] == 1.0 and math.isnan(out.displacement[1])
    assert list(out.stamp) == list(stamps(0, 2))
    with pytest.raises(ConfigError):
        Decimator(0)
