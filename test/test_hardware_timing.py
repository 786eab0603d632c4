"""Rig timing (piezo_stage.hardware.timing): the sensor's sample clock recovered from bursty
reception times, and the playout that applies commands at their stamps."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.hardware import ConfigError
from piezo_stage.hardware.timing import CommandPlayout, SampleClock, set_realtime_priority

from property_support import examples

pytestmark = pytest.mark.unit

RATE = 1000.0
T0 = 1_795_000_000_000_000_000  # ns, a wall-clock epoch like the ROS clock's


def bursts(n_samples: int, rng: np.random.Generator, lost: set[int] = frozenset()):
    """(reception time [ns], sample times [ns]) of the blocks a reader sees: samples taken every
    1/RATE s from T0, delivered every ~2 ms poll with a random extra delay (USB/pty FIFO, the
    reader's scheduling: mostly < 1 ms, sometimes tens of ms); samples in `lost` never arrive."""
    taken = T0 + np.round(np.arange(n_samples) * 1e9 / RATE).astype(np.int64)
    out, k, t = [], 0, T0
    while k < n_samples:
        t += int(2e6 + (rng.exponential(0.3e6) if rng.random() > 0.02 else rng.uniform(10e6, 60e6)))
        j = int(np.searchsorted(taken, t - 100_000, side="right"))  # 0.1 ms minimum link delay
        if j > k:
            kept = [i for i in range(k, j) if i not in lost]
            out.append((t, taken[kept]))
            k = j
    return out


def test_sample_clock_recovers_the_sensor_clock_from_bursty_reception():
    rng = np.random.default_rng(4)
    clock = SampleClock(RATE, window=2.0)
    errors, backwards = [], 0
    last = None
    for t_recv, truth in bursts(20_000, rng):
        stamps = np.asarray(clock.stamps(t_recv, len(truth)))
        assert np.all(stamps <= t_recv)  # never later than received
        errors.append(stamps - truth)
        if last is not None and stamps[0] <= last:
            backwards += 1
        last = stamps[-1]
    err = np.concatenate(errors) * 1e-9
    reception_error = 2e-3  # what stamping at reception gives at best: the poll period
    assert backwards == 0
    # after the first block, every stamp is within the minimum link delay of the true sample
    # time plus the exponential delay's lower tail (0.1 ms + a few us), far below the poll period
    assert np.max(np.abs(err[100:])) < 0.2e-3 < reception_error
    assert np.all(np.diff(np.concatenate(errors)[100:]) < 5e5)  # no jumps: one clock


def test_sample_clock_follows_lost_samples_within_its_window():
    rng = np.random.default_rng(5)
    clock = SampleClock(RATE, window=0.5)
    lost = set(range(5000, 5010))  # 10 frames lost on the link: the counter falls 10 samples behind
    out = []
    for t_recv, truth in bursts(12_000, rng, lost):
        out.append((truth, clock.stamps(t_recv, len(truth))))
    truth = np.concatenate([a for a, _ in out])
    stamps = np.concatenate([b for _, b in out])
    err = (stamps - truth) * 1e-9
    before = err[(truth < T0 + 4.9e9)]
    long_after = err[truth > T0 + 7.0e9]  # the 0.5 s window has forgotten the older envelope
    assert np.max(np.abs(before[100:])) < 0.2e-3
    assert (
        np.min(err[(truth > T0 + 5.01e9) & (truth < T0 + 5.3e9)]) < -9e-3
    )  # 10 samples early at first
    assert np.max(np.abs(long_after)) < 0.2e-3  # then back on the sensor's clock


@settings(max_examples=examples(200), deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(1, 40), st.floats(0.0, 0.05)),  # block size, its link delay [s]
        min_size=2,
        max_size=200,
    ),
    st.floats(0.01, 2.0),
)
@example([(1, 0.01), (1, 0.0)], 2.0)  # the second block lowers the envelope below the first
@example([(1, 0.0007383159840143263), (1, 0.0)], 1.0)  # ... to less than half a period after it
def test_sample_clock_stamps_only_increase_half_a_period_apart(blocks, window):
    """Whatever the link's delays, a stream's stamps increase, at least half a period apart: a
    reception earlier than the envelope (which lowers t0) never sends time back."""
    clock = SampleClock(RATE, window=window)
    stamps, k, latest = [], 0, T0
    for size, delay in blocks:
        k += size
        # the block's last sample was taken at k/RATE; it arrives `delay` later (in order)
        latest = max(latest, T0 + round(k * 1e9 / RATE + delay * 1e9))
        stamps += clock.stamps(latest, size)
    assert len(stamps) == k
    assert np.all(np.diff(stamps) >= round(0.5e9 / RATE)), np.diff(stamps).min()


def test_sample_clock_validation_and_reset():
    with pytest.raises(ConfigError):
        SampleClock(0.0)
    with pytest.raises(ConfigError):
        SampleClock(1000.0, window=0.0)
    clock = SampleClock(100.0)
    a = clock.stamps(T0, 3)
    assert list(np.diff(a)) == [10_000_000, 10_000_000] and a[-1] == T0 and clock.count == 3
    clock.reset()
    assert clock.count == 0 and clock.stamps(T0 + 10**9, 1)[0] == T0 + 10**9
    assert clock.stamps(T0, 0) == []


class HeldClock:
    """Wall time that stands still until ``release()``: commands are queued against one fixed
    "now", however long the host takes to push them, then time runs (on the monotonic clock)."""

    def __init__(self) -> None:
        self.base = time.time()
        self._released: float | None = None

    def release(self) -> None:
        self._released = time.monotonic()

    def __call__(self) -> float:
        if self._released is None:
            return self.base
        return self.base + time.monotonic() - self._released


def test_playout_applies_each_command_at_its_stamp_in_stamp_order():
    applied: list[tuple[float, float]] = []
    done = threading.Event()
    clock = HeldClock()

    def apply(v: float, command: bool, received: float | None) -> None:
        assert command  # no hold_period: only the commands themselves
        applied.append((clock(), v))
        if len(applied) == 20:
            done.set()

    playout = CommandPlayout(apply, delay=0.05, clock=clock, max_ahead=1.0).start()
    try:
        now = clock.base
        stamps = now + 0.02 * np.arange(18)
        order = np.random.default_rng(1).permutation(18)  # arrive out of order (two publishers)
        for i in order:
            playout.push(float(stamps[i]), float(i))
        playout.push(now - 1.0, -1.0)  # a second late: applied at once, counted
        playout.push(now + 100.0, 99.0)  # a foreign clock: held max_ahead only, counted
        clock.release()
        assert done.wait(30.0)
    finally:
        playout.stop()
    values = [v for _, v in applied]
    assert values[0] == -1.0 and playout.late == 1
    assert values[1:19] == list(range(18))  # stamp order, not arrival order
    assert values[19] == 99.0 and playout.ahead == 1
    for t, v in applied[1:19]:
        assert t >= stamps[int(v)] + 0.05  # never before its time
    assert applied[19][0] >= now + 1.0  # the foreign-clock command after max_ahead, not before
    assert playout.pending == 0 and playout.applied == 20 and playout.error is None


def test_playout_keeps_running_after_a_failed_apply_and_stop_drops_the_queue():
    seen: list[float] = []

    def apply(v: float, command: bool, received: float | None) -> None:
        if v == 1.0:
            raise RuntimeError("link down")
        seen.append(v)

    playout = CommandPlayout(apply, delay=0.0).start()
    now = time.time()
    for k in range(3):
        playout.push(now + 0.01 * k, float(k))
    deadline = time.monotonic() + 10.0
    while len(seen) < 2 and time.monotonic() < deadline:
        time.sleep(0.01)
    playout.push(time.time() + 60.0, 5.0)
    playout.stop()
    assert seen == [0.0, 2.0] and isinstance(playout.error, RuntimeError)
    assert playout.pending == 0  # the 60 s-ahead command was dropped by stop()
    with pytest.raises(ConfigError):
        CommandPlayout(apply, delay=-1.0)
    with pytest.raises(ConfigError):
        CommandPlayout(apply, delay=2.0, max_ahead=1.0)


def test_realtime_priority_zero_is_a_no_op_and_refusal_is_reported():
    assert set_realtime_priority(0) is None
    result: list = []
    t = threading.Thread(target=lambda: result.append(set_realtime_priority(1)))
    t.start()
    t.join()
    assert result[0] is None or "refused" in result[0]  # either granted, or said why not
