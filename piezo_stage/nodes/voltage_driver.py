"""`voltage_driver` node: the amplifier (PI GCS2 or Thorlabs MDT69x) behind ``voltage_command``.

Same topics, types, units and QoS as the simulated ``plant`` (docs/design.md §3): subscribes
``voltage_command`` (COMMAND_QOS), publishes ``voltage`` (SENSOR_QOS: the value the device
acknowledged, stamped when it was sent — before the ``ERR?`` round trip that confirms it — and
the device read-back every 1/readback_rate_hz s) and ``/diagnostics``. Every safety rule lives in
:class:`piezo_stage.hardware.driver.VoltageDriver`
(limits = configured ∩ device, slew rate, watchdog, safe shutdown, reconnect); this node adds
only what needs the ROS clock:

- a command with a non-finite voltage is rejected here and counted (it never reaches the core);
- with ``max_command_age`` > 0 a command whose header stamp is older than that w.r.t. the node
  clock (unstamped commands included) is late and rejected;
- ``apply_at_stamp`` (open-loop excitation, e.g. identification runs): each command is applied at
  its header stamp + ``command_delay`` by :class:`piezo_stage.hardware.timing.CommandPlayout`
  (its own thread, SCHED_FIFO at ``realtime_priority`` when allowed) instead of on arrival, so
  the applied waveform is the commanded one shifted by a constant delay and not warped by the
  transport's variable latency (the identifier cuts periods on the time axis). The excitation
  node stamps its commands ``lead`` seconds ahead for this (then ``command_delay`` = 0 keeps its
  run marks aligned with the applied voltage). Commands arriving after their time are applied at
  once and counted (``late_playout`` on /diagnostics). ``hold_period`` > 0 fills the intervals
  between queued commands with linearly interpolated values every ``hold_period`` s (a
  first-order hold; every value written is published on ``voltage``). Off (the default, and what
  a closed loop needs): on arrival;
- ``tick()`` (the watchdog) runs on a steady wall-clock timer, so a stalled ``/clock`` cannot
  keep the amplifier at its last voltage;
- SIGINT/SIGTERM: ``on_shutdown()`` ramps to ``safe_voltage`` and leaves the amplifier in open
  loop there (``VoltageDriver.shutdown``), publishing the final read-back.
"""

from __future__ import annotations

import math
import sys
import threading
from typing import Sequence

from rclpy.parameter import Parameter

from piezo_stage.hardware import (
    DriverState,
    HardwareError,
    NonFiniteVoltageError,
    VoltageDriver,
    make_amplifier,
)
from piezo_stage.hardware.amplifier import AMPLIFIERS
from piezo_stage.hardware.errors import CommandExpired
from piezo_stage.hardware.stamps import StampPolicy
from piezo_stage_msgs.msg import Voltage

from .axis_inlet import AxisInlet, Playout, Rejection, check_apply_at_stamp, start_playout
from .base import PiezoNode
from .diagnostics import ERROR, OK, WARN, Diagnosis, Diagnostics
from .driver_config import driver_config
from .handoff import Handoff
from .parameters import on_set
from .qos import COMMAND_QOS, SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run, set_stamp, stamp_clock, wall_clock
from .settings import VoltageDriverSettings
from .spec import Param, ParameterTable

PARAMETERS = ParameterTable(
    "voltage_driver",
    (
        Param(
            "backend",
            "gcs",
            "amplifier protocol: gcs (PI E-709/E-625/E-727) or mdt69x (Thorlabs)",
            choices=tuple(AMPLIFIERS),
            read_only=True,
        ),
        Param(
            "url",
            "tcp://127.0.0.1:50000",
            "link: tcp://host:port, /dev/ttyUSB0, serial:///dev/ttyUSB0?baudrate=115200",
            read_only=True,
        ),
        Param(
            "baud",
            0,
            "serial baud rate (0: the backend's default)",
            range=(0, 4_000_000),
            read_only=True,
        ),
        Param(
            "axis",
            "",
            "GCS axis (empty: the first SAI? lists) or MDT69x channel x|y|z (empty: x)",
            read_only=True,
        ),
        Param(
            "channel", 1, "GCS piezo output channel (VOL?/VMA?/VMI?)", range=(1, 64), read_only=True
        ),
        Param(
            "error_pipeline",
            0,
            "GCS: ERR? replies that may be outstanding (0: each write waits "
            "for its ERR?; rig_loop: the loop does not wait for the device's round trip, and a "
            "refused write is reported at most this many writes late)",
            range=(0, 64),
            read_only=True,
        ),
        Param(
            "io_timeout",
            0.5,
            "reply timeout of one device exchange",
            "s",
            (0.01, 10.0),
            read_only=True,
        ),
        Param(
            "v_min",
            0.0,
            "configured lower limit (intersected with the device's)",
            "V",
            read_only=True,
        ),
        Param(
            "v_max",
            100.0,
            "configured upper limit (intersected with the device's)",
            "V",
            read_only=True,
        ),
        Param(
            "safe_voltage",
            0.0,
            "voltage after a watchdog timeout and on shutdown",
            "V",
            read_only=True,
        ),
        Param(
            "slew_rate",
            0.0,
            "slew-rate limit (0: none); one write steps at most slew_rate x "
            "min(watchdog_period, 25 ms), longer moves are ramps",
            "V/s",
            (0.0, 1e9),
            read_only=True,
        ),
        Param(
            "command_timeout",
            0.5,
            "watchdog: ramp to safe_voltage after this long without a command (0: off)",
            "s",
            (0.0, 3600.0),
            read_only=True,
        ),
        Param(
            "watchdog_period",
            0.01,
            "period of the watchdog timer (wall clock), which also writes the steps of a ramp",
            "s",
            (1e-3, 1.0),
            read_only=True,
        ),
        Param(
            "readback_rate_hz",
            20.0,
            "rate of the device read-back published on voltage (0: off)",
            "Hz",
            (0.0, 1000.0),
            read_only=True,
        ),
        Param(
            "max_command_age",
            0.0,
            "reject commands stamped longer ago than this w.r.t. the node clock (0: off)",
            "s",
            (0.0, 3600.0),
            read_only=True,
        ),
        Param(
            "max_stamp_ahead",
            5.0,
            "reject commands stamped further ahead of the node clock than "
            "this (a foreign or broken clock)",
            "s",
            (1e-3, 3600.0),
            read_only=True,
        ),
        Param(
            "apply_at_stamp",
            False,
            "apply each command at its stamp + command_delay (wall clock) "
            "instead of on arrival: open-loop runs without the transport's latency jitter",
            read_only=True,
        ),
        Param(
            "command_delay",
            0.0,
            "with apply_at_stamp: added to the stamps",
            "s",
            (0.0, 10.0),
            read_only=True,
        ),
        Param(
            "hold_period",
            0.0,
            "with apply_at_stamp: write values interpolated between queued "
            "commands every hold_period s (first-order hold; 0: hold each command)",
            "s",
            (0.0, 1.0),
            read_only=True,
        ),
        Param(
            "realtime_priority",
            0,
            "SCHED_FIFO priority of the apply_at_stamp playout thread and of "
            "the executor's thread, and in rig_loop of the loop thread (1-99, when the system "
            "allows it; 0: normal)",
            range=(0, 99),
            read_only=True,
        ),
        Param(
            "reconnect_attempts",
            3,
            "tries to reopen a dropped link per attempt round (in a "
            "background thread, every round until it is back; 0: never)",
            range=(0, 100),
            read_only=True,
        ),
    ),
    summary="Piezo amplifier driver (PI GCS2, Thorlabs MDT69x): voltage_command -> device, "
    "with limits, slew and watchdog.",
    settings_type=VoltageDriverSettings,
)


class VoltageDriverNode(PiezoNode):
    """With a ``handoff``: part of the rig loop (:mod:`.rig_loop`), whose loop thread calls
    :meth:`command` directly; no voltage_command subscription (the controller in the same
    process still publishes the topic), every publication through ``handoff``."""

    def __init__(self, handoff: Handoff | None = None, overrides: Sequence[Parameter] = ()) -> None:
        super().__init__(
            "voltage_driver", namespace=DEFAULT_NAMESPACE, parameter_overrides=list(overrides)
        )
        self._handoff = handoff
        p: VoltageDriverSettings = self.declare_settings(PARAMETERS)
        if p.apply_at_stamp:
            check_apply_at_stamp(self, "rig_loop" if handoff is not None else "")

        amplifier = make_amplifier(
            p.backend,
            p.url,
            axis=p.axis or None,
            channel=p.channel,
            timeout=p.io_timeout,
            baudrate=p.baud or None,
            pipeline=p.error_pipeline,
        )
        self.driver = VoltageDriver(amplifier, driver_config(p))
        self.max_age = float(p.max_command_age)
        self.stamps = StampPolicy(
            self.max_age, p.max_stamp_ahead, require_stamp=self.max_age > 0 or p.apply_at_stamp
        )
        # the limits and safety settings are read-only in the table; so is the clock they use
        on_set(
            self,
            lambda changed: (
                "use_sim_time is fixed at start (the stamp checks and the watchdog depend on it)"
                if "use_sim_time" in changed
                else None
            ),
        )
        self._now_ns = stamp_clock(self)
        self.url = p.url
        self.info = self.driver.connect()
        self.inlet = AxisInlet(
            "",
            self.get_logger(),
            self.stamps,
            self._apply,
            self._received,
            lambda: self.driver.last_sent,
            self.info.applied,
        )
        self._link_errors = 0
        self._watchdog_trips = 0
        self._last_error = ""
        self._lock = threading.Lock()  # commands come from the executor or from the playout thread
        self._playouts = Playout()
        if p.apply_at_stamp:
            playout = self.inlet.playout = start_playout(self._apply, p, self._playouts)
            self.driver.on_timeout.append(playout.clear)  # the watchdog owns the output

        self._pub = self.create_publisher(Voltage, "voltage", SENSOR_QOS)
        self._msg = Voltage()
        if handoff is None:
            self.create_subscription(Voltage, "voltage_command", self._on_command, COMMAND_QOS)
        self.create_timer(p.watchdog_period, self._watchdog, clock=wall_clock())
        # composed: the loop thread reads back right after a write, when one is due (a timer's
        # device round trip would hold the driver while a sample waits to be answered)
        self._readback_period = 1.0 / p.readback_rate_hz if p.readback_rate_hz > 0 else math.inf
        self._readback_due = 0.0 if p.readback_rate_hz > 0 else math.inf  # 0: never
        if p.readback_rate_hz > 0 and handoff is None:
            self.create_timer(self._readback_period, self._readback, clock=wall_clock())
        self._diagnostics = Diagnostics(self, f"{p.backend} {self.url}", self._diagnose)
        self._reported_down = False
        lim = self.driver.limits
        assert lim is not None  # set by driver.connect() above, never unset
        self.get_logger().info(
            f"{self.info.identity} axis {self.info.axis} on {self.url}: limits "
            f"[{lim.v_min:g}, {lim.v_max:g}] V, output {self.info.applied:g} V"
        )

    # ------------------------------------------------------------------ commands
    def _on_command(self, msg: Voltage) -> None:
        self.inlet.on_command(msg, self.get_clock().now().nanoseconds * 1e-9)

    def _received(self) -> float:
        """A command arrived: the watchdog counts from now (the driver's clock)."""
        received = self.driver.clock()
        self.driver.command_received(received)
        return received

    @property
    def last_sent(self) -> float:
        """The voltage last written to the device [V]."""
        return self.driver.last_sent

    def command(self, voltage: float, publish: bool = True) -> None:
        """A command from the composed loop (its own thread): the watchdog counts from now; the
        device read-back follows the write when one is due (``publish`` False: the value
        written is not published on ``voltage``)."""
        received = self._received()
        self._apply(voltage, True, received, publish)
        if received >= self._readback_due:
            self._readback_due = received + self._readback_period
            self._readback()

    def _apply(
        self,
        voltage: float,
        command: bool = True,
        received: float | None = None,
        publish: bool = True,
    ) -> None:
        """Send one accepted command (from the executor, or from the playout thread when due) and
        publish it; ``command`` False: a value the playout interpolated, sent and published too
        (``voltage`` is what the device applies, stamped when applied: the identification reads it
        as held values)."""
        with self._lock:
            if not command:
                sent_at = self._now_ns()
                try:
                    result = self.driver.set_voltage(voltage, received)
                except CommandExpired:
                    return
                except HardwareError as exc:
                    self._link_error(exc)
                    return
                self._publish(result.sent, sent_at)
                return
            self.inlet.last_command = voltage
            sent_at = self._now_ns()  # applied when the device gets it, not after ERR?
            try:
                result = self.driver.set_voltage(voltage, received)
            except NonFiniteVoltageError as exc:  # not after the check above; kept for safety
                self.inlet.reject(Rejection.NONFINITE, str(exc))
                return
            except CommandExpired as exc:  # queued before the watchdog fired
                self.inlet.reject(Rejection.EXPIRED, str(exc))
                return
            except HardwareError as exc:
                self._link_error(exc)
                return
            self.inlet.wrote(result)
            if publish:
                self._publish(result.sent, sent_at)
            else:
                self.inlet.applied = result.sent

    def _link_error(self, exc: Exception) -> None:
        self._link_errors += 1
        self._last_error = str(exc)
        self.get_logger().error(f"amplifier link: {exc}", throttle_duration_sec=1.0)
        if not self.driver.connected and not self._reported_down:
            self._reported_down = True
            self._diagnostics.publish()  # ERROR now, not at the next period

    # ------------------------------------------------------------------ timers
    def _watchdog(self) -> None:
        # under the command lock: the playout or the loop thread may be between a write and its
        # publication, which the comparison below would take for a ramp step and publish twice
        with self._lock:
            trips = self.driver.trips
            try:
                state = self.driver.tick()
            except HardwareError as exc:
                self._link_error(exc)
                return
            if (
                self.driver.last_sent != self.inlet.applied
                and state is not DriverState.DISCONNECTED
            ):
                self._publish(self.driver.last_sent)  # a step of a ramp (toward a command or safe)
        if self.driver.trips != trips:
            self._watchdog_trips = self.driver.trips
            self.get_logger().warn(
                "no voltage command for "
                f"{self.driver.config.command_timeout:g} s: "
                f"ramping to {self.driver.config.safe_voltage:g} V"
            )

    def _readback(self) -> None:
        if not self.driver.connected:
            return  # the watchdog reopens the link
        try:
            self._publish(self.driver.read_voltage())
        except HardwareError as exc:
            self._link_error(exc)

    def _publish(self, voltage: float, stamp: int | None = None) -> None:
        """Publish an applied voltage, stamped [ns] when it was sent (default: now)."""
        self.inlet.applied = voltage
        stamp = self._now_ns() if stamp is None else stamp
        if self._handoff is None:
            self._send(voltage, stamp)
        else:
            self._handoff.put(self._send, voltage, stamp)

    def _send(self, voltage: float, stamp: int) -> None:
        msg = self._msg  # reused: rclpy serializes at publish
        set_stamp(msg.header, stamp)
        msg.voltage = voltage
        self._pub.publish(msg)

    # ------------------------------------------------------------------ health, shutdown
    def _diagnose(self) -> Diagnosis:
        d = self.driver
        lim = d.limits
        assert lim is not None  # set by driver.connect() in __init__, never unset
        values = {
            "state": d.state.value,
            "connected": d.connected,
            "identity": self.info.identity,
            "axis": self.info.axis,
            "v_min": lim.v_min,
            "v_max": lim.v_max,
            "safe_voltage": d.config.safe_voltage,
            "last_sent": d.last_sent,
            **self.inlet.values(),
            "watchdog_trips": self._watchdog_trips,
            "rejected_expired": d.expired,
            "device_writes": d.writes,
            "reconnects": d.reconnects,
            "link_errors": self._link_errors,
            "last_error": self._last_error or d.last_link_error,
        }
        if self.inlet.playout is not None:
            values["executor_priority"] = (
                self._playouts.executor_priority or self.settings.realtime_priority
            )
        self._reported_down = not d.connected
        if not d.connected:
            return Diagnosis(ERROR, f"disconnected from {self.url}", values)
        rejected, text = self.inlet.refused(d.expired)
        if rejected or d.state in (DriverState.TIMED_OUT, DriverState.SAFE):
            return Diagnosis(WARN, f"{d.state.value}; {text}", values)
        return Diagnosis(OK, d.state.value, values)

    def on_shutdown(self) -> None:
        """Ramp to safe_voltage at the slew rate and leave the amplifier there (open loop)."""
        self._playouts.stop()  # queued commands are dropped: the ramp owns the output now
        applied = self.driver.shutdown()  # SafeStateNotReached: run() exits 1 with the reason
        self._publish(applied)
        if self._handoff is not None:
            self._handoff.drain()  # the executor no longer spins: publish what is left now
        self.get_logger().info(
            f"shut down at {applied:g} V (safe_voltage {self.driver.config.safe_voltage:g} V)"
        )


def main(args: list[str] | None = None) -> int:
    return run(VoltageDriverNode, args)


if __name__ == "__main__":
    sys.exit(main())
