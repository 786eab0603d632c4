"""Replay timing and topic selection of the player (pure: the node adapts them to rclpy)."""

from __future__ import annotations

import time
from typing import Sequence

from .errors import BagError


class PlaybackError(BagError, ValueError):
    """A playback setting is invalid (unknown topic in the filter, malformed remap, rate, ...)."""


def parse_remaps(items: Sequence[str]) -> dict[str, str]:
    """``["from:=to", ...]`` -> ``{from: to}``."""
    remaps: dict[str, str] = {}
    for item in items:
        src, sep, dst = item.partition(":=")
        if not sep or not src.strip() or not dst.strip():
            raise PlaybackError(f"remap {item!r} is not of the form 'from:=to'")
        remaps[src.strip()] = dst.strip()
    return remaps


class PlaybackClock:
    """Bag time [ns] as a function of wall time [s, monotonic]: ``start_ns`` at ``resume()``,
    advancing ``rate`` times faster than the wall clock, frozen while paused. Not thread safe:
    the owner holds a lock.
    """

    def __init__(self, start_ns: int, rate: float, paused: bool = False) -> None:
        if rate <= 0:
            raise PlaybackError(f"a playback clock needs rate > 0, got {rate}")
        self.rate = rate
        self._bag_ns = start_ns  # bag time at the last pause / resume
        self._wall: float | None = None  # wall time of the last resume (None = paused)
        self.paused = True
        if not paused:
            self.resume(time.monotonic())

    def now(self, wall: float) -> int:
        """Bag time [ns] at wall time ``wall``; while paused, the bag time it was paused at."""
        if self._wall is None:
            return self._bag_ns
        return self._bag_ns + int((wall - self._wall) * self.rate * 1e9)

    def due(self, bag_ns: int) -> float | None:
        """Wall time at which ``bag_ns`` is reached; None while paused."""
        if self._wall is None:
            return None
        return self._wall + (bag_ns - self._bag_ns) / (self.rate * 1e9)

    def pause(self, wall: float) -> None:
        """Freeze the bag time at its value at ``wall`` (no-op while paused)."""
        if not self.paused:
            self._bag_ns, self._wall, self.paused = self.now(wall), None, True

    def resume(self, wall: float) -> None:
        """Let the bag time advance again from ``wall`` on (no-op while running)."""
        if self.paused:
            self._wall, self.paused = wall, False
