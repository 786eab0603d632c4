"""A multi-axis stage on emulators: one amplifier and one optoNCDT sensor per axis around one
simulated coupled stage (docs/design.md section 10, ``emulate scanner``).

The amplifier (GCS, E-727 class, or MDT693B) drives every axis: axis i of the stage takes the
voltage its device channel applies. All axes are stepped together, once per sample of one grid
(t0 + k/rate, t0 the first sample any sensor takes), with each channel's voltage in force then
(:class:`~.amplifier.VoltageHistory`); sensor i streams
``standoff + reading_i``, axis i's coupled displacement. Each sensor keeps its own sample clock
(its own server): its samples map to the grid's at a fixed offset, so the sensors see the same
stage, stepped once. Any object with ``step(commands, dt) -> (applied, readings, status)`` per
axis serves as the stage (``piezo_stage.model.stage.CoupledStage``). With an amplifier bandwidth
each channel's command reaches its axis through the amplifier's low-pass
(:class:`~.amplifier.AmplifierLowPass`), the stage stepped :func:`~.amplifier.substeps_for`
times per sample (``step_voltages``, as the ``plant`` node does). A stage of one axis is the
rig (:mod:`.rig`).
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections.abc import Sequence
from typing import Callable, Protocol

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigError
from ..optoncdt import FrameFormat
from .amplifier import (
    AmplifierLowPass,
    VoltageHistory,
    amplifier_endpoint,
    amplifier_model,
    substep_times,
    substeps_for,
)
from .optoncdt_device import OptoNCDTDeviceModel
from .server import EmulatorServer, Faults

__all__ = ["CoupledAxes", "ScannerCoupling", "ScannerEmulator"]

#: grid samples [s] kept for a sensor that reads late (after a stall); older ones are gone
BACKLOG_S = 3.0
#: longest a sensor waits [s] for the amplifier to handle what reached it before a sample
HEARD_WAIT = 1.0


class CoupledAxes(Protocol):
    """What the scanner steps (module docstring), e.g. ``CoupledStage``."""

    def step(
        self, commands: Sequence[float], dt: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """Hold ``commands[i]`` on axis i for dt; (applied, readings, status) per axis."""

    def step_voltages(
        self, voltages: NDArray[np.float64], h: float, every: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
        """Hold ``voltages[i, k]`` on axis i for h each; rows of samples every ``every`` steps."""


class ScannerCoupling:
    """The sensors' displacement source: steps the stage on one sample grid (module docstring).

    ``channels[i]`` is axis i's channel on the amplifier; :meth:`on_axis_voltage` is the
    amplifier model's ``on_axis_voltage`` callback (other channels are ignored);
    :meth:`source` gives sensor i's ``source(times)``. ``bandwidth_hz`` > 0: the amplifier's
    low-pass of ``filter_order`` between each channel's command and its axis.
    """

    def __init__(
        self,
        stage: CoupledAxes,
        channels: Sequence[str],
        rate: float,
        standoff: float,
        initial_voltages: dict[str, float] | None = None,
        clock: Callable[[], float] = time.monotonic,
        bandwidth_hz: float = 0.0,
        filter_order: int = 2,
    ) -> None:
        if len(set(channels)) != len(channels) or not channels:
            raise ConfigError(f"one distinct channel per axis, got {list(channels)!r}")
        self.stage = stage
        self.channels = tuple(channels)
        self.rate = float(rate)
        self.dt = 1.0 / rate
        self.standoff = standoff
        start = initial_voltages or {}
        self.histories = {c: VoltageHistory(start.get(c, 0.0), clock) for c in self.channels}
        axes = getattr(stage, "axes", ())
        #: stage steps per sample, through the amplifier's low-pass (1: an ideal amplifier)
        self.substeps = max((substeps_for(a, rate, bandwidth_hz) for a in axes), default=1)
        h = self.dt / self.substeps
        self.lowpass = (
            [AmplifierLowPass(bandwidth_hz, filter_order, h, start.get(c, 0.0)) for c in channels]
            if bandwidth_hz > 0.0
            else []
        )
        self.lock = threading.Lock()
        self.origin: float | None = None  # absolute time of grid sample 0
        self.steps = 0  # grid samples computed so far
        n = len(self.channels)
        self._ring = np.full((max(2, math.ceil(BACKLOG_S * rate)), n), math.nan)
        self.applied = np.zeros(n)  # last voltages the stage received [V]
        self.readings = np.zeros(n)  # last sensor readings of the stage [m]
        #: server time up to which the amplifier has handled its input (its server's
        #: ``heard_until``); None: always now
        self.heard: Callable[[], float] | None = None
        self.clock = clock

    def on_axis_voltage(self, channel: str, value: float, at: float | None = None) -> None:
        """The amplifier applied ``value`` on ``channel`` at server time ``at`` (None: now)."""
        history = self.histories.get(channel)
        if history is not None:
            with self.lock:
                history.record(value, at)

    def source(self, axis: int, sensor_origin: Callable[[], float | None]) -> "_AxisSource":
        """Sensor ``axis``'s source; ``sensor_origin()`` is its sample 0's server time."""
        if not 0 <= axis < len(self.channels):
            raise ConfigError(f"axis index {axis} outside 0..{len(self.channels) - 1}")
        return _AxisSource(self, axis, sensor_origin)

    def _advance(self, last: int) -> None:
        """Step the stage through grid sample ``last`` (lock held)."""
        assert self.origin is not None  # set by the first grid_offset() call
        if self.lowpass:
            self._advance_filtered(last)
            return
        ring = self._ring
        while self.steps <= last:
            t = self.origin + self.steps * self.dt
            volts = [self.histories[c].value_at(t) for c in self.channels]
            applied, readings, status = self.stage.step(volts, self.dt)
            ok = (np.asarray(status) == 0) & np.isfinite(readings)
            ring[self.steps % len(ring)] = np.where(ok, self.standoff + readings, math.nan)
            self.applied, self.readings = np.asarray(applied), np.asarray(readings)
            self.steps += 1

    def _advance_filtered(self, last: int) -> None:
        """:meth:`_advance` through the amplifiers' low-pass: the pending samples in batches of
        at most the backlog, each channel's command in force at each substep filtered.
        """
        assert self.origin is not None
        while self.steps <= last:
            self._filtered_batch(min(last, self.steps + len(self._ring) - 1))

    def _filtered_batch(self, last: int) -> None:
        assert self.origin is not None
        ring, n = self._ring, len(self._ring)
        k = np.arange(self.steps, last + 1, dtype=np.float64)
        h = self.dt / self.substeps
        t_sub = substep_times(self.origin + k * self.dt, self.substeps, h)
        volts = np.vstack(
            [
                lowpass.run(self.histories[c].values_at(t_sub))
                for c, lowpass in zip(self.channels, self.lowpass)
            ]
        )
        applied, readings, status = self.stage.step_voltages(volts, h, self.substeps)
        ok = (np.asarray(status) == 0) & np.isfinite(readings)
        ring[np.arange(self.steps, last + 1) % n] = np.where(ok, self.standoff + readings, math.nan)
        self.applied, self.readings = np.asarray(applied[-1]), np.asarray(readings[-1])
        self.steps = last + 1

    def readings_at(self, axis: int, index: NDArray[np.int64]) -> NDArray[np.float64]:
        """Sensor ``axis``'s readings at grid samples ``index`` (after :meth:`grid_offset`); a
        sample older than the backlog reads the oldest kept.
        """
        if index.size:
            self._wait_heard(int(index.max()))
        with self.lock:
            if index.size:
                self._advance(int(index.max()))
            oldest = max(0, self.steps - len(self._ring))
            kept = np.maximum(index, oldest)
            out: NDArray[np.float64] = self._ring[kept % len(self._ring), axis]  # a copy
            return out

    def _wait_heard(self, last: int) -> None:
        """Wait (at most :data:`HEARD_WAIT`) until the amplifier has handled every command that
        reached it before grid sample ``last``: one that came during a stall of this process
        applies from its arrival, as on the device, not from the first sample after the stall.
        """
        heard, origin = self.heard, self.origin
        if heard is None or origin is None or last < self.steps:
            return
        t = origin + last * self.dt
        deadline = None
        while heard() < t:
            now = self.clock()
            deadline = now + HEARD_WAIT if deadline is None else deadline
            if now >= deadline:
                return
            time.sleep(2e-4)

    def grid_offset(self, origin: float) -> int:
        """Grid samples between the grid's sample 0 and a sensor's sample 0 at ``origin``; the
        first sensor to ask starts the grid there.
        """
        with self.lock:
            if self.origin is None:
                self.origin = origin
            return round((origin - self.origin) * self.rate)


class _AxisSource:
    """One sensor's ``source(times)``: its samples on the shared grid at a fixed offset."""

    def __init__(
        self, coupling: ScannerCoupling, axis: int, origin: Callable[[], float | None]
    ) -> None:
        self.coupling, self.axis, self.origin = coupling, axis, origin
        self._offset: int | None = None

    def __call__(self, times: NDArray[np.float64]) -> NDArray[np.float64]:
        if self._offset is None:
            origin = self.origin()
            self._offset = self.coupling.grid_offset(time.monotonic() if origin is None else origin)
        k = np.rint(np.asarray(times, dtype=np.float64) * self.coupling.rate).astype(np.int64)
        return self.coupling.readings_at(self.axis, np.maximum(k + self._offset, 0))


class ScannerEmulator:
    """The amplifier (GCS on TCP or pty, or MDT693B on pty) and one optoNCDT sensor per axis
    (each on a pty) around one coupled stage; ``axes`` and ``channels`` name the stage's axes in
    order and their channels on the amplifier (None: a one-channel amplifier, an E-709 or an
    MDT694B, for a stage of one axis); ``amplifier_bandwidth`` [Hz] (0: ideal) and
    ``amplifier_filter_order`` (1 or 2): the amplifier's output low-pass
    (:class:`~.amplifier.AmplifierLowPass`) between command and stage; ``sensor_link``: each
    sensor's pty link, ``{axis}`` replaced by its axis's name.
    """

    def __init__(
        self,
        stage: CoupledAxes,
        axes: Sequence[str],
        channels: Sequence[str] | None,
        sensor_format: FrameFormat,
        measuring_range: float,
        *,
        amplifier: str = "gcs",
        amplifier_tcp_port: int | None = None,
        amplifier_link: str | None = None,
        amplifier_range: tuple[float, float] | None = None,
        rate: float = 1000.0,
        standoff: float | None = None,
        sensor_errors: float = 0.0,
        amplifier_faults: Faults | None = None,
        sensor_faults: Faults | None = None,
        seed: int | None = None,
        sensor_link: str | None = None,
        realtime_priority: int = 0,
        amplifier_bandwidth: float = 0.0,
        amplifier_filter_order: int = 2,
    ) -> None:
        self.amplifier = amplifier_model(amplifier, amplifier_range, amplifier_tcp_port, channels)
        channels = self.amplifier.axes if channels is None else channels
        if len(axes) != len(channels):
            raise ConfigError(f"{len(axes)} axes need as many channels, got {len(channels)}")
        if sensor_link is not None and len(axes) > 1 and "{axis}" not in sensor_link:
            raise ConfigError(f"sensor link {sensor_link!r} needs {{axis}}: one pty per axis")
        self.axes = tuple(axes)
        standoff = 0.5 * measuring_range if standoff is None else standoff
        start = self.amplifier.applied_voltages()
        self.coupling = ScannerCoupling(
            stage,
            channels,
            rate,
            standoff,
            start,
            bandwidth_hz=amplifier_bandwidth,
            filter_order=amplifier_filter_order,
        )
        self.amplifier.on_axis_voltage = self.coupling.on_axis_voltage
        self.amplifier_server = EmulatorServer(
            self.amplifier,
            faults=amplifier_faults,
            realtime_priority=realtime_priority,
            **amplifier_endpoint(amplifier_tcp_port, amplifier_link),
        )
        self.coupling.heard = self.amplifier_server.heard_until
        self.sensors: list[OptoNCDTDeviceModel] = []
        self.sensor_servers: list[EmulatorServer] = []
        for i, name in enumerate(self.axes):
            sensor = OptoNCDTDeviceModel(
                sensor_format,
                measuring_range,
                rate,
                error_probability=sensor_errors,
                seed=None if seed is None else seed + i,
            )
            sensor.source = self.coupling.source(i, _origin_of(sensor))
            self.sensors.append(sensor)
            self.sensor_servers.append(
                EmulatorServer(
                    sensor,
                    pty=True,
                    pty_link=None if sensor_link is None else sensor_link.replace("{axis}", name),
                    faults=_faults_for(sensor_faults, i),
                    realtime_priority=realtime_priority,
                )
            )

    @property
    def servers(self) -> dict[str, EmulatorServer]:
        """The servers by name: the amplifier's (``gcs``/``mdt69x``), ``optoncdt <axis>``."""
        named = {self.amplifier.name: self.amplifier_server}
        named.update(
            (f"optoncdt {axis}", server) for axis, server in zip(self.axes, self.sensor_servers)
        )
        return named

    def start(self) -> "ScannerEmulator":
        """Start every server; returns the scanner."""
        for server in self.servers.values():
            server.start()
        return self

    def stop(self) -> None:
        """Stop every server (the sensors first)."""
        for server in self.sensor_servers:
            server.stop()
        self.amplifier_server.stop()

    def __enter__(self) -> "ScannerEmulator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _faults_for(faults: Faults | None, i: int) -> Faults | None:
    """Sensor i's faults: ``faults`` itself for the first, for each other its own copy (its
    own generator, seeded ``seed + i``).
    """
    if faults is None or i == 0:
        return faults
    return dataclasses.replace(faults, seed=None if faults.seed is None else faults.seed + i)


def _origin_of(sensor: OptoNCDTDeviceModel) -> Callable[[], float | None]:
    """``sensor``'s sample 0 time (None before its first sample)."""
    return lambda: sensor.t0
