"""When an identification run is complete, live: the excitation's marks (``run``, ``steady``)
say where each run starts and ends, the sample streams say when the data of a finished run
has arrived, and a long silence says that no more will come (ch. 10: two steady runs, x(t)
and x(t) + q, are identified together).

:class:`RunTracker` is the state machine of the ``identifier`` node (no rclpy): feed it the
marks as they arrive and poll it with the sample streams' progress; it returns the runs
ready to be processed and says once when the streams fell silent before two runs were
complete. Runs are cut as ``piezo-stage identify`` cuts a bag
(:func:`piezo_stage.identification.io.intervals_from_marks`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum

from .io import intervals_from_marks

#: runs needed for an identification: x(t) and x(t) + q (ch. 10)
RUNS_NEEDED = 2


class Phase(str, Enum):
    """What a mark says about its run."""

    SETTLING = "settling"  # a new run, not yet periodic
    STEADY = "steady"  # the run's recorded periods
    OVER = "over"  # the run's end (the plan is done)


@dataclass(frozen=True)
class Poll:
    """What :meth:`RunTracker.poll` found: runs whose data has arrived (process them in this
    order), whether the streams are silent, and whether that silence is a failure to report
    (fewer than two complete runs; said once per silence).
    """

    ready: tuple[int, ...]
    silent: bool
    stalled: bool


@dataclass
class RunTracker:
    """Run completion and stream silence for live identification (see the module docstring).

    A run is complete when a steady mark of it is followed by another mark that is not a
    steady mark of the same run (the next run's first mark, or the plan's end mark). It is
    ready once both streams have passed that mark's stamp (topics arrive independently), or
    when the streams have been silent for ``settle_time`` wall seconds.

    Silence is said from the second of quiet polls each at most ``confirm_within`` seconds
    after the one before: after a stall of the host the node's timer runs before it takes the
    messages that arrived meanwhile, so the first quiet poll may only mean that the node itself
    was not running (seen: a run identified from 162 of its samples on a loaded host).

    The source's clock (``poll(clock=...)``: the node's sim time, which a player or a lockstep
    plant publishes) moving is activity too: a recording can hold a long stretch without
    samples (the sample bag ``ch10_identification``: 64 s of receive time, played at rate 5 for
    13 wall seconds), and a replay crossing it is not silent; silence is then the source
    stopped (the bag played, the plant gone).
    """

    marks: list[tuple[float, int, bool]] = field(default_factory=list)
    offsets: dict[int, float] = field(default_factory=dict)
    completed: list[int] = field(default_factory=list)
    _pending: list[tuple[float, int]] = field(default_factory=list)
    _last: tuple[int, bool] | None = None
    _count: int = 0
    _clock: float | None = None
    _changed_at: float | None = None
    _reported: bool = False
    confirm_within: float = 1.0
    _quiet_at: float | None = None  # the last poll that found the streams quiet

    def mark(self, t: float, run: int, steady: bool, offset: float = 0.0) -> Phase | None:
        """Record an excitation mark at stamp ``t`` [s]; return its phase when it changes the
        run's state (for the log), else None.
        """
        self.marks.append((t, run, steady))
        self.offsets[run] = offset
        previous, self._last = self._last, (run, steady)
        if (
            previous is not None
            and previous[1]
            and self._last != previous
            and previous[0] not in self.completed
        ):
            self.completed.append(previous[0])
            self._pending.append((t, previous[0]))
        if previous == self._last:
            return None
        if steady:
            return Phase.STEADY
        return Phase.SETTLING if previous is None or previous[0] != run else Phase.OVER

    def intervals(self) -> list[tuple[int, float, float]]:
        """``(run, start, stop)`` of the runs so far; one unbounded run 0 without marks."""
        return intervals_from_marks(self.marks) if self.marks else [(0, -math.inf, math.inf)]

    def interval(self, run: int) -> tuple[int, float, float] | None:
        """``(run, start, stop)`` of run ``run``; None when the marks do not have it (yet)."""
        return next((i for i in self.intervals() if i[0] == run), None)

    @property
    def pending(self) -> bool:
        """Completed runs not yet handed out by :meth:`poll`."""
        return bool(self._pending)

    def poll(
        self,
        samples: int,
        latest: float,
        now: float,
        settle_time: float,
        identified: bool = False,
        clock: float | None = None,
    ) -> Poll:
        """``samples``: samples received so far (both streams); ``latest``: the stamp [s] both
        streams have reached (the smaller of their last stamps); ``now``: wall time [s];
        ``identified``: a result exists (silence is then no failure); ``clock``: the source's
        time [s] when the node runs on one (sim time), else None: while it moves the streams
        are not silent. Call it periodically (every 0.1 s in the node): silence needs two quiet
        polls (see the class).
        """
        moved = clock is not None and clock != self._clock
        self._clock = clock
        if samples != self._count or moved or self._changed_at is None:
            self._count, self._changed_at, self._reported = samples, now, False
        quiet = samples > 0 and now - self._changed_at > settle_time
        confirmed = self._quiet_at is not None and now - self._quiet_at <= self.confirm_within
        silent = quiet and confirmed
        self._quiet_at = now if quiet else None
        ready = []
        while self._pending and (self._pending[0][0] <= latest or silent):
            ready.append(self._pending.pop(0)[1])
        stalled = (
            silent and not self._reported and not identified and len(self.completed) < RUNS_NEEDED
        )
        self._reported = self._reported or stalled
        return Poll(tuple(ready), silent, stalled)
