"""Where a loop's set point comes from: yr, ẏr, ÿr at each step.

``topic`` (the last value given to :meth:`SetPoint.receive`, ẏr unknown), ``second_order`` (the
thesis's yr of §11.4.1, started at the first step), ``constant`` (``reference``) or
``trajectory`` (x_d of :mod:`.trajectory` in closed form, time from the first step; a node then
publishes x_d as the reference recorders see).
"""

from __future__ import annotations

import enum
import math

from .reference import SecondOrderReference
from .trajectory import Trajectory

#: a set point at one instant: (yr [m], ẏr [m/s] or None when unknown, ÿr [m/s²])
Reference = tuple[float, float | None, float]


class ReferenceSource(str, enum.Enum):
    """Where :class:`SetPoint` takes yr from (see the module docstring)."""

    TOPIC = "topic"  # the reference topic
    SECOND_ORDER = "second_order"  # the thesis's yr
    CONSTANT = "constant"  # the reference parameter
    TRAJECTORY = "trajectory"  # x_d of the trajectory_* parameters, published on reference


class SetPoint:
    """yr(t) from ``source`` (see the module docstring); ``source`` and ``reference`` may change
    between steps.
    """

    def __init__(
        self,
        source: ReferenceSource,
        reference: float = 0.0,
        *,
        trajectory: Trajectory | None = None,
        y0: float = 20e-6,
        ydot0: float = 0.0,
    ) -> None:
        self.source = ReferenceSource(source)
        self.reference = float(reference)  # the constant set point [m]
        self.received = float(reference)  # the last value from the topic [m]
        self.trajectory = trajectory
        self._y0, self._ydot0 = y0, ydot0
        self._second_order: SecondOrderReference | None = None
        self._t_trajectory: float | None = None  # the trajectory's time origin: its first step

    def start_at(self, t: float) -> None:
        """Start the trajectory's time at ``t`` [s] (default: the first step's time); several
        axes given one origin run their trajectories in step.
        """
        if self._t_trajectory is None:
            self._t_trajectory = float(t)

    def receive(self, value: float) -> None:
        """A set point from the topic (ignored unless finite)."""
        if math.isfinite(value):
            self.received = float(value)

    @property
    def publishes(self) -> bool:
        """True when the set point is generated here (trajectory): recorders need it published."""
        return self.source is ReferenceSource.TRAJECTORY and self.trajectory is not None

    def evaluate(self, t: float) -> Reference:
        """(yr, ẏr or None when unknown, ÿr) at time ``t`` [s]."""
        source = self.source
        if source is ReferenceSource.SECOND_ORDER:
            if self._second_order is None:
                self._second_order = SecondOrderReference(y0=self._y0, ydot0=self._ydot0, t_start=t)
            return self._second_order.at(t)
        if source is ReferenceSource.TRAJECTORY and self.trajectory is not None:
            if self._t_trajectory is None:
                self._t_trajectory = t
            return self.trajectory.at(t - self._t_trajectory)
        if source is ReferenceSource.CONSTANT:
            return self.reference, 0.0, 0.0
        return self.received, None, 0.0
