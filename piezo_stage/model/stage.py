"""The simulated stage: amplifier -> Bouc-Wen plant -> laser sensor (small composable models).

``SimulatedStage.step(command_voltage, dt) -> (applied_voltage, displacement, status)`` is what
the ``plant`` node and the rig emulator call; the node only schedules it. Defaults are ideal
(no limits, infinite bandwidth, no slew limit, no quantisation, no noise, unlimited range).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from enum import IntEnum
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from .errors import InvalidCommandError, ParameterValueError
from .parameter_set import ParameterSet
from .plant import DEFAULT_TOL, DynamicPlant, StaticPlant, _check_dt
from .stage_file import Stage

__all__ = [
    "AmplifierModel",
    "AxesSample",
    "CoupledStage",
    "SensorModel",
    "SimulatedStage",
    "SensorStatus",
    "LASER_RANGE",
    "LASER_RESOLUTION",
]

#: Micro-Epsilon optoNCDT 1607-500 of the thesis rig (11.2.1): 500 um range, 0.1 um resolution
LASER_RANGE = 500e-6
LASER_RESOLUTION = 0.1e-6


class SensorStatus(IntEnum):
    """Status codes of ``piezo_stage_msgs/Displacement`` (docs/design.md section 3)."""

    OK = 0
    NO_TARGET = 1
    TOO_CLOSE = 2
    TOO_FAR = 3
    INVALID = 4


def _finite_command(value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError) as exc:
        raise InvalidCommandError(f"command voltage must be a number, got {value!r}") from exc
    if not math.isfinite(value):
        raise InvalidCommandError(f"command voltage must be finite, got {value!r}")
    return value


class AmplifierModel:
    """Voltage amplifier: clamp to [v_min, v_max], first-order lag, slew-rate limit.

    ``bandwidth_hz`` = 0 is an ideal (instantaneous) amplifier, ``slew_rate`` = 0 no slew limit.
    Per step: target = clamp(command); v <- target + (v - target) exp(-2 pi f dt) (exact for a
    first-order lag with the target held); the change is limited to slew_rate * dt.
    """

    def __init__(
        self,
        v_min: float = -math.inf,
        v_max: float = math.inf,
        bandwidth_hz: float = 0.0,
        slew_rate: float = 0.0,
        initial_voltage: float = 0.0,
    ) -> None:
        v_min, v_max = float(v_min), float(v_max)
        if math.isnan(v_min) or math.isnan(v_max) or not v_min < v_max:
            raise ParameterValueError(
                f"amplifier limits need v_min < v_max, got [{v_min!r}, {v_max!r}]"
            )
        if not (math.isfinite(bandwidth_hz) and bandwidth_hz >= 0.0):
            raise ParameterValueError(f"bandwidth_hz must be >= 0 (0: ideal), got {bandwidth_hz!r}")
        if not (math.isfinite(slew_rate) and slew_rate >= 0.0):
            raise ParameterValueError(f"slew_rate must be >= 0 (0: none), got {slew_rate!r}")
        self.v_min, self.v_max = v_min, v_max
        self.bandwidth_hz = float(bandwidth_hz)
        self.slew_rate = float(slew_rate)
        self.reset(initial_voltage)

    def clamp(self, value: float) -> float:
        """Clamp ``value`` to [v_min, v_max]."""
        return min(self.v_max, max(self.v_min, value))

    def reset(self, voltage: float = 0.0) -> None:
        """Set the output voltage (clamped)."""
        self.voltage = self.clamp(_finite_command(voltage))

    def step(self, command: float, dt: float) -> float:
        """Output voltage after holding ``command`` for dt (NaN/inf raise InvalidCommandError)."""
        target = self.clamp(_finite_command(command))
        dt = _check_dt(dt)
        new = target
        if self.bandwidth_hz > 0.0:
            new = target + (self.voltage - target) * math.exp(
                -2.0 * math.pi * self.bandwidth_hz * dt
            )
        if self.slew_rate > 0.0:
            limit = self.slew_rate * dt
            new = self.voltage + min(limit, max(-limit, new - self.voltage))
        self.voltage = self.clamp(new)
        return self.voltage


class SensorModel:
    """Laser triangulation sensor: measuring range, gaussian noise (seeded), quantisation.

    Displacements below ``range_min`` read TOO_CLOSE, above ``range_max`` TOO_FAR (value NaN);
    otherwise OK with value round((y + noise) / resolution) * resolution. ``resolution`` = 0
    and ``noise_std`` = 0 turn those effects off.
    """

    def __init__(
        self,
        noise_std: float = 0.0,
        resolution: float = 0.0,
        range_min: float = -math.inf,
        range_max: float = math.inf,
        seed: int = 0,
    ) -> None:
        if not (math.isfinite(noise_std) and noise_std >= 0.0):
            raise ParameterValueError(f"noise_std must be >= 0, got {noise_std!r}")
        if not (math.isfinite(resolution) and resolution >= 0.0):
            raise ParameterValueError(f"resolution must be >= 0, got {resolution!r}")
        if math.isnan(range_min) or math.isnan(range_max) or not range_min < range_max:
            raise ParameterValueError(
                f"sensor range needs range_min < range_max, got [{range_min!r}, {range_max!r}]"
            )
        self.noise_std = float(noise_std)
        self.resolution = float(resolution)
        self.range_min, self.range_max = float(range_min), float(range_max)
        self.seed = int(seed)
        self._rng = np.random.default_rng(self.seed)
        unbounded = math.isinf(range_min) and math.isinf(range_max)
        self._ideal = noise_std == 0.0 and resolution == 0.0 and unbounded

    @classmethod
    def laser(cls, midpoint: float = 0.0, noise_std: float = 0.0, seed: int = 0) -> "SensorModel":
        """The thesis laser (optoNCDT 1607-500): 500 um range centred on ``midpoint``, 0.1 um
        steps.
        """
        half = 0.5 * LASER_RANGE
        return cls(
            noise_std=noise_std,
            resolution=LASER_RESOLUTION,
            range_min=midpoint - half,
            range_max=midpoint + half,
            seed=seed,
        )

    def measure(self, displacement: float) -> tuple[float, int]:
        """(reading, status) for the true displacement; the reading is NaN unless status is OK."""
        if not math.isfinite(displacement):
            return math.nan, int(SensorStatus.INVALID)
        if displacement < self.range_min:
            return math.nan, int(SensorStatus.TOO_CLOSE)
        if displacement > self.range_max:
            return math.nan, int(SensorStatus.TOO_FAR)
        value = displacement
        if self.noise_std > 0.0:
            value += self.noise_std * float(self._rng.standard_normal())
        if self.resolution > 0.0:
            steps = value / self.resolution
            value = round(steps) * self.resolution if math.isfinite(steps) else math.inf
        if not math.isfinite(value):  # noise or quantum beyond the largest float: no reading
            return math.nan, int(SensorStatus.INVALID)
        return value, int(SensorStatus.OK)

    def measure_many(
        self, displacements: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """:meth:`measure` of each displacement in turn (the same noise draws, in order),
        vectorised: (readings, statuses).
        """
        y = np.asarray(displacements, dtype=float)
        if self._ideal:  # the displacement itself, INVALID where it is not finite
            finite = np.isfinite(y)
            if finite.all():
                return y.copy(), np.zeros(y.shape, dtype=np.int64)
        status = np.full(y.shape, int(SensorStatus.OK), dtype=np.int64)
        status[y > self.range_max] = int(SensorStatus.TOO_FAR)
        status[y < self.range_min] = int(SensorStatus.TOO_CLOSE)
        status[~np.isfinite(y)] = int(SensorStatus.INVALID)
        ok = status == int(SensorStatus.OK)
        values = np.full(y.shape, math.nan)
        values[ok] = y[ok]
        if self.noise_std > 0.0:
            values[ok] += self.noise_std * self._rng.standard_normal(int(ok.sum()))
        if self.resolution > 0.0:
            with np.errstate(over="ignore"):
                values[ok] = np.round(values[ok] / self.resolution) * self.resolution
        lost = ok & ~np.isfinite(values)  # noise or quantum beyond the largest float
        values[lost], status[lost] = math.nan, int(SensorStatus.INVALID)
        return values, status


class SimulatedStage:
    """Amplifier -> plant (static (10.15) or dynamic (11.1)) -> sensor, one step at a time."""

    def __init__(
        self,
        parameter_set: ParameterSet,
        amplifier: AmplifierModel | None = None,
        sensor: SensorModel | None = None,
        x0: float = 0.0,
        xdot0: float = 0.0,
        w0: float | None = None,
        initial_voltage: float = 0.0,
        tol: float = DEFAULT_TOL,
    ) -> None:
        self.parameter_set = parameter_set
        self.amplifier = amplifier if amplifier is not None else AmplifierModel()
        self.sensor = sensor if sensor is not None else SensorModel()
        self.amplifier.reset(initial_voltage)
        w0 = parameter_set.w0 if w0 is None else w0
        if parameter_set.form == "dynamic":
            dynamics = parameter_set.dynamics
            assert dynamics is not None  # ParameterSet: the dynamic form has dynamics
            self.plant: StaticPlant | DynamicPlant = DynamicPlant(
                parameter_set.bouc_wen, dynamics, x0=x0, xdot0=xdot0, w0=w0, tol=tol
            )
        else:
            self.plant = StaticPlant(parameter_set.bouc_wen, w0=w0, v0=self.amplifier.voltage)
        self.steps = 0
        self.time = 0.0

    def _plant_output(self) -> float:
        return self.plant.output()

    def output(self) -> tuple[float, float, int]:
        """(applied voltage, sensor reading, status) now, without advancing."""
        value, status = self.sensor.measure(self._plant_output())
        return self.amplifier.voltage, value, status

    def step(self, command_voltage: float, dt: float) -> tuple[float, float, int]:
        """Hold ``command_voltage`` for dt; return (applied voltage, sensor reading, status).

        NaN/inf commands raise :class:`InvalidCommandError` and leave the state unchanged.
        """
        applied = self.amplifier.step(command_voltage, dt)
        if isinstance(self.plant, DynamicPlant):
            y = self.plant.step(applied, dt)
        else:
            y = self.plant.step(applied)
        self.steps += 1
        self.time += dt
        value, status = self.sensor.measure(y)
        return applied, value, status

    def step_many(
        self, commands: NDArray[np.float64], dt: float, every: int = 1
    ) -> NDArray[np.float64]:
        """:meth:`step` for each of ``commands`` in turn; rows (applied, reading, status) after
        steps every-1, 2 every-1, ... (one plant call when the amplifier is ideal: the rig
        emulator's substeps).
        """
        commands = np.asarray(commands, dtype=float)
        ideal = self.amplifier.bandwidth_hz == 0.0 and self.amplifier.slew_rate == 0.0
        out = np.empty((commands.size // every, 3))
        if not ideal:
            for k, command in enumerate(commands):
                row = self.step(float(command), dt)
                if (k + 1) % every == 0:
                    out[k // every] = row
            return out
        if not np.all(np.isfinite(commands)):
            raise InvalidCommandError("command voltages must be finite")
        _check_dt(dt)
        applied = np.minimum(np.maximum(commands, self.amplifier.v_min), self.amplifier.v_max)
        if isinstance(self.plant, DynamicPlant):
            x, _, _ = self.plant.simulate(applied, dt)
            y = x + self.plant.params.y0
        else:
            y = self.plant.simulate(applied)
        if commands.size:
            self.amplifier.voltage = float(applied[-1])
        self.steps += commands.size
        self.time += commands.size * dt
        picked = slice(every - 1, out.shape[0] * every, every)
        out[:, 0] = applied[picked]
        out[:, 1], out[:, 2] = self.sensor.measure_many(y[picked])
        return out


class AxesSample(NamedTuple):
    """One step of a :class:`CoupledStage`, per axis in the stage's order."""

    applied: NDArray[np.float64]  #: amplifier output voltages [V]
    readings: NDArray[np.float64]  #: sensor readings [m] (NaN unless the status is OK)
    status: NDArray[np.int64]  #: :class:`SensorStatus` codes


class CoupledStage:
    """N axes of a :class:`~piezo_stage.model.stage_file.Stage`, each an amplifier and a plant,
    whose sensors read the coupled displacements y = y0 + C (y* - y0), one step at a time.

    Each axis is a :class:`SimulatedStage` with an ideal sensor (its own displacement y*),
    starting from ``x0``, ``xdot0``, ``w0`` (None: its parameter set's) and ``initial_voltage``;
    ``sensors[i]`` then measures axis i's coupled displacement.
    """

    def __init__(
        self,
        stage: Stage,
        amplifiers: Sequence[AmplifierModel] | None = None,
        sensors: Sequence[SensorModel] | None = None,
        tol: float = DEFAULT_TOL,
        x0: float = 0.0,
        xdot0: float = 0.0,
        w0: float | None = None,
        initial_voltage: float = 0.0,
    ) -> None:
        n = len(stage.axes)
        amplifiers = (
            list(amplifiers) if amplifiers is not None else [AmplifierModel() for _ in range(n)]
        )
        sensors = list(sensors) if sensors is not None else [SensorModel() for _ in range(n)]
        if len(amplifiers) != n or len(sensors) != n:
            raise ParameterValueError(
                f"a stage of {n} axes needs {n} amplifiers and {n} sensors, "
                f"got {len(amplifiers)} and {len(sensors)}"
            )
        self.stage = stage
        self.axes = [
            SimulatedStage(
                axis.model,
                amplifier=amp,
                x0=x0,
                xdot0=xdot0,
                w0=w0,
                initial_voltage=initial_voltage,
                tol=tol,
            )
            for axis, amp in zip(stage.axes, amplifiers)
        ]
        self.sensors = sensors
        self._y0 = stage.rest_outputs()
        self._own = np.array([a.output()[1] for a in self.axes])
        self.time = 0.0

    def _measure(self, applied: NDArray[np.float64]) -> AxesSample:
        coupled = self._y0 + self.stage.coupling @ (self._own - self._y0)
        readings = np.empty(len(self.axes))
        status = np.empty(len(self.axes), dtype=np.int64)
        for i, sensor in enumerate(self.sensors):
            readings[i], status[i] = sensor.measure(float(coupled[i]))
        return AxesSample(applied, readings, status)

    def output(self) -> AxesSample:
        """(applied voltages, sensor readings, statuses) now, without advancing."""
        return self._measure(np.array([a.amplifier.voltage for a in self.axes]))

    def step_voltages(self, voltages: NDArray[np.float64], h: float, every: int) -> AxesSample:
        """Hold ``voltages[i, k]`` on axis i for ``h`` each, k = 0, 1, ... (what an amplifier
        applies between samples, e.g. a low-pass's output; each axis's amplifier limits
        applied); a sample of the coupled sensors after every ``every`` steps: arrays of shape
        (samples, axes). Non-finite voltages raise :class:`InvalidCommandError` before any axis
        moves.
        """
        voltages = np.asarray(voltages, dtype=float)
        n_axes = len(self.axes)
        if voltages.ndim != 2 or voltages.shape[0] != n_axes or voltages.shape[1] < every:
            raise InvalidCommandError(
                f"a stage of {n_axes} axes needs an (axes x steps) array of at least {every} "
                f"steps, got shape {voltages.shape}"
            )
        if not np.all(np.isfinite(voltages)):
            raise InvalidCommandError("voltages must be finite")
        n = voltages.shape[1] // every
        applied, own = np.empty((n, n_axes)), np.empty((n, n_axes))
        for i, axis in enumerate(self.axes):
            rows = axis.step_many(voltages[i, : n * every], h, every)
            applied[:, i], own[:, i] = rows[:, 0], rows[:, 1]
        self._own = own[-1].copy()
        self.time += n * every * h
        coupled = self._y0 + (own - self._y0) @ self.stage.coupling.T
        readings = np.empty((n, n_axes))
        status = np.empty((n, n_axes), dtype=np.int64)
        for i, sensor in enumerate(self.sensors):
            readings[:, i], status[:, i] = sensor.measure_many(coupled[:, i])
        return AxesSample(applied, readings, status)

    def step(self, commands: Sequence[float], dt: float) -> AxesSample:
        """Hold ``commands[i]`` on axis i for dt; (applied, readings, statuses) per axis. A NaN or
        infinite command raises :class:`InvalidCommandError` before any axis moves.
        """
        values = [_finite_command(c) for c in commands]
        if len(values) != len(self.axes):
            raise InvalidCommandError(
                f"a stage of {len(self.axes)} axes needs as many commands, got {len(values)}"
            )
        applied = np.empty(len(self.axes))
        for i, (axis, command) in enumerate(zip(self.axes, values)):
            applied[i], self._own[i], _ = axis.step(command, dt)
        self.time += dt
        return self._measure(applied)
