"""optoNCDT frame formats and stream parser: conversions, error values, ASCII separation, resync,
fuzz."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from piezo_stage.hardware.errors import ConfigError
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

MR = 10e-3  # 10 mm sensor
K = FrameCheck().relock_frames
FORMATS = {"ild1700": (), "ild1320-18": (18,), "ild1320-16": (16,), "ild1750": ()}


def fmt_of(name: str):
    return frame_format(name.split("-")[0], *FORMATS[name])


def feed_chunked(
    parser: OptoNCDTParser, data: bytes, rng: np.random.Generator, max_chunk: int = 4096
):
    blocks, i = [], 0
    while i < len(data):
        n = int(rng.integers(1, max_chunk + 1))
        blocks.append(parser.feed(data[i : i + n]))
        i += n
    return SampleBlock.concat(blocks)


def locked(fmt, raw) -> bytes:
    """Frames of ``raw`` each sent K times in a row (K = the relock count), so a fresh parser
    locks on and the last copy of each shows the status the value maps to."""
    return encode_values(fmt, np.repeat(np.asarray(raw), K))


def reference_frames(fmt, data: bytes) -> list[int]:
    """Well-formed frames found by a regular expression (independent of the parser's numpy scan)."""
    if fmt.bytes_per_value == 2:
        return [
            ((m[0] & 0x7F) << 7) | (m[1] & 0x7F)
            for m in (mt.group() for mt in re.finditer(rb"[\x80-\xff][\x00-\x7f]", data, re.S))
        ]
    out = []
    for mt in re.finditer(rb"[\x00-\x3f][\x40-\x7f][\x80-\xbf]", data, re.S):
        lo, mid, hi = mt.group()
        out.append((((hi & 0x3F) << 12) | ((mid & 0x3F) << 6) | (lo & 0x3F)) & fmt.mask)
    return out


# --- conversions and codes (ILD1700 manual worked examples) --------------------------------------
def test_ild1700_manual_examples():
    fmt = frame_format("ild1700")
    assert fmt.to_metres(8184, MR) == pytest.approx(5.000e-3, abs=1e-6)  # mid of range
    assert fmt.to_metres(10261, MR) == pytest.approx(6.294e-3, abs=1e-6)
    assert fmt.to_metres(161, MR) == pytest.approx(0.0, abs=1e-6)  # start of range
    assert encode_values(fmt, np.array([2099])) == bytes([0x90, 0x33])


def test_family_conversions_round_trip():
    for name in FORMATS:
        fmt = fmt_of(name)
        d = np.linspace(0.001, 0.009, 17)
        raw = fmt.from_metres(d, MR)
        resolution = MR * (fmt.scale if fmt.family != "ild1750" else 1 / 65536)
        assert np.max(np.abs(fmt.to_metres(raw, MR) - d)) <= resolution
    assert frame_format("ild1750").to_metres(98232, MR) == 0.0
    assert frame_format("ild1750").to_metres(98232 + 65536, MR) == pytest.approx(MR)
    assert frame_format("ild1320").to_metres(65520, MR) == pytest.approx(1.01 * MR)
    with pytest.raises(ConfigError):
        frame_format("ild9999")
    with pytest.raises(ConfigError):
        frame_format("ild1320", 17)


@pytest.mark.parametrize(
    "family, raw, status",
    [
        ("ild1700", 16370, Status.NO_TARGET),
        ("ild1700", 16372, Status.TOO_CLOSE),
        ("ild1700", 16374, Status.TOO_FAR),
        ("ild1700", 16376, Status.INVALID),
        ("ild1700", 16383, Status.INVALID),
        ("ild1700", 16369, Status.INVALID),
        ("ild1700", 100, Status.TOO_CLOSE),
        ("ild1700", 16300, Status.TOO_FAR),
        ("ild1700", 8184, Status.OK),
        ("ild1320", 262076, Status.NO_TARGET),
        ("ild1320", 262077, Status.TOO_CLOSE),
        ("ild1320", 262078, Status.TOO_FAR),
        ("ild1320", 262075, Status.INVALID),
        ("ild1320", 262082, Status.INVALID),
        ("ild1320", 100000, Status.INVALID),
        ("ild1320", 32760, Status.OK),
        ("ild1750", 262076, Status.NO_TARGET),
        ("ild1750", 98231, Status.TOO_CLOSE),
        ("ild1750", 98232 + 65537, Status.TOO_FAR),
        ("ild1750", 130000, Status.OK),
    ],
)
def test_error_values_map_to_status(family, raw, status):
    fmt = frame_format(family)
    block = OptoNCDTParser(fmt, MR).feed(locked(fmt, [raw]))
    assert len(block) == K and block.status[-1] == status and block.raw[-1] == raw
    assert np.isnan(block.displacement[-1]) == (status != Status.OK)


def test_sixteen_bit_mode_ignores_d16_d17():
    fmt = frame_format("ild1320", 16)
    block = OptoNCDTParser(fmt, MR).feed(locked(fmt, [(3 << 16) | 32760, 65535]))
    assert block.raw[K - 1 :: K].tolist() == [32760, 65535]
    assert block.status[K - 1 :: K].tolist() == [Status.OK, Status.INVALID]


# --- framing -------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(FORMATS))
def test_every_split_point_gives_the_same_samples(name):
    fmt = fmt_of(name)
    raw = fmt.from_metres(np.linspace(0.002, 0.008, 7), MR)
    data = encode_values(fmt, raw)
    for cut in range(1, len(data)):
        parser = OptoNCDTParser(fmt, MR)
        block = SampleBlock.concat([parser.feed(data[:cut]), parser.feed(data[cut:])])
        assert block.raw.tolist() == raw.tolist()
        assert parser.stats.discarded == 0


def test_later_values_of_a_block_are_not_displacements():
    fmt = frame_format("ild1320")
    raw = np.array([30000, 500, 31000, 600])  # displacement, intensity, displacement, intensity
    block = OptoNCDTParser(fmt, MR).feed(
        encode_values(fmt, raw, later=np.array([0, 1, 0, 1], bool))
    )
    assert block.raw.tolist() == [30000, 31000]


def test_ascii_reply_between_frames_is_separated():
    fmt = frame_format("ild1320")
    raw = fmt.from_metres(np.full(40, 0.005), MR)
    frames = [encode_values(fmt, raw[i : i + 1]) for i in range(raw.size)]
    reply = b"GETINFO\r\nName: ILD1320-10\r\nMR: 10 mm\r\n->"
    stream = bytearray()
    for k, frame in enumerate(frames):
        stream += frame + reply[2 * k : 2 * k + 2]
    parser = OptoNCDTParser(fmt, MR)
    block = feed_chunked(parser, bytes(stream), np.random.default_rng(0), max_chunk=5)
    assert block.raw.tolist() == raw.tolist()
    assert parser.ascii.pop_reply() == reply
    assert parser.ascii.pop_reply() is None


@pytest.mark.parametrize("name", list(FORMATS))
def test_resynchronises_after_lost_and_corrupt_bytes(name):
    fmt = fmt_of(name)
    rng = np.random.default_rng(7)
    d = rng.uniform(0.0005, 0.0095, 20000)
    clean = np.frombuffer(encode_values(fmt, fmt.from_metres(d, MR)), dtype=np.uint8)
    faulty = clean.copy()
    hit = rng.random(faulty.size) < 0.002
    faulty[hit] = rng.integers(0, 256, int(hit.sum()), dtype=np.uint8)
    faulty = faulty[rng.random(faulty.size) >= 0.002]
    parser = OptoNCDTParser(fmt, MR, FrameCheck(max_speed=float("inf")))  # the values jump: no gate
    block = feed_chunked(parser, faulty.tobytes(), rng)
    ok = block.status == Status.OK
    # ~0.4 % of bytes damaged costs only the frames they hit and the K after each (relock)
    assert ok.sum() >= (1 - 0.004 * fmt.bytes_per_value * (K + 1)) * d.size
    assert np.all((block.displacement[ok] >= 0) & (block.displacement[ok] <= MR))
    assert block.raw.tolist() == reference_frames(fmt, faulty.tobytes())


# --- fuzz ----------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", list(FORMATS))
def test_fuzz_million_random_bytes(name):
    """10^6 seeded random bytes: no crash; every sample is a well-formed frame; none is OK."""
    fmt = fmt_of(name)
    rng = np.random.default_rng(2024)
    data = rng.integers(0, 256, 1_000_000, dtype=np.uint8).tobytes()
    parser = OptoNCDTParser(fmt, MR)
    block = feed_chunked(parser, data, rng)
    assert block.raw.tolist() == reference_frames(fmt, data)
    assert len(block) > 1000 and not np.any(block.status == Status.OK)
    assert np.all(np.isnan(block.displacement))
    stats = parser.stats
    n_frame_bytes = fmt.bytes_per_value * (stats.frames + stats.later_values)
    assert n_frame_bytes + stats.text_bytes + stats.discarded + len(parser._tail) == len(data)


@pytest.mark.parametrize("name", ["ild1320-18", "ild1750"])
def test_fuzz_mixed_stream_with_ascii_and_faults(name):
    """Frames, ASCII replies and random garbage interleaved, then bytes dropped and corrupted."""
    fmt = fmt_of(name)
    rng = np.random.default_rng(99)
    parts = []
    for _ in range(7000):
        parts.append(encode_values(fmt, fmt.from_metres(rng.uniform(0, MR, 50), MR)))
        kind = rng.integers(0, 3)
        if kind == 0:
            parts.append(b"MEASRATE\r\nMEASRATE 1.000\r\n->")
        elif kind == 1:
            parts.append(rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes())
    data = np.frombuffer(b"".join(parts), dtype=np.uint8).copy()
    assert data.size >= 1_000_000
    hit = rng.random(data.size) < 0.01
    data[hit] = rng.integers(0, 256, int(hit.sum()), dtype=np.uint8)
    data = data[rng.random(data.size) >= 0.01].tobytes()
    parser = OptoNCDTParser(fmt, MR)
    block = feed_chunked(parser, data, rng)
    ok = block.status == Status.OK
    assert np.all((block.displacement[ok] >= 0) & (block.displacement[ok] <= MR))
    assert block.raw.tolist() == reference_frames(fmt, data)
    assert parser.stats.text_bytes > 0


# --- the few-frames path -------------------------------------------------------------------------
@given(
    st.sampled_from(list(FORMATS)),
    st.integers(0, 2**32 - 1),
    st.lists(st.tuples(st.integers(0, 3), st.integers(1, 40)), min_size=1, max_size=40),
)
@settings(max_examples=examples(150))
@example("ild1320-18", 1, [(0, 12), (2, 3), (0, 12)])
def test_the_few_frames_path_decides_as_the_numpy_path(name, seed, pieces):
    """Invariant for any stream (runs of frames with error values, later values, garbage and
    ASCII text) cut into any chunks: the Python path for chunks of a few whole frames gives the
    same samples, statuses and statistics as the numpy path alone."""
    fmt = fmt_of(name)
    rng = np.random.default_rng(seed)
    width = fmt.bytes_per_value
    chunks: list[bytes] = []  # frames in chunks of whole frames, or cut anywhere
    for kind, n in pieces:
        raw = rng.integers(0, 1 << fmt.value_bits, n)
        if kind == 0:  # a slow ramp of measurements (the gate passes it)
            raw = fmt.from_metres(np.linspace(0.004, 0.0041, n) + rng.normal(0, 1e-7), MR)
        later = rng.random(n) < 0.2 if kind == 1 and width == 3 else None
        data = encode_values(fmt, raw, later=later)
        step = width * int(rng.integers(1, 6)) if rng.random() < 0.7 else int(rng.integers(1, 7))
        chunks += [data[i : i + step] for i in range(0, len(data), step)]
        if kind == 3:
            chunks.append(
                b"MEASRATE 1.000\r\n->"
                if fmt.ascii_commands
                else bytes(rng.integers(0, 256, 5, dtype=np.uint8))
            )
    fast, slow = OptoNCDTParser(fmt, MR), OptoNCDTParser(fmt, MR)
    slow.few_frames = 0
    a = SampleBlock.concat([fast.feed(c) for c in chunks])
    b = SampleBlock.concat([slow.feed(c) for c in chunks])
    assert a.raw.tolist() == b.raw.tolist() and a.status.tolist() == b.status.tolist()
    np.testing.assert_array_equal(a.displacement, b.displacement)
    assert fast.stats == slow.stats
