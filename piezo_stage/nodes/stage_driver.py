"""`stage_driver` node: the voltage driver of a multi-channel amplifier serving every axis of a
stage over one link (docs/design.md §10; a PI E-727, a Thorlabs MDT693B).

The stage file names the axes and their channels on the device. Per axis, in the axis's
namespace and as ``voltage_driver`` does for its one axis: subscribes ``<axis>/voltage_command``
(COMMAND_QOS), publishes ``<axis>/voltage`` (SENSOR_QOS: the value written, stamped when sent,
and the device read-back every 1/readback_rate_hz s); ``/diagnostics`` has one status per axis
(``<node>/<axis>``) and one for the link (``<node>``). Every safety rule, per axis, lives in
:class:`piezo_stage.hardware.stage_driver.StageDriver` (limits, slew cap between every two
writes, watchdog from the axis's own last command, reconnect; shutdown ramps all axes together);
this node adds what needs ROS: non-finite commands and badly stamped ones (``max_command_age``,
``max_stamp_ahead``) are refused here and never sent (:mod:`.axis_inlet`, as in
``voltage_driver``); ``apply_at_stamp`` plays each axis's commands at their stamps +
``command_delay`` (a play-out thread per axis), and ``write_rate_hz`` chooses how commands leave:
0, each when accepted or due (that axis alone); > 0, the latest command of every axis together,
one device command per period (GCS ``SVA 1 a 2 b``). SIGINT/SIGTERM: ``on_shutdown()`` ramps every
axis to ``safe_voltage`` (exit 1 naming the axes that did not get there).

Bad input, exit 2 with one line and nothing sent: a stage file that does not load, a channel the
device does not list (GCS ``SAI?``), a backend that has no such channel.
"""

from __future__ import annotations

import functools
import sys
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

from rclpy.parameter import Parameter

from piezo_stage.config_path import ConfigNotFoundError, find_user_file
from piezo_stage.hardware import DriverState, HardwareError
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
from .driver_config import AXIS_SAFETY, driver_config
from .errors import RosParameterError
from .handoff import Handoff
from .parameters import on_set
from .qos import COMMAND_QOS, SENSOR_QOS
from .runtime import DEFAULT_NAMESPACE, run, set_stamp, stamp_clock, wall_clock
from .settings import StageDriverSettings
from .spec import Param, ParameterTable
from .voltage_driver import PARAMETERS as VOLTAGE_DRIVER

#: voltage_driver's entries, taken as they are: the link and every axis's rules
_SHARED = (
    ("backend", "url", "baud", "error_pipeline", "io_timeout")
    + AXIS_SAFETY
    + ("readback_rate_hz", "max_command_age", "max_stamp_ahead")
    + ("apply_at_stamp", "command_delay", "hold_period", "realtime_priority")
)

PARAMETERS = ParameterTable(
    "stage_driver",
    (
        Param(
            "stage_file",
            "xy_scanner.yaml",
            "stage file (name in config/ or path): the axes, in order, and their channels "
            "on the device",
            read_only=True,
        ),
        *(VOLTAGE_DRIVER[name] for name in _SHARED),
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
    summary="Multi-channel amplifier driver (PI E-727, Thorlabs MDT693B): <axis>/voltage_command "
    "-> the axis's channel, limits, slew and watchdog per axis, one link.",
    settings_type=StageDriverSettings,
)


@dataclass
class _Axis:
    """One axis's topics and inlet (its safety state is its driver's)."""

    name: str
    channel: str
    publish: Callable[[float, int], None]
    inlet: AxisInlet


def _load(name: str) -> Stage:
    """The stage file ``name``; a refusal is bad input (exit 2)."""
    try:
        return load_stage(find_user_file(name))
    except (ConfigNotFoundError, StageFileError) as exc:
        raise RosParameterError(f"stage_driver: stage_file: {exc}") from None


def _connect(p: StageDriverSettings, stage: Stage) -> StageDriver:
    """The stage's driver, connected; a configuration the device refuses is bad input."""
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
        raise RosParameterError(f"stage_driver: {stage.path}: {exc}") from None
    return driver


class StageDriverNode(PiezoNode):
    """With a ``handoff``: part of the stage's composed loop (:mod:`.scanner_loop`), whose loop
    thread calls :meth:`set_voltages` and whose hand-off publishes what the node publishes; the
    watchdog and the read-back stay in the executor's thread, under the node's lock."""

    def __init__(
        self,
        handoff: Handoff | None = None,
        overrides: Sequence[Parameter] = (),
        namespace: str = DEFAULT_NAMESPACE,
    ) -> None:
        super().__init__("stage_driver", namespace=namespace, parameter_overrides=list(overrides))
        self._handoff = handoff
        self._lock = threading.Lock()  # the loop thread writes, the executor's timers tick
        self.publish_every = 1  # the composed loop's writes published (its topics' decimation)
        self._loop_writes = 0
        p: StageDriverSettings = self.declare_settings(PARAMETERS)
        self.stage = _load(p.stage_file)
        self.url = p.url
        if p.apply_at_stamp:
            check_apply_at_stamp(self, "scanner_loop" if handoff is not None else "")
        self.stamps = StampPolicy(
            p.max_command_age,
            p.max_stamp_ahead,
            require_stamp=p.max_command_age > 0 or p.apply_at_stamp,
        )
        on_set(
            self,
            lambda changed: (
                "use_sim_time is fixed at start (the stamp checks depend on it)"
                if "use_sim_time" in changed
                else None
            ),
        )
        self._now_ns = stamp_clock(self)
        self.driver = _connect(p, self.stage)
        self._link_errors = 0
        self._last_error = ""
        self._reported_down = False
        #: write_rate_hz > 0: the latest accepted command of each axis, (voltage, received)
        self._pending: dict[str, tuple[float, float | None]] = {}
        self.axes: dict[str, _Axis] = {}
        self._playouts = Playout()
        for stage_axis in self.stage.axes:
            driver = self.driver.drivers[stage_axis.channel]
            channel = stage_axis.channel
            apply = functools.partial(self._accept, channel)
            inlet = AxisInlet(
                stage_axis.name,
                self.get_logger(),
                self.stamps,
                apply,
                functools.partial(self._received, channel),
                functools.partial(getattr, driver, "last_sent"),
                driver.last_sent,
            )
            axis = _Axis(stage_axis.name, channel, self._publisher(stage_axis.name), inlet)
            self.axes[channel] = axis
            if handoff is not None:
                continue  # the composed loop writes: its controllers' commands are for recorders
            if p.apply_at_stamp:
                inlet.playout = start_playout(apply, p, self._playouts)
                driver.on_timeout.append(inlet.playout.clear)  # the watchdog owns the output
            self.create_subscription(
                Voltage,
                f"{axis.name}/voltage_command",
                functools.partial(self._on_command, axis),
                COMMAND_QOS,
            )
        self._batched = p.write_rate_hz > 0
        if self._batched:
            self.create_timer(1.0 / p.write_rate_hz, self._write_pending, clock=wall_clock())
        self.create_timer(p.watchdog_period, self._watchdog, clock=wall_clock())
        if p.readback_rate_hz > 0:
            self.create_timer(1.0 / p.readback_rate_hz, self._readback, clock=wall_clock())
        self._diagnostics = Diagnostics(
            self, f"{p.backend} {self.url}", self._diagnose_link, parts=self._diagnose_axes
        )
        first = next(iter(self.driver.drivers.values()))
        identity = first.info.identity if first.info is not None else "?"
        self.get_logger().info(
            f"{identity} on {self.url}: "
            + ", ".join(
                f"{a.name} on {a.channel} at {a.inlet.applied:g} V" for a in self.axes.values()
            )
        )

    def _publisher(self, axis: str) -> Callable[[float, int], None]:
        """Publish on ``<axis>/voltage`` (voltage [V], stamp [ns]); one message reused."""
        pub = self.create_publisher(Voltage, f"{axis}/voltage", SENSOR_QOS)
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

    def _accept(self, channel: str, voltage: float, command: bool, received: float | None) -> None:
        """An accepted command (or a value its play-out interpolated) for ``channel``: written
        now, or with the others at the next write period (``write_rate_hz``)."""
        if command:
            self.axes[channel].inlet.last_command = voltage
        if self._batched:
            self._pending[channel] = (voltage, received)
        else:
            self._write({channel: (voltage, received)})

    def set_voltages(self, values: Mapping[str, float]) -> None:
        """The composed loop's write ({channel: voltage}): the watchdog of each axis counts from
        now; one device command for all (each axis's safety rules apply); every
        ``publish_every``-th such write is published on the axes' ``voltage``."""
        self._loop_writes += 1
        batch: dict[str, tuple[float, float | None]] = {}
        for channel, voltage in values.items():
            self.axes[channel].inlet.last_command = voltage
            batch[channel] = (voltage, self._received(channel))
        self._write(batch, (self._loop_writes - 1) % self.publish_every == 0)

    def _write_pending(self) -> None:
        if self._pending:
            batch, self._pending = self._pending, {}
            self._write(batch)

    def _write(self, batch: dict[str, tuple[float, float | None]], publish: bool = True) -> None:
        """Write ``batch`` ({channel: (voltage, received)}) as one device command; publish what
        each axis sent (``publish`` False: only keep it)."""
        sent_at = self._now_ns()  # applied when the device gets it, not after ERR?
        try:
            with self._lock:
                results = self.driver.set_voltages(
                    {c: v for c, (v, _) in batch.items()}, {c: t for c, (_, t) in batch.items()}
                )
        except HardwareError as exc:
            self._link_error(exc)
            return
        for channel, result in results.items():
            axis = self.axes[channel]
            if isinstance(result, SetResult):
                axis.inlet.wrote(result)
                if publish:
                    self._publish(axis, result.sent, sent_at)
                else:
                    axis.inlet.applied = result.sent
            elif isinstance(result, CommandExpired):  # counted by the axis's driver
                axis.inlet.reject(Rejection.EXPIRED, str(result))
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
        with self._lock:
            trips = {c: d.trips for c, d in self.driver.drivers.items()}
            states = self.driver.tick()  # every axis's ramp step, in one command
        for channel, axis in self.axes.items():
            d = self.driver.drivers[channel]
            if (
                d.last_sent != axis.inlet.applied
                and states[channel] is not DriverState.DISCONNECTED
            ):
                self._publish(axis, d.last_sent)  # a step of a ramp (toward a command or safe)
            if d.trips != trips[channel]:
                self.get_logger().warn(
                    f"{axis.name}: no voltage command for {d.config.command_timeout:g} s: "
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
        drivers = self.driver.drivers
        down = [self.axes[c].name for c, d in drivers.items() if not d.connected]
        values = {
            "axes": " ".join(a.name for a in self.axes.values()),
            "channels": " ".join(a.channel for a in self.axes.values()),
            "connected": not down,
            "device_writes": self.driver.link.writes,
            "reconnects": max(d.reconnects for d in drivers.values()),
            "link_errors": self._link_errors,
            "last_error": self._last_error
            or next((d.last_link_error for d in drivers.values() if d.last_link_error), ""),
        }
        self._reported_down = bool(down)
        if down:
            return Diagnosis(ERROR, f"disconnected from {self.url} ({', '.join(down)})", values)
        return Diagnosis(OK, f"{len(drivers)} axes on {self.url}", values)

    def _diagnose_axes(self) -> dict[str, Diagnosis]:
        return {axis.name: self._diagnose(axis) for axis in self.axes.values()}

    def _diagnose(self, axis: _Axis) -> Diagnosis:
        d = self.driver.drivers[axis.channel]
        lim = d.limits
        assert lim is not None  # set by connect() in __init__, never unset
        values = {
            "state": d.state.value,
            "connected": d.connected,
            "channel": axis.channel,
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
        """Ramp every axis to its safe_voltage together and leave the amplifier there."""
        self._playouts.stop()  # queued commands are dropped: the ramp owns the outputs now
        self._pending.clear()
        try:
            with self._lock:
                applied = self.driver.shutdown()
        except SafeStateNotReached as exc:  # run() exits 1 with the reason, per channel
            names = ", ".join(f"{a.name} on {a.channel}" for a in self.axes.values())
            raise SafeStateNotReached(f"{exc} (axes {names})") from exc
        for channel, voltage in applied.items():
            self._publish(self.axes[channel], voltage)
        self.get_logger().info(
            "shut down at "
            + ", ".join(f"{self.axes[c].name} {v:g} V" for c, v in applied.items())
            + f" (safe_voltage {self.settings.safe_voltage:g} V)"
        )
        if self._handoff is not None:
            self._handoff.drain()  # the executor no longer spins: publish what is left now


def main(args: list[str] | None = None) -> int:
    return run(StageDriverNode, args)


if __name__ == "__main__":
    sys.exit(main())
