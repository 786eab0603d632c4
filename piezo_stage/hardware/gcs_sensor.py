"""A PI controller's own position sensor (E-727, E-709: capacitive or strain gauge) as the loop's
displacement source, polled over GCS: ``POS? <axis>`` answers ``<axis>=<position in um>``.

:class:`GCSPositionReader` has the surface the ``laser_reader`` node uses of an optoNCDT reader
(:class:`~piezo_stage.hardware.sensor.LinkReader`). It opens a GCS link of its own: over TCP a
second connection next to the voltage driver's (PI's E-727/E-709 accept several TCP clients
sharing one controller state, and so does the emulator, ``piezo-stage emulate e727``); a serial
port cannot be shared, so with the driver on it use TCP for one of them. It sends ``SAI?`` on
connecting (the axis must be listed: :class:`ConfigError` otherwise) and then only ``POS?`` for
that axis: never ``ERR?``, which would read and clear an error the driver's own ``ERR?`` is
owed (the controller's error latch is one for all connections), nor a query the controller
could refuse.

Polling is deadline-paced on a grid of ``1 / rate`` s: one query per slot, a slot the host
missed (it came back late) is skipped and counted, never caught up with a burst; each answer is
one sample, in metres (um x 1e-6) with status OK. A reply that is not exactly one line
``<axis>=<finite number>`` for this axis is a sample with status INVALID and NaN, counted;
so is a query unanswered within ``reply_timeout``, after which the next :meth:`read` raises
:class:`ConnectionLost` (the caller reconnects: a fresh connection, so that the late reply
cannot pass for the next query's). Bytes waiting before a query are no reply to it: dropped
and counted. ``stale``: no valid reply for ``stale_timeout`` s.
"""

from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass
from typing import Callable, ClassVar, Mapping

import numpy as np

from .errors import ConfigError, ConnectionLost, DeviceTimeout
from .gcs import gcs_reply_end, split_reply
from .optoncdt import SampleBlock, Status
from .sensor import LinkReader
from .transport import ReplyBuffer, Transport, make_transport

UM = 1e-6  #: m per um (``POS?`` answers um)
#: a GCS number: optional sign, digits with an optional decimal point, optional exponent
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_OK, _INVALID = int(Status.OK), int(Status.INVALID)
GCS_BAUDRATE = 115200  #: the serial default of PI's controllers
#: s for the SAI? reply on connecting (a controller, or an emulator catching up with its servo
#: clock, may take longer to answer its first query than a poll may)
CONNECT_TIMEOUT = 1.0


@dataclass(frozen=True)
class GCSReaderConfig:
    """The polled axis and how its link is handled (module docstring)."""

    axis: str = "1"  # GCS axis identifier (listed by SAI?)
    rate: float = 1000.0  # Hz: polls per second
    reply_timeout: float = 0.05  # s to wait for a reply before the sample is INVALID
    stale_timeout: float = 0.5  # s without a valid reply before `stale`
    reconnect_attempts: int = 3
    reconnect_delay: float = 0.2  # s

    def __post_init__(self) -> None:
        if not (self.axis and self.axis.isascii() and self.axis.isprintable()):
            raise ConfigError(f"GCS axis must be a printable ASCII name, got {self.axis!r}")
        if " " in self.axis or "=" in self.axis:
            raise ConfigError(f"GCS axis must not hold a space or '=', got {self.axis!r}")
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ConfigError(f"poll rate must be > 0 Hz, got {self.rate}")
        if not (self.reply_timeout > 0 and self.stale_timeout > 0):
            raise ConfigError("reply_timeout and stale_timeout must be > 0 s")


def parse_position(reply: bytes, axis: str) -> float | None:
    """The position [m] of ``axis`` in a ``POS?`` reply (``<axis>=<um>`` and its LF), or None
    when the reply is anything else: another axis, several lines, not a finite number, not
    ASCII.
    """
    if not reply.isascii():
        return None
    lines = split_reply(reply)
    if len(lines) != 1:
        return None
    item, sep, value = lines[0].partition("=")
    if not sep or item != axis or _NUMBER.fullmatch(value) is None:
        return None
    um = float(value)
    return um * UM if math.isfinite(um) else None


def _everything(buffer: bytes) -> int:
    """ReplyBuffer completion that takes all that is buffered (to drop it)."""
    return len(buffer)


@dataclass
class PollStats:
    """Counters of :class:`GCSPositionReader`."""

    polls: int = 0  # POS? queries sent
    frames: int = 0  # valid replies (samples OK)
    invalid_replies: int = 0  # replies that were not <axis>=<finite number>
    reply_timeouts: int = 0  # queries unanswered within reply_timeout
    missed_polls: int = 0  # grid slots skipped because the host came back late
    discarded: int = 0  # bytes that were waiting before a query (no reply to it)


class GCSPositionReader(LinkReader[GCSReaderConfig]):
    """``POS? <axis>`` of a PI controller polled at ``config.rate`` (module docstring)."""

    WARNINGS: ClassVar[Mapping[str, str]] = {
        "invalid_replies": "reply(ies) not '<axis>=<number>'",
        "reply_timeouts": "poll(s) unanswered",
        "missed_polls": "poll slot(s) missed (host late)",
        "unsolicited_bytes_dropped": "unsolicited byte(s) dropped",
    }

    def __init__(
        self,
        transport: Transport,
        config: GCSReaderConfig,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(transport, clock)
        self.config = config
        self.period = 1.0 / config.rate
        self.stats = PollStats()
        self.axes: list[str] = []  # what SAI? listed at the last connect
        self._replies = ReplyBuffer(transport)
        self._query = f"POS? {config.axis}\n".encode("ascii")
        self._due: float | None = None  # the next poll's slot (None: the next read starts the grid)
        self._timed_out = False

    @classmethod
    def from_url(
        cls,
        url: str,
        config: GCSReaderConfig,
        baudrate: int | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> "GCSPositionReader":
        """A reader on the transport for ``url`` (``tcp://host:port``, or a serial port)."""
        return cls(make_transport(url, baudrate or GCS_BAUDRATE), config, clock)

    # --- link -----------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the link and check that ``SAI?`` lists the axis (ConfigError if not); the
        controller's answer, not the open link, counts as a sign of life (``stale``).
        """
        self.transport.open()
        self.restart()
        self._check_axis()
        self.received()

    def restart(self) -> None:
        """Drop what the link held; the next :meth:`read` starts the poll grid."""
        self._replies.clear()
        self.transport.reset_input()
        self._due = None
        self._timed_out = False

    def _check_axis(self) -> None:
        reply = self._exchange(b"SAI?\n", max(self.config.reply_timeout, CONNECT_TIMEOUT))
        if reply is None:
            raise DeviceTimeout(f"no reply to 'SAI?' from {self.transport.url} on connecting")
        self.axes = [a.strip() for a in split_reply(reply) if a.strip()]
        if self.config.axis not in self.axes:
            self.transport.close()
            raise ConfigError(
                f"axis {self.config.axis!r} not on the controller at {self.transport.url} "
                f"(SAI? lists {self.axes})"
            )

    def counters(self) -> dict[str, int]:
        """The poll counters under the names the node's diagnostics give them."""
        s = self.stats
        return {
            "frames": s.frames,
            "polls": s.polls,
            "invalid_replies": s.invalid_replies,
            "reply_timeouts": s.reply_timeouts,
            "missed_polls": s.missed_polls,
            "unsolicited_bytes_dropped": s.discarded,
        }

    # --- samples --------------------------------------------------------------------------------
    def read(self, timeout: float = 0.05) -> SampleBlock:
        """The next poll's sample, when its slot comes within ``timeout`` s (else an empty block
        after ``timeout``); a poll in progress is waited for (up to ``reply_timeout``).
        ConnectionLost after a poll that timed out (module docstring).
        """
        if self._timed_out:
            self._timed_out = False
            raise ConnectionLost(
                f"no reply to {self._query.decode().strip()!r} from {self.transport.url} within "
                f"{self.config.reply_timeout:g} s: reopening the link (a late reply must not "
                "pass for the next query's)"
            )
        due = self.clock() if self._due is None else self._due
        wait = due - self.clock()
        if wait > timeout:
            time.sleep(max(timeout, 0.0))
            return SampleBlock.empty()
        if wait > 0:
            time.sleep(wait)
        self._next_slot(due)
        return self._sample(self._poll())

    def _next_slot(self, due: float) -> None:
        """Move the deadline from ``due`` to the next grid slot ahead, counting the slots
        skipped.
        """
        late = max(int((self.clock() - due) // self.period), 0)
        self.stats.missed_polls += late
        self._due = due + (late + 1) * self.period

    def _poll(self) -> float | None:
        """One ``POS?``: the position [m], or None (invalid reply or timeout, counted)."""
        self.stats.polls += 1
        reply = self._exchange(self._query, self.config.reply_timeout)
        if reply is None:
            self.stats.reply_timeouts += 1
            self._timed_out = True
            return None
        value = parse_position(reply, self.config.axis)
        if value is None:
            self.stats.invalid_replies += 1
            return None
        self.stats.frames += 1
        self.received()
        return value

    def _exchange(self, query: bytes, timeout: float) -> bytes | None:
        """Send ``query`` and return its reply, or None when none came within ``timeout`` s;
        whatever was waiting before is dropped (it answers no query of ours).
        """
        while (junk := self._replies.poll(_everything)) is not None:
            self.stats.discarded += len(junk)
        self.transport.write(query)
        try:
            return self._replies.read_reply(gcs_reply_end, timeout)
        except DeviceTimeout:
            return None

    @staticmethod
    def _sample(value: float | None) -> SampleBlock:
        """One sample: OK with ``value`` [m], or INVALID with NaN (``raw`` 0: no digital value)."""
        ok = value is not None
        return SampleBlock(
            np.array([value if ok else math.nan]),
            np.array([_OK if ok else _INVALID], np.uint8),
            np.zeros(1, np.int64),
        )
