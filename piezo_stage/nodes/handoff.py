"""The composed loop's hand-off: what its thread publishes, queued and drained where the loop has
the most time (:class:`Handoff`; :mod:`.rig_loop` measures the alternatives)."""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Callable

from rclpy.node import Node

from piezo_stage.hardware.timing import set_realtime_priority

from .runtime import wall_clock

#: s between the executor's publications of what the loop queued: at most, and at least
PUBLISH_PERIOD = 0.01
MIN_PUBLISH_PERIOD = 0.002
#: samples of the loop per publication above 2 kHz (each drain holds the GIL for its whole
#: length: the one sample that arrives meanwhile waits for it)
DRAIN_SAMPLES = 20


def publish_period(rate_hz: float) -> float:
    """s between drains of the hand-off at a ``rate_hz`` loop: ``DRAIN_SAMPLES`` samples' worth
    within [``MIN_PUBLISH_PERIOD``, ``PUBLISH_PERIOD``] (bench/control_loop.py, 10 kHz, the
    executor's thread draining: 10 ms p99 0.53-0.56 ms, 2 ms 0.41-0.53 ms, 1 ms 0.49-0.53 ms;
    at 1 kHz 10 ms is the better)."""
    return min(PUBLISH_PERIOD, max(MIN_PUBLISH_PERIOD, DRAIN_SAMPLES / rate_hz))


#: publications the publisher thread makes in a row, then it sleeps SLICE_GAP: a drain gives
#: the CPU back to the machine every ~0.1-0.2 ms instead of holding it for the whole drain
DRAIN_SLICE = 8
SLICE_GAP = 2e-4


class Handoff:
    """What the loop publishes (realtime_tools' RealtimePublisher, without its thread): :meth:`put`
    is a deque append (from any thread); the loop thread calls :meth:`drain_due` after each write
    and each idle read, which publishes the queue in order every ``period``. A drain holds the GIL
    for its whole length, so it runs where the loop has the most time: right after a write
    (bench/control_loop.py, 10 kHz: p99 0.35 ms, 54 µs per sample, against 0.41-0.53 ms and
    64 µs for the executor's thread draining every 2 ms). The alternatives bench/control_loop.py
    measures (``controller.publish_in``): ``executor`` a wall-clock timer of the
    executor drains (:meth:`attach`); ``publisher`` a thread of its own
    below the loop's priority, in slices (:meth:`start_publisher`: a drain in the SCHED_FIFO loop
    thread keeps a CPU from the machine's other processes for its whole length, 1-9 ms of CPU
    each on a loaded host); ``inline`` every publication at once."""

    def __init__(self, inline: bool = False, period: float = PUBLISH_PERIOD) -> None:
        self._queue: deque[tuple[Callable[..., None], tuple[Any, ...]]] = deque()
        self.after_drain: list[Callable[[], None]] = []
        self.inline = inline
        self.period = period
        self.in_loop = True
        self._next = 0.0
        self._lock = threading.Lock()  # one drain at a time: publications stay in order
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.publisher_error: str | None = None

    def start_publisher(self, priority: int) -> None:
        """Drain from a thread of its own every ``period``, in slices of ``DRAIN_SLICE``
        publications ``SLICE_GAP`` apart, at SCHED_FIFO ``priority`` (0: normal). Below the
        loop thread's priority, the loop preempts it on a shared CPU; above the machine's
        ordinary processes, a GIL it holds is never stuck behind them."""
        self.in_loop = False
        self._thread = threading.Thread(
            target=self._publish_loop, args=(priority,), name="loop-publisher", daemon=True
        )
        self._thread.start()

    def _publish_loop(self, priority: int) -> None:
        self.publisher_error = set_realtime_priority(priority)
        while not self._stop.wait(self.period):
            self.drain(sliced=True)

    def close(self) -> None:
        """Stop the publisher thread (if any) and publish what is left."""
        self._stop.set()
        if self._thread is not None and self._thread.ident is not None:
            self._thread.join(timeout=2.0)
        self.drain()

    def attach(self, node: Node, period: float) -> None:
        """Drain from the executor's thread every ``period`` instead of the loop's."""
        self.in_loop = False
        node.create_timer(period, self.drain, clock=wall_clock())

    def put(self, publish: Callable[..., None], *args: Any) -> None:
        if self.inline:
            publish(*args)
            return
        self._queue.append((publish, args))

    def drain_due(self) -> None:
        """The loop thread's drain: when ``period`` has gone since the last."""
        if self.in_loop:
            now = time.monotonic()
            if now >= self._next:
                self._next = now + self.period
                self.drain()

    def drain(self, sliced: bool = False) -> None:
        """Publish the queue in order (``sliced``: sleeping ``SLICE_GAP`` every ``DRAIN_SLICE``)."""
        queue = self._queue
        with self._lock:
            count = 0
            while queue:
                publish, args = queue.popleft()
                publish(*args)
                count += 1
                if sliced and count % DRAIN_SLICE == 0 and queue:
                    time.sleep(SLICE_GAP)
            for done in self.after_drain:
                done()
