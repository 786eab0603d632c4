"""The optoNCDT sensors of a stage's axes, read in one thread: one cycle per sensor period.

:class:`StageSensors` waits on every sensor's descriptor with one selector and reads each that
is ready without blocking; :class:`~.optoncdt.OptoNCDTParser` (each axis's
:class:`~.sensor.SensorReader`: frame lock, speed gate) decodes the bytes and each axis's
:class:`~.timing.SampleClock` stamps them at the sensors' ``rate``; with ``decimation`` N each
axis's :class:`~.decimation.Decimator` makes one sample of N, as the reader node does, and the
loop's rate is ``rate`` / N. Per axis it keeps every sample of the cycle, up to
``max_pending`` (default ``MAX_BACKLOG`` s of them; older ones are dropped and counted in
``dropped``): the loop steps on each, oldest first, in :meth:`StageSensors.take`'s sub-cycles.

Alignment: a cycle is due when every axis has a sample newer than the last cycle, or ``align``
seconds (default half a period) after the first of them arrived. Synchronised sensors (one
master, the others on its sync output, all at one rate) deliver a period's frames together, so
the master paces the cycles and each cycle carries one sample of every axis; unsynchronised
ones add up to ``align`` of latency to the earliest axis. Any axis may start a cycle, so a
sensor that stalls (or goes invalid) never stops the others: in a cycle it missed, it is not
``fresh`` (its loop checks its gap). A sensor whose link drops leaves the selector (``down``,
its reason in ``errors``) and misses the cycles while a thread of its own reopens the link
(``reconnect_attempts`` tries, then again after ``RECONNECT_PAUSE``): the loop's thread never
waits for a reconnect, and the other axes go on. Once reopened, the loop's next wait takes it
back (``reconnects``), its sample clock and decimator started afresh.
"""

from __future__ import annotations

import math
import os
import selectors
import threading
import time
from collections.abc import Callable, Sequence

from .decimation import Decimator
from .errors import ConfigError, TransportError
from .sensor import SensorReader
from .timing import SampleClock
from .transport import READ_SIZE

__all__ = ["StageSensors"]


#: [s] of samples an axis keeps for one cycle: a loop stalled this long (a loaded host's
#: scheduler, 50-90 ms was seen) is caught up, every sample stepped; older ones are dropped
MAX_BACKLOG = 0.25

#: [s] between two rounds of reconnect attempts of a lost sensor link
RECONNECT_PAUSE = 0.5


class StageSensors:
    """The sensors ``readers[i]`` of axis i at ``rate`` [Hz], each sample of the loop the
    mean of ``decimation`` of theirs (module docstring); after a due :meth:`wait`, each of the
    cycle's :meth:`depth` sub-cycles is :meth:`take`'s: then ``value``, ``status``, ``stamp``
    [ns] and ``fresh`` hold it. ``align`` [s] is in the loop's periods (``rate`` / N). The
    stamps are ``stamp_ns``'s (the nodes' clock); ``clock_ns`` times the waits.
    """

    def __init__(
        self,
        readers: Sequence[SensorReader],
        rate: float,
        align: float | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
        stamp_window: float = 2.0,
        max_pending: int | None = None,
        decimation: int = 1,
        stamp_ns: Callable[[], int] = time.time_ns,
    ) -> None:
        if not readers:
            raise ConfigError("a stage has one sensor per axis, got none")
        if not (math.isfinite(rate) and rate > 0):
            raise ConfigError(f"sample rate must be > 0 Hz, got {rate}")
        n = len(readers)
        self.decimators = [Decimator(decimation) for _ in range(n)]
        self.rate = rate / decimation  # the loop's
        align = 0.5 / self.rate if align is None else align
        if not 0 <= align < 2.0 / self.rate:
            raise ConfigError(f"align must be in [0, 2 periods) s, got {align}")
        self.readers = tuple(readers)
        self._align_ns = round(align * 1e9)
        self._clock_ns, self._stamp_ns = clock_ns, stamp_ns
        self.clocks = [SampleClock(rate, stamp_window) for _ in range(n)]
        self.value = [math.nan] * n
        self.status = [0] * n
        self.stamp = [0] * n
        self.fresh = [False] * n
        self.down = [False] * n
        self.dropped = [0] * n  # samples never stepped: more than max_pending in one cycle
        self.samples = [0] * n
        # the cycle's samples per axis, oldest first: value, status, stamp [ns]
        self._values: list[list[float]] = [[] for _ in range(n)]
        self._statuses: list[list[int]] = [[] for _ in range(n)]
        self._stamps: list[list[int]] = [[] for _ in range(n)]
        backlog = math.ceil(MAX_BACKLOG * self.rate) if max_pending is None else max_pending
        self._max_pending = max(1, int(backlog))
        self.errors: list[TransportError | None] = [None] * n
        self.reconnects = [0] * n
        self._back = [False] * n  # reopened by its reconnect thread, not yet taken back
        self._closing = threading.Event()
        self._first_ns: int | None = None  # when the cycle's first fresh sample arrived
        self._fresh_count = 0
        self._live = n  # axes whose link is up
        self._sel: selectors.BaseSelector | None = None

    def connect(self) -> None:
        """Open every sensor's link and register it with the selector."""
        self._sel = selectors.DefaultSelector()
        self._closing.clear()
        for decimator in self.decimators:
            decimator.reset()
        for i, reader in enumerate(self.readers):
            reader.connect()
            self._sel.register(reader.transport.fileno(), selectors.EVENT_READ, i)

    def close(self) -> None:
        """Close every link (a reconnect thread stops at its next attempt)."""
        self._closing.set()
        if self._sel is not None:
            self._sel.close()
            self._sel = None
        for reader in self.readers:
            reader.close()

    def wait(self, timeout: float) -> bool:
        """Read what arrives until a cycle is due (True) or ``timeout`` s passed with no fresh
        sample (False).
        """
        sel = self._sel
        if sel is None:
            raise ConfigError("StageSensors.wait before connect()")
        clock = self._clock_ns
        deadline = clock() + round(timeout * 1e9)
        if True in self._back:
            self._take_back(sel)
        while True:
            now = clock()
            if self._fresh_count >= self._live and self._fresh_count:
                return True
            first = self._first_ns
            if first is not None:
                due = first + self._align_ns
                if now >= due:
                    return True
                wait_ns = due - now
            elif now >= deadline:
                return False
            else:
                wait_ns = deadline - now
            for key, _ in sel.select(wait_ns * 1e-9):
                self._read(key.data, key.fd, clock())

    def _read(self, i: int, fd: int, now_ns: int) -> None:
        try:
            data = os.read(fd, READ_SIZE)
        except BlockingIOError:
            return
        except OSError as exc:
            self._lose(i, fd, TransportError(f"sensor {i}: read failed: {exc}"))
            return
        if not data:
            self._lose(i, fd, TransportError(f"sensor {i}: the link closed"))
            return
        block = self.readers[i].parser.feed(data)
        k = len(block)
        if not k:
            return
        stamps = self.clocks[i].stamps(self._stamp_ns(), k)
        displacement, status = block.displacement.tolist(), block.status.tolist()
        decimator = self.decimators[i]
        if decimator.n > 1:
            out = decimator.feed(displacement, status, stamps)
            displacement, status, stamps = out.displacement, out.status, out.stamp
            k = len(status)
            if not k:
                return
        self.samples[i] += k
        if not self.fresh[i]:
            self.fresh[i] = True
            self._fresh_count += 1
            if self._first_ns is None:
                self._first_ns = now_ns
        values, statuses, stamps_i = self._values[i], self._statuses[i], self._stamps[i]
        values.extend(displacement)
        statuses.extend(status)
        stamps_i.extend(stamps)
        extra = len(values) - self._max_pending
        if extra > 0:
            del values[:extra], statuses[:extra], stamps_i[:extra]
            self.dropped[i] += extra

    def depth(self) -> int:
        """The due cycle's sub-cycles: the most samples an axis brought."""
        return max(len(v) for v in self._values)

    def take(self, j: int, depth: int) -> None:
        """Sub-cycle ``j`` of ``depth``, aligned at the end (the last holds every fresh axis's
        newest sample): axis i is fresh with its sample ``len_i − depth + j`` when there is one.
        """
        for i, values in enumerate(self._values):
            k = len(values) - depth + j
            if k >= 0:
                self.value[i], self.status[i] = values[k], self._statuses[i][k]
                self.stamp[i], self.fresh[i] = self._stamps[i][k], True
            else:
                self.fresh[i] = False

    def _lose(self, i: int, fd: int, exc: TransportError) -> None:
        if self._sel is not None:
            self._sel.unregister(fd)
        self.down[i], self.errors[i] = True, exc
        self._live -= 1
        threading.Thread(target=self._reconnect, args=(i,), daemon=True).start()

    def _reconnect(self, i: int) -> None:
        """Reopen axis ``i``'s link (its own thread) until it opens or the sensors close."""
        reader = self.readers[i]
        while not self._closing.is_set():
            try:
                reader.reconnect()
            except TransportError as exc:
                self.errors[i] = exc
                self._closing.wait(RECONNECT_PAUSE)
                continue
            if self._closing.is_set():
                reader.close()
            else:
                self._back[i] = True
            return

    def _take_back(self, sel: selectors.BaseSelector) -> None:
        """Put the reopened links back in the selector (the loop's thread)."""
        for i, back in enumerate(self._back):
            if back:
                self._back[i] = False
                self.clocks[i].reset()
                self.decimators[i].reset()
                sel.register(self.readers[i].transport.fileno(), selectors.EVENT_READ, i)
                self.down[i], self.errors[i] = False, None
                self.reconnects[i] += 1
                self._live += 1

    def now_ns(self) -> int:
        """Now [ns] on the clock of the stamps."""
        return self._stamp_ns()

    def next_cycle(self) -> None:
        """The cycle was taken: every axis waits for a newer sample."""
        fresh = self.fresh
        for i in range(len(fresh)):
            fresh[i] = False
            self._values[i].clear()
            self._statuses[i].clear()
            self._stamps[i].clear()
        self._fresh_count = 0
        self._first_ns = None
