"""``PIEZO_QUICK=1`` shortens what it says it shortens and nothing else: ``identify --device``
lets each run settle at most 8 periods, keeps the recorded ones and says so on stderr."""

from __future__ import annotations

import argparse

import pytest

from piezo_stage.commands.quick import QUICK_SETTLE_PERIODS, QUICK_VARIABLE
from piezo_stage.commands.servo_identify import excitation_from

pytestmark = pytest.mark.unit


def _args(periods: str) -> argparse.Namespace:
    return argparse.Namespace(
        voltage="0,300", offset=100.0, periods=periods, period=1.0, record_rate=1
    )


@pytest.mark.parametrize(
    ("periods", "quick", "settle"),
    [("16,6", True, QUICK_SETTLE_PERIODS), ("16,6", False, 16), ("2,6", True, 2)],
)
def test_a_quick_device_identification_settles_fewer_periods_and_records_as_many(
    monkeypatch, capsys, periods, quick, settle
):
    monkeypatch.setenv(QUICK_VARIABLE, "1" if quick else "0")
    excitation = excitation_from(_args(periods), 0.0, 400.0)
    assert (excitation.settle_periods, excitation.record_periods) == (settle, 6)
    err = capsys.readouterr().err
    said = f"{QUICK_SETTLE_PERIODS} settling periods instead of 16"
    assert (said in err) == (quick and periods == "16,6"), err
