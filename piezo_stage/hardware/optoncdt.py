"""Micro-Epsilon optoNCDT digital (RS422) output: frame formats, value conversion, stream parser.

Families (``FrameFormat``):

- ``ild1700`` (also ILD1402): 2 bytes per value, H = 1·D13..D7, L = 0·D6..D0 (14 bit);
  d = (x·1.02/16368 − 0.01)·MR; error values 16370–16383 [ILD1700 manual §7.4/§8.2].
- ``ild1320`` (also ILD1420/ILD2300): 3 bytes L/M/H whose top two bits are 00/01/10 (11 on H
  marks a later value of an output block, e.g. intensity), 18 bit (or 16 bit);
  d = (x·1.02/65520 − 0.01)·MR; 18-bit error values 262075–262082.
- ``ild1750`` (also ILD1900): same 3-byte framing, d = (x − 98232)/65536·MR.

Samples are metres from the start of the measuring range (MR in metres). A sample is OK only
when it came from a well-formed frame, is a measurement value (not an error code) and lies in
[0, MR]; below 0 it is TOO_CLOSE, above MR TOO_FAR; a status other than OK carries NaN.

The parser finds frames vectorised (numpy over each received chunk): a frame is a contiguous
L, M, H byte triple (or H, L pair) with the right flag bits; every other byte goes to the ASCII
command channel (ILD1320/1750 families answer ASCII commands between measurement frames) or is
counted as discarded. On top of that it keeps a **frame lock** (:class:`FrameCheck`), the same
for every family: any byte between two frames (discarded, garbage, or text) is a framing error
and unlocks; unlocked, nothing is OK until ``relock_frames`` consecutive well-formed frames
agree (each within the speed gate of the one before), so the frame next to lost or discarded
bytes is never OK. The **speed gate** refuses a value implying a speed above ``max_speed``
[m/s] since the last accepted one (the stage cannot move that fast); ``relock_frames``
refusals in a row unlock. Refused and withheld frames are samples with status INVALID (the
sample count stays on the sensor's clock); each cause has its counter in :class:`ParserStats`.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Protocol, cast

import numpy as np
from numpy.typing import NDArray

from .errors import ConfigError


class Status(enum.IntEnum):
    """Sample status, same values as the Displacement message constants."""

    OK = 0
    NO_TARGET = 1
    TOO_CLOSE = 2
    TOO_FAR = 3
    INVALID = 4


#: chunks of at most this many frames (the stream of a loop that keeps up) take the Python path
FEW_FRAMES = 32
# the members as plain ints, looked up once (a per-frame path)
_OK, _TOO_CLOSE, _TOO_FAR, _INVALID = (
    int(s) for s in (Status.OK, Status.TOO_CLOSE, Status.TOO_FAR, Status.INVALID)
)


# Error value tables. ILD1700 codes from the ILD1700 manual §7.4 ("Digital error modes").
# ILD1320-family codes are from memory of the ILD1320/1420 manuals and NOT verified here (the
# manual page could not be retrieved): 262075 too much data for the baud rate, 262076 no peak,
# 262077 peak before the measuring range, 262078 peak after it, 262079 value cannot be
# evaluated, 262080 peak too wide, 262081 laser off, 262082 reserved. The ILD1750/1900 table
# is assumed equal to the ILD1320 one — confirm both on real hardware.
_ILD1700_ERRORS = {
    16370: Status.NO_TARGET,
    16372: Status.TOO_CLOSE,
    16374: Status.TOO_FAR,
    16376: Status.INVALID,
    16378: Status.INVALID,
    16380: Status.INVALID,
}
_ILD18BIT_ERRORS = {
    262075: Status.INVALID,
    262076: Status.NO_TARGET,
    262077: Status.TOO_CLOSE,
    262078: Status.TOO_FAR,
    262079: Status.INVALID,
    262080: Status.INVALID,
    262081: Status.INVALID,
    262082: Status.INVALID,
}


@dataclass(frozen=True)
class FrameFormat:
    """One family's binary output format and digital-value -> metres conversion."""

    family: str
    bytes_per_value: int  # 2 (H/L) or 3 (L/M/H)
    value_bits: int  # bits carried by a frame (14 or 18)
    mask: int  # bits of the frame that hold the value (16-bit mode drops D16, D17)
    measurement_max: int  # largest raw value that is a measurement (larger ones are not)
    error_range: tuple[int, int]  # inclusive range of error values
    errors: dict[int, Status]  # specific error values; others in error_range -> INVALID
    scale: float  # d = (x * scale - offset) * MR
    offset: float
    ascii_commands: bool  # answers the ASCII command set (GETINFO, MEASRATE, ...)
    default_baudrate: int
    status_lut: NDArray[np.uint8] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        lut = np.full(1 << self.value_bits, Status.INVALID, dtype=np.uint8)
        lut[: self.measurement_max + 1] = Status.OK
        lo, hi = self.error_range
        lut[lo : hi + 1] = Status.INVALID
        for code, status in self.errors.items():
            lut[code] = status
        lut.setflags(write=False)
        object.__setattr__(self, "status_lut", lut)

    def to_metres(self, raw: NDArray[np.int64], measuring_range: float) -> NDArray[np.float64]:
        """Digital value(s) -> metres from the start of the measuring range."""
        return (np.asarray(raw, dtype=np.float64) * self.scale - self.offset) * measuring_range

    def from_metres(
        self, distance: NDArray[np.float64], measuring_range: float
    ) -> NDArray[np.int64]:
        """Inverse of :meth:`to_metres`, rounded to the nearest digital value and clipped."""
        x = (np.asarray(distance, dtype=np.float64) / measuring_range + self.offset) / self.scale
        return np.minimum(np.maximum(np.rint(x), 0), self.measurement_max).astype(np.int64)

    def error_value(self, status: Status) -> int:
        """The error value a sensor of this family sends for ``status`` (not OK)."""
        for code, st in sorted(self.errors.items()):
            if st == status:
                return code
        return self.error_range[0]


class _FormatFactory(Protocol):
    """A family's :class:`FrameFormat` for its output bits (default: the family's usual)."""

    def __call__(self, bits: int = ...) -> FrameFormat: ...


def _make_formats() -> dict[str, _FormatFactory]:
    def ild1700(bits: int = 14) -> FrameFormat:
        if bits != 14:
            raise ConfigError("the ILD1700/ILD1402 format carries 14-bit values")
        return FrameFormat(
            "ild1700",
            2,
            14,
            0x3FFF,
            16368,
            (16370, 16383),
            _ILD1700_ERRORS,
            1.02 / 16368,
            0.01,
            False,
            115200,
        )

    def ild1320(bits: int = 18) -> FrameFormat:
        if bits == 18:
            return FrameFormat(
                "ild1320",
                3,
                18,
                0x3FFFF,
                65520,
                (262075, 262143),
                _ILD18BIT_ERRORS,
                1.02 / 65520,
                0.01,
                True,
                921600,
            )
        if bits == 16:  # 16-bit error values not confirmed: everything above 65520 is INVALID
            return FrameFormat(
                "ild1320",
                3,
                18,
                0xFFFF,
                65520,
                (65521, 65535),
                {},
                1.02 / 65520,
                0.01,
                True,
                921600,
            )
        raise ConfigError(f"ILD1320-family output is 16 or 18 bit, got {bits}")

    def ild1750(bits: int = 18) -> FrameFormat:
        if bits != 18:
            raise ConfigError("the ILD1750/ILD1900 format carries 18-bit values")
        return FrameFormat(
            "ild1750",
            3,
            18,
            0x3FFFF,
            262074,
            (262075, 262143),
            _ILD18BIT_ERRORS,
            1.0 / 65536,
            98232 / 65536,
            True,
            921600,
        )

    return {
        "ild1700": ild1700,
        "ild1402": ild1700,
        "ild1320": ild1320,
        "ild1420": ild1320,
        "ild2300": ild1320,
        "ild1750": ild1750,
        "ild1900": ild1750,
    }


FAMILIES = _make_formats()


def frame_format(family: str, bits: int | None = None) -> FrameFormat:
    """The :class:`FrameFormat` of ``family`` (one of :data:`FAMILIES`)."""
    key = family.lower().replace("-", "")
    if key not in FAMILIES:
        raise ConfigError(f"unknown optoNCDT family {family!r}; choose from {sorted(FAMILIES)}")
    return FAMILIES[key]() if bits is None else FAMILIES[key](bits)


def encode_values(
    fmt: FrameFormat, raw: NDArray[np.int64], later: NDArray[np.bool_] | None = None
) -> bytes:
    """Encode digital values as frames (the sensor side; used by the emulator and tests).

    ``later`` marks values that are later values of an output block (H flag 11, 3-byte formats).
    """
    raw = np.asarray(raw, dtype=np.int64)
    if fmt.bytes_per_value == 2:
        out = np.empty((raw.size, 2), dtype=np.uint8)
        out[:, 0] = 0x80 | ((raw >> 7) & 0x7F)
        out[:, 1] = raw & 0x7F
        return out.tobytes()
    out = np.empty((raw.size, 3), dtype=np.uint8)
    out[:, 0] = raw & 0x3F
    out[:, 1] = 0x40 | ((raw >> 6) & 0x3F)
    h_flag = np.full(raw.size, 0x80, dtype=np.uint8)
    if later is not None:
        h_flag[np.asarray(later, dtype=bool)] = 0xC0
    out[:, 2] = h_flag | ((raw >> 12) & 0x3F)
    return out.tobytes()


@dataclass(frozen=True)
class SampleBlock:
    """Samples decoded from one chunk, in arrival order."""

    displacement: NDArray[np.float64]  # float64 [m], NaN where status != OK
    status: NDArray[np.uint8]  # Status values
    raw: NDArray[np.int64]  # digital values as received

    @staticmethod
    def empty() -> "SampleBlock":
        """A block of no samples."""
        return SampleBlock(np.empty(0), np.empty(0, dtype=np.uint8), np.empty(0, dtype=np.int64))

    @staticmethod
    def concat(blocks: list["SampleBlock"]) -> "SampleBlock":
        """The blocks joined in order into one."""
        if not blocks:
            return SampleBlock.empty()
        return SampleBlock(
            np.concatenate([b.displacement for b in blocks]),
            np.concatenate([b.status for b in blocks]),
            np.concatenate([b.raw for b in blocks]),
        )

    def __len__(self) -> int:
        return int(self.status.size)


@dataclass(frozen=True)
class FrameCheck:
    """Frame lock and plausibility gate of :class:`OptoNCDTParser` (see the module docstring)."""

    relock_frames: int = 6  # k: consecutive agreeing frames before values are OK again (>= 2)
    max_speed: float = 0.1  # m/s: larger implied speeds are refused (inf: no gate)
    rate: float = 1000.0  # Hz: the sensor's measuring rate (time between frames for the gate)

    def __post_init__(self) -> None:
        if not 2 <= self.relock_frames <= 1000:
            raise ConfigError(f"relock_frames must be in [2, 1000], got {self.relock_frames}")
        if not self.max_speed > 0:
            raise ConfigError(f"max_speed must be > 0 m/s (inf: no gate), got {self.max_speed}")
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ConfigError(f"rate must be > 0 Hz, got {self.rate}")


@dataclass
class ParserStats:
    """Counters of :class:`OptoNCDTParser`: frames, values and bytes by what became of them."""

    frames: int = 0  # well-formed frames (first values of a block)
    later_values: int = 0  # well-formed frames flagged as later values of a block (ignored)
    ok: int = 0  # samples with status OK
    errors: int = 0  # error values sent by the sensor (status NO_TARGET, TOO_CLOSE, ...)
    text_bytes: int = 0  # bytes handed to the ASCII channel
    discarded: int = 0  # bytes that were neither frame nor ASCII text
    framing_errors: int = 0  # runs of non-frame bytes between frames (each unlocks)
    relock_withheld: int = 0  # well-formed frames withheld while relocking (status INVALID)
    speed_rejected: int = 0  # values refused by the speed gate (status INVALID)
    lock_losses: int = 0  # times a lock was lost (framing error, or relock_frames refusals)


class AsciiChannel:
    """Collects ASCII command replies (they end with the prompt ``->``) between frames."""

    PROMPT = b"->"
    MAX_BUFFER = 8192

    def __init__(self) -> None:
        self._text = bytearray()
        self._replies: list[bytes] = []

    def feed(self, data: NDArray[np.uint8]) -> int:
        """Keep printable ASCII, CR and LF; return how many bytes were dropped."""
        keep = ((data >= 0x20) & (data < 0x7F)) | (data == 0x0D) | (data == 0x0A)
        self._text += data[keep].tobytes()
        while (i := self._text.find(self.PROMPT)) >= 0:
            self._replies.append(bytes(self._text[: i + len(self.PROMPT)]))
            del self._text[: i + len(self.PROMPT)]
        if len(self._text) > self.MAX_BUFFER:
            del self._text[: len(self._text) - self.MAX_BUFFER]
        return int(data.size - np.count_nonzero(keep))

    def pop_reply(self) -> bytes | None:
        """The oldest complete reply (ending with the prompt), or None."""
        return self._replies.pop(0) if self._replies else None

    def clear(self) -> None:
        """Drop the text and the replies collected so far."""
        self._text.clear()
        self._replies.clear()


class OptoNCDTParser:
    """Incremental parser of an optoNCDT stream, with frame lock and speed gate (see module)."""

    def __init__(
        self, fmt: FrameFormat, measuring_range: float, check: FrameCheck | None = None
    ) -> None:
        if not measuring_range > 0:
            raise ConfigError(f"measuring range must be > 0 m, got {measuring_range}")
        self.fmt = fmt
        self.measuring_range = float(measuring_range)
        self.check = check or FrameCheck()
        self.ascii = AsciiChannel()
        self.stats = ParserStats()
        # the speed gate's slack: two digital steps (rounding on both sides)
        self._quantum = 2.0 * abs(fmt.scale) * self.measuring_range
        self.few_frames = FEW_FRAMES  # 0: every chunk through the numpy path
        self.reset()

    def gate(self, frames: NDArray[np.intp] | int) -> NDArray[np.floating] | float:
        """The speed gate: the largest change [m] an accepted value may show over ``frames``
        frames since the last accepted one (``max_speed`` × frames / rate + two digital
        steps).
        """
        return self.check.max_speed / self.check.rate * frames + self._quantum

    def reset(self) -> None:
        """Forget the stream (after (re)connecting: unlocked until relock_frames agree)."""
        self._tail = np.empty(0, dtype=np.uint8)
        self.ascii.clear()
        self._gap = 1  # non-frame bytes since the last frame (a new stream starts unlocked)
        self._good = 0  # consecutive agreeing frames since the last framing error
        self._ref = math.nan  # last accepted value [m]
        self._since = 0  # frames since it
        self._refused = 0  # consecutive speed-gate refusals while locked

    def feed(self, data: bytes) -> SampleBlock:
        """Parse the next chunk; the bytes of an incomplete frame wait for the next chunk."""
        if not data:
            return SampleBlock.empty()
        if len(data) <= self.few_frames * self.fmt.bytes_per_value and not self._tail.size:
            block = self._feed_frames(data)
            if block is not None:
                return block
        buf = np.concatenate([self._tail, np.frombuffer(data, dtype=np.uint8)])
        width = self.fmt.bytes_per_value
        ends = self._frame_ends(buf)  # index of each frame's last byte
        decided = max(buf.size - (width - 1), int(ends[-1]) + 1 if ends.size else 0)
        in_frame = np.zeros(buf.size, dtype=bool)
        for k in range(width):
            in_frame[ends - k] = True
        other = buf[:decided][~in_frame[:decided]]
        self._tail = buf[decided:].copy()
        self._route_other(other)
        # non-frame bytes in front of each frame (the first one also those of earlier chunks)
        starts = ends - (width - 1)
        # (numpy's stubs type the diff of an int64 array as timedelta64)
        steps = cast(NDArray[np.int64], np.diff(np.concatenate([[-1], ends]).astype(np.int64)))
        gaps = steps - width
        if gaps.size:
            gaps[0] = self._gap + int(starts[0])
            self._gap = decided - (int(ends[-1]) + 1)
        else:
            self._gap += decided
        return self._decode(buf, ends, gaps)

    def _frame_ends(self, buf: NDArray[np.uint8]) -> NDArray[np.intp]:
        if self.fmt.bytes_per_value == 2:  # H (bit 7 set) followed by L (bit 7 clear)
            return np.flatnonzero((buf[:-1] >= 0x80) & (buf[1:] < 0x80)) + 1
        flags = buf >> 6  # L: 00, M: 01, H: 10 (first value) or 11 (later value of a block)
        return np.flatnonzero((flags[2:] >= 2) & (flags[1:-1] == 1) & (flags[:-2] == 0)) + 2

    def _route_other(self, other: NDArray[np.uint8]) -> None:
        if not other.size:
            return
        if self.fmt.ascii_commands:
            dropped = self.ascii.feed(other)
            self.stats.text_bytes += int(other.size) - dropped
            self.stats.discarded += dropped
        else:
            self.stats.discarded += int(other.size)

    def _decode(
        self, buf: NDArray[np.uint8], ends: NDArray[np.intp], gaps: NDArray[np.int64]
    ) -> SampleBlock:
        if not ends.size:
            return SampleBlock.empty()
        b = buf.astype(np.int64)
        if self.fmt.bytes_per_value == 2:
            first = np.ones(ends.size, dtype=bool)
            raw = ((b[ends - 1] & 0x7F) << 7) | (b[ends] & 0x7F)
        else:
            first = b[ends] < 0xC0
            raw = ((b[ends] & 0x3F) << 12) | ((b[ends - 1] & 0x3F) << 6) | (b[ends - 2] & 0x3F)
        raw &= self.fmt.mask
        status = self.fmt.status_lut[raw].copy()
        distance = self.fmt.to_metres(raw, self.measuring_range)
        ok = status == _OK
        status[ok & (distance < 0.0)] = _TOO_CLOSE
        status[ok & (distance > self.measuring_range)] = _TOO_FAR
        self.stats.errors += int(np.count_nonzero((status != _OK) & first))
        status = np.array(
            self._lock(status.tolist(), distance.tolist(), first.tolist(), gaps.tolist()),
            dtype=np.uint8,
        )
        keep = first
        status, distance, raw = status[keep], distance[keep], raw[keep]
        distance[status != _OK] = np.nan
        self.stats.frames += int(raw.size)
        self.stats.later_values += int(ends.size - raw.size)
        self.stats.ok += int(np.count_nonzero(status == _OK))
        return SampleBlock(distance, status, raw)

    def _lock(
        self, status: list[int], distance: list[float], first: list[bool], gaps: list[int]
    ) -> list[int]:
        """Frame lock and speed gate, frame by frame: OK values not passing become INVALID."""
        check, stats = self.check, self.stats
        k, step, slack = check.relock_frames, check.max_speed / check.rate, self._quantum
        out = list(status)
        ok_value = _OK
        for i, (st, d, is_first, gap) in enumerate(zip(status, distance, first, gaps)):
            if gap > 0:
                stats.framing_errors += 1
                if self._good >= k:
                    stats.lock_losses += 1
                self._good, self._ref, self._refused = 0, math.nan, 0
            if not is_first:
                continue
            self._since += 1
            if st != ok_value:
                continue  # an error value: well-formed, but nothing to compare
            if self._good and abs(d - self._ref) <= step * self._since + slack:
                self._good += 1
                self._ref, self._since, self._refused = d, 0, 0
                if self._good >= k:
                    continue  # locked and plausible: OK
                stats.relock_withheld += 1
            elif self._good >= k:  # locked: refuse this value
                stats.speed_rejected += 1
                self._refused += 1
                if self._refused >= k:  # the reference itself is doubtful: relock from here
                    stats.lock_losses += 1
                    self._good, self._ref, self._since, self._refused = 1, d, 0, 0
            else:  # the first of a new run (after an error, or disagreeing with the run)
                if self._good:
                    stats.speed_rejected += 1
                else:
                    stats.relock_withheld += 1
                self._good, self._ref, self._since = 1, d, 0
            out[i] = _INVALID
        return out

    def _feed_frames(self, data: bytes) -> SampleBlock | None:
        """The common case of a stream in lock, decoded with Python ints (numpy costs more than
        the work for a few frames): ``data`` is whole well-formed frames and nothing else, as
        :meth:`_frame_ends` would find them. None for anything else (the general path).
        """
        fmt = self.fmt
        frames = self._split_lmh(data) if fmt.bytes_per_value == 3 else self._split_hl(data)
        if frames is None or len(frames[0]) * fmt.bytes_per_value != len(data):
            return None
        raws, first = frames
        lut, mr, scale, offset = fmt.status_lut, self.measuring_range, fmt.scale, fmt.offset
        status = [int(lut[r]) for r in raws]
        distance = [(r * scale - offset) * mr for r in raws]
        if min(distance, default=0.0) < 0.0 or max(distance, default=0.0) > mr:
            _mark_out_of_range(status, distance, mr)
        self.stats.errors += sum(1 for st, f in zip(status, first) if st != _OK and f)
        gaps = [self._gap] + [0] * (len(raws) - 1)
        self._gap = 0
        status = self._lock(status, distance, first, gaps)
        return self._few_frames_block(raws, first, status, distance)

    def _split_lmh(self, data: bytes) -> tuple[list[int], list[bool]] | None:
        """Values and first-value flags of L, M, H frames (flags 00, 01, 10 or 11 on H); None
        at the first byte that does not fit.
        """
        mask = self.fmt.mask
        raws: list[int] = []
        first: list[bool] = []
        for i in range(0, len(data) - 2, 3):
            lo, mid, hi = data[i], data[i + 1], data[i + 2]
            if lo >= 0x40 or mid >> 6 != 1 or hi < 0x80:
                return None
            raws.append((((hi & 0x3F) << 12) | ((mid & 0x3F) << 6) | (lo & 0x3F)) & mask)
            first.append(hi < 0xC0)
        return raws, first

    def _split_hl(self, data: bytes) -> tuple[list[int], list[bool]] | None:
        """Values and first-value flags (all True) of H, L frames (bit 7 set, clear); None at
        the first byte that does not fit.
        """
        mask = self.fmt.mask
        raws: list[int] = []
        for i in range(0, len(data) - 1, 2):
            hi, lo = data[i], data[i + 1]
            if hi < 0x80 or lo >= 0x80:
                return None
            raws.append((((hi & 0x7F) << 7) | (lo & 0x7F)) & mask)
        return raws, [True] * len(raws)

    def _few_frames_block(
        self, raws: list[int], first: list[bool], status: list[int], distance: list[float]
    ) -> SampleBlock:
        """The samples of the first values (later values dropped), counted in ``stats``."""
        keep = [i for i, f in enumerate(first) if f]
        out_status = [status[i] for i in keep]
        out_distance = [distance[i] if status[i] == _OK else math.nan for i in keep]
        stats = self.stats
        stats.frames += len(keep)
        stats.later_values += len(raws) - len(keep)
        stats.ok += out_status.count(_OK)
        return SampleBlock(
            np.array(out_distance, dtype=np.float64),
            np.array(out_status, dtype=np.uint8),
            np.array([raws[i] for i in keep], dtype=np.int64),
        )


def _mark_out_of_range(status: list[int], distance: list[float], mr: float) -> None:
    """Mark OK values below 0 TOO_CLOSE and above ``mr`` TOO_FAR, in place."""
    for i, (st, d) in enumerate(zip(status, distance)):
        if st == _OK and d < 0.0:
            status[i] = _TOO_CLOSE
        elif st == _OK and d > mr:
            status[i] = _TOO_FAR
