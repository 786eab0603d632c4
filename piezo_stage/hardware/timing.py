"""Timing of a real rig: when a voltage is applied, and when a sensor sample was taken.

The identification (thesis 9.1.3, Steps 1-2) cuts the recorded input into periods on the time
axis, so the input must be periodic *in the stamps*: T-wave periods that agree to better than
1 % (``CycleOptions.period_tolerance``) and samples of v and y paired at the same instant. Two
things on a host computer break that, and both are fixed here at their source:

- :class:`CommandPlayout` — the commands of an open-loop excitation reach the amplifier after
  a variable transport delay (DDS, the subscriber's executor, the scheduler: on a loaded 2-core
  host p50 ~2 ms, p99 ~55 ms, max > 100 ms were measured), so the *applied* waveform is the
  commanded one warped in time. The playout applies each command at ``stamp + delay`` from its
  own thread: the applied waveform is the commanded one, shifted by the constant ``delay``
  (0 when the sender stamps its commands ahead of time, as the excitation node's ``lead``
  does, so that its run marks stay aligned with what is applied); only commands arriving later
  than that are applied at once (and counted).
- :class:`SampleClock` — a sensor samples on its own crystal, but its frames reach the host in
  bursts (UART/USB FIFO, USB latency timer, the reader's poll period). Stamping at reception
  adds that jitter (and makes stamps go backwards between bursts). The sensor's n-th sample was
  taken at ``t0 + n / rate``; ``t0`` is the lower envelope of ``t_reception − n / rate`` (the
  bursts only ever add delay), tracked over a sliding window so that lost frames and a slow
  drift of the sensor's crystal are followed.

What is left is the host's scheduling of the thread that writes to the device (on a saturated
2-core host the playout thread, or the emulated device, can wait tens of ms for a CPU):
:func:`set_realtime_priority` puts the calling thread in SCHED_FIFO when the system allows it
(root, CAP_SYS_NICE, or an ``rtprio`` limit in /etc/security/limits.conf on a rig PC).
"""

from __future__ import annotations

import heapq
import itertools
import math
import os
import sys
import threading
import time
from collections import deque
from typing import Callable

from .errors import ConfigError

#: [s] how long a thread may hold the GIL while another waits (Python's default: 5 ms): the
#: playout thread of apply_at_stamp gets it within 0.5 ms; the composed rig loop's thread,
#: which answers each sensor sample, within 50 µs
PLAYOUT_SWITCH_INTERVAL = 5e-4
LOOP_SWITCH_INTERVAL = 5e-5


def shorten_switch_interval(seconds: float) -> None:
    """Let a waiting thread take the GIL within ``seconds`` (never lengthens what another part
    of the process asked for): the one place a process's switch interval is set.
    """
    sys.setswitchinterval(min(sys.getswitchinterval(), seconds))


def set_realtime_priority(priority: int) -> str | None:
    """Run the calling thread under SCHED_FIFO at ``priority`` (1-99; 0 does nothing).

    Returns None on success (or for 0), else why it was not possible (the thread keeps its
    normal priority): callers report it and go on.
    """
    if priority <= 0:
        return None
    if not hasattr(os, "sched_setscheduler"):
        return "SCHED_FIFO is not available on this platform"
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(min(int(priority), 99)))
    except OSError as exc:
        return (
            f"SCHED_FIFO priority {priority} refused ({exc.strerror}); "
            "allow it with an rtprio limit"
        )
    return None


class SampleClock:
    """Stamps [ns] of a constant-rate sample stream from the reception times of its blocks.

    ``stamps(t_ns, n)``: ``n`` samples arrived at ``t_ns`` (the last of them just received);
    returns the time each was taken, ``t0 + k / rate`` with ``t0`` = min of
    ``t_reception − k_last / rate`` over the last ``window`` seconds. A stamp is never later than
    its reception; a frame lost on the link delays the following stamps by 1/rate until the
    window has forgotten the older, earlier envelope (≤ ``window`` s). Stamps only increase, at
    least half a period apart: when a reception earlier than the window's envelope lowers
    ``t0``, the next stamps close the step back half a period per sample (a loop that steps on
    every sample never sees time go back).
    """

    def __init__(self, rate: float, window: float = 2.0) -> None:
        if not (math.isfinite(rate) and rate > 0):
            raise ConfigError(f"sample rate must be > 0 Hz, got {rate}")
        if not window > 0:
            raise ConfigError(f"envelope window must be > 0 s, got {window}")
        self.rate = float(rate)
        self.window = float(window)
        self._half_period_ns = round(0.5e9 / rate)
        self.reset()

    def reset(self) -> None:
        """Forget the stream (after a reconnect the sensor's sample counter restarts for us)."""
        self._base_ns: int | None = None
        self._last_ns: int | None = None  # the newest stamp given
        self._count = 0
        self._offsets: deque[tuple[float, float]] = deque()  # (t_reception, offset) [s from base]

    @property
    def count(self) -> int:
        """Samples stamped since the last reset."""
        return self._count

    def stamps(self, t_ns: int, n: int) -> list[int]:
        """The stamps [ns] of ``n`` samples, the last of them received at ``t_ns`` (Python ints:
        a loop that steps per sample takes them one by one).
        """
        if n <= 0:
            return []
        if self._base_ns is None:
            self._base_ns = int(t_ns)
        base, rate, count = self._base_ns, self.rate, self._count
        t = (int(t_ns) - base) * 1e-9
        offset = t - (count + n - 1) / rate
        offsets = self._offsets
        while offsets and offsets[-1][1] >= offset:
            offsets.pop()  # monotone deque: its front is the window's minimum
        offsets.append((t, offset))
        while offsets[0][0] < t - self.window:
            offsets.popleft()
        t0 = offsets[0][1]
        self._count = count + n
        out = [base + round((t0 + k / rate) * 1e9) for k in range(count, count + n)]
        last, step = self._last_ns, self._half_period_ns
        if last is not None and out[0] < last + step:
            for k, stamp in enumerate(out):
                last = out[k] = max(stamp, last + step)
        self._last_ns = out[-1]
        return out


class CommandPlayout:
    """Apply each command at ``stamp + delay`` (wall clock, seconds) from a dedicated thread.

    ``push(stamp, voltage, received)`` queues a command; the thread calls ``apply(voltage, True,
    received)`` when it is due, in stamp order (``received``: when the command arrived; the
    driver refuses one received before its watchdog fired). With ``hold_period`` > 0 it also
    fills the interval between a command and the next one already queued with ``apply(value,
    False, received of the next one)`` every ``hold_period`` s, linearly interpolated (a
    first-order hold): the device's output then follows the straight
    lines between the commands, which is how a sampled record of them is read back (a linear
    interpolation between the stamped values), up to the finer staircase of ``hold_period`` —
    not a staircase lagging it by half a command period. A command that is already due when it
    arrives (it came later than ``delay``) is applied at once and counted in ``late``; one due
    more than ``max_ahead`` s from now (a foreign clock) is held for ``max_ahead`` only and
    counted in ``ahead``. ``clear()`` drops what is queued (the watchdog and the shutdown ramp
    take over the output); ``stop()`` ends the thread.
    """

    def __init__(
        self,
        apply: Callable[[float, bool, float | None], None],
        delay: float,
        clock: Callable[[], float] = time.time,
        max_pending: int = 100_000,
        realtime_priority: int = 0,
        max_ahead: float = 5.0,
        hold_period: float = 0.0,
        max_hold_gap: float = 0.1,
    ) -> None:
        if not (math.isfinite(delay) and delay >= 0):
            raise ConfigError(f"playout delay must be >= 0 s, got {delay}")
        if not (math.isfinite(max_ahead) and max_ahead >= delay):
            raise ConfigError(f"max_ahead must be >= the delay, got {max_ahead}")
        self.apply = apply
        self.delay = float(delay)
        self.clock = clock
        if not (math.isfinite(hold_period) and hold_period >= 0):
            raise ConfigError(f"hold_period must be >= 0 s, got {hold_period}")
        self.hold_period = float(hold_period)
        self.max_hold_gap = float(max_hold_gap)  # no interpolation across a longer gap (a pause)
        self.max_pending = max_pending
        self.max_ahead = float(max_ahead)
        self.ahead = 0  # commands due implausibly far ahead (held for max_ahead)
        self.late = 0  # commands that arrived after their due time
        self.dropped = 0  # commands dropped because the queue was full
        self.applied = 0
        self.error: Exception | None = None  # last exception raised by apply()
        self.realtime_priority = realtime_priority  # SCHED_FIFO priority of the thread (0: normal)
        self.realtime_error: str | None = None  # why it could not be had
        # (due, seq, voltage, received)
        self._queue: list[tuple[float, int, float, float | None]] = []
        self._seq = itertools.count()
        self._cv = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._run, name="command-playout", daemon=True)

    def start(self) -> "CommandPlayout":
        """Start the thread; returns the playout."""
        self._thread.start()
        return self

    def push(self, stamp: float, voltage: float, received: float | None = None) -> None:
        """Queue ``voltage`` for ``stamp`` + delay; ``received`` (when it arrived, on the
        caller's clock) is handed to ``apply`` with it.
        """
        now = self.clock()
        due = stamp + self.delay
        with self._cv:
            if due <= now:
                self.late += 1
            elif due > now + self.max_ahead:
                self.ahead += 1
                due = now + self.max_ahead
            if len(self._queue) >= self.max_pending:
                self.dropped += 1
                return
            heapq.heappush(self._queue, (due, next(self._seq), float(voltage), received))
            self._cv.notify()

    @property
    def pending(self) -> int:
        """Commands queued and not yet applied."""
        with self._cv:
            return len(self._queue)

    def clear(self) -> None:
        """Drop the queued commands."""
        with self._cv:
            self._queue.clear()

    def stop(self) -> None:
        """Drop the queue and end the thread (waits up to 5 s for it)."""
        with self._cv:
            self._stop = True
            self._queue.clear()
            self._cv.notify()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        self.realtime_error = set_realtime_priority(self.realtime_priority)
        last: tuple[float, float] | None = None  # (due, voltage) of the last command applied
        emitted = -math.inf  # time of the last output (command or interpolated)
        while True:
            with self._cv:
                item: tuple[tuple[float, int, float, float | None], bool] | None = None
                while not self._stop:
                    if not self._queue:
                        self._cv.wait()
                        continue
                    now = self.clock()
                    due, _, v1, received = self._queue[0]
                    if due <= now:
                        item = (heapq.heappop(self._queue), True)
                        break
                    wake = due
                    if (
                        self.hold_period > 0
                        and last is not None
                        and 0 < due - last[0] <= self.max_hold_gap
                    ):
                        t_fill = emitted + self.hold_period
                        if t_fill <= now:
                            frac = (now - last[0]) / (due - last[0])
                            item = ((now, 0, last[1] + frac * (v1 - last[1]), received), False)
                            break
                        wake = min(wake, t_fill)
                    self._cv.wait(wake - now)
                if self._stop:
                    return
            assert item is not None  # the loop only ends without one when stopped
            (t, _, voltage, received), is_command = item
            if is_command:
                last = (t, voltage)
            emitted = self.clock()
            try:
                self.apply(voltage, is_command, received)
                self.applied += int(is_command)
            except Exception as exc:  # the owner reports it; the playout keeps running
                self.error = exc
