"""The composed loop of a stage of N >= 1 axes, without ROS: every axis of one amplifier (a
multi-channel one, or a single channel for a stage of one) in one thread, one write per sensor
cycle (docs/design.md §10).

Per cycle each axis's :class:`Law` steps on every sample the axis brought, oldest first, one
sub-cycle (:meth:`StageLoop.step`) per sample, or, when the axis brought none this
(sub-)cycle, gets the tick of its silence (``check_gap``: within ``max_gap`` the axis holds,
beyond it its loop opens). After the last sub-cycle, the newest output of every axis that has
one leaves in one :meth:`~piezo_stage.hardware.stage_driver.StageDriver.set_voltages` call (GCS
``SVA 1 a 2 b 3 c``), where each axis's safety rules apply; the older outputs of the cycle are
superseded, and counted; an axis without an output is left out of the write and its amplifier
channel keeps its last voltage. :class:`SupervisedLaw` is such a law from core pieces alone
(:class:`~.supervision.LoopSupervisor` and a :class:`~.setpoint.SetPoint`);
:func:`run_stage_loop` is the loop thread over the sensors' cycles
(:class:`~piezo_stage.hardware.stage_sensors.StageSensors`, or for one axis
:class:`~piezo_stage.hardware.axis_sensor.AxisSensor`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Callable, Protocol

from piezo_stage.hardware.errors import HardwareError

from .controller import ControlOutput
from .setpoint import SetPoint
from .supervision import Gap, LoopSupervisor

__all__ = [
    "Cycles",
    "Law",
    "Row",
    "StageAmplifier",
    "StageLoop",
    "StageOrigin",
    "SupervisedLaw",
    "publish_every",
    "run_stage_loop",
]

#: one row of LoopSamples per sample: stamp [ns], displacement, status, reference, u, u_ff,
#: loop_closed (the applied voltage is the cycle's)
Row = tuple[int, float, int, float, float, float, bool]


class Law(Protocol):
    """One axis's supervised law, as the loop steps it."""

    #: outputs never written: a newer one of the same cycle replaced them
    superseded: int

    @property
    def last_step(self) -> ControlOutput | None:
        """The law's output of the last :meth:`on_sample`, None when it did not step."""

    def on_sample(self, stamp_ns: int, x: float, ok: bool, publish: bool = True) -> float | None:
        """One sample → the voltage to write (None: nothing to write)."""

    def check_gap(self, t: float) -> float | None:
        """A tick without a sample at ``t`` [s] → the voltage to write, or None."""


def publish_every(sample_rate: float, topics_rate: float) -> int:
    """Every how many samples the per-sample topics take one: the smallest N that keeps them at
    or below ``topics_rate`` [Hz] for a ``sample_rate`` [Hz] stream.
    """
    return max(1, math.ceil(sample_rate / topics_rate - 1e-9))


class StageAmplifier(Protocol):
    """The multi-channel amplifier (:class:`~piezo_stage.hardware.stage_driver.StageDriver`)."""

    def set_voltages(self, values: Mapping[str, float]) -> object:
        """Write every named axis in one device command, each with its own safety rules."""


#: a (sub-)cycle's hook before the laws step: (value, status, stamp [ns], fresh, now [ns],
#: last: the cycle's last sub-cycle, where every fresh axis holds its newest sample)
Before = Callable[[Sequence[float], Sequence[int], Sequence[int], Sequence[bool], int, bool], None]


class Cycles(Protocol):
    """The sensors' side of the loop (:class:`~piezo_stage.hardware.stage_sensors.StageSensors`):
    per axis every sample of the cycle, one sub-cycle at a time, and whether the axis has one.
    """

    value: list[float]
    status: list[int]
    stamp: list[int]
    fresh: list[bool]

    def wait(self, timeout: float) -> bool:
        """Block until a cycle is due (True) or ``timeout`` s passed without one (False)."""

    def depth(self) -> int:
        """The due cycle's sub-cycles (the most samples an axis brought)."""

    def take(self, j: int, depth: int) -> None:
        """Sub-cycle ``j`` of ``depth`` into value, status, stamp, fresh."""

    def next_cycle(self) -> None:
        """The cycle was taken: no axis is fresh any more."""

    def now_ns(self) -> int:
        """Now [ns], on the clock of the stamps (a gap is now less an axis's newest stamp)."""


class StageOrigin:
    """The one time origin [ns] of a stage's trajectories and tables (``ns``, None until
    :meth:`start`): the earliest of the newest samples of the axes fresh in the starting cycle's
    last sub-cycle, the first sample stepped. Each axis steps from its first sample at or after
    it (:meth:`steps`): an axis whose samples arrive late still has older ones to come, and a
    scan's record holds its origin only if no stepped sample precedes it.
    """

    def __init__(self) -> None:
        self.ns: int | None = None

    def start(self, stamp: Sequence[int], fresh: Sequence[bool]) -> int:
        """Start at the earliest ``stamp`` of the ``fresh`` axes (at least one is)."""
        self.ns = min(s for s, f in zip(stamp, fresh) if f)
        return self.ns

    def steps(self, stamp_ns: int) -> bool:
        """A sample stamped ``stamp_ns`` is stepped (the stage started at or before it)."""
        return self.ns is not None and stamp_ns >= self.ns


class SupervisedLaw:
    """One axis's supervised law: :class:`LoopSupervisor` around its PID, the set point from
    ``setpoint``; the voltage to write (``u_bias`` added, within the amplifier's limits), or the
    hold voltage while the loop is open (as the controller node's ``on_sample``).
    """

    def __init__(self, supervisor: LoopSupervisor, setpoint: SetPoint) -> None:
        self.supervisor, self.setpoint = supervisor, setpoint
        self.last_step: ControlOutput | None = None

    @property
    def superseded(self) -> int:
        """Outputs never written (the supervisor's count)."""
        return self.supervisor.superseded

    @superseded.setter
    def superseded(self, n: int) -> None:
        self.supervisor.superseded = n

    def on_sample(self, stamp_ns: int, x: float, ok: bool, publish: bool = True) -> float | None:
        """One sample taken at ``stamp_ns`` → the voltage to write now (None: none yet)."""
        t = stamp_ns * 1e-9
        self.last_step = None
        sup = self.supervisor
        if not sup.sample(t, x, ok):
            return sup.hold_command()
        yr, yr_dot, yr_ddot = self.setpoint.evaluate(t)
        out = self.last_step = sup.step(t, yr, yr_dot, yr_ddot)
        return sup.command(out)

    def check_gap(self, t: float) -> float | None:
        """A tick without a sample at ``t`` [s]: the hold voltage once the loop opened, else
        None (the output holds).
        """
        sup = self.supervisor
        return sup.hold_command() if sup.check_gap(t) is Gap.OPENED else None


class StageLoop:
    """The step of the stage's loop (module docstring): ``laws[i]`` drives ``axes[i]``.
    ``before(value, status, stamp, fresh, now_ns, last)`` runs before the laws of each (sub-)cycle
    step (the stage's start; a coupled stage's own frames, from every axis at once; None once
    there is nothing left to do there); ``after()`` after every write
    and idle tick (a node's hand-off drain); ``every``: the laws' ``publish`` flag is True on
    every ``every``-th step.
    """

    def __init__(
        self,
        axes: Sequence[str],
        laws: Sequence[Law],
        amplifier: StageAmplifier,
        after: Callable[[], None] | None = None,
        every: int = 1,
        before: Before | None = None,
    ) -> None:
        if len(axes) != len(laws) or not axes:
            raise ValueError(f"one law per axis: {len(axes)} axes, {len(laws)} laws")
        self.axes, self.laws, self.amplifier = tuple(axes), tuple(laws), amplifier
        self._after, self.before = after, before
        self.every = max(1, int(every))
        self.cycles = 0  # cycles written
        self.steps = 0  # (sub-)cycles stepped
        self.write_failures = 0  # cycles whose write failed on the link (the driver reconnects)
        self.last_error: HardwareError | None = None
        self._values: dict[str, float] = {}
        self._pairs = tuple(zip(self.axes, self.laws))

    def step(
        self,
        value: Sequence[float],
        status: Sequence[int],
        stamp: Sequence[int],
        fresh: Sequence[bool],
        now_ns: int,
        write: bool = True,
    ) -> None:
        """One cycle at ``now_ns`` (the sensors' clock): axis i steps on (``value[i]``,
        ``status[i]`` (0: valid), ``stamp[i]``) when ``fresh[i]``, else checks its gap; every
        output goes out in one write (``write`` False: a sub-cycle, its outputs kept for the
        cycle's write, where a newer one of the same axis replaces them).
        """
        publish = self.steps % self.every == 0
        self.steps += 1
        if self.before is not None:
            self.before(value, status, stamp, fresh, now_ns, write)
        values, t = self._values, now_ns * 1e-9
        for i, (axis, law) in enumerate(self._pairs):
            if fresh[i]:
                u = law.on_sample(stamp[i], value[i], status[i] == 0, publish)
            else:
                u = law.check_gap(t)
            if u is not None:
                if axis in values:
                    law.superseded += 1
                values[axis] = u
        if write:
            self.cycles += 1
            self._write(values)

    def idle(self, now_ns: int) -> None:
        """A wait that brought no cycle: every axis checks its gap (hold, or open)."""
        values, t = self._values, now_ns * 1e-9
        for axis, law in self._pairs:
            u = law.check_gap(t)
            if u is not None:
                values[axis] = u
        self._write(values)

    def _write(self, values: dict[str, float]) -> None:
        if values:
            try:
                self.amplifier.set_voltages(values)
            except HardwareError as exc:  # every axis of the command is down: it reconnects
                self.write_failures += 1
                self.last_error = exc
            values.clear()
        if self._after is not None:
            self._after()


class Stopping(Protocol):
    """What ends a loop thread: a ``threading.Event``, or a flag a signal handler sets."""

    def is_set(self) -> bool: ...


def run_stage_loop(sensors: Cycles, loop: StageLoop, stop: Stopping, poll: float = 0.005) -> None:
    """The loop thread: each due cycle → :meth:`StageLoop.step` on each of its sub-cycles,
    oldest first (every sample of every axis stepped, one write after the last), each ``poll``
    s without one → :meth:`StageLoop.idle`, until ``stop`` is set.
    """
    clock_ns = sensors.now_ns
    wait, next_cycle, step, idle = sensors.wait, sensors.next_cycle, loop.step, loop.idle
    depth, take = sensors.depth, sensors.take
    value, status, stamp, fresh = sensors.value, sensors.status, sensors.stamp, sensors.fresh
    while not stop.is_set():
        if wait(poll):
            now, n = clock_ns(), depth()
            for j in range(n):
                take(j, n)
                step(value, status, stamp, fresh, now, j == n - 1)
            next_cycle()
        else:
            idle(clock_ns())
