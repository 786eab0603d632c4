"""One axis's sensor read in the calling thread, on any link: the ``laser_reader`` node's read
thread, and the loop of a stage of one axis.

:class:`AxisSensor` blocks in its :class:`~.sensor.LinkReader`'s ``read`` (an optoNCDT stream,
or a PI controller's sensor polled on its grid), stamps each block when it arrives with a
:class:`~.timing.SampleClock` at ``rate`` and makes one sample of ``decimation`` with a
:class:`~.decimation.Decimator`: a blocking read stamps a block as it arrives, where a periodic
poll would stamp it up to a poll period late (a lag the sample clock cannot remove). A link
that fails is reopened at the next wait (the clock and the decimator forget the old stream);
until it is, each wait fails after ``timeout``. It holds a block's samples as
:class:`~.stage_sensors.StageSensors` holds a cycle's of several axes (the
:class:`~piezo_stage.control.stage_loop.Cycles` the stage's loop steps): one sub-cycle a sample,
oldest first.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from .decimation import Decimated, Decimator
from .errors import TransportError
from .sensor import LinkReader
from .timing import SampleClock

__all__ = ["AxisSensor"]

#: what a link event says: the error that took the link down, or None when it is back
LinkEvent = Callable[[str | None], None]


class AxisSensor:
    """The sensor ``reader`` at ``rate`` [Hz] (module docstring), its samples stamped by
    ``stamp_ns`` (the node's clock [ns]); ``on_link`` hears the link go down and come back;
    ``sleep(timeout)`` is the wait after a failed one (an event's ``wait`` ends it early).
    After a due :meth:`wait`, ``block`` holds the samples and :meth:`take` puts sample ``j``
    in ``value[0]``, ``status[0]``, ``stamp[0]``.
    """

    def __init__(
        self,
        reader: LinkReader[Any],
        rate: float,
        decimation: int = 1,
        stamp_ns: Callable[[], int] = time.time_ns,
        stamp_window: float = 2.0,
        on_link: LinkEvent | None = None,
        sleep: Callable[[float], object] = time.sleep,
    ) -> None:
        self.reader = reader
        self.clock = SampleClock(rate, stamp_window)
        self.decimator = Decimator(decimation)
        self.rate = rate / decimation  # the loop's
        self._stamp_ns, self._on_link, self._sleep = stamp_ns, on_link, sleep
        self.block = Decimated([], [], [])
        self.value, self.status, self.stamp = [math.nan], [0], [0]
        self.fresh = [False]
        self.samples, self.dropped = [0], [0]  # per axis, as StageSensors counts
        self.connected = True
        self.link_errors = 0
        self.last_error = ""

    @property
    def reconnects(self) -> list[int]:
        """Per axis: links reopened."""
        return [self.reader.reconnects]

    @property
    def errors(self) -> list[str | None]:
        """Per axis: why its link is down, None while it is up."""
        return [None if self.connected else self.last_error]

    def connect(self) -> None:
        """Forget what the link held (samples older than the start would reach the loop in one
        late block).
        """
        self.reader.restart()
        self._forget()

    def close(self) -> None:
        """Close the link."""
        self.reader.close()

    def _forget(self) -> None:
        self.clock.reset()
        self.decimator.reset()

    def wait(self, timeout: float) -> bool:
        """Read what arrives within ``timeout`` s (reopening a lost link first): True when it
        made samples (then ``block`` holds them).
        """
        reader = self.reader
        try:
            if not self.connected:
                reader.reconnect()
                self.connected = True
                self._forget()
                if self._on_link is not None:
                    self._on_link(None)
            raw = reader.read(timeout)
        except TransportError as exc:
            self.connected = False
            self.link_errors += 1
            self.last_error = str(exc)
            if self._on_link is not None:
                self._on_link(self.last_error)
            self._sleep(timeout)  # a dead link fails at once: retry at the wait's pace
            return False
        k = len(raw)
        if not k:
            return False
        stamps = self.clock.stamps(self._stamp_ns(), k)
        block = self.decimator.feed(raw.displacement.tolist(), raw.status.tolist(), stamps)
        if not block.status:
            return False
        self.block = block
        self.samples[0] += len(block.status)
        return True

    def depth(self) -> int:
        """The block's samples."""
        return len(self.block.status)

    def take(self, j: int, depth: int) -> None:
        """Sample ``j`` of the block (``depth``: its length)."""
        block = self.block
        self.value[0], self.status[0], self.stamp[0] = (
            block.displacement[j],
            block.status[j],
            block.stamp[j],
        )
        self.fresh[0] = True

    def now_ns(self) -> int:
        """Now [ns] on the clock of the stamps."""
        return self._stamp_ns()

    def next_cycle(self) -> None:
        """The block was taken."""
        self.fresh[0] = False
        self.block = Decimated([], [], [])
