"""The composed loop's step without ROS (control/rig_loop.py): a block of samples → the law on
each → one write of the newest output → a row per sample; a read that timed out → the law's
gap check; the per-sample topics' decimation."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from piezo_stage.control.controller import ControllerConfig, TimeVaryingPID
from piezo_stage.control.rig_loop import RigLoop, Row, TopicDecimation
from piezo_stage.control.supervision import LoopSupervisor, SupervisionConfig

pytestmark = pytest.mark.unit

STEP = TimeVaryingPID(ControllerConfig(), closed=True).update(0.0, 0.0)


class Law:
    """A law that answers each valid sample with 10·x (its output stamped as a step) and an
    invalid one with the hold 1.0 V; ``gap`` what check_gap answers."""

    def __init__(self, gap: float | None = None) -> None:
        self.last_step = None
        self.calls: list[tuple[int, float, bool, bool]] = []
        self.gap, self.gaps = gap, []

    def on_sample(self, stamp_ns: int, x: float, ok: bool, publish: bool) -> float | None:
        self.calls.append((stamp_ns, x, ok, publish))
        if not ok:
            self.last_step = None
            return 1.0
        self.last_step = replace(STEP, reference=2 * x, u_ff=3 * x, loop_closed=True)
        return 10 * x

    def check_gap(self, t: float) -> float | None:
        self.gaps.append(t)
        return self.gap


class Amplifier:
    def __init__(self) -> None:
        self.last_sent = math.nan
        self.writes: list[tuple[float, bool]] = []

    def command(self, voltage: float, publish: bool = True) -> None:
        self.last_sent = voltage
        self.writes.append((voltage, publish))


def make(law: Law, topics_every: float = 1.0) -> tuple[RigLoop, Amplifier, list, list]:
    amplifier, blocks, after = Amplifier(), [], []
    supervisor = LoopSupervisor(
        TimeVaryingPID(ControllerConfig()), SupervisionConfig(rate_hz=1000.0)
    )
    loop = RigLoop(
        law,
        amplifier,
        supervisor,
        TopicDecimation(1000.0, 1000.0 / topics_every),
        lambda rows, applied: blocks.append((rows, applied)),
        lambda: after.append(True),
    )
    return loop, amplifier, blocks, after


def test_a_block_steps_the_law_on_every_sample_and_writes_the_newest_output_once():
    law = Law()
    loop, amplifier, blocks, after = make(law)
    assert loop.step([1.0, 2.0, 3.0], [0, 0, 0], [10, 20, 30]) is None  # every sample due
    assert [c[:3] for c in law.calls] == [(10, 1.0, True), (20, 2.0, True), (30, 3.0, True)]
    assert amplifier.writes == [(30.0, True)]
    assert loop.supervisor.superseded == 2  # 10 V and 20 V were never written
    rows, applied = blocks[0]
    assert applied == 30.0 and after == [True]
    assert rows == [
        (ns, x, 0, 2 * x, 10 * x, 3 * x, True) for ns, x in ((10, 1.0), (20, 2.0), (30, 3.0))
    ]


def test_an_invalid_sample_writes_the_hold_and_leaves_no_law_figures():
    law = Law()
    loop, amplifier, blocks, _ = make(law)
    loop.step([1.0, 5.0], [0, 3], [10, 20])
    assert law.calls[1][2] is False and amplifier.writes == [(1.0, True)]
    row: Row = blocks[0][0][1]
    assert row[:3] == (20, 5.0, 3) and math.isnan(row[3]) and row[4:] == (1.0, 0.0, False)


def test_a_block_without_an_output_writes_nothing():
    class Silent(Law):
        def on_sample(self, stamp_ns, x, ok, publish):  # waiting for a recorder, say
            super().on_sample(stamp_ns, x, ok, publish)
            self.last_step = None
            return None

    loop, amplifier, blocks, after = make(Silent())
    loop.step([1.0], [0], [10])
    assert amplifier.writes == [] and loop.supervisor.superseded == 0 and after == [True]
    rows, applied = blocks[0]
    assert math.isnan(applied) and math.isnan(rows[0][4])


@pytest.mark.parametrize("gap, writes", [(None, []), (42.0, [(42.0, True)])])
def test_a_read_that_timed_out_asks_the_law_about_the_gap(gap, writes):
    law = Law(gap)
    loop, amplifier, blocks, after = make(law)
    loop.idle(2_500_000_000)
    assert law.gaps == [2.5] and amplifier.writes == writes and after == [True] and blocks == []


def test_the_per_sample_topics_take_every_nth_sample_and_the_write_follows_the_last():
    law = Law()
    loop, amplifier, _, _ = make(law, topics_every=2.0)
    assert loop.step([1.0, 2.0, 3.0], [0, 0, 0], [1, 2, 3]) == [True, False, True]
    assert loop.step([4.0, 5.0], [0, 0], [4, 5]) == [False, True]
    assert [c[3] for c in law.calls] == [True, False, True, False, True]
    assert amplifier.writes == [(30.0, True), (50.0, True)]


def test_topics_take_every_nth_sample_across_reads():
    assert TopicDecimation(1000.0, 2000.0).every == 1 and TopicDecimation(2000.0, 2000.0).every == 1
    topics = TopicDecimation(10_000.0, 2000.0)
    masks = [topics.due(n) for n in (3, 1, 7, 4)]  # reads of 3, 1, 7 and 4 samples
    assert topics.every == 5
    assert np.flatnonzero(np.concatenate(masks)).tolist() == [0, 5, 10]
