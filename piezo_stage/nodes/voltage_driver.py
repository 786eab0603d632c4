"""`voltage_driver` node: the amplifier (PI GCS2 or Thorlabs MDT69x) behind ``voltage_command``,
for one axis or for every axis of a stage over one link (docs/design.md §3, §10).

Same topics, types, units and QoS as the simulated ``plant``, per axis: subscribes
``voltage_command`` (COMMAND_QOS), publishes ``voltage`` (SENSOR_QOS: the value the device
acknowledged, stamped when it was sent — before the ``ERR?`` round trip that confirms it — and
the device read-back every 1/readback_rate_hz s) and ``/diagnostics``. Without ``stage_file``
the axis is ``axis`` on output ``channel`` and its topics are unprefixed; with one, the stage
file names the axes and their channels on the device, each axis's topics are in ``<axis>/``,
and ``/diagnostics`` has one status per axis (``<node>/<axis>``) beside the link's. Every safety
rule, per axis, lives in :class:`piezo_stage.hardware.stage_driver.StageDriver` (limits =
configured ∩ device, slew cap between every two writes, watchdog from the axis's own last
command, safe shutdown, reconnect; a stage's writes of one call leave as one device command);
this node adds only what needs ROS:

- a command with a non-finite voltage or a stamp the stamp policy refuses (``max_command_age``,
  ``max_stamp_ahead``) is rejected here and counted (it never reaches the core;
  :mod:`.axis_inlet`);
- ``apply_at_stamp`` (open-loop excitation, e.g. identification runs): each axis's commands are
  applied at their header stamp + ``command_delay`` by
  :class:`piezo_stage.hardware.timing.CommandPlayout` (a thread per axis, SCHED_FIFO at
  ``realtime_priority`` when allowed) instead of on arrival, so the applied waveform is the
  commanded one shifted by a constant delay and not warped by the transport's variable latency
  (the identifier cuts periods on the time axis). The excitation node stamps its commands
  ``lead`` seconds ahead for this. Commands arriving after their time are applied at once and
  counted (``late_playout`` on /diagnostics). ``hold_period`` > 0 fills the intervals between
  queued commands with linearly interpolated values every ``hold_period`` s (a first-order hold;
  every value written is published on ``voltage``). Off (the default, and what a closed loop
  needs): on arrival;
- ``write_rate_hz`` chooses how commands leave: 0, each when accepted or due (that axis alone);
  > 0, the latest command of every axis together, one device command per period (GCS
  ``SVA 1 a 2 b``);
- ``tick()`` (the watchdog) runs on a steady wall-clock timer, so a stalled ``/clock`` cannot
  keep the amplifier at its last voltage;
- SIGINT/SIGTERM: ``on_shutdown()`` ramps every axis to its ``safe_voltage`` together and leaves
  the amplifier in open loop there, publishing the final read-back (exit 1 naming the axes that
  did not get there).

Bad input, exit 2 with one line and nothing sent: a stage file that does not load, a channel the
device does not list (GCS ``SAI?``), a backend that has no such channel.
"""

from __future__ import annotations

import functools
import math
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from rclpy.parameter import Parameter

from piezo_stage.config_path import ConfigNotFoundError, find_user_file
from piezo_stage.hardware import DriverState, HardwareError, NonFiniteVoltageError, make_amplifier
from piezo_stage.hardware.amplifier import AMPLIFIERS, DeviceInfo
from piezo_stage.hardware.axis_link import make_axis_link
from piezo_stage.hardware.driver import SetResult
from piezo_stage.hardware.errors import (
    CommandExpired,
    ConfigError,
    SafeStateNotReached,
    SafetyError,
)
from piezo_stage.hardware.stage_driver import StageDriver
from piezo_stage.hardware.stamps import StampPolicy
from piezo_stage.model.stage_file import Stage, StageFileError, load_stage
from piezo_stage_msgs.msg import Voltage

from .axis_inlet import AxisInlet, Playout, Rejection, check_apply_at_stamp, start_playout
from .base import PiezoNode
from .diagnostics import ERROR, OK, WARN, Diagnosis, Diagnostics
from .driver_config import driver_config
from .errors import RosParameterError
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
            "stage_file",
            "",
            "stage file (name in config/ or path): the axes, in order, and their channels on "
            "the device, each axis's topics in <axis>/; empty: one axis (axis, channel), its "
            "topics unprefixed",
            read_only=True,
        ),
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
            "without stage_file: GCS axis (empty: the first SAI? lists) or MDT69x channel x|y|z "
            "(empty: x)",
            read_only=True,
        ),
        Param(
            "channel",
            1,
            "without stage_file: GCS piezo output channel (VOL?/VMA?/VMI?)",
            range=(1, 64),
            read_only=True,
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
        Param(
            "write_rate_hz",
            0.0,
            "0: each command is written as it arrives (its axis alone); > 0: the latest "
            "command of every axis is written together, one device command per period",
            "Hz",
            (0.0, 1000.0),
            read_only=True,
        ),
    ),
    summary="Piezo amplifier driver (PI GCS2, Thorlabs MDT69x) of one axis or of a stage's "
    "axes over one link: voltage_command -> device, with limits, slew and watchdog per axis.",
    settings_type=VoltageDriverSettings,
)


@dataclass
class _Axis:
    """One axis's topics and inlet (its safety state is its driver's): ``name`` its topics'
    namespace ("" for the one axis without a stage file), ``channel`` its driver's key."""

    name: str
    channel: str
    publish: Callable[[float, int], None]
    inlet: AxisInlet


def _load(name: str, node: str) -> Stage:
    """The stage file ``name``; a refusal is bad input (exit 2)."""
    try:
        return load_stage(find_user_file(name))
    except (ConfigNotFoundError, StageFileError) as exc:
        raise RosParameterError(f"{node}: stage_file: {exc}") from None


def _connect(p: VoltageDriverSettings, stage: Stage | None, node: str) -> StageDriver:
    """The driver of the stage's axes (None: the one axis ``axis``/``channel``), connected; a
    stage's configuration the device refuses is bad input."""
    if stage is None:
        amplifier = make_amplifier(
            p.backend,
            p.url,
            axis=p.axis or None,
            channel=p.channel,
            timeout=p.io_timeout,
            baudrate=p.baud or None,
            pipeline=p.error_pipeline,
        )
        one = StageDriver.of_one(amplifier, driver_config(p))
        one.connect()
        return one
    channels = [axis.channel for axis in stage.axes]
    try:
        link = make_axis_link(
            p.backend,
            p.url,
            channels,
            timeout=p.io_timeout,
            baudrate=p.baud or None,
            pipeline=p.error_pipeline,
        )
        driver = StageDriver(link, dict.fromkeys(channels, driver_config(p)))
        driver.connect()
    except (ConfigError, SafetyError) as exc:
        raise RosParameterError(f"{node}: {stage.path}: {exc}") from None
    return driver


class VoltageDriverNode(PiezoNode):
    """With a ``handoff``: part of a composed loop (:mod:`.stage_loop`: ``rig_loop``, one axis
    or a stage), whose loop thread calls :meth:`set_voltages` directly;
    no voltage_command subscription (the controllers in the same process still publish the
    topic), every publication through ``handoff``; the watchdog stays in the executor's thread,
    under the node's lock."""

    TABLE: ParameterTable[VoltageDriverSettings] = PARAMETERS

    def __init__(
        self,
        handoff: Handoff | None = None,
        overrides: Sequence[Parameter] = (),
        namespace: str = DEFAULT_NAMESPACE,
    ) -> None:
        name = self.TABLE.node
        super().__init__(name, namespace=namespace, parameter_overrides=list(overrides))
        self._handoff = handoff
        #: the loop or play-out threads write, the executor's timers tick
        self._lock = threading.Lock()
        self.publish_every = 1  # the composed loop's writes published (its topics' decimation)
        self._loop_writes = 0
        p: VoltageDriverSettings = self.declare_settings(self.TABLE)
        self.stage = _load(p.stage_file, name) if p.stage_file else None
        self.url = p.url
        if p.apply_at_stamp:
            check_apply_at_stamp(self, "rig_loop" if handoff is not None else "")
        self.stamps = StampPolicy(
            p.max_command_age,
            p.max_stamp_ahead,
            require_stamp=p.max_command_age > 0 or p.apply_at_stamp,
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
        self.driver = _connect(p, self.stage, name)
        self._link_errors = 0
        self._last_error = ""
        self._reported_down = False
        #: write_rate_hz > 0: the latest accepted command of each axis, (voltage, received)
        self._pending: dict[str, tuple[float, float | None]] = {}
        self.axes: dict[str, _Axis] = {}
        self._playouts = Playout()
        names = [(a.name, a.channel) for a in self.stage.axes] if self.stage else [("", "")]
        for axis_name, channel in names:
            driver = self.driver.drivers[channel]
            apply = functools.partial(self._accept, channel)
            inlet = AxisInlet(
                axis_name,
                self.get_logger(),
                self.stamps,
                apply,
                functools.partial(self._received, channel),
                functools.partial(getattr, driver, "last_sent"),
                driver.last_sent,
            )
            axis = _Axis(axis_name, channel, self._publisher(axis_name), inlet)
            self.axes[channel] = axis
            if handoff is not None:
                continue  # the composed loop writes: its controllers' commands are for recorders
            if p.apply_at_stamp:
                inlet.playout = start_playout(apply, p, self._playouts)
                driver.on_timeout.append(inlet.playout.clear)  # the watchdog owns the output
            self.create_subscription(
                Voltage,
                self._topic(axis_name, "voltage_command"),
                functools.partial(self._on_command, axis),
                COMMAND_QOS,
            )
        self._first = next(iter(self.axes))  # the one axis's channel (the first of a stage's)
        self._batched = p.write_rate_hz > 0
        if self._batched:
            self.create_timer(1.0 / p.write_rate_hz, self._write_pending, clock=wall_clock())
        self.create_timer(p.watchdog_period, self._watchdog, clock=wall_clock())
        # composed: the loop thread reads back right after a write, when one is due
        self._readback_period = 1.0 / p.readback_rate_hz if p.readback_rate_hz > 0 else math.inf
        self._readback_due = 0.0 if p.readback_rate_hz > 0 else math.inf
        if p.readback_rate_hz > 0 and handoff is None:
            self.create_timer(self._readback_period, self._readback, clock=wall_clock())
        self._diagnostics = Diagnostics(
            self,
            f"{p.backend} {self.url}",
            self._diagnose_link,
            parts=self._diagnose_axes if self.stage is not None else None,
        )
        self.get_logger().info(self._started())

    def require_stage(self) -> Stage:
        """The stage file's stage; bad input (exit 2) without one (a stage's composed loop)."""
        if self.stage is None:
            raise RosParameterError(
                f"{self.get_name()}: stage_file is empty: the stage's loop needs one"
            )
        return self.stage

    @staticmethod
    def _topic(axis: str, topic: str) -> str:
        return f"{axis}/{topic}" if axis else topic

    @property
    def info(self) -> DeviceInfo:
        """The first axis's device (identity, axis, limits and output when connected)."""
        info = next(iter(self.driver.drivers.values())).info
        assert info is not None  # set by connect() in __init__, never unset
        return info

    def _started(self) -> str:
        if self.stage is None:
            d = next(iter(self.driver.drivers.values()))
            lim = d.limits
            assert lim is not None  # set by connect() in __init__, never unset
            return (
                f"{self.info.identity} axis {self.info.axis} on {self.url}: limits "
                f"[{lim.v_min:g}, {lim.v_max:g}] V, output {self.info.applied:g} V"
            )
        return f"{self.info.identity} on {self.url}: " + ", ".join(
            f"{a.name} on {a.channel} at {a.inlet.applied:g} V" for a in self.axes.values()
        )

    def _publisher(self, axis: str) -> Callable[[float, int], None]:
        """Publish on the axis's ``voltage`` (voltage [V], stamp [ns]); one message reused."""
        pub = self.create_publisher(Voltage, self._topic(axis, "voltage"), SENSOR_QOS)
        msg = Voltage()

        def send(voltage: float, stamp: int) -> None:
            set_stamp(msg.header, stamp)
            msg.voltage = voltage
            pub.publish(msg)

        return send

    # ------------------------------------------------------------------ commands
    def _on_command(self, axis: _Axis, msg: Voltage) -> None:
        axis.inlet.on_command(msg, self.get_clock().now().nanoseconds * 1e-9)

    def _received(self, channel: str) -> float:
        """A command for ``channel`` arrived: its watchdog counts from now (its driver's
        clock)."""
        received = self.driver.drivers[channel].clock()
        self.driver.command_received(channel, received)
        return received

    @property
    def last_sent(self) -> float:
        """The voltage last written to the (first) axis [V]."""
        return self.driver.drivers[self._first].last_sent

    def _accept(self, channel: str, voltage: float, command: bool, received: float | None) -> None:
        """An accepted command (or, ``command`` False, a value its play-out interpolated) for
        ``channel``: written now, or with the others at the next write period
        (``write_rate_hz``)."""
        if command:
            self.axes[channel].inlet.last_command = voltage
        if self._batched:
            self._pending[channel] = (voltage, received)
        else:
            self._write_one(channel, voltage, received, counted=command)

    def set_voltages(self, values: Mapping[str, float]) -> None:
        """The composed loop's write ({channel: voltage}, its own thread): the watchdog of each
        axis counts from now; one device command for all (each axis's safety rules apply); every
        ``publish_every``-th such write is published on the axes' ``voltage``; the device
        read-back follows the write when one is due (a timer's device round trip would hold the
        driver while a sample waits to be answered)."""
        self._loop_writes += 1
        batch: dict[str, tuple[float, float | None]] = {}
        received = 0.0
        for channel, voltage in values.items():
            self.axes[channel].inlet.last_command = voltage
            received = self._received(channel)
            batch[channel] = (voltage, received)
        self._write(batch, (self._loop_writes - 1) % self.publish_every == 0)
        if received >= self._readback_due:
            self._readback_due = received + self._readback_period
            self._readback()

    def _write_pending(self) -> None:
        if self._pending:
            batch, self._pending = self._pending, {}
            self._write(batch)

    def _write(self, batch: dict[str, tuple[float, float | None]], publish: bool = True) -> None:
        """Write ``batch`` ({channel: (voltage, received)}) as one device command and publish
        what each axis sent (``publish`` False: only keep it)."""
        with self._lock:
            sent_at = self._now_ns()  # applied when the device gets it, not after ERR?
            try:
                results = self.driver.set_voltages(
                    {c: v for c, (v, _) in batch.items()}, {c: t for c, (_, t) in batch.items()}
                )
            except HardwareError as exc:
                self._link_error(exc)
                return
            for channel, result in results.items():
                self._wrote(self.axes[channel], result, sent_at, publish)

    def _write_one(
        self,
        channel: str,
        voltage: float,
        received: float | None,
        publish: bool = True,
        counted: bool = True,
    ) -> None:
        """One axis's write alone, straight to its driver (nothing to batch: a command as it
        arrives, a play-out's value, the one-axis loop's output); ``counted`` False: a value
        the play-out interpolated (an expired one is dropped silently)."""
        with self._lock:
            sent_at = self._now_ns()
            try:
                result: SetResult | HardwareError = self.driver.drivers[channel].set_voltage(
                    voltage, received
                )
            except HardwareError as exc:
                result = exc
            self._wrote(self.axes[channel], result, sent_at, publish, counted)

    def _wrote(
        self,
        axis: _Axis,
        result: SetResult | HardwareError,
        sent_at: int,
        publish: bool,
        counted: bool = True,
    ) -> None:
        """What an axis's write did: published and counted, or refused, or a link error; under
        the node's lock (a watchdog turn between a write and its publication would take the
        value for a ramp step and publish it twice)."""
        if isinstance(result, SetResult):
            if counted:
                axis.inlet.wrote(result)
            if publish:
                self._publish(axis, result.sent, sent_at)
            else:
                axis.inlet.applied = result.sent
        elif isinstance(result, CommandExpired):  # counted by the axis's driver
            if counted:
                axis.inlet.reject(Rejection.EXPIRED, str(result))
        elif isinstance(result, NonFiniteVoltageError):  # not after the inlet's check
            axis.inlet.reject(Rejection.NONFINITE, str(result))
        else:
            self._link_error(result)

    def _link_error(self, exc: Exception) -> None:
        self._link_errors += 1
        self._last_error = str(exc)
        self.get_logger().error(f"amplifier link: {exc}", throttle_duration_sec=1.0)
        connected = all(d.connected for d in self.driver.drivers.values())
        if not connected and not self._reported_down:
            self._reported_down = True
            self._diagnostics.publish()  # ERROR now, not at the next period

    # ------------------------------------------------------------------ timers
    def _watchdog(self) -> None:
        # under the lock: a play-out or loop thread may be between a write and its
        # publication, which the comparison below would take for a ramp step and publish twice
        with self._lock:
            trips = {c: d.trips for c, d in self.driver.drivers.items()}
            try:
                states = self.driver.tick()  # every axis's ramp step, in one command
            except HardwareError as exc:
                self._link_error(exc)
                return
            for channel, axis in self.axes.items():
                d = self.driver.drivers[channel]
                if (
                    d.last_sent != axis.inlet.applied
                    and states[channel] is not DriverState.DISCONNECTED
                ):
                    self._publish(axis, d.last_sent)  # a ramp step (toward a command or safe)
        for channel, axis in self.axes.items():
            d = self.driver.drivers[channel]
            if d.trips != trips[channel]:
                self.get_logger().warn(
                    f"{axis.inlet.prefix}no voltage command for {d.config.command_timeout:g} s: "
                    f"ramping to {d.config.safe_voltage:g} V"
                )

    def _readback(self) -> None:
        for channel, axis in self.axes.items():
            d = self.driver.drivers[channel]
            if not d.connected:
                continue  # the driver reopens the link
            try:
                with self._lock:
                    voltage = d.read_voltage()
            except HardwareError as exc:
                self._link_error(exc)
                return
            self._publish(axis, voltage)

    def _publish(self, axis: _Axis, voltage: float, stamp: int | None = None) -> None:
        """Publish an axis's applied voltage, stamped [ns] when it was sent (default: now)."""
        axis.inlet.applied = voltage
        stamp = self._now_ns() if stamp is None else stamp
        if self._handoff is None:
            axis.publish(voltage, stamp)
        else:
            self._handoff.put(axis.publish, voltage, stamp)

    # ------------------------------------------------------------------ health, shutdown
    def _diagnose_link(self) -> Diagnosis:
        """The link's status; without a stage file, its one axis's too."""
        drivers = self.driver.drivers
        down = [self.axes[c].name for c, d in drivers.items() if not d.connected]
        values = {
            "connected": not down,
            "identity": self.info.identity,
            "device_writes": self.driver.link.writes,
            "reconnects": max(d.reconnects for d in drivers.values()),
            "link_errors": self._link_errors,
            "last_error": self._last_error
            or next((d.last_link_error for d in drivers.values() if d.last_link_error), ""),
        }
        if self._playouts.playouts:
            values["executor_priority"] = (
                self._playouts.executor_priority or self.settings.realtime_priority
            )
        self._reported_down = bool(down)
        if self.stage is None:
            axis = next(iter(self.axes.values()))
            one = self._diagnose(axis)
            return Diagnosis(one.level, one.message, {**one.values, **values})
        values["axes"] = " ".join(a.name for a in self.axes.values())
        values["channels"] = " ".join(a.channel for a in self.axes.values())
        if down:
            return Diagnosis(ERROR, f"disconnected from {self.url} ({', '.join(down)})", values)
        return Diagnosis(OK, f"{len(drivers)} axes on {self.url}", values)

    def _diagnose_axes(self) -> dict[str, Diagnosis]:
        return {axis.name: self._diagnose(axis) for axis in self.axes.values()}

    def _diagnose(self, axis: _Axis) -> Diagnosis:
        d = self.driver.drivers[axis.channel]
        lim = d.limits
        assert lim is not None  # set by connect() in __init__, never unset
        info = d.info
        values = {
            "state": d.state.value,
            "connected": d.connected,
            "axis": info.axis if info is not None else axis.channel,
            "v_min": lim.v_min,
            "v_max": lim.v_max,
            "safe_voltage": d.config.safe_voltage,
            "last_sent": d.last_sent,
            **axis.inlet.values(),
            "rejected_expired": d.expired,
            "watchdog_trips": d.trips,
            "device_writes": d.writes,
        }
        if not d.connected:
            return Diagnosis(ERROR, f"disconnected from {self.url}", values)
        rejected, text = axis.inlet.refused(d.expired)
        if rejected or d.state in (DriverState.TIMED_OUT, DriverState.SAFE):
            return Diagnosis(WARN, f"{d.state.value}; {text}", values)
        return Diagnosis(OK, d.state.value, values)

    def on_shutdown(self) -> None:
        """Ramp every axis to its safe_voltage together, at the slew rate, and leave the
        amplifier there (open loop)."""
        self._playouts.stop()  # queued commands are dropped: the ramp owns the outputs now
        self._pending.clear()
        try:
            with self._lock:
                applied = self.driver.shutdown()
        except SafeStateNotReached as exc:  # run() exits 1 with the reason, per channel
            if self.stage is None:
                raise
            names = ", ".join(f"{a.name} on {a.channel}" for a in self.axes.values())
            raise SafeStateNotReached(f"{exc} (axes {names})") from exc
        for channel, voltage in applied.items():
            self._publish(self.axes[channel], voltage)
        if self._handoff is not None:
            self._handoff.drain()  # the executor no longer spins: publish what is left now
        self.get_logger().info(
            "shut down at "
            + ", ".join(
                f"{self.axes[c].inlet.prefix.replace(':', '')}{v:g} V" for c, v in applied.items()
            )
            + f" (safe_voltage {self.settings.safe_voltage:g} V)"
        )


def main(args: list[str] | None = None) -> int:
    return run(VoltageDriverNode, args)


if __name__ == "__main__":
    sys.exit(main())
