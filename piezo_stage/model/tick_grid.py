"""A fixed grid of timer instants that a late timer callback catches up on (the plant's and the
excitation's timers: no gap in the stamps after a stalled process).
"""

from __future__ import annotations


class TickGrid:
    """The instants t0 + k·period that a timer callback has to serve, on a fixed grid: a late
    tick gets every instant it missed (each to be handled with its own stamp), so a stalled
    process leaves no gap in the stamps. After a stall longer than ``max_backlog`` instants the
    older ones are skipped (counted in ``dropped``) and the grid resumes at the latest one.
    The first call starts the grid at its ``now_ns``.
    """

    def __init__(self, period_ns: int, max_backlog: int) -> None:
        if period_ns <= 0 or max_backlog < 1:
            raise ValueError("TickGrid needs period_ns > 0 and max_backlog >= 1")
        self.period_ns = int(period_ns)
        self.max_backlog = int(max_backlog)
        self.next_ns: int | None = None
        self.dropped = 0

    def due(self, now_ns: int) -> range:
        """Grid instants [ns] whose time has come since the last call, oldest first."""
        if self.next_ns is None:
            self.next_ns = now_ns
        count = (now_ns - self.next_ns) // self.period_ns + 1
        if count <= 0:
            return range(0)
        if count > self.max_backlog:  # a long stall: resynchronise on the latest grid instant
            self.dropped += count - 1
            self.next_ns += (count - 1) * self.period_ns
            count = 1
        start = self.next_ns
        self.next_ns += count * self.period_ns
        return range(start, self.next_ns, self.period_ns)
