"""The voltage a trajectory needs by the ch. 11 inverse model, against an amplifier's range.

The ch. 11 model (11.1)-(11.3) has the displacement as the Bouc-Wen input, so the voltage that
makes the stage follow x_d is the model evaluated along x_d (:func:`.feedforward.feedforward`):

    u = m·ẍ_d + c·ẋ_d + κx·x_d + κw·w(x_d),   w driven by x_d from w = 0 at x_d(0)

(Σ κ_i·x_d^i, the polynomial of (10.4), when the set has more than κx; x_d from the model's
offset y0). :func:`voltage_need` is the range of u over the first :data:`NEED_PERIODS` periods of
a periodic trajectory (the first from rest, as a tracking run starts, then the limit cycle) or
over a file's whole record, sampled :data:`NEED_SAMPLES` times per period: the continuous
model, whatever the loop's rate. At a low rate the sampled feedforward's staircase spans less
(the 1 kHz staircase of a 10 Hz triangle over 6-46 µm on the ch. 11 rig: 59-484 V, against
21-524 V here), because each step rings the 7 kHz resonance up to the corners; a stage held at
x_d, or tracking it slowly, needs the continuous figure, so the check keeps it.

:class:`AmplifierRange` admits a need that lies inside [u_min, u_max] less a margin at each end
for the PID's share (:data:`PID_MARGIN` of the span): with the feedforward the law supplies
what the model misses, ~p % of u for a model p % off (a model 1 % off misses ~5 V at 480 V),
and the learning, which stays within [u_min, u_max], converges to the plant's need rather than
the model's. :func:`largest_amplitude` finds by bisection the largest amplitude the range admits
at a given offset (the need's interval grows with the amplitude: x_d's extremes, |w|'s and
|ẋ_d|, |ẍ_d| all do).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from .errors import ControlError
from .feedforward import FeedforwardModel, feedforward
from .trajectory import Trajectory

#: share of the amplifier's span kept free at each end for the PID (module docstring)
PID_MARGIN = 0.02
#: periods of a periodic trajectory evaluated: from rest, then the limit cycle of w
NEED_PERIODS = 3
#: samples per period (a file's record: over the record)
NEED_SAMPLES = 2000
#: relative resolution of :func:`largest_amplitude`
AMPLITUDE_TOLERANCE = 1e-4


class VoltageRangeError(ControlError):
    """An amplifier range that admits nothing, or a bad input to the search."""


@dataclass(frozen=True)
class VoltageNeed:
    """The lowest and the highest voltage [V] the model says a trajectory needs."""

    low: float
    high: float


def voltage_need(model: FeedforwardModel, trajectory: Trajectory) -> VoltageNeed:
    """The lowest and the highest u = m·ẍ_d + c·ẋ_d + κx·x_d + κw·w(x_d) along ``trajectory``
    (the ch. 11 inverse model, (11.1) with w of (11.3) driven by x_d from w = 0 at x_d(0); see
    the module docstring for the periods and the sampling).
    """
    periodic = trajectory.periodic
    n = NEED_SAMPLES * (NEED_PERIODS if periodic else 1)
    span = trajectory.period * (NEED_PERIODS if periodic else 1)
    t = np.arange(n + 1) * (span / n)
    x, v, a = trajectory.evaluate(t)
    u, _ = feedforward(model, x, v, a, 0.0)
    return VoltageNeed(float(np.min(u)), float(np.max(u)))


@dataclass(frozen=True)
class AmplifierRange:
    """What an amplifier (and the controller's clamp) lets through, [u_min, u_max] V; a need is
    admitted within ``margin`` of either end (``PID_MARGIN`` of the span; 0 for an unbounded
    range).
    """

    u_min: float
    u_max: float
    margin_share: float = PID_MARGIN

    def __post_init__(self) -> None:
        if math.isnan(self.u_min) or math.isnan(self.u_max) or not self.u_min < self.u_max:
            raise VoltageRangeError(f"need u_min < u_max, got [{self.u_min}, {self.u_max}]")
        if not 0.0 <= self.margin_share < 0.5:
            raise VoltageRangeError(f"margin_share must be in [0, 0.5), got {self.margin_share}")

    @property
    def margin(self) -> float:
        """[V] kept free at each end for the PID."""
        span = self.u_max - self.u_min
        return self.margin_share * span if math.isfinite(span) else 0.0

    @property
    def usable(self) -> tuple[float, float]:
        """[u_min + margin, u_max − margin]: where a need is admitted."""
        return self.u_min + self.margin, self.u_max - self.margin

    def admits(self, need: VoltageNeed) -> bool:
        """Whether ``need`` lies within :attr:`usable`."""
        low, high = self.usable
        return low <= need.low and need.high <= high


def largest_amplitude(
    model: FeedforwardModel,
    trajectory_at: Callable[[float], Trajectory],
    amplifier: AmplifierRange,
    upper: float,
    tolerance: float = AMPLITUDE_TOLERANCE,
) -> float:
    """The largest amplitude in (0, ``upper``] whose trajectory (``trajectory_at(amplitude)``, at
    a fixed offset) ``amplifier`` admits, to ``tolerance``·upper below the exact one (bisection;
    the need grows with the amplitude); 0.0 when not even ``tolerance``·upper is admitted.
    """
    if not (math.isfinite(upper) and upper > 0):
        raise VoltageRangeError(f"upper must be a finite amplitude > 0, got {upper}")

    def admitted(amplitude: float) -> bool:
        return amplifier.admits(voltage_need(model, trajectory_at(amplitude)))

    if admitted(upper):
        return upper
    lo, hi = tolerance * upper, upper
    if not admitted(lo):
        return 0.0
    while hi - lo > tolerance * upper:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if admitted(mid) else (lo, mid)
    return lo
