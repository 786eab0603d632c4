"""The rig loop's step, without ROS: one block of sensor samples → the law on each (with its
supervision) → one amplifier write → a row per sample for the batch; and the tick of a read
that timed out (the sensor's silence: hold, or open the loop beyond ``max_gap``).

:class:`RigLoop` drives two ports: the law (the controller's ``on_sample``/``check_gap``:
:class:`~piezo_stage.control.supervision.LoopSupervisor` around
:class:`~piezo_stage.control.controller.TimeVaryingPID`) and the amplifier (the driver's
``command``: every safety rule of :class:`~piezo_stage.hardware.driver.VoltageDriver`). The
composed ROS process (:mod:`piezo_stage.nodes.rig_loop`) gives it its nodes; a test gives it
plain objects.
"""

from __future__ import annotations

import math
from typing import Callable, Protocol

from .controller import ControlOutput
from .supervision import LoopSupervisor

#: one row of LoopSamples per sample: stamp [ns], displacement, status, reference, u, u_ff,
#: loop_closed (the applied voltage is the block's)
Row = tuple[int, float, int, float, float, float, bool]


class Law(Protocol):
    """The supervised law the loop steps."""

    @property
    def last_step(self) -> ControlOutput | None:
        """The law's output of the last :meth:`on_sample`, None when it did not step."""

    def on_sample(self, stamp_ns: int, x: float, ok: bool, publish: bool) -> float | None:
        """One sample → the voltage to write now (None: nothing to write)."""

    def check_gap(self, t: float) -> float | None:
        """A tick without a sample at ``t`` [s] → the voltage to write now, or None."""


class Amplifier(Protocol):
    """The amplifier the loop writes."""

    @property
    def last_sent(self) -> float:
        """The voltage last written [V]."""

    def command(self, voltage: float, publish: bool = True) -> None:
        """Write ``voltage`` (within the driver's limits and slew; the watchdog counts from
        now); ``publish`` False: not on the per-sample topics.
        """


class TopicDecimation:
    """Which samples go on the per-sample topics: every ``every``-th, ``every`` the smallest
    that keeps them at or below ``topics_rate`` [Hz] for a ``sample_rate`` [Hz] stream.
    """

    def __init__(self, sample_rate: float, topics_rate: float) -> None:
        self.every = max(1, math.ceil(sample_rate / topics_rate - 1e-9))
        self._count = 0

    def due(self, n: int) -> list[bool]:
        """Of the next ``n`` samples, those due."""
        count, every = self._count, self.every
        self._count = count + n
        return [k % every == 0 for k in range(count, count + n)]


class RigLoop:
    """The step of the composed loop: :meth:`step` for each block of samples the sensor link
    delivered, :meth:`idle` for each read that timed out. ``rows(block, applied)`` takes the
    block's rows and the voltage applied after it; ``after()`` runs after every write or idle
    tick (the hand-off's drain: publishing where the loop has the most time); ``supervisor``
    counts the outputs never written.
    """

    def __init__(
        self,
        law: Law,
        amplifier: Amplifier,
        supervisor: LoopSupervisor,
        topics: TopicDecimation,
        rows: Callable[[list[Row], float], None],
        after: Callable[[], None],
    ) -> None:
        self.law, self.amplifier, self.supervisor, self.topics = law, amplifier, supervisor, topics
        self._rows, self._after = rows, after

    def step(self, value: list[float], status: list[int], stamp: list[int]) -> list[bool] | None:
        """The law steps on every sample (status 0: valid); the amplifier gets the newest
        output once (the samples of one read arrived together: the older outputs are already
        superseded, and counted). Returns which samples the per-sample topics take (None:
        all).
        """
        law, nan = self.law, math.nan
        due = self.topics.due(len(value))
        u, outputs = None, 0
        rows: list[Row] = []
        for x, st, ns, publish in zip(value, status, stamp, due):
            out = law.on_sample(ns, x, st == 0, publish)
            if out is not None:
                u, outputs = out, outputs + 1
            step = law.last_step
            rows.append(
                (ns, x, st, nan, nan if out is None else out, 0.0, False)
                if step is None or out is None
                else (ns, x, st, step.reference, out, step.u_ff, step.loop_closed)
            )
        if u is not None:
            self.amplifier.command(u, publish=due[-1])
            self.supervisor.superseded += outputs - 1
        self._rows(rows, self.amplifier.last_sent)
        self._after()
        return None if self.topics.every == 1 else due

    def idle(self, now_ns: int) -> None:
        """A read that timed out at ``now_ns``: hold, or open the loop past ``max_gap``."""
        u = self.law.check_gap(now_ns * 1e-9)
        if u is not None:
            self.amplifier.command(u)
        self._after()
