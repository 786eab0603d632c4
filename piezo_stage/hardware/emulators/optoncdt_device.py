"""Emulated Micro-Epsilon optoNCDT streaming binary measurement frames at a fixed rate.

The displacement comes from ``source(times) -> metres from the start of the measuring range``
(default: mid-range plus a 1 Hz sine of MR/10). Values outside [0, MR] or NaN are sent as the
family's error values (too close / too far / no target), like the real sensor.
``error_probability`` replaces random samples by error values (fault injection).

Families with the ASCII command set (ILD1320/1420/2300/1750/1900) answer ``GETINFO``,
``MEASRATE`` (query, or set in kHz) and ``HELP``; the reply (command echo, lines ending CR LF,
prompt ``->``; refused commands ``Exx <text>``) is spread between measurement frames, as the real
sensor keeps streaming while it answers. ILD1700/1402 use binary command frames, which are not
emulated: their command input is ignored.
"""

from __future__ import annotations

import math
import threading
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigError
from ..optoncdt import FrameFormat, Status, encode_values

Source = Callable[[NDArray[np.float64]], NDArray[np.float64]]


class OptoNCDTDeviceModel:
    """State of the emulated sensor (see the module docstring), shared by all connections."""

    name = "optoncdt"

    def __init__(
        self,
        fmt: FrameFormat,
        measuring_range: float,
        rate: float = 1000.0,
        source: Source | None = None,
        error_probability: float = 0.0,
        seed: int | None = None,
        extra_values: int = 0,
    ) -> None:
        if not measuring_range > 0:
            raise ConfigError(f"measuring range must be > 0 m, got {measuring_range}")
        if not 0 < rate <= 100_000:
            raise ConfigError(f"rate must be in (0, 100000] Hz, got {rate}")
        if not 0.0 <= error_probability <= 1.0:
            raise ConfigError(f"error_probability must be in [0, 1], got {error_probability}")
        if extra_values and fmt.bytes_per_value != 3:
            raise ConfigError("only 3-byte formats carry extra values per block")
        self.fmt = fmt
        self.measuring_range = measuring_range
        self.rate = rate
        self.source = source or self._default_source
        self.error_probability = error_probability
        self.extra_values = extra_values  # later values per block (H flag 11), e.g. intensity
        self.rng = np.random.default_rng(seed)
        self.lock = threading.Lock()
        self.sent_samples = 0
        self.last_displacement = math.nan
        self._t0: float | None = None
        self._reply = bytearray()
        self.commands: list[str] = []

    @property
    def t0(self) -> float | None:
        """Server time (``time.monotonic``) of sample 0; ``source`` gets times relative to it."""
        return self._t0

    def synchronise(self, t0: float) -> None:
        """Take sample 0 at server time ``t0`` (``time.monotonic``, shared by every process of
        the host): sensors given one ``t0`` sample together, as on one sync line.
        """
        with self.lock:
            self._t0 = float(t0)

    @property
    def stream_period(self) -> float:
        """Seconds between :meth:`stream` calls: one sample period, at most 2 ms."""
        return min(1.0 / self.rate, 0.002)

    def _default_source(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        mr = self.measuring_range
        return 0.5 * mr + 0.1 * mr * np.sin(2 * np.pi * t)

    def next_due(self) -> float | None:
        """Server time at which the next sample is due (None before the first): the server wakes
        then, so each frame leaves when its sample is taken, as from a real sensor, and not up to
        a stream period later (a lag the reader's sample clock cannot see, since it only removes
        the jitter above the smallest delay).
        """
        with self.lock:
            if self._t0 is None:
                return None
            return self._t0 + self.sent_samples / self.rate + 1e-9

    def session(self) -> "_AsciiSession":
        """A connection's session: ASCII commands in, replies queued into the stream."""
        return _AsciiSession(self)

    # --- measurement stream ---------------------------------------------------------------------
    def encode(self, distance: NDArray[np.float64]) -> NDArray[np.int64]:
        """Metres from the start of the range -> digital values, out-of-range as error values."""
        d = np.asarray(distance, dtype=np.float64)
        if ((d >= 0.0) & (d <= self.measuring_range)).all():  # the usual case, and cheaper
            raw = self.fmt.from_metres(d, self.measuring_range)
        else:
            raw = self.fmt.from_metres(np.nan_to_num(d, nan=0.0), self.measuring_range)
            raw[d < 0] = self.fmt.error_value(Status.TOO_CLOSE)
            raw[d > self.measuring_range] = self.fmt.error_value(Status.TOO_FAR)
            raw[np.isnan(d)] = self.fmt.error_value(Status.NO_TARGET)
        if self.error_probability:
            hit = self.rng.random(raw.size) < self.error_probability
            codes = np.array(sorted(self.fmt.errors) or [self.fmt.error_range[0]])
            raw[hit] = self.rng.choice(codes, int(np.count_nonzero(hit)))
        return raw

    def stream(self, now: float) -> bytes:
        """The frames of the samples due by ``now`` (at most 1 s of them), the pending reply between
        them; the first call starts the sample clock.
        """
        with self.lock:
            if self._t0 is None:
                self._t0 = now
            due = int((now - self._t0) * self.rate) + 1 - self.sent_samples
            if due <= 0:
                return self._take_reply()
            due = min(due, int(self.rate) + 1)  # after a stall, do not burst more than 1 s
            times = (self.sent_samples + np.arange(due)) / self.rate
            distance = np.asarray(self.source(times), dtype=np.float64)
            self.sent_samples += due
            self.last_displacement = float(distance[-1])
            frames = self._frames(self.encode(distance))
            return self._interleave(frames)

    def _frames(self, raw: NDArray[np.int64]) -> list[bytes]:
        if not self.extra_values:
            data = encode_values(self.fmt, raw)
            w = self.fmt.bytes_per_value
            return [data[i : i + w] for i in range(0, len(data), w)]
        block = np.repeat(raw, 1 + self.extra_values)
        later = np.tile([False] + [True] * self.extra_values, raw.size)
        data = encode_values(self.fmt, block, later)
        w = 3 * (1 + self.extra_values)
        return [data[i : i + w] for i in range(0, len(data), w)]

    def _interleave(self, frames: list[bytes]) -> bytes:
        """Frames with the pending ASCII reply spread between them (never inside a frame)."""
        if not self._reply:
            return b"".join(frames)
        chunk = -(-len(self._reply) // len(frames))
        out = bytearray()
        for frame in frames:
            out += frame
            out += self._reply[:chunk]
            del self._reply[:chunk]
        return bytes(out)

    def _take_reply(self) -> bytes:
        data, self._reply = bytes(self._reply), bytearray()
        return data

    # --- ASCII commands -------------------------------------------------------------------------
    def execute(self, line: str) -> None:
        """Queue the reply to one ASCII command line (sent between the next frames)."""
        with self.lock:
            self.commands.append(line)
            if not self.fmt.ascii_commands:
                return  # ILD1700/1402: binary command protocol, not emulated
            body = self._run(line.split())
            text = line + "\r\n" + "".join(f"{b}\r\n" for b in body) + "->"
            self._reply += text.encode("ascii")

    def _run(self, words: list[str]) -> list[str]:
        name, args = words[0].upper(), words[1:]
        if name == "GETINFO" and not args:
            return [
                f"Name: {self.fmt.family.upper()} (piezo_stage emulator)",
                "Serial: 00000001",
                "Option: 000",
                f"Measuring range: {self.measuring_range * 1e3:g} mm",
                f"Output: {self.fmt.value_bits} bit binary",
            ]
        if name == "MEASRATE":
            if not args:
                return [f"MEASRATE {self.rate / 1000:.3f}"]
            try:
                khz = float(args[0])
            except ValueError:
                return ["E02 Wrong parameter type"]
            if not 0.01 <= khz <= 10.0 or len(args) > 1:
                return ["E03 Value out of range"]
            self.rate = khz * 1000.0
            self._t0, self.sent_samples = None, 0
            return []
        if name == "HELP":
            return ["GETINFO", "MEASRATE [kHz]", "HELP"]
        return ["E01 Unknown command"]


class _AsciiSession:
    def __init__(self, model: OptoNCDTDeviceModel) -> None:
        self.model = model
        self._buf = bytearray()

    def handle(self, data: bytes, now: float) -> bytes:
        self._buf += data
        while True:
            ends = [i for i in (self._buf.find(b"\r"), self._buf.find(b"\n")) if i >= 0]
            if not ends:
                return b""
            i = min(ends)
            line = self._buf[:i].decode("ascii", errors="replace").strip()
            del self._buf[: i + 1]
            if line:
                self.model.execute(line)
