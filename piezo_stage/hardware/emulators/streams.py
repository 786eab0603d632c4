"""Damaged optoNCDT byte streams with their ground truth, for fault tests and ``bench/faults.py``.

:func:`sensor_stream` encodes displacements the way the sensor emulator does and records, for
every byte, the frame it came from; :func:`damage` loses, replaces or inserts bytes and keeps
that record aligned (inserted garbage has origin -1). :func:`score` reads a stream with
:class:`~piezo_stage.hardware.optoncdt.OptoNCDTParser` and compares every OK value with the true
value of the frame its last byte came from.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..optoncdt import FrameCheck, FrameFormat, OptoNCDTParser, encode_values


def sensor_stream(
    fmt: FrameFormat, distance: np.ndarray, measuring_range: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(bytes as uint8, frame index of each byte, true value of each frame [m])."""
    raw = fmt.from_metres(np.asarray(distance, dtype=np.float64), measuring_range)
    data = np.frombuffer(encode_values(fmt, raw), dtype=np.uint8)
    origin = np.repeat(np.arange(raw.size), fmt.bytes_per_value)
    return data, origin, fmt.to_metres(raw, measuring_range)


def damage(
    data: np.ndarray,
    origin: np.ndarray,
    rng: np.random.Generator,
    width: int,
    *,
    lose_one: bool = False,
    replace_one: bool = False,
    corrupt: float = 0.0,
    drop: float = 0.0,
    garbage: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Damage a stream: one byte of every frame lost (``lose_one``) or replaced (``replace_one``),
    bytes replaced/lost with probability ``corrupt``/``drop``, and before a frame with probability
    ``garbage`` a burst of 1-32 random bytes inserted."""
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
    frames: int  # well-formed frames the parser found
    ok: int  # OK values
    wrong: int  # OK values off the true value by more than the tolerance
    worst: float  # largest |error| of an OK value [m] (0 when none)


def score(
    parser: OptoNCDTParser,
    data: np.ndarray,
    origin: np.ndarray,
    truth: np.ndarray,
    tolerance: float,
    chunk: int = 4096,
) -> Score:
    """Feed ``data`` in chunks; compare each OK value with the truth of its last byte's frame."""
    blocks = [parser.feed(data[i : i + chunk].tobytes()) for i in range(0, data.size, chunk)]
    status = np.concatenate([b.status for b in blocks]) if blocks else np.empty(0)
    value = np.concatenate([b.displacement for b in blocks]) if blocks else np.empty(0)
    ends = frame_ends(parser.fmt, data)
    first = data[ends] < 0xC0 if parser.fmt.bytes_per_value == 3 else np.ones(ends.size, bool)
    ends = ends[first][: status.size]
    ok = status == 0
    src = origin[ends[ok]]
    err = np.where(src >= 0, np.abs(value[ok] - truth[np.maximum(src, 0)]), np.inf)
    return Score(
        int(status.size),
        int(ok.sum()),
        int(np.count_nonzero(err > tolerance)),
        float(err.max()) if err.size else 0.0,
    )


def frame_ends(fmt: FrameFormat, buf: np.ndarray) -> np.ndarray:
    """Index of the last byte of every well-formed frame (flag bits only)."""
    return OptoNCDTParser(fmt, 1.0, FrameCheck())._frame_ends(np.asarray(buf, dtype=np.uint8))
