"""Header-stamp checks of incoming voltage commands: a bad stamp is a counted rejection.

A stamp is (sec, nanosec) as it came off the wire (``builtin_interfaces/Time``: sec is a signed
int32, so a hand-made message can carry -1). :meth:`StampPolicy.check` classifies it against
``now`` (the node clock, seconds) without building a ``rclpy.time.Time`` (which raises on
negative seconds):

- NEGATIVE: sec < 0; MALFORMED: nanosec outside [0, 1e9);
- UNSTAMPED: 0.0 while stamps matter (``require_stamp``: an age limit, or application at the stamp);
- AHEAD: further ahead of ``now`` than ``max_ahead`` (a foreign or broken clock: year 2038);
- TOO_OLD: older than ``max_age`` (when > 0).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

from .errors import ConfigError


class StampVerdict(enum.Enum):
    """Outcome of :meth:`StampPolicy.check` (module docstring)."""

    OK = "ok"
    NEGATIVE = "negative"
    MALFORMED = "malformed"
    UNSTAMPED = "unstamped"
    AHEAD = "ahead"
    TOO_OLD = "too_old"


@dataclass(frozen=True)
class StampPolicy:
    """Which stamps of incoming commands are refused (module docstring)."""

    max_age: float = 0.0  # s; 0: age not checked
    max_ahead: float = 5.0  # s; stamps further in the future are refused
    require_stamp: bool = False  # an unstamped (zero) command is refused

    def __post_init__(self) -> None:
        if not (math.isfinite(self.max_age) and self.max_age >= 0):
            raise ConfigError(f"max_age must be >= 0 s, got {self.max_age}")
        if not self.max_ahead > 0:
            raise ConfigError(f"max_ahead must be > 0 s, got {self.max_ahead}")

    def check(self, sec: int, nanosec: int, now: float) -> tuple[StampVerdict, float]:
        """(verdict, age [s]; NaN when the stamp is unusable) of a stamp against ``now`` [s]."""
        if sec < 0:
            return StampVerdict.NEGATIVE, math.nan
        if not 0 <= nanosec < 1_000_000_000:
            return StampVerdict.MALFORMED, math.nan
        if sec == 0 and nanosec == 0:
            return (StampVerdict.UNSTAMPED if self.require_stamp else StampVerdict.OK), math.nan
        age = now - (sec + nanosec * 1e-9)
        if age < -self.max_ahead:
            return StampVerdict.AHEAD, age
        if self.max_age > 0 and age > self.max_age:
            return StampVerdict.TOO_OLD, age
        return StampVerdict.OK, age
