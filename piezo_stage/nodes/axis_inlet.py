"""One axis's command inlet in ``voltage_driver`` (its one axis, or each axis of its stage):
what a ``voltage_command`` passes before it reaches the axis's driver, the counters of what was
refused, and the play-out of ``apply_at_stamp``.

A command is refused here, counted and logged (once a second per kind), and never written when
its voltage is not finite, when it is older than ``max_command_age`` (late) or when its stamp is
one the :class:`~piezo_stage.hardware.stamps.StampPolicy` refuses. An accepted one restarts the
axis's watchdog (``received``) and is written at once, or, with a
:class:`~piezo_stage.hardware.timing.CommandPlayout`, at its stamp + ``command_delay``.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

from rclpy.node import Node

from piezo_stage.bag.types import stamp_seconds
from piezo_stage.hardware.driver import SetResult
from piezo_stage.hardware.stamps import StampPolicy, StampVerdict
from piezo_stage.hardware.timing import (
    PLAYOUT_SWITCH_INTERVAL,
    CommandPlayout,
    set_realtime_priority,
    shorten_switch_interval,
)

from .errors import RosParameterError

__all__ = ["AxisInlet", "Playout", "Rejection", "check_apply_at_stamp", "start_playout"]


class Rejection(enum.Enum):
    """Why a voltage command was not applied."""

    NONFINITE = "nonfinite"
    LATE = "late"  # older than max_command_age
    STAMP = "stamp"  # a stamp the StampPolicy refuses
    EXPIRED = "expired"  # received before the watchdog fired


class Logger(Protocol):
    """rclpy's logger, as far as the inlet uses it."""

    def warn(self, message: str, **kwargs: Any) -> Any: ...


#: a command to write: (voltage [V], is a command (False: a value the play-out interpolated),
#: when it was received on the driver's clock)
Apply = Callable[[float, bool, "float | None"], None]


class PlayoutSettings(Protocol):
    """The settings fields of ``apply_at_stamp`` (voltage_driver's table)."""

    @property
    def command_delay(self) -> float: ...
    @property
    def hold_period(self) -> float: ...
    @property
    def realtime_priority(self) -> int: ...
    @property
    def max_stamp_ahead(self) -> float: ...


@dataclass
class Playout:
    """The play-outs of a node's axes and what their priority settings met."""

    playouts: list[CommandPlayout] = field(default_factory=list)
    executor_priority: str | None = None  # why the executor's thread has no SCHED_FIFO

    def stop(self) -> None:
        """Drop every queue and end the threads (the shutdown ramp owns the outputs)."""
        for playout in self.playouts:
            playout.stop()


def check_apply_at_stamp(node: Node, loop: str) -> None:
    """Refuse (:class:`RosParameterError`) ``apply_at_stamp`` where it cannot work: in a
    composed ``loop`` (its laws' outputs are written as they are computed) or under
    ``use_sim_time`` (the play-out waits on the wall clock)."""
    name = node.get_name()
    if loop:
        raise RosParameterError(
            f"{name}: apply_at_stamp plays commands that arrive on voltage_command at their "
            f"stamps; in the composed loop ({loop}) the outputs are written as they are "
            "computed: set apply_at_stamp false"
        )
    if node.get_parameter("use_sim_time").value:
        raise RosParameterError(
            f"{name}: apply_at_stamp needs wall-clock stamps: not with use_sim_time"
        )


def start_playout(apply: Apply, s: PlayoutSettings, playout: Playout) -> CommandPlayout:
    """An axis's play-out thread, started, added to ``playout``; the first also raises the
    executor's thread to ``realtime_priority``: the play-out needs the GIL, and a
    normal-priority holder preempted by other processes would stall it for tens of ms."""
    if not playout.playouts:
        shorten_switch_interval(PLAYOUT_SWITCH_INTERVAL)
        playout.executor_priority = set_realtime_priority(s.realtime_priority)
    started = CommandPlayout(
        apply,
        s.command_delay,
        realtime_priority=s.realtime_priority,
        hold_period=s.hold_period,
        max_ahead=max(s.max_stamp_ahead, s.command_delay),
    ).start()
    playout.playouts.append(started)
    return started


class AxisInlet:
    """The inlet of the axis ``label`` names in logs ("" for a node's only axis): ``apply``
    writes an accepted command, ``received()`` restarts the axis's watchdog and returns when
    (the driver's clock), ``last_sent()`` is the voltage the device holds."""

    def __init__(
        self,
        label: str,
        logger: Logger,
        stamps: StampPolicy,
        apply: Apply,
        received: Callable[[], float],
        last_sent: Callable[[], float],
        applied: float,
    ) -> None:
        self.prefix = f"{label}: " if label else ""
        self.logger, self.stamps, self.apply = logger, stamps, apply
        self._received, self._last_sent = received, last_sent
        self.playout: CommandPlayout | None = None
        self.applied = applied  # the voltage last published
        self.last_command = math.nan
        self.commands = 0
        self.clamped = 0
        self.rejected_nonfinite = 0
        self.rejected_late = 0
        self.rejected_stamp = {v.value: 0 for v in StampVerdict if v is not StampVerdict.OK}

    def on_command(self, msg: Any, now: float) -> None:
        """A ``voltage_command`` (a ``Voltage`` message) received at ``now`` [s], node clock."""
        voltage, stamp = msg.voltage, msg.header.stamp
        sec, nanosec = stamp.sec, stamp.nanosec
        if not math.isfinite(voltage):
            self.reject(Rejection.NONFINITE, f"non-finite voltage command {voltage}")
            return
        verdict, age = self.stamps.check(sec, nanosec, now)
        if verdict is StampVerdict.TOO_OLD:
            self.reject(
                Rejection.LATE,
                f"late voltage command ({age:.3g} s old > max_command_age "
                f"{self.stamps.max_age:g} s)",
            )
            return
        if verdict is not StampVerdict.OK:
            self.rejected_stamp[verdict.value] += 1
            self.reject(
                Rejection.STAMP,
                f"voltage command with a {verdict.value} stamp ({sec} s {nanosec} ns)",
            )
            return
        received = self._received()  # the watchdog counts from arrival
        self.last_command = voltage
        if self.playout is not None:
            self.playout.push(stamp_seconds(stamp), voltage, received)
        else:
            self.apply(voltage, True, received)

    def wrote(self, result: SetResult) -> None:
        """A command's write went through (clamped or not)."""
        self.commands += 1
        self.clamped += int(result.clamped)

    def reject(self, kind: Rejection, text: str) -> None:
        """Count (but EXPIRED: the driver counts) and log a refused command."""
        # one log call site per kind: rclpy throttles per call site
        text = f"{self.prefix}rejected {text}: output stays at {self._last_sent():g} V"
        if kind is Rejection.LATE:
            self.rejected_late += 1
            self.logger.warn(text, throttle_duration_sec=1.0)
        elif kind is Rejection.STAMP:  # counted by on_command, per verdict
            self.logger.warn(text, throttle_duration_sec=1.0)
        elif kind is Rejection.EXPIRED:
            self.logger.warn(text, throttle_duration_sec=1.0)
        else:
            self.rejected_nonfinite += 1
            self.logger.warn(text, throttle_duration_sec=1.0)

    def values(self) -> dict[str, Any]:
        """The inlet's /diagnostics values (with its play-out's)."""
        values: dict[str, Any] = {
            "last_command": self.last_command,
            "applied": self.applied,
            "commands": self.commands,
            "clamped_commands": self.clamped,
            "rejected_nonfinite": self.rejected_nonfinite,
            "rejected_late": self.rejected_late,
            **{f"rejected_stamp_{k}": n for k, n in self.rejected_stamp.items()},
        }
        playout = self.playout
        if playout is not None:
            values.update(
                command_delay=playout.delay,
                late_playout=playout.late,
                ahead_playout=playout.ahead,
                pending_playout=playout.pending,
                playout_priority=playout.realtime_error or playout.realtime_priority,
            )
        return values

    def refused(self, expired: int) -> tuple[int, str]:
        """How many commands were refused (``expired``: the driver's count too) and what, for a
        WARN summary."""
        bad_stamps = sum(self.rejected_stamp.values())
        return self.rejected_nonfinite + self.rejected_late + bad_stamps + expired, (
            f"{self.rejected_nonfinite} non-finite, {self.rejected_late} late, {bad_stamps} "
            f"badly stamped and {expired} expired command(s) rejected"
        )
