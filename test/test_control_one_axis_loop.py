"""The composed loop of a stage of one axis without ROS (control/stage_loop.py), as the rig's
loop runs it: a block of samples → the law on each → one write of the newest output; a read
that timed out → the law's gap check; the per-sample topics' decimation."""

from __future__ import annotations

import pytest

from piezo_stage.control.stage_loop import StageLoop, publish_every

pytestmark = pytest.mark.unit


class Law:
    """A law that answers each valid sample with 10·x and an invalid one with the hold 1.0 V;
    ``gap`` what check_gap answers."""

    def __init__(self, gap: float | None = None) -> None:
        self.last_step = None
        self.superseded = 0
        self.calls: list[tuple[int, float, bool, bool]] = []
        self.gap, self.gaps = gap, []

    def on_sample(self, stamp_ns: int, x: float, ok: bool, publish: bool = True) -> float | None:
        self.calls.append((stamp_ns, x, ok, publish))
        return 10 * x if ok else 1.0

    def check_gap(self, t: float) -> float | None:
        self.gaps.append(t)
        return self.gap


class Amplifier:
    def __init__(self) -> None:
        self.writes: list[dict[str, float]] = []

    def set_voltages(self, values: dict[str, float]) -> None:
        self.writes.append(dict(values))


def make(law: Law, every: int = 1) -> tuple[StageLoop, Amplifier, list]:
    amplifier, after = Amplifier(), []
    loop = StageLoop([""], [law], amplifier, after=lambda: after.append(True), every=every)
    return loop, amplifier, after


def block(loop: StageLoop, xs, status, stamps, now: int = 0) -> None:
    """One read of ``len(xs)`` samples: a sub-cycle each, the write after the last."""
    for j, (x, st, ns) in enumerate(zip(xs, status, stamps)):
        loop.step([x], [st], [ns], [True], now, j == len(xs) - 1)


def test_a_block_steps_the_law_on_every_sample_and_writes_the_newest_output_once():
    law = Law()
    loop, amplifier, after = make(law)
    block(loop, [1.0, 2.0, 3.0], [0, 0, 0], [10, 20, 30])
    assert [c[:3] for c in law.calls] == [(10, 1.0, True), (20, 2.0, True), (30, 3.0, True)]
    assert amplifier.writes == [{"": 30.0}] and after == [True]
    assert law.superseded == 2  # 10 V and 20 V were never written
    assert loop.cycles == 1 and loop.steps == 3


def test_an_invalid_sample_writes_the_hold():
    law = Law()
    loop, amplifier, _ = make(law)
    block(loop, [1.0, 5.0], [0, 3], [10, 20])
    assert law.calls[1][2] is False and amplifier.writes == [{"": 1.0}]


def test_a_block_without_an_output_writes_nothing():
    class Silent(Law):
        def on_sample(self, stamp_ns, x, ok, publish=True):  # waiting for a recorder, say
            super().on_sample(stamp_ns, x, ok, publish)
            return None

    law = Silent()
    loop, amplifier, after = make(law)
    block(loop, [1.0], [0], [10])
    assert amplifier.writes == [] and law.superseded == 0 and after == [True]


@pytest.mark.parametrize("gap, writes", [(None, []), (42.0, [{"": 42.0}])])
def test_a_read_that_timed_out_asks_the_law_about_the_gap(gap, writes):
    law = Law(gap)
    loop, amplifier, after = make(law)
    loop.idle(2_500_000_000)
    assert law.gaps == [2.5] and amplifier.writes == writes and after == [True]


def test_the_per_sample_topics_take_every_nth_sample_across_reads():
    law = Law()
    loop, amplifier, _ = make(law, every=2)
    block(loop, [1.0, 2.0, 3.0], [0, 0, 0], [1, 2, 3])
    block(loop, [4.0, 5.0], [0, 0], [4, 5])
    assert [c[3] for c in law.calls] == [True, False, True, False, True]
    assert amplifier.writes == [{"": 30.0}, {"": 50.0}]


def test_topics_take_the_fewest_samples_that_keep_them_at_their_rate():
    assert publish_every(1000.0, 2000.0) == 1 and publish_every(2000.0, 2000.0) == 1
    assert publish_every(10_000.0, 2000.0) == 5 and publish_every(10_000.0, 100.0) == 100
    assert publish_every(10_000.0, 3000.0) == 4  # 2500 Hz: at most the rate asked
