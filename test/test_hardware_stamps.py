"""Stamp checks of voltage commands: every bad stamp is a verdict, never an exception."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.hardware.errors import ConfigError
from piezo_stage.hardware.stamps import StampPolicy, StampVerdict

from property_support import examples

pytestmark = pytest.mark.unit

NOW = 1.8e9  # s, a wall-clock time in 2027


@pytest.mark.parametrize(
    "sec, nanosec, verdict",
    [
        (-1, 0, StampVerdict.NEGATIVE),
        (-(2**31), 5, StampVerdict.NEGATIVE),
        (5, 10**9, StampVerdict.MALFORMED),
        (5, -1, StampVerdict.MALFORMED),
        (0, 0, StampVerdict.UNSTAMPED),
        (2**31 - 1, 0, StampVerdict.AHEAD),  # year 2038
        (int(NOW) - 3600, 0, StampVerdict.TOO_OLD),  # an hour old
        (int(NOW), 0, StampVerdict.OK),
        (int(NOW) + 1, 0, StampVerdict.OK),
    ],
)
def test_verdicts(sec, nanosec, verdict):
    policy = StampPolicy(max_age=0.5, max_ahead=5.0, require_stamp=True)
    assert policy.check(sec, nanosec, NOW)[0] is verdict


def test_sim_time_clock_at_zero_refuses_wall_stamps():
    """use_sim_time without /clock: the node clock reads 0; wall-clock stamps are far ahead."""
    assert StampPolicy(0.5).check(int(NOW) - 3600, 0, 0.0)[0] is StampVerdict.AHEAD


def test_without_checks_unstamped_is_fine_and_bad_config_is_refused():
    assert StampPolicy().check(0, 0, NOW)[0] is StampVerdict.OK
    for bad in (dict(max_age=-1.0), dict(max_age=math.nan), dict(max_ahead=0.0)):
        with pytest.raises(ConfigError):
            StampPolicy(**bad)


@settings(max_examples=examples(100))
@given(
    sec=st.integers(-(2**31), 2**31 - 1),
    nanosec=st.integers(-(2**31), 2**32 - 1),
    now=st.floats(0.0, 4e9),
    max_age=st.floats(0.0, 3600.0),
)
def test_property_any_stamp_gives_a_verdict(sec, nanosec, now, max_age):
    verdict, age = StampPolicy(max_age, 5.0, True).check(sec, nanosec, now)
    assert isinstance(verdict, StampVerdict)
    if verdict is StampVerdict.OK:
        assert -5.0 <= age and (max_age == 0 or age <= max_age)
