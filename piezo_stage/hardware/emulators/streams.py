"""Damaged optoNCDT byte streams with their ground truth, for fault tests and ``bench/faults.py``.

:func:`sensor_stream` encodes displacements the way the sensor emulator does and records, for
every byte, the frame it came from; :func:`damage` loses, replaces or inserts bytes and keeps
that record aligned (inserted garbage has origin -1). :func:`score` reads a stream with
:class:`~piezo_stage.hardware.optoncdt.OptoNCDTParser` and checks every OK value against the
truth at its place and against the speed gate (:class:`Score`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..optoncdt import FrameCheck, FrameFormat, OptoNCDTParser, SampleBlock, encode_values


def sensor_stream(
    fmt: FrameFormat, distance: NDArray[np.float64], measuring_range: float
) -> tuple[NDArray[np.uint8], NDArray[np.intp], NDArray[np.float64]]:
    """(bytes as uint8, frame index of each byte, true value of each frame [m])."""
    raw = fmt.from_metres(np.asarray(distance, dtype=np.float64), measuring_range)
    data = np.frombuffer(encode_values(fmt, raw), dtype=np.uint8)
    origin = np.repeat(np.arange(raw.size), fmt.bytes_per_value)
    return data, origin, fmt.to_metres(raw, measuring_range)


def damage(
    data: NDArray[np.uint8],
    origin: NDArray[np.intp],
    rng: np.random.Generator,
    width: int,
    *,
    lose_one: bool = False,
    replace_one: bool = False,
    corrupt: float = 0.0,
    drop: float = 0.0,
    garbage: float = 0.0,
) -> tuple[NDArray[np.uint8], NDArray[np.intp]]:
    """Damage a stream: one byte of every frame lost (``lose_one``) or replaced (``replace_one``),
    bytes replaced/lost with probability ``corrupt``/``drop``, and before a frame with probability
    ``garbage`` a burst of 1-32 random bytes inserted.
    """
    data, origin = data.copy(), origin.copy()
    n_frames = data.size // width
    pick = np.arange(n_frames) * width + rng.integers(0, width, n_frames)
    if replace_one:
        data[pick] = rng.integers(0, 256, n_frames, dtype=np.uint8)
    if corrupt:
        hit = rng.random(data.size) < corrupt
        data[hit] = rng.integers(0, 256, int(hit.sum()), dtype=np.uint8)
    keep = np.ones(data.size, dtype=bool)
    if lose_one:
        keep[pick] = False
    if drop:
        keep &= rng.random(data.size) >= drop
    if garbage:
        parts, origins = [], []
        bursts = np.flatnonzero(rng.random(n_frames) < garbage)
        edges = np.concatenate([[0], bursts * width, [data.size]])
        for a, b in zip(edges[:-1], edges[1:]):
            parts.append(data[a:b][keep[a:b]])
            origins.append(origin[a:b][keep[a:b]])
            if b < data.size:
                junk = rng.integers(0, 256, int(rng.integers(1, 33)), dtype=np.uint8)
                parts.append(junk)
                origins.append(np.full(junk.size, -1))
        return np.concatenate(parts), np.concatenate(origins)
    return data[keep], origin[keep]


@dataclass(frozen=True)
class Score:
    """What the parser made of a damaged stream, against the truth.

    The *place* of a frame is the sensor frame of the last sensor byte at or before its end
    (an inserted frame sits where it was inserted). A frame is *exact* when all its bytes are
    one sensor frame's and its value is that frame's. Two OK values are *in reach* when no
    framing error lies between them and they are fewer than ``relock_frames`` frames apart:
    the parser then compared the second with the first (the speed gate).
    """

    frames: int  # well-formed frames the parser found
    ok: int  # OK values
    wrong: int  # OK values off the truth at their place by more than the tolerance
    worst: float  # largest |error| of an OK value [m] (0 when none)
    damaged_ok: int  # OK values from frames that are not exact (damaged or inserted bytes)
    gate_breaks: int  # OK values further from the OK value in reach before them than the gate
    beyond_gate: int  # damaged OK values further from the truth than the gate allows, counted
    #                   from the exact OK value in reach before them
    chained: int  # damaged OK values with no exact OK value in reach before them (the only ones
    #               whose error the gate does not bound: it adds up along such a chain)


def score(
    parser: OptoNCDTParser,
    data: NDArray[np.uint8],
    origin: NDArray[np.intp],
    truth: NDArray[np.float64],
    tolerance: float,
    chunk: int = 4096,
) -> Score:
    """Feed ``data`` in chunks and score every OK value (see :class:`Score`)."""
    fmt, check = parser.fmt, parser.check
    blocks = [parser.feed(data[i : i + chunk].tobytes()) for i in range(0, data.size, chunk)]
    block = SampleBlock.concat(blocks)
    ends = frame_ends(fmt, data)
    width = fmt.bytes_per_value
    lock = np.cumsum(np.diff(np.concatenate([[-width], ends])) > width)  # +1 at each gap
    first = data[ends] < 0xC0 if width == 3 else np.ones(ends.size, bool)
    ends, lock = ends[first][: len(block)], lock[first][: len(block)]
    place = np.maximum.accumulate(np.maximum(origin, 0))[ends]
    own = origin[ends]
    one_frame = np.all([origin[ends - k] == own for k in range(1, width)], axis=0) & (own >= 0)
    exact = one_frame & (block.raw == fmt.from_metres(truth[place], parser.measuring_range))

    idx = np.flatnonzero(block.status == 0)
    value, err = block.displacement[idx], np.abs(block.displacement[idx] - truth[place[idx]])
    # successive OK values in reach of each other, and the speed gate between them
    steps = np.diff(idx)
    reach = (steps < check.relock_frames) & (np.diff(lock[idx]) == 0)
    gate = parser.gate(steps)
    quantum = abs(fmt.scale) * parser.measuring_range
    breaks = reach & (np.abs(np.diff(value)) > gate * (1 + 1e-9))
    after_exact = reach & exact[idx[:-1]] & ~exact[idx[1:]]
    bound = gate + np.abs(np.diff(truth[place[idx]])) + quantum
    beyond = after_exact & (err[1:] > bound * (1 + 1e-9))
    damaged = ~exact[idx]
    chained = damaged.copy()
    chained[1:] &= ~after_exact
    return Score(
        frames=len(block),
        ok=int(idx.size),
        wrong=int(np.count_nonzero(err > tolerance)),
        worst=float(err.max()) if err.size else 0.0,
        damaged_ok=int(damaged.sum()),
        gate_breaks=int(breaks.sum()),
        beyond_gate=int(beyond.sum()),
        chained=int(chained.sum()),
    )


def frame_ends(fmt: FrameFormat, buf: NDArray[np.uint8]) -> NDArray[np.intp]:
    """Index of the last byte of every well-formed frame (flag bits only)."""
    return OptoNCDTParser(fmt, 1.0, FrameCheck())._frame_ends(np.asarray(buf, dtype=np.uint8))
