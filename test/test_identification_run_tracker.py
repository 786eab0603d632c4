"""The identifier's run-completion and silence state machine (pure; no ROS)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from piezo_stage.identification.io import intervals_from_marks
from piezo_stage.identification.run_tracker import Phase, Poll, RunTracker

from property_support import examples

pytestmark = pytest.mark.unit

SETTLE = 10.0


def _plan(tracker: RunTracker, runs: int = 2, period: float = 1.0) -> list[Phase | None]:
    """Marks of an excitation plan: each run settles one period and is steady for two, then
    the plan's end mark (not steady) after the last run."""
    phases, t = [], 0.0
    for run in range(runs):
        phases.append(tracker.mark(t, run, False, offset=100.0 * run))
        phases.append(tracker.mark(t + period, run, True, offset=100.0 * run))
        phases.append(tracker.mark(t + 2 * period, run, True, offset=100.0 * run))
        t += 3 * period
    phases.append(tracker.mark(t, runs - 1, False, offset=100.0 * (runs - 1)))
    return phases


def test_a_run_is_complete_at_the_next_runs_mark_and_the_plans_end():
    tracker = RunTracker()
    phases = _plan(tracker)
    assert phases == [
        Phase.SETTLING,
        Phase.STEADY,
        None,
        Phase.SETTLING,
        Phase.STEADY,
        None,
        Phase.OVER,
    ]
    assert tracker.completed == [0, 1] and tracker.offsets == {0: 0.0, 1: 100.0}
    assert tracker.intervals() == intervals_from_marks(tracker.marks)
    assert tracker.interval(1) == (1, 3.0, 6.0) and tracker.interval(7) is None


def test_a_run_is_handed_out_once_both_streams_passed_its_end():
    tracker = RunTracker()
    _plan(tracker)
    assert tracker.poll(100, latest=2.9, now=0.0, settle_time=SETTLE).ready == ()
    assert tracker.poll(200, latest=3.0, now=1.0, settle_time=SETTLE).ready == (0,)
    assert tracker.pending
    assert tracker.poll(300, latest=6.0, now=2.0, settle_time=SETTLE).ready == (1,)
    assert not tracker.pending
    assert tracker.poll(300, latest=6.0, now=3.0, settle_time=SETTLE).ready == ()  # once only


def test_silence_hands_out_what_is_complete_and_reports_too_few_runs_once():
    tracker = RunTracker()
    tracker.mark(0.0, 0, False)
    tracker.mark(1.0, 0, True)
    tracker.mark(3.0, 0, False)  # the plan's end after one run: one complete run
    assert tracker.poll(50, latest=2.0, now=0.0, settle_time=SETTLE) == Poll((), False, False)
    assert not tracker.poll(50, latest=2.0, now=SETTLE + 1, settle_time=SETTLE).silent  # quiet
    quiet = tracker.poll(50, latest=2.0, now=SETTLE + 1.1, settle_time=SETTLE)
    assert quiet == Poll((0,), True, True)
    again = tracker.poll(50, latest=2.0, now=SETTLE + 2, settle_time=SETTLE)
    assert again.silent and not again.stalled  # said once per silence
    tracker.poll(60, latest=2.5, now=SETTLE + 3, settle_time=SETTLE)  # data again, then silence
    tracker.poll(60, latest=2.5, now=2 * SETTLE + 4, settle_time=SETTLE)
    assert tracker.poll(60, latest=2.5, now=2 * SETTLE + 4.1, settle_time=SETTLE).stalled


def test_a_stall_of_the_host_is_not_silence_when_the_samples_were_waiting():
    """The node's timer runs first after a stall: the first quiet poll only arms; the samples
    that arrived during the stall are taken before the next poll and cancel it."""
    tracker = RunTracker()
    tracker.mark(0.0, 0, False)
    tracker.mark(1.0, 0, True)
    tracker.mark(3.0, 0, False)
    tracker.poll(50, latest=1.5, now=0.0, settle_time=SETTLE)
    stalled_host = tracker.poll(50, latest=1.5, now=SETTLE + 0.2, settle_time=SETTLE)
    assert stalled_host == Poll((), False, False)
    taken = tracker.poll(80, latest=3.0, now=SETTLE + 0.3, settle_time=SETTLE)
    assert taken == Poll((0,), False, False)  # ready because the streams passed its end
    # two quiet polls further apart than confirm_within: the second only arms again
    tracker.poll(80, latest=3.0, now=2 * SETTLE + 1, settle_time=SETTLE)
    assert not tracker.poll(80, latest=3.0, now=2 * SETTLE + 3, settle_time=SETTLE).silent
    assert tracker.poll(80, latest=3.0, now=2 * SETTLE + 3.1, settle_time=SETTLE).stalled


def test_no_failure_without_samples_or_once_identified():
    tracker = RunTracker()
    assert not tracker.poll(0, latest=-math.inf, now=100.0, settle_time=SETTLE).silent
    tracker.poll(10, latest=1.0, now=0.0, settle_time=SETTLE)
    tracker.poll(10, latest=1.0, now=SETTLE + 1, settle_time=SETTLE, identified=True)
    late = tracker.poll(10, latest=1.0, now=SETTLE + 1.1, settle_time=SETTLE, identified=True)
    assert late.silent and not late.stalled


def test_without_marks_the_whole_stream_is_run_0():
    assert RunTracker().intervals() == [(0, -math.inf, math.inf)]


@settings(max_examples=examples(100))
@given(st.lists(st.tuples(st.integers(0, 3), st.booleans()), max_size=40))
def test_each_run_completes_at_most_once_and_only_after_a_steady_mark(marks):
    tracker = RunTracker()
    steady_seen: set[int] = set()
    for k, (run, steady) in enumerate(marks):
        tracker.mark(float(k), run, steady)
        if steady:
            steady_seen.add(run)
    assert len(tracker.completed) == len(set(tracker.completed))
    assert set(tracker.completed) <= steady_seen
    handed = tracker.poll(len(marks) + 1, latest=math.inf, now=0.0, settle_time=SETTLE).ready
    assert list(handed) == tracker.completed
