"""optoNCDT reader under damaged streams: frame lock, relock after k agreeing frames,
speed gate — for every frame family.

The streams are the emulator's encoding of a slow sine with a record of which frame every byte
came from (``piezo_stage.hardware.emulators.streams``), so each OK value is compared with the
true value of its frame. Tolerance: 1e-3 of the measuring range.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.hardware.emulators.streams import damage, frame_ends, score, sensor_stream
from piezo_stage.hardware.optoncdt import (
    FrameCheck,
    OptoNCDTParser,
    SampleBlock,
    Status,
    encode_values,
    frame_format,
)

from property_support import examples

pytestmark = pytest.mark.unit

MR = 2e-3  # the rig's 2 mm sensor
RATE = 1000.0
TOL = 1e-3 * MR
FAMILIES = {"ild1700": None, "ild1320-18": 18, "ild1320-16": 16, "ild1750": None}
# the true motion: 5 % of MR at 0.5 Hz, peak speed 0.31 mm/s; the gate allows 1 mm/s
CHECK = FrameCheck(relock_frames=6, max_speed=1e-3, rate=RATE)


def feed_all(parser: OptoNCDTParser, data: bytes, chunk: int = 4096) -> SampleBlock:
    return SampleBlock.concat(
        [parser.feed(data[i : i + chunk]) for i in range(0, len(data), chunk)]
    )


def fmt_of(name: str):
    return frame_format(name.split("-")[0], FAMILIES[name])


def truth_stream(fmt, n: int = 100_000):
    t = np.arange(n) / RATE
    return sensor_stream(fmt, 0.5 * MR + 0.05 * MR * np.sin(2 * np.pi * 0.5 * t), MR)


@pytest.mark.parametrize("name", list(FAMILIES))
@pytest.mark.parametrize(
    "mode",
    [
        dict(lose_one=True),
        dict(replace_one=True),
        dict(corrupt=1e-3),
        dict(corrupt=1e-3, drop=1e-3, garbage=1e-3),
    ],
    ids=["lose-one-per-frame", "replace-one-per-frame", "corrupt-1e-3", "mixed"],
)
def test_no_ok_value_is_off_by_more_than_1e3_of_the_range(name, mode):
    fmt = fmt_of(name)
    data, origin, truth = truth_stream(fmt)
    data, origin = damage(data, origin, np.random.default_rng(5), fmt.bytes_per_value, **mode)
    result = score(OptoNCDTParser(fmt, MR, CHECK), data, origin, truth, TOL)
    assert result.wrong == 0, result
    if "corrupt" in mode:  # sparse damage costs only the frames near it
        assert result.ok > 0.9 * truth.size


@pytest.mark.parametrize("name", list(FAMILIES))
def test_a_frame_next_to_discarded_or_lost_bytes_is_never_ok(name):
    fmt = fmt_of(name)
    data, origin, truth = truth_stream(fmt, 20_000)
    data, origin = damage(
        data,
        origin,
        np.random.default_rng(8),
        fmt.bytes_per_value,
        drop=3e-3,
        corrupt=3e-3,
        garbage=3e-3,
    )
    parser = OptoNCDTParser(fmt, MR, CHECK)
    status = parser.feed(data.tobytes()).status
    ends = frame_ends(fmt, data)  # later-value frames (3-byte H flag 11) are frames too
    gap_before = np.diff(np.concatenate([[-1], ends])) > fmt.bytes_per_value
    if fmt.bytes_per_value == 3:
        gap_before = gap_before[data[ends] < 0xC0]
    gap_before = gap_before[: status.size]
    assert gap_before.sum() > 50 and (status == Status.OK).sum() > 0.5 * status.size
    assert not np.any(status[gap_before] == Status.OK)


@pytest.mark.parametrize("name", list(FAMILIES))
def test_publishing_again_within_10_good_frames_after_garbage(name):
    fmt = fmt_of(name)
    rng = np.random.default_rng(3)
    data, _, _ = truth_stream(fmt, 40)
    latencies = []
    for _ in range(300):
        parser = OptoNCDTParser(fmt, MR, CHECK)
        parser.feed(data.tobytes())  # locked
        garbage = rng.integers(0, 256, int(rng.integers(1, 200)), dtype=np.uint8).tobytes()
        block = parser.feed(garbage + data.tobytes())
        # the good frames are the last 40 samples; the first OK one among them
        good = block.status[-40:] == Status.OK
        assert good.any() and good[np.argmax(good) :].all()  # once back, it stays
        latencies.append(int(np.argmax(good)) + 1)
        assert not np.any(block.status[:-40] == Status.OK)  # nothing from the garbage
    assert max(latencies) <= 10, max(latencies)


@pytest.mark.parametrize("name", list(FAMILIES))
def test_a_million_random_bytes_give_no_ok_value(name):
    fmt = fmt_of(name)
    data = np.random.default_rng(2026).integers(0, 256, 1_000_000, dtype=np.uint8).tobytes()
    parser = OptoNCDTParser(fmt, MR)  # the default check (max_speed 0.1 m/s, 6 frames)
    block = feed_all(parser, data)
    assert len(block) > 10_000 and not np.any(block.status == Status.OK)
    assert parser.stats.framing_errors > 1000 and parser.stats.lock_losses == 0


def test_speed_gate_refuses_a_jump_and_counts_it():
    fmt = fmt_of("ild1320-18")
    _, _, truth = truth_stream(fmt, 200)
    raw = fmt.from_metres(truth, MR)
    raw[100] += 4096  # a spike of 6 % MR in one frame, framing intact
    parser = OptoNCDTParser(fmt, MR, CHECK)
    block = parser.feed(encode_values(fmt, raw))
    assert block.status[100] == Status.INVALID and np.all(
        block.status[CHECK.relock_frames : 100] == 0
    )
    assert np.all(block.status[101:] == Status.OK)
    assert parser.stats.speed_rejected == 1 and parser.stats.framing_errors == 1  # the start


@settings(max_examples=examples(40), deadline=None)
@given(
    name=st.sampled_from(list(FAMILIES)),
    seed=st.integers(0, 2**32 - 1),
    drop=st.sampled_from([0.0, 1e-3, 1e-2]),
    corrupt=st.sampled_from([0.0, 1e-3, 1e-2]),
    garbage=st.sampled_from([0.0, 1e-3, 1e-2]),
    lose_one=st.booleans(),
    replace_one=st.booleans(),
    chunk=st.integers(1, 5000),
)
# two inserted bytes that form a well-framed ILD1700 frame within the gate of its neighbours
@example("ild1700", 505656, 1e-3, 1e-3, 1e-2, False, False, 1)
def test_property_every_ok_value_is_within_the_speed_gate_under_any_damage(
    name, seed, drop, corrupt, garbage, lose_one, replace_one, chunk
):
    """What the reader guarantees for every stream: two OK values in reach of each other (one
    lock, fewer than relock_frames frames apart) differ by no more than the speed gate, so a
    damaged or inserted frame that passes is off by at most one gate from the exact value before
    it. The protocol has no checksum: a damaged frame inside the gate cannot be told from a real
    one, and a chain of them adds up (``Score.chained``; bench/faults.py measures how often)."""
    fmt = fmt_of(name)
    data, origin, truth = truth_stream(fmt, 5000)
    data, origin = damage(
        data,
        origin,
        np.random.default_rng(seed),
        fmt.bytes_per_value,
        drop=drop,
        corrupt=corrupt,
        garbage=garbage,
        lose_one=lose_one,
        replace_one=replace_one,
    )
    result = score(OptoNCDTParser(fmt, MR, CHECK), data, origin, truth, TOL, chunk=chunk)
    assert result.gate_breaks == 0 and result.beyond_gate == 0, result


def test_an_inserted_frame_inside_the_gate_is_ok_and_off_by_less_than_one_gate():
    """No reader can refuse it: the stream holds no checksum. It costs less than one gate."""
    fmt = fmt_of("ild1700")
    data, origin, truth = truth_stream(fmt, 5000)
    data, origin = damage(
        data, origin, np.random.default_rng(505656), 2, drop=1e-3, corrupt=1e-3, garbage=1e-2
    )
    parser = OptoNCDTParser(fmt, MR, CHECK)
    result = score(parser, data, origin, truth, TOL, chunk=1)
    assert result.damaged_ok >= 1 and result.chained == 0 and result.beyond_gate == 0, result
    gate = parser.gate(1)
    assert result.worst < gate + 0.05 * MR * np.pi / RATE < TOL, result
