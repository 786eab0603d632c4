"""A whole rig on emulators: amplifier and sensor bound to one simulated stage.

The amplifier emulator's applied voltage drives the plant; the sensor emulator steps the plant
once per sample (dt = 1/rate, so the plant runs on the sensor's sample clock) and streams
``standoff + displacement`` (metres from the start of its measuring range). The plant sees, for
the sample taken at ``t0 + k/rate``, the voltage the amplifier applied at that instant (each
applied voltage is kept with its arrival time), not the voltage at the moment the emulator's
thread gets round to computing the sample: as on a real rig, the physics run in real time
whatever the host's scheduling, and a late burst of samples still describes the past. Any object
with
``step(command_voltage, dt) -> (applied_voltage, displacement, status)`` serves as the stage
(``piezo_stage.model.stage.SimulatedStage``).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Sequence
from typing import Callable, Protocol, TypedDict

import numpy as np
from numpy.typing import NDArray

from ..errors import ConfigError
from ..mdt69x import AXES as MDT_AXES
from ..optoncdt import FrameFormat
from .gcs_device import GCSDeviceModel
from .mdt_device import MDTDeviceModel
from .optoncdt_device import OptoNCDTDeviceModel
from .server import EmulatorServer, Faults


class _Endpoint(TypedDict, total=False):
    """Where :class:`EmulatorServer` serves the amplifier: a pty (and its link) or TCP."""

    pty: bool
    pty_link: str | None
    tcp_port: int


def amplifier_model(
    kind: str,
    amplifier_range: tuple[float, float] | None = None,
    tcp_port: int | None = None,
    channels: Sequence[str] | None = None,
) -> GCSDeviceModel | MDTDeviceModel:
    """The amplifier emulator of a rig: ``gcs`` (E-709 class, or with ``channels`` an E-727
    class listing exactly those axes in ``SAI?``; ``amplifier_range`` its VMI?/VMA?) or
    ``mdt69x`` (MDT694B, or with ``channels`` an MDT693B, whose channels are x, y, z; pty only).
    """
    if amplifier_range is not None and kind != "gcs":
        raise ConfigError(
            "amplifier_range sets the GCS controller's VMI?/VMA?; the MDT69x has its vlimit switch"
        )
    if kind == "gcs":
        if amplifier_range is None:
            return GCSDeviceModel(axes=channels)
        return GCSDeviceModel(v_min=amplifier_range[0], v_max=amplifier_range[1], axes=channels)
    if kind != "mdt69x":
        raise ConfigError(f"amplifier must be 'gcs' or 'mdt69x', got {kind!r}")
    if tcp_port is not None:
        raise ConfigError("the MDT69x emulator serves a pty only")
    if channels is None:
        return MDTDeviceModel()
    unknown = [c for c in channels if c not in MDT_AXES]
    if unknown:
        raise ConfigError(
            f"channel(s) {', '.join(unknown)} are not MDT693B channels ({', '.join(MDT_AXES)})"
        )
    return MDTDeviceModel("MDT693B")


def amplifier_endpoint(tcp_port: int | None, link: str | None) -> _Endpoint:
    """Where the amplifier is served: TCP ``tcp_port``, else a pty (at ``link`` when given)."""
    if tcp_port is None:
        return {"pty": True, "pty_link": link}
    if link is not None:
        raise ConfigError("an amplifier link names a pty: not with a TCP amplifier")
    return {"tcp_port": tcp_port}


class Stage(Protocol):
    """What the rig steps (see the module docstring), e.g. ``SimulatedStage``."""

    def step(self, command_voltage: float, dt: float) -> tuple[float, float, int]:
        """Apply ``command_voltage`` over ``dt`` [s]; returns (applied, displacement, status)."""


class AmplifierLowPass:
    """The amplifier's finite bandwidth: a Butterworth low-pass (order 1 or 2, corner
    ``bandwidth_hz``) from the commanded to the applied voltage, exact for a command held over
    each step ``h`` (ZOH discretisation), starting at rest at ``initial_voltage``.
    """

    def __init__(self, bandwidth_hz: float, order: int, h: float, initial_voltage: float) -> None:
        from scipy import signal

        if order not in (1, 2) or not bandwidth_hz > 0.0:
            raise ConfigError(
                f"amplifier low-pass: order 1 or 2 and bandwidth > 0 Hz, got "
                f"{order}, {bandwidth_hz!r}"
            )
        b, a = signal.butter(order, 2.0 * math.pi * bandwidth_hz, analog=True)
        bd, ad, _ = signal.cont2discrete((b, a), h, method="zoh")
        self.b, self.a = np.ravel(bd), np.ravel(ad)
        self.zi = signal.lfilter_zi(self.b, self.a) * float(initial_voltage)  # at rest

    def run(self, commands: NDArray[np.float64]) -> NDArray[np.float64]:
        """The applied voltage at the end of each step, ``commands[i]`` held over step i."""
        from scipy import signal

        out, self.zi = signal.lfilter(self.b, self.a, commands, zi=self.zi)
        return out


def substeps_for(stage: Stage, rate: float, bandwidth_hz: float) -> int:
    """Plant steps per sensor sample under a low-pass: 20 per period of its corner and 7 per
    period of the stage's natural frequency sqrt(kappa_x/m)/(2 pi) (11.1), whichever is more
    (a staircase any coarser rings the resonance and dithers the hysteresis away).
    """
    if not bandwidth_hz > 0.0:
        return 1
    f = 20.0 * bandwidth_hz
    ps = getattr(stage, "parameter_set", None)
    if ps is not None and ps.form == "dynamic":
        f = max(f, 7.0 * math.sqrt(ps.bouc_wen.kappa_x / ps.dynamics.m) / (2.0 * math.pi))
    return max(1, math.ceil(f / rate))


def substep_times(times: NDArray[np.float64], substeps: int, h: float) -> NDArray[np.float64]:
    """The ends of the ``substeps`` steps of ``h`` that lead to each of ``times``, in order."""
    lags = (substeps - 1 - np.arange(substeps)) * h
    out: NDArray[np.float64] = (np.asarray(times)[:, None] - lags[None, :]).ravel()
    return out


class VoltageHistory:
    """An amplifier output's applied voltages with their arrival times (server clock), in time
    order, from ``initial_voltage`` at -inf: the voltage in force at any later instant. Not
    locked: its owner holds a lock around it.
    """

    def __init__(self, initial_voltage: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self.entries: deque[tuple[float, float]] = deque([(-math.inf, float(initial_voltage))])

    def record(self, value: float, at: float | None = None) -> None:
        """``value`` applied at ``at`` (None: now); an earlier time than the last is moved up."""
        t = self.clock() if at is None else at
        if t < self.entries[-1][0]:  # keep the history in time order
            t = self.entries[-1][0]
        self.entries.append((t, float(value)))

    def value_at(self, t: float) -> float:
        """The voltage in force at ``t``; forgets what was replaced before ``t`` (ask in time
        order).
        """
        entries = self.entries
        while len(entries) > 1 and entries[1][0] <= t:
            entries.popleft()
        return entries[0][1]

    def values_at(self, times: NDArray[np.float64]) -> NDArray[np.float64]:
        """The voltage in force at each of ``times`` (increasing); forgets what was replaced
        before the last of them.
        """
        entries = self.entries
        hist_t = np.fromiter((t for t, _ in entries), np.float64, len(entries))
        hist_v = np.fromiter((v for _, v in entries), np.float64, len(entries))
        idx = np.clip(np.searchsorted(hist_t, times, side="right") - 1, 0, None)
        for _ in range(int(idx[-1]) if idx.size else 0):
            entries.popleft()
        out: NDArray[np.float64] = hist_v[idx]
        return out


class RigCoupling:
    """The sensor's displacement source: steps the stage with the amplifier's applied voltage.

    :meth:`on_voltage` (the amplifier model's callback) records each applied voltage with its
    time (``clock``, the emulator servers' ``time.monotonic``); a call with sample times
    relative to ``origin()`` steps the stage once per sample with the voltage in force then.
    """

    def __init__(
        self,
        stage: Stage,
        rate: float,
        standoff: float,
        initial_voltage: float = 0.0,
        clock: Callable[[], float] = time.monotonic,
        bandwidth_hz: float = 0.0,
        filter_order: int = 2,
    ) -> None:
        self.stage = stage
        self.dt = 1.0 / rate
        #: the stage is stepped this many times per sample through the amplifier's low-pass
        self.substeps = substeps_for(stage, rate, bandwidth_hz)
        self.lowpass = (
            AmplifierLowPass(bandwidth_hz, filter_order, self.dt / self.substeps, initial_voltage)
            if bandwidth_hz > 0.0
            else None
        )
        self.standoff = standoff
        self.clock = clock
        # absolute time of relative sample time 0 (set by RigEmulator)
        self.origin: Callable[[], float] = lambda: 0.0
        self.lock = threading.Lock()
        self.history = VoltageHistory(initial_voltage, clock)
        self.applied = 0.0  # last voltage the plant received [V]
        self.displacement = 0.0  # last plant output [m]

    def on_voltage(self, value: float, at: float | None = None) -> None:
        """The amplifier applied ``value`` at server time ``at`` (None: now)."""
        with self.lock:
            self.history.record(value, at)

    def _step_many(self, voltages: NDArray[np.float64], h: float) -> NDArray[np.float64]:
        """Rows (applied, reading, status) at the end of each sample (every ``substeps``)."""
        step_many = getattr(self.stage, "step_many", None)
        if step_many is not None:
            rows: NDArray[np.float64] = step_many(voltages, h, self.substeps)
            return rows
        out = np.empty((voltages.size // self.substeps, 3))
        for i, v in enumerate(voltages):
            row = self.stage.step(float(v), h)
            if (i + 1) % self.substeps == 0:
                out[i // self.substeps] = row
        return out

    def __call__(self, times: NDArray[np.float64]) -> NDArray[np.float64]:
        """Sensor readings (standoff + displacement [m], NaN when not OK) at ``times`` [s] from
        ``origin()``, one stage step per sample (class docstring).
        """
        out = np.empty(len(times))
        t_abs = self.origin() + np.asarray(times, dtype=np.float64)
        with self.lock:
            if self.lowpass is None:
                for k in range(len(times)):
                    volts = self.history.value_at(float(t_abs[k]))
                    applied, y, status = self.stage.step(volts, self.dt)
                    out[k] = self._reading(applied, y, status)
                return out
            # the command in force at each substep, through the amplifier's low-pass
            h = self.dt / self.substeps
            held = self.history.values_at(substep_times(t_abs, self.substeps, h))
            rows = self._step_many(self.lowpass.run(held), h)
            for k, (applied, y, status) in enumerate(rows):
                out[k] = self._reading(applied, y, status)
        return out

    def _reading(self, applied: float, y: float, status: float) -> float:
        self.applied, self.displacement = float(applied), float(y)
        return self.standoff + y if int(status) == 0 and math.isfinite(y) else math.nan


class RigEmulator:
    """Amplifier (GCS on TCP or pty, or MDT69x on pty) + optoNCDT sensor (pty) around one stage.

    ``amplifier_bandwidth`` [Hz] (0: ideal) and ``amplifier_filter_order`` (1 or 2): the
    amplifier's output low-pass (:class:`AmplifierLowPass`) between command and stage.
    """

    def __init__(
        self,
        stage: Stage,
        sensor_format: FrameFormat,
        measuring_range: float,
        *,
        amplifier: str = "gcs",
        amplifier_tcp_port: int | None = None,
        rate: float = 1000.0,
        standoff: float | None = None,
        sensor_errors: float = 0.0,
        amplifier_faults: Faults | None = None,
        sensor_faults: Faults | None = None,
        seed: int | None = None,
        sensor_link: str | None = None,
        amplifier_link: str | None = None,
        amplifier_range: tuple[float, float] | None = None,
        realtime_priority: int = 0,
        amplifier_bandwidth: float = 0.0,
        amplifier_filter_order: int = 2,
    ) -> None:
        self.amplifier = amplifier_model(amplifier, amplifier_range, amplifier_tcp_port)
        standoff = 0.5 * measuring_range if standoff is None else standoff
        self.coupling = RigCoupling(
            stage,
            rate,
            standoff,
            self.amplifier.applied_voltage,
            bandwidth_hz=amplifier_bandwidth,
            filter_order=amplifier_filter_order,
        )
        self.amplifier.on_voltage = self.coupling.on_voltage
        self.sensor = OptoNCDTDeviceModel(
            sensor_format,
            measuring_range,
            rate,
            source=self.coupling,
            error_probability=sensor_errors,
            seed=seed,
        )
        self.coupling.origin = lambda: self.sensor.t0 or 0.0
        self.amplifier_server = EmulatorServer(
            self.amplifier,
            faults=amplifier_faults,
            realtime_priority=realtime_priority,
            **amplifier_endpoint(amplifier_tcp_port, amplifier_link),
        )
        self.sensor_server = EmulatorServer(
            self.sensor,
            pty=True,
            pty_link=sensor_link,
            faults=sensor_faults,
            realtime_priority=realtime_priority,
        )

    @property
    def servers(self) -> dict[str, EmulatorServer]:
        """The two servers by device name (the amplifier's, ``optoncdt``)."""
        return {self.amplifier.name: self.amplifier_server, "optoncdt": self.sensor_server}

    def start(self) -> "RigEmulator":
        """Start both servers; returns the rig."""
        self.amplifier_server.start()
        self.sensor_server.start()
        return self

    def stop(self) -> None:
        """Stop both servers (the sensor first)."""
        self.sensor_server.stop()
        self.amplifier_server.stop()

    def __enter__(self) -> "RigEmulator":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
