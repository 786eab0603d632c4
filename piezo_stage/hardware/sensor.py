"""optoNCDT sensor reader: link handling on top of :class:`OptoNCDTParser`.

``SensorReader.read()`` returns the samples decoded since the last call (a
:class:`SampleBlock`, possibly empty); ``command()`` runs an ASCII command while samples keep
arriving (they are kept for the next ``read()``); ``reconnect()`` reopens a dropped link.
``stale`` tells when no frame arrived for ``stale_timeout`` seconds (for diagnostics).

:class:`LinkReader` is what the ``laser_reader`` node knows of a reader, shared with
:class:`~piezo_stage.hardware.gcs_sensor.GCSPositionReader` (a PI controller's own sensor):
the link (connect, reconnect, close, :meth:`~LinkReader.restart`), staleness, and the counters
its diagnostics report (:meth:`~LinkReader.counters`, :meth:`~LinkReader.warning`).
"""

from __future__ import annotations

import logging
import re
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Callable, ClassVar, Generic, Iterator, Mapping, Protocol, TypeVar

from .errors import ConfigError, ConnectionLost, DeviceTimeout, SensorCommandError, TransportError
from .optoncdt import FrameCheck, OptoNCDTParser, SampleBlock, frame_format
from .transport import Transport, make_transport

log = logging.getLogger(__name__)
_ERROR_LINE = re.compile(r"^E(\d+)\b\s*(.*)$")


@dataclass(frozen=True)
class SensorConfig:
    """An optoNCDT sensor and how its link and frames are handled (see the module docstring)."""

    family: str  # ild1700, ild1402, ild1320, ild1420, ild2300, ild1750, ild1900
    measuring_range: float  # MR [m]
    bits: int | None = None  # 16 or 18 for the ILD1320 family (default 18)
    stale_timeout: float = 0.5  # s without frames before `stale`
    rate: float = 1000.0  # Hz: the sensor's measuring rate (speed gate)
    max_speed: float = 0.1  # m/s: values implying a faster stage are refused (inf: no gate)
    relock_frames: int = 6  # consecutive agreeing frames after a framing error before OK again
    reconnect_attempts: int = 3
    reconnect_delay: float = 0.2  # s

    def __post_init__(self) -> None:
        if not self.measuring_range > 0:
            raise ConfigError(f"measuring_range must be > 0 m, got {self.measuring_range}")
        if not self.stale_timeout > 0:
            raise ConfigError(f"stale_timeout must be > 0 s, got {self.stale_timeout}")
        FrameCheck(self.relock_frames, self.max_speed, self.rate)  # raises ConfigError when bad

    @property
    def frame_check(self) -> FrameCheck:
        """The parser's frame lock and speed gate from this configuration."""
        return FrameCheck(self.relock_frames, self.max_speed, self.rate)


class LinkConfig(Protocol):
    """What :class:`LinkReader` reads of a reader's configuration."""

    @property
    def stale_timeout(self) -> float:
        """Seconds without a sample before the reader is ``stale``."""

    @property
    def reconnect_attempts(self) -> int:
        """Tries of :meth:`LinkReader.reconnect`."""

    @property
    def reconnect_delay(self) -> float:
        """Seconds between two tries."""


C = TypeVar("C", bound=LinkConfig)


class LinkReader(ABC, Generic[C]):
    """A displacement sensor's reader as the ``laser_reader`` node uses it (module docstring).

    Subclasses set ``config``, implement :meth:`restart`, :meth:`read` and :meth:`counters`, and
    call :meth:`received` when a sample arrived; ``WARNINGS`` names the counters whose rise the
    node reports as a warning.
    """

    #: counters whose rise is a warning -> what the warning calls one of them
    WARNINGS: ClassVar[Mapping[str, str]] = {}

    config: C

    def __init__(self, transport: Transport, clock: Callable[[], float]) -> None:
        self.transport = transport
        self.clock = clock
        self._t_frame = -float("inf")
        self.reconnects = 0

    @abstractmethod
    def restart(self) -> None:
        """Forget what the link held (received bytes, a parser's state, a poll's pacing)."""

    @abstractmethod
    def read(self, timeout: float = 0.05) -> SampleBlock:
        """The samples since the last call, waiting up to about ``timeout`` s for some."""

    @abstractmethod
    def counters(self) -> dict[str, int]:
        """The reader's counters for diagnostics; ``frames`` (samples received) is always one."""

    def warning(self, before: Mapping[str, int], now: Mapping[str, int]) -> str:
        """What the ``WARNINGS`` counters rose by from ``before`` to ``now`` ("" if nothing)."""
        rises = ((now[key] - before.get(key, 0), label) for key, label in self.WARNINGS.items())
        return ", ".join(f"{rise} {label}" for rise, label in rises if rise)

    def received(self) -> None:
        """Note that a sample arrived now (``stale`` counts from here)."""
        self._t_frame = self.clock()

    # --- link -----------------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the link and :meth:`restart`."""
        self.transport.open()
        self.restart()
        self.received()

    def reconnect(self) -> None:
        """Close and reopen the link, ``reconnect_attempts`` tries; ConnectionLost if all fail."""
        self.transport.close()
        last: Exception | None = None
        for attempt in range(max(self.config.reconnect_attempts, 1)):
            if attempt:
                time.sleep(self.config.reconnect_delay)
            try:
                self.connect()
                self.reconnects += 1
                return
            except TransportError as exc:
                last = exc
                self.transport.close()
        raise ConnectionLost(f"could not reconnect to {self.transport.url}: {last}") from last

    def close(self) -> None:
        """Close the link."""
        self.transport.close()

    @property
    def stale(self) -> bool:
        """Whether no sample arrived for ``stale_timeout`` seconds."""
        return self.clock() - self._t_frame > self.config.stale_timeout


class SensorReader(LinkReader[SensorConfig]):
    """Samples and ASCII commands of one optoNCDT sensor over a transport (module docstring)."""

    WARNINGS: ClassVar[Mapping[str, str]] = {
        "sample_errors": "error value(s)",
        "resync_bytes_discarded": "byte(s) discarded (resync)",
        "relock_withheld": "frame(s) withheld (lock)",
        "speed_rejected": "frame(s) refused (speed gate)",
    }

    def __init__(
        self,
        transport: Transport,
        config: SensorConfig,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(transport, clock)
        self.config = config
        self.parser = OptoNCDTParser(
            frame_format(config.family, config.bits), config.measuring_range, config.frame_check
        )
        self._pending: list[SampleBlock] = []

    @classmethod
    def from_url(
        cls,
        url: str,
        config: SensorConfig,
        baudrate: int | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> "SensorReader":
        """A reader on the transport for ``url`` (``baudrate`` default: the frame format's)."""
        fmt = frame_format(config.family, config.bits)
        return cls(make_transport(url, baudrate or fmt.default_baudrate), config, clock)

    def restart(self) -> None:
        """Drop stale input and reset the parser."""
        self.transport.reset_input()
        self.parser.reset()

    def counters(self) -> dict[str, int]:
        """The parser's counters under the names the node's diagnostics give them."""
        stats = self.parser.stats
        return {
            "frames": stats.frames,
            "sample_errors": stats.errors,
            "resync_bytes_discarded": stats.discarded,
            "framing_errors": stats.framing_errors,
            "lock_losses": stats.lock_losses,
            "relock_withheld": stats.relock_withheld,
            "speed_rejected": stats.speed_rejected,
        }

    # --- samples --------------------------------------------------------------------------------
    def _receive(self, timeout: float) -> None:
        data = self.transport.read(timeout)
        if data:
            block = self.parser.feed(data)
            if len(block):
                self._pending.append(block)
                self.received()

    def read(self, timeout: float = 0.05) -> SampleBlock:
        """Samples received since the last call, waiting up to ``timeout`` s if there are none."""
        if not self._pending:
            self._receive(timeout)
        pending, self._pending = self._pending, []
        return pending[0] if len(pending) == 1 else SampleBlock.concat(pending)

    def samples(self, timeout: float = 0.05) -> Iterator[SampleBlock]:
        """Endless iterator of non-empty sample blocks (ConnectionLost when the link drops)."""
        while True:
            block = self.read(timeout)
            if len(block):
                yield block

    # --- ASCII commands -------------------------------------------------------------------------
    def command(self, text: str, timeout: float = 1.0) -> list[str]:
        """Run an ASCII command; returns the reply lines without echo and prompt."""
        if not self.parser.fmt.ascii_commands:
            raise SensorCommandError(
                "n/a",
                f"{self.parser.fmt.family} uses a binary command "
                "protocol, which this reader does not implement",
                text,
            )
        self.parser.ascii.clear()
        self.transport.write(text.encode("ascii") + b"\r\n")
        deadline = self.clock() + timeout
        while (reply := self.parser.ascii.pop_reply()) is None:
            remaining = deadline - self.clock()
            if remaining <= 0:
                raise DeviceTimeout(
                    f"no reply to {text!r} from {self.transport.url} within {timeout} s"
                )
            self._receive(min(remaining, 0.05))
        lines = [ln.strip() for ln in reply[:-2].decode("ascii").replace("\r", "\n").split("\n")]
        lines = [ln for ln in lines if ln]
        if lines and lines[0].upper() == text.strip().upper():
            lines = lines[1:]
        for line in lines:
            if (match := _ERROR_LINE.match(line)) is not None:
                raise SensorCommandError(f"E{match.group(1)}", match.group(2) or line, text)
        return lines

    def get_info(self, timeout: float = 1.0) -> dict[str, str]:
        """``GETINFO`` as a dict of ``key: value`` lines."""
        info = {}
        for line in self.command("GETINFO", timeout):
            key, sep, value = line.partition(":")
            if sep:
                info[key.strip()] = value.strip()
        return info
