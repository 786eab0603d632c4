"""Emulated PI E-727-class controller (E-709: its one-axis form) with its own servo clock, bound
to a simulated stage: what PI's GCS 2.0 manual (E727T0005) describes for the commands below.

The controller's state advances in whole servo cycles (50 us, ``SPA? 1 0x0E000200``) to the
arrival time of each command line (relative to ``start``), a chunk of cycles at a time: the
per-cycle output voltages are built with numpy and the stage is stepped once per chunk
(``step_voltages``), not once per host sample and not per cycle in Python.

Output per axis (axis i drives output channel i and reads input channel i):

- servo off (``SVO 0``): the voltage set by ``SVA``/``SVR``, or the wave generator's output;
- servo on (``SVO 1``): a discrete integral controller on the axis's sensor at the servo rate,
  u[k+1] = u[k] + (lam / g) (r[k] - y^[k]), r the target (``MOV``/``MVR`` or the generator's
  output), lam = 1 - exp(-cycle / servo_time_constant), g the stage's quasi-static gain
  [um/V]. The sensor is read once per chunk of at most :data:`SERVO_CHUNK` cycles; within a
  chunk y^ is that reading extrapolated through g (one stage step per chunk, vectorised with
  ``scipy.signal.lfilter``), so the loop closes on the real (hysteretic, coupled) stage every
  chunk and settles without steady error. ``ONT?``: |target - POS?| <= ``on_target_tolerance``.

Commands beyond :class:`~.gcs_device.GCSDeviceModel`'s: ``POS?``, ``TSP?``, ``TMN?``,
``TMX?``, ``ONT?``, ``MVR``, ``SVR``, ``ECO?``, ``HDR?``, ``HPA?``, ``SPA``/``SPA?``, ``TNR?``,
``DRC``/``DRC?``, ``DRT``/``DRT?``, ``RTR``/``RTR?``, ``DRL?``, ``DRR?``, ``WAV``
(``SIN_P``, ``LIN``, ``RAMP``, ``PNT``; append ``X``/``&``/``+``), ``WAV?``, ``GWD?``,
``WMS?``, ``WCL``, ``WSL``/``WSL?``, ``WGC``/``WGC?``, ``WTR``/``WTR?``, ``WOS``/``WOS?``,
``WGO``/``WGO?``, ``TWG?``, and the single characters #5 (motion?), #7 (ready?), #24 (stop).
Positions are in um as PI reports them (the stage's metres x 1e6).

Wave generator g drives axis g: with the servo off its output (table point + ``WOS`` offset)
is the output voltage, with the servo on it is the target; one table point per ``WTR``
servo cycles; ``WGC`` cycles (0: endless), then it stops holding its last value. Start mode
1 (start now) only; ``WTR`` interpolation 0 only. ``LIN``/``RAMP`` speed-up/down lengths
are accepted but the curves stay straight; a ``SIN_P``/``RAMP`` curve longer than its
segment wraps around the segment's start.

Data recorder (manual section "Data Recording"): ``TNR?`` tables sharing
:data:`MAX_RECORD_POINTS` points (0x16000200) equally; point k holds what cycle k reads and
sets: the sensor before the cycle's output acts, and that output; a point every ``RTR`` servo
cycles,
recording all tables from the trigger until they are full. ``WGO`` (start) always triggers;
``DRT`` 1 adds any command changing a position (``MOV``, ``MVR``, ``SVA``, ``SVR``), 2 the
next command (then back to 0), 3 (a digital input) never fires here. ``DRR?`` answers in the
GCS array format (``# ... = ...`` header lines, ``# END_HEADER``, one row per point), what
PIPython's ``qDRR`` reads; :meth:`PIControllerModel.recorded` gives the same arrays in
Python. :meth:`PIControllerModel.inject_drr_fault` cuts or corrupts the next ``DRR?`` reply.

Idle gaps (no generator running, nothing recording) longer than :data:`IDLE_SKIP_S` are
skipped but for their last :data:`IDLE_KEEP_S`: a held voltage or target has settled by then.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.signal import lfilter

from ..errors import ConfigError
from ..gcs import (
    ERR_INVALID_AXIS,
    ERR_PARAM_RANGE,
    ERR_SERVO_OFF_MOVE,
    ERR_SERVO_ON,
    ERR_SYNTAX,
    ERR_VOLTAGE_LIMITS,
    format_value,
)
from .gcs_device import IDN, IDN_E727, GCSDeviceModel, _CommandError, _LineSession

__all__ = [
    "DataRecorder",
    "PIControllerModel",
    "ServoStage",
    "WaveGenerator",
    "gcs_array",
    "wave_segment",
]

Array = NDArray[np.float64]

SERVO_CYCLE = 50e-6  #: s, ``SPA? 1 0x0E000200`` (servo update time)
MAX_RECORD_POINTS = 262144  #: data recorder points shared by the tables (0x16000200)
RECORD_TABLES = 8  #: ``TNR?`` at power-up (0x16000300)
WAVE_TABLES = 8  #: wave tables 1..8
MAX_WAVE_POINTS = 65536  #: points per wave table (``WMS?``)
SERVO_CHUNK = 20  #: cycles between sensor reads of the servo's chunked integrator (1 ms)
BUSY_CHUNK = 4000  #: cycles per stage step while generating or recording
IDLE_CHUNK = 1 << 16  #: cycles per stage step otherwise
IDLE_SKIP_S = 0.1  #: idle gaps longer than this are skipped but for their last IDLE_KEEP_S
#: what an idle gap keeps: the held output has settled by then (the ch. 11 rig's resonance
#: decays in ~1 ms), and simulating a whole second made the first command after an idle
#: minute wait a second for its answer (a client's 1 s timeout)
IDLE_KEEP_S = 0.05
UM = 1e6  #: um per m

PARAM_SERVO_CYCLE = 0x0E000200
PARAM_RECORD_RATE = 0x16000000
PARAM_MAX_POINTS = 0x16000200
PARAM_RECORD_TABLES = 0x16000300

#: GCS codes beyond those :mod:`..gcs` names
ERR_POSITION_LIMITS, ERR_STOPPED, ERR_UNKNOWN_PARAMETER, ERR_PROTECTED = 7, 10, 54, 60
ERR_WAVE_RUNNING = 73

#: ``DRC`` record options (``HDR?``): what a table records of its source
RECORD_OPTIONS = {
    0: "Nothing is recorded",
    1: "Target Position of axis",
    2: "Current Position of axis",
    3: "Position Error of axis",
    7: "Control Voltage of output channel",
    8: "Sensor Normalized of input channel",
}
#: ``DRT`` trigger options (``HDR?``)
TRIGGER_OPTIONS = {
    0: "Default setting (WGO starts recording)",
    1: "Any command changing position (MOV, MVR, SVA, SVR)",
    2: "Next command, then trigger option 0",
    3: "Digital input line (not emulated: never fires)",
}
#: parameters ``SPA?``/``HPA?`` know: id -> (type, description, writable)
PARAMETERS = {
    PARAM_RECORD_RATE: ("INT", "Data Recorder Table Rate", True),
    PARAM_SERVO_CYCLE: ("FLOAT", "Servo Update Time", False),
    PARAM_MAX_POINTS: ("INT", "Data Recorder Max Points", False),
    PARAM_RECORD_TABLES: ("INT", "Data Recorder Chan Number", True),
}


class ServoStage(Protocol):
    """What the controller drives (``piezo_stage.model.stage.CoupledStage``)."""

    def step_voltages(self, voltages: Array, h: float, every: int) -> Any:
        """Hold ``voltages[i, k]`` on axis i for h each; (applied, readings [m], status) rows
        after every ``every`` steps.
        """

    def output(self) -> Any:
        """(applied, readings [m], status) now."""


def _int(text: str, low: int = 0, high: int | None = None) -> int:
    """``text`` as an integer in [low, high] (error 1 if not an integer, 17 if outside)."""
    try:
        value = int(text, 0)
    except ValueError:
        raise _CommandError(ERR_SYNTAX) from None
    if value < low or (high is not None and value > high):
        raise _CommandError(ERR_PARAM_RANGE)
    return value


def _float(text: str) -> float:
    return GCSDeviceModel._number(text)


# --- wave tables ------------------------------------------------------------------------------
def _place(segment: Array, start: int, curve: Array, wrap: bool) -> Array:
    """Write ``curve`` into ``segment`` from index ``start`` (wrapping around or cut)."""
    index = start + np.arange(curve.size)
    if wrap:
        segment[index % segment.size] = curve
    else:
        keep = index < segment.size
        segment[index[keep]] = curve[keep]
    return segment


def wave_segment(kind: str, args: list[str]) -> Array:
    """One ``WAV`` segment (manual: WAV): ``SIN_P``/``LIN``/``RAMP`` args ``seglength amp
    offset wavelength startpoint [speedupdown] [center]``; ``PNT`` is handled by the caller.
    """
    counts = {"SIN_P": 6, "LIN": 6, "RAMP": 7}
    if kind not in counts:
        raise _CommandError(ERR_SYNTAX)
    if len(args) != counts[kind]:
        raise _CommandError(ERR_SYNTAX)
    seglength = _int(args[0], 1, MAX_WAVE_POINTS)
    amp, offset = _float(args[1]), _float(args[2])
    length = _int(args[3], 1, MAX_WAVE_POINTS)
    start = _int(args[4], 0, seglength - 1)
    k = np.arange(length, dtype=float)
    segment = np.full(seglength, offset)
    if kind == "LIN":
        _int(args[5])  # speed-up/down: accepted, not modelled
        segment[start:] = offset + amp
        return _place(segment, start, offset + amp * k / max(length - 1, 1), wrap=False)
    center = _int(args[5 if kind == "SIN_P" else 6], 0, length)
    if kind == "RAMP":
        _int(args[5])
        up = k / max(center, 1)
        down = (length - k) / max(length - center, 1)
        shape = np.where(k <= center, up, down)
    else:
        rise = 0.5 * (1.0 - np.cos(np.pi * k / max(center, 1)))
        fall = 0.5 * (1.0 + np.cos(np.pi * (k - center) / max(length - center, 1)))
        shape = np.where(k <= center, rise, fall)
    return _place(segment, start, offset + amp * np.clip(shape, 0.0, 1.0), wrap=True)


@dataclass
class WaveGenerator:
    """One wave generator (``WSL``, ``WGC``, ``WTR``, ``WOS``, ``WGO``)."""

    table: int = 0  #: connected wave table (0: none)
    cycles: int = 0  #: ``WGC`` (0: endless)
    rate: int = 1  #: ``WTR``: servo cycles per table point
    offset: float = 0.0  #: ``WOS``
    mode: int = 0  #: ``WGO`` mode while running, 0 when stopped
    start: int = 0  #: servo cycle of the start

    def output(self, points: Array, cycles: NDArray[np.int64]) -> tuple[Array, int | None]:
        """(values at servo ``cycles``, the cycle it ends at or None) of a running generator."""
        step = (cycles - self.start) // self.rate
        end = None
        if self.cycles:
            last = self.cycles * points.size - 1
            step = np.minimum(step, last)
            end = self.start + (last + 1) * self.rate
        return points[step % points.size] + self.offset, end


@dataclass
class DataRecorder:
    """The data recorder's state (``DRC``, ``DRT``, ``RTR``, ``TNR?``)."""

    n_axes: int
    tables: int = RECORD_TABLES
    rate: int = 1  #: ``RTR``
    trigger: int = 0  #: ``DRT`` option, for every table
    sources: list[str] = field(default_factory=list)
    options: list[int] = field(default_factory=list)
    data: Array = field(default_factory=lambda: np.zeros((0, 0)))
    start: int = 0  #: servo cycle of point 0 of the recording
    count: int = 0  #: points recorded (``DRL?``)
    active: bool = False

    def __post_init__(self) -> None:
        self.resize(self.tables)

    @property
    def capacity(self) -> int:
        """Points per table: the shared points in equal shares."""
        return MAX_RECORD_POINTS // self.tables

    def resize(self, tables: int) -> None:
        """``tables`` tables; the default configuration (axis i's current position)."""
        self.tables = tables
        self.sources = [str(min(i, self.n_axes - 1) + 1) for i in range(tables)]
        self.options = [2 if i < self.n_axes else 0 for i in range(tables)]
        self.data = np.zeros((tables, self.capacity))
        self.count, self.active = 0, False

    def trigger_at(self, cycle: int) -> None:
        """Start a recording at servo cycle ``cycle``."""
        self.start, self.count, self.active = cycle, 0, True

    def take(self, cycles: NDArray[np.int64], columns: Callable[[int, str], Array]) -> None:
        """Record the points among ``cycles``; ``columns(option, source)`` gives a table's
        values at each of them.
        """
        offset = cycles - self.start
        j = offset // self.rate
        mask = (offset >= 0) & (offset % self.rate == 0) & (j < self.capacity)
        if not np.any(mask):
            return
        for t in range(self.tables):
            if self.options[t]:
                self.data[t, j[mask]] = columns(self.options[t], self.sources[t])[mask]
        self.count = int(j[mask][-1]) + 1
        self.active = self.count < self.capacity


def gcs_array(names: Sequence[str], columns: Array, sample_time: float) -> list[str]:
    """Reply lines of a GCS array (``DRR?``, ``GWD?``): header, ``# END_HEADER``, rows."""
    header = [
        "# REM E-727",
        "# VERSION = 1",
        "# TYPE = 1",
        "# SEPARATOR = 32",
        f"# DIM = {len(names)}",
        f"# SAMPLE_TIME = {sample_time:.9f}",
        f"# NDATA = {columns.shape[1] if columns.ndim == 2 else 0}",
    ]
    header += [f"# NAME{i} = {name}" for i, name in enumerate(names)]
    rows = [" ".join(format_value(v) for v in row) for row in np.asarray(columns).T]
    return header + ["# END_HEADER"] + rows


class PIControllerModel(GCSDeviceModel):
    """State of the emulated E-727 (module docstring), shared by all connections.

    ``stage`` builds the simulated stage (called twice: once to measure its travel range and
    gain with a slow ramp, once for the stage driven); ``axes`` are the GCS axis identifiers,
    one per stage axis in order. ``start`` is the server time of servo cycle 0 (default: now
    on ``clock``).
    """

    name = "e727"

    def __init__(
        self,
        stage: Callable[[], ServoStage],
        axes: Sequence[str] = ("1", "2", "3"),
        *,
        v_min: float = -30.0,
        v_max: float = 130.0,
        servo_on: bool = False,
        servo_cycle: float = SERVO_CYCLE,
        servo_time_constant: float = 1e-3,
        on_target_tolerance: float = 0.02,
        start: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        on_axis_voltage: Callable[[str, float, float | None], None] | None = None,
    ) -> None:
        super().__init__(
            v_min=v_min,
            v_max=v_max,
            servo_on=servo_on,
            axes=axes,
            on_axis_voltage=on_axis_voltage,
        )
        if not (servo_cycle > 0 and servo_time_constant > 0 and on_target_tolerance > 0):
            raise ConfigError("servo_cycle, servo_time_constant, on_target_tolerance must be > 0")
        self.idn = IDN_E727 if len(self.axes) > 1 else IDN
        self.cycle_time = float(servo_cycle)
        self.tolerance = float(on_target_tolerance)
        self._lam = 1.0 - math.exp(-servo_cycle / servo_time_constant)
        self.clock = clock
        self.start = clock() if start is None else float(start)
        self.low, self.high, self.gain = _probe(stage(), len(self.axes), v_min, v_max)
        self.stage = stage()
        self.cycle = 0  #: servo cycles run so far
        n = len(self.axes)
        sample = self.stage.output()
        self.applied = np.zeros(n)  #: output voltages in force [V]
        self.position = np.asarray(sample[1], dtype=float) * UM  #: last sensor readings [um]
        self.recorder = DataRecorder(n)
        self.waves: dict[int, Array] = {}
        self.generators = [WaveGenerator() for _ in range(n)]
        self._drr_fault: str | None = None
        self._rows: dict[str, Array] = {}
        self._handlers.update(self._more_handlers())

    # --- public ---------------------------------------------------------------------------------
    def session(self) -> "_ControllerSession":
        """A connection's session (lines, and PI's single-character commands)."""
        return _ControllerSession(self)

    def cycle_at(self, now: float) -> int:
        """The servo cycle the controller has reached at server time ``now``."""
        return max(0, math.floor((now - self.start) / self.cycle_time))

    def advance_to(self, now: float | None = None) -> None:
        """Run the servo clock to server time ``now`` (default: the clock's now)."""
        with self.lock:
            self._advance(self.cycle_at(self.clock() if now is None else now))

    def recorded(self, table: int, now: float | None = None) -> Array:
        """Data recorder table ``table`` (1-based): the points recorded so far (``DRR?``)."""
        self.advance_to(now)
        with self.lock:
            return self.recorder.data[table - 1, : self.recorder.count].copy()

    def inject_drr_fault(self, kind: str) -> None:
        """The next ``DRR?`` reply is ``"cut"`` after half its rows (the link then stays
        silent: a reader times out) or carries one ``"malformed"`` row.
        """
        if kind not in ("cut", "malformed"):
            raise ConfigError(f"DRR? fault must be 'cut' or 'malformed', got {kind!r}")
        self._drr_fault = kind

    def execute(self, line: str, now: float | None = None) -> bytes:
        """Run the clock to ``now`` (the line's arrival), then the line (GCSDeviceModel)."""
        with self.lock:
            self._advance(self.cycle_at(self.clock() if now is None else now))
            if line.split() and self.recorder.trigger == 2:
                self.recorder.trigger = 0
                self.recorder.trigger_at(self.cycle)
        return super().execute(line, now)

    # --- the servo clock (lock held) ------------------------------------------------------------
    def _busy(self) -> bool:
        return self.recorder.active or any(g.mode for g in self.generators)

    def _advance(self, cycle: int) -> None:
        if cycle <= self.cycle:
            return
        while self.cycle < cycle:
            skip = cycle - self.cycle - round(IDLE_KEEP_S / self.cycle_time)
            if not self._busy() and skip > IDLE_SKIP_S / self.cycle_time:
                self.cycle += skip
            limit = SERVO_CHUNK if any(self.servo.values()) else BUSY_CHUNK
            if not self._busy() and limit == BUSY_CHUNK:
                limit = IDLE_CHUNK
            self._run_chunk(min(cycle - self.cycle, limit))

    def _wave_values(self, i: int, cycles: NDArray[np.int64]) -> Array | None:
        """Generator i's output at ``cycles`` (None when it is not running); stops it at its
        end (holding its last value as the voltage or the target).
        """
        gen = self.generators[i]
        if not gen.mode:
            return None
        values, end = gen.output(self.waves.get(gen.table, np.zeros(1)), cycles)
        if end is not None and end <= cycles[-1] + 1:
            gen.mode = 0
            axis = self.axes[i]
            if self.servo[axis]:
                self.targets[axis] = float(values[-1])
            else:
                self.voltages[axis] = float(np.clip(values[-1], self.v_min, self.v_max))
        return values

    def _servo(self, i: int, targets: Array) -> Array:
        """The integral controller's voltages for one chunk (module docstring)."""
        g = self.gain[i]
        error = targets - self.position[i]
        u = lfilter([0.0, self._lam / g], [1.0, -(1.0 - self._lam)], error)
        return np.asarray(np.clip(self.applied[i] + u, self.v_min, self.v_max), dtype=float)

    def _run_chunk(self, n: int) -> None:
        cycles = self.cycle + np.arange(n, dtype=np.int64)
        volts, targets = np.empty((len(self.axes), n)), np.empty((len(self.axes), n))
        for i, axis in enumerate(self.axes):
            wave = self._wave_values(i, cycles)
            if self.servo[axis]:
                targets[i] = self.targets[axis] if wave is None else wave
                volts[i] = self._servo(i, targets[i])
            else:
                targets[i] = self.targets[axis]
                held = self.voltages[axis] if wave is None else wave
                volts[i] = np.clip(held, self.v_min, self.v_max)
        every = 1 if self.recorder.active else n
        before = self.position.copy()  # the sensor as cycle `self.cycle` reads it
        applied, readings, _ = self.stage.step_voltages(volts, self.cycle_time, every)
        position = np.asarray(readings, dtype=float) * UM
        self.applied = np.asarray(applied[-1], dtype=float).copy()
        self.position = position[-1].copy()
        if self.recorder.active:
            # cycle k records the sensor it reads and the output it then sets: the position
            # before the cycle's voltage acts (the one after is cycle k + 1's reading)
            read = np.vstack([before, position[:-1]]).T
            self._rows = {"target": targets, "position": read, "volts": volts}
            self.recorder.take(cycles, self._column)
        self.cycle += n

    def _column(self, option: int, source: str) -> Array:
        """Per-cycle values of record ``option`` of ``source`` over the chunk just run."""
        i = self.axes.index(self._axis_of.get(source, source))
        target, position = self._rows["target"][i], self._rows["position"][i]
        column = {1: target, 2: position, 8: position, 3: target - position}.get(option)
        return np.asarray(self._rows["volts"][i] if column is None else column, dtype=np.float64)

    def _trigger_motion(self) -> None:
        """A command changed a position: DRT option 1 starts a recording."""
        if self.recorder.trigger == 1:
            self.recorder.trigger_at(self.cycle)

    # --- handlers -------------------------------------------------------------------------------
    def _more_handlers(self) -> dict[str, Callable[[list[str]], list[str] | None]]:
        def axis_q(value: Callable[[int], float]) -> Callable[[list[str]], list[str]]:
            return lambda a: self._axis_query(a, lambda x: format_value(value(self._i(x))))

        def chan_q(value: Callable[[int], float]) -> Callable[[list[str]], list[str]]:
            return lambda a: self._channel_query(a, lambda x: format_value(value(self._i(x))))

        return {
            "*IDN?": lambda a: [self.idn],
            "SVO": self._svo,
            "SVA": self._sva,
            "SVR": self._svr,
            "MOV": self._mov,
            "MVR": self._mvr,
            "POS?": axis_q(lambda i: self.position[i]),
            "ONT?": lambda a: self._axis_query(a, lambda x: str(int(self._on_target(x)))),
            "TMN?": axis_q(lambda i: self.low[i]),
            "TMX?": axis_q(lambda i: self.high[i]),
            "VOL?": chan_q(lambda i: self.applied[i]),
            "TSP?": chan_q(lambda i: self.position[i]),
            "ECO?": lambda a: [" ".join(a)],
            "HDR?": lambda a: self._hdr(),
            "HPA?": lambda a: self._hpa(),
            "SPA?": self._spa_q,
            "SPA": self._spa,
            "TNR?": lambda a: [str(self.recorder.tables)],
            "RTR?": lambda a: [str(self.recorder.rate)],
            "RTR": self._rtr,
            "DRC": self._drc,
            "DRC?": lambda a: self._table_query(a, self._drc_line),
            "DRT": self._drt,
            "DRT?": lambda a: self._table_query(a, lambda t: f"{self.recorder.trigger} 0"),
            "DRL?": lambda a: self._table_query(a, lambda t: str(self.recorder.count)),
            "DRR?": self._drr,
            "TWG?": lambda a: [str(len(self.generators))],
            "WAV": self._wav,
            "WAV?": self._wav_q,
            "WMS?": self._wms_q,
            "GWD?": self._gwd,
            "WCL": self._wcl,
            "WSL": lambda a: self._gen_set(a, "table", lambda v: _int(v, 0, WAVE_TABLES)),
            "WSL?": lambda a: self._gen_query(a, lambda g: str(g.table)),
            "WGC": lambda a: self._gen_set(a, "cycles", lambda v: _int(v, 0)),
            "WGC?": lambda a: self._gen_query(a, lambda g: str(g.cycles)),
            "WOS": lambda a: self._gen_set(a, "offset", _float),
            "WOS?": lambda a: self._gen_query(a, lambda g: format_value(g.offset)),
            "WTR": self._wtr,
            "WTR?": lambda a: self._gen_query(a, lambda g: f"{g.rate} 0"),
            "WGO": self._wgo,
            "WGO?": lambda a: self._gen_query(a, lambda g: str(g.mode)),
        }

    def _i(self, axis: str) -> int:
        return self.axes.index(axis)

    def _on_target(self, axis: str) -> bool:
        i = self._i(axis)
        return self.servo[axis] and abs(self.targets[axis] - self.position[i]) <= self.tolerance

    def _svo(self, args: list[str]) -> None:
        pairs = [(self._check_axis(a), self._flag(f)) for a, f in self._pairs(args)]
        for axis, flag in pairs:
            i = self._i(axis)
            if flag and not self.servo[axis]:
                self.targets[axis] = float(self.position[i])  # no jump: target = position
            if not flag and self.servo[axis]:
                self.voltages[axis] = float(self.applied[i])  # the output holds
            self.servo[axis] = flag

    def _not_generating(self, axes: Sequence[str]) -> None:
        if any(self.generators[self._i(a)].mode for a in axes):
            raise _CommandError(ERR_WAVE_RUNNING)

    def _sva(self, args: list[str]) -> None:
        values = self._axis_values(args)
        self._open_loop(values)

    def _svr(self, args: list[str]) -> None:
        values = self._axis_values(args)
        self._open_loop({a: self.voltages[a] + v for a, v in values.items()})

    def _open_loop(self, values: dict[str, float]) -> None:
        if self.refuse_sva_when_servo_on and any(self.servo[a] for a in values):
            raise _CommandError(ERR_SERVO_ON)
        self._not_generating(list(values))
        if any(not self.v_min <= v <= self.v_max for v in values.values()):
            raise _CommandError(ERR_VOLTAGE_LIMITS)
        for axis, value in values.items():
            self._set_voltage(axis, value)
        self._trigger_motion()

    def _mov(self, args: list[str]) -> None:
        self._closed_loop(self._axis_values(args))

    def _mvr(self, args: list[str]) -> None:
        values = self._axis_values(args)
        self._closed_loop({a: self.targets[a] + v for a, v in values.items()})

    def _closed_loop(self, values: dict[str, float]) -> None:
        if not all(self.servo[a] for a in values):
            raise _CommandError(ERR_SERVO_OFF_MOVE)
        self._not_generating(list(values))
        if any(not self.low[self._i(a)] <= v <= self.high[self._i(a)] for a, v in values.items()):
            raise _CommandError(ERR_POSITION_LIMITS)
        self.targets.update(values)
        self._trigger_motion()

    # parameters
    def _hpa(self) -> list[str]:
        lines = ["The following parameters are valid:"]
        for pid, (kind, text, _) in sorted(PARAMETERS.items()):
            lines.append(f"0x{pid:08X}=\t0\t1\t{kind}\tController\t{text}")
        return lines + ["end of help"]

    def _param_value(self, pid: int) -> str:
        values = {
            PARAM_SERVO_CYCLE: format_value(self.cycle_time),
            PARAM_RECORD_RATE: str(self.recorder.rate),
            PARAM_MAX_POINTS: str(MAX_RECORD_POINTS),
            PARAM_RECORD_TABLES: str(self.recorder.tables),
        }
        return values[pid]

    def _param(self, item: str, text: str) -> int:
        if item != "1" and item not in self.servo:
            raise _CommandError(ERR_INVALID_AXIS)
        pid = _int(text)
        if pid not in PARAMETERS:
            raise _CommandError(ERR_UNKNOWN_PARAMETER)
        return pid

    def _spa_q(self, args: list[str]) -> list[str]:
        if not args:
            pairs = [("1", f"0x{pid:08X}") for pid in sorted(PARAMETERS)]
        else:
            pairs = self._pairs(args)
        return [
            f"{item} {text}={self._param_value(self._param(item, text))}" for item, text in pairs
        ]

    def _spa(self, args: list[str]) -> None:
        if not args or len(args) % 3:
            raise _CommandError(ERR_SYNTAX)
        triples = [(self._param(*args[k : k + 2]), args[k + 2]) for k in range(0, len(args), 3)]
        if any(not PARAMETERS[pid][2] for pid, _ in triples):
            raise _CommandError(ERR_PROTECTED)
        for pid, value in triples:
            if pid == PARAM_RECORD_RATE:
                self.recorder.rate = _int(value, 1, 1 << 20)
            else:
                self.recorder.resize(_int(value, 1, RECORD_TABLES))

    # data recorder
    def _hdr(self) -> list[str]:
        lines = ["#RecordOptions"]
        lines += [f"{k}={v}" for k, v in RECORD_OPTIONS.items()]
        lines += ["#TriggerOptions"] + [f"{k}={v}" for k, v in TRIGGER_OPTIONS.items()]
        lines += [
            "#Parameters to be set with SPA",
            f"0x{PARAM_RECORD_TABLES:08X}=Data Recorder Chan Number",
            "#Additional information",
            f"{self.recorder.tables} datarecorder tables",
            f"{MAX_RECORD_POINTS} points shared by the tables",
            f"servo cycle {format_value(self.cycle_time)} s; RTR sets points per servo cycles",
            "end of help",
        ]
        return lines

    def _table(self, text: str) -> int:
        return _int(text, 1, self.recorder.tables) - 1

    def _table_query(self, args: list[str], value: Callable[[int], str]) -> list[str]:
        tables = [self._table(a) for a in args] or list(range(self.recorder.tables))
        return [f"{t + 1}={value(t)}" for t in tables]

    def _drc_line(self, t: int) -> str:
        return f"{self.recorder.sources[t]} {self.recorder.options[t]}"

    def _drc(self, args: list[str]) -> None:
        if not args or len(args) % 3:
            raise _CommandError(ERR_SYNTAX)
        rows = []
        for k in range(0, len(args), 3):
            table, source, option = self._table(args[k]), args[k + 1], _int(args[k + 2])
            if option not in RECORD_OPTIONS:
                raise _CommandError(ERR_PARAM_RANGE)
            if option and source not in self.servo and source not in self._axis_of:
                raise _CommandError(ERR_INVALID_AXIS)
            rows.append((table, source, option))
        for table, source, option in rows:
            self.recorder.sources[table], self.recorder.options[table] = source, option

    def _drt(self, args: list[str]) -> None:
        if len(args) != 3:
            raise _CommandError(ERR_SYNTAX)
        if args[0] != "0":
            self._table(args[0])
        trigger = _int(args[1])
        if trigger not in TRIGGER_OPTIONS:
            raise _CommandError(ERR_PARAM_RANGE)
        self.recorder.trigger = trigger

    def _rtr(self, args: list[str]) -> None:
        if len(args) != 1:
            raise _CommandError(ERR_SYNTAX)
        self.recorder.rate = _int(args[0], 1, 1 << 20)

    def _array_args(self, args: list[str], default_n: int, n_max: int) -> tuple[int, int]:
        """(first index, count) of ``DRR?``/``GWD?`` ``[start [n [tables]]]`` (start 1-based)."""
        first = _int(args[0], 1) - 1 if args else 0
        count = _int(args[1], 1) if len(args) > 1 else default_n - first
        if first + count > n_max or count < 0:
            raise _CommandError(ERR_PARAM_RANGE)
        return first, count

    def _drr(self, args: list[str]) -> list[str]:
        rec = self.recorder
        first, count = self._array_args(args, rec.count, rec.capacity)
        tables = [self._table(a) for a in args[2:]] or [
            t for t in range(rec.tables) if rec.options[t]
        ]
        names = [f"{RECORD_OPTIONS[rec.options[t]]} {rec.sources[t]}" for t in tables]
        lines = gcs_array(
            names, rec.data[tables, first : first + count], self.cycle_time * rec.rate
        )
        return self._with_drr_fault(lines, len(lines) - count)

    def _with_drr_fault(self, lines: list[str], header: int) -> list[str]:
        fault, self._drr_fault = self._drr_fault, None
        rows = len(lines) - header
        if fault == "malformed" and rows:
            lines[header + rows // 2] = "0.5 #garbled"
        if fault == "cut":  # the last row sent ends in " \n" (more to come) and nothing follows
            lines = lines[: header + rows // 2]
            lines[-1] += " "
        return lines

    # wave generator
    def _wave_table(self, text: str) -> int:
        return _int(text, 1, WAVE_TABLES)

    def _wav(self, args: list[str]) -> None:
        if len(args) < 3 or args[1] not in ("X", "&", "+"):
            raise _CommandError(ERR_SYNTAX)
        table, append, kind = self._wave_table(args[0]), args[1], args[2]
        if any(g.mode and g.table == table for g in self.generators):
            raise _CommandError(ERR_WAVE_RUNNING)
        old = self.waves.get(table, np.zeros(0)) if append != "X" else np.zeros(0)
        if kind == "PNT":
            points = self._pnt(old, args[3:])
        else:
            segment = wave_segment(kind, args[3:])
            if append == "+":
                points = np.zeros(max(old.size, segment.size))
                points[: old.size] += old
                points[: segment.size] += segment
            else:
                points = np.concatenate([old, segment])
        if points.size > MAX_WAVE_POINTS:
            raise _CommandError(ERR_PARAM_RANGE)
        self.waves[table] = points

    @staticmethod
    def _pnt(old: Array, args: list[str]) -> Array:
        """``PNT startpoint n p1..pn``: points written from 1-based ``startpoint`` on."""
        if len(args) < 3:
            raise _CommandError(ERR_SYNTAX)
        first, n = _int(args[0], 1, MAX_WAVE_POINTS) - 1, _int(args[1], 1, MAX_WAVE_POINTS)
        if len(args) != n + 2:
            raise _CommandError(ERR_SYNTAX)
        values = np.array([_float(v) for v in args[2:]])
        points = np.zeros(max(old.size, first + n))
        points[: old.size] = old
        points[first : first + n] = values
        return points

    def _wms_q(self, args: list[str]) -> list[str]:
        tables = [self._wave_table(a) for a in args] or range(1, WAVE_TABLES + 1)
        return [f"{t}={MAX_WAVE_POINTS}" for t in tables]

    def _wav_q(self, args: list[str]) -> list[str]:
        if not args or len(args) % 2:
            raise _CommandError(ERR_SYNTAX)
        out = []
        for table, param in zip(args[::2], args[1::2]):
            if _int(param) != 1:
                raise _CommandError(ERR_PARAM_RANGE)
            size = self.waves.get(self._wave_table(table), np.zeros(0)).size
            out.append(f"{table} {param}={size}")
        return out

    def _gwd(self, args: list[str]) -> list[str]:
        tables = [self._wave_table(a) for a in args[2:]] or sorted(self.waves)
        sizes = {self.waves.get(t, np.zeros(0)).size for t in tables}
        if len(sizes) > 1 or not tables:
            raise _CommandError(ERR_PARAM_RANGE)
        first, count = self._array_args(args, sizes.pop(), min(w.size for w in self._of(tables)))
        columns = np.array([w[first : first + count] for w in self._of(tables)])
        return gcs_array([f"Wave table {t}" for t in tables], columns, self.cycle_time)

    def _of(self, tables: list[int]) -> list[Array]:
        return [self.waves.get(t, np.zeros(0)) for t in tables]

    def _wcl(self, args: list[str]) -> None:
        tables = [self._wave_table(a) for a in args]
        if not tables:
            raise _CommandError(ERR_SYNTAX)
        if any(g.mode and g.table in tables for g in self.generators):
            raise _CommandError(ERR_WAVE_RUNNING)
        for table in tables:
            self.waves.pop(table, None)

    def _generator(self, text: str) -> WaveGenerator:
        return self.generators[_int(text, 1, len(self.generators)) - 1]

    def _gen_query(self, args: list[str], value: Callable[[WaveGenerator], str]) -> list[str]:
        ids = [_int(a, 1, len(self.generators)) for a in args]
        ids = ids or list(range(1, len(self.generators) + 1))
        return [f"{g}={value(self.generators[g - 1])}" for g in ids]

    def _gen_set(self, args: list[str], attr: str, parse: Callable[[str], object]) -> None:
        pairs = [(self._generator(g), parse(v)) for g, v in self._pairs(args)]
        if attr == "table" and any(gen.mode for gen, _ in pairs):
            raise _CommandError(ERR_WAVE_RUNNING)
        for gen, value in pairs:
            setattr(gen, attr, value)

    def _wtr(self, args: list[str]) -> None:
        if not args or len(args) % 3:
            raise _CommandError(ERR_SYNTAX)
        rows = []
        for k in range(0, len(args), 3):
            gens = self.generators if args[k] == "0" else [self._generator(args[k])]
            rate, interpolation = _int(args[k + 1], 1, 1 << 20), _int(args[k + 2])
            if interpolation != 0:
                raise _CommandError(ERR_PARAM_RANGE)
            rows += [(gen, rate) for gen in gens]
        for gen, rate in rows:
            gen.rate = rate

    def _wgo(self, args: list[str]) -> None:
        pairs = [(self._generator(g), _int(m)) for g, m in self._pairs(args)]
        if any(mode not in (0, 1) for _, mode in pairs):
            raise _CommandError(ERR_PARAM_RANGE)
        if any(mode and not self.waves.get(gen.table, np.zeros(0)).size for gen, mode in pairs):
            raise _CommandError(ERR_PARAM_RANGE)
        started = False
        for gen, mode in pairs:
            i = self.generators.index(gen)
            if gen.mode and not mode:  # stopped: the output holds its value
                self._hold(i)
            if mode and not gen.mode:
                gen.start, started = self.cycle, True
            gen.mode = mode
        if started:
            self.recorder.trigger_at(self.cycle)

    def _hold(self, i: int) -> None:
        axis = self.axes[i]
        if self.servo[axis]:
            self.targets[axis] = float(self.position[i])
        else:
            self.voltages[axis] = float(self.applied[i])

    def stop_all(self) -> None:
        """#24: stop every generator (outputs hold); error 10 latched."""
        with self.lock:
            for i, gen in enumerate(self.generators):
                if gen.mode:
                    self._hold(i)
                    gen.mode = 0
            if not self.error:
                self.error = ERR_STOPPED


def _probe(stage: ServoStage, n: int, v_min: float, v_max: float) -> tuple[Array, Array, Array]:
    """(TMN?, TMX? [um], quasi-static gain [um/V]) per axis: a slow ramp 0 -> v_min -> v_max ->
    v_min through the stage (every axis together) at 1 ms per step.
    """
    legs = [np.linspace(0.0, v_min, 200), np.linspace(v_min, v_max, 800)]
    legs.append(np.linspace(v_max, v_min, 800))
    ramp = np.concatenate(legs)
    _, readings, _ = stage.step_voltages(np.tile(ramp, (n, 1)), 1e-3, 1)
    y = np.asarray(readings, dtype=float) * UM
    rising = y[200:1000]
    gain = (rising[-1] - rising[0]) / (v_max - v_min)
    if not (np.all(np.isfinite(y)) and np.all(np.abs(gain) > 0)):
        raise ConfigError("the stage's sensors read no finite, changing position over VMI..VMA")
    return y.min(axis=0), y.max(axis=0), np.asarray(gain, dtype=float)


class _ControllerSession(_LineSession):
    """Lines as :class:`_LineSession`; PI's single characters #5, #7 and #24 answered at once."""

    model: PIControllerModel

    def handle(self, data: bytes, now: float) -> bytes:
        out = bytearray()
        for byte in (5, 7, 24):
            if byte in data:
                data = data.replace(bytes([byte]), b"")
                out += self._single(byte)
        return bytes(out) + super().handle(data, now)

    def _single(self, byte: int) -> bytes:
        if byte == 24:
            self.model.stop_all()
            return b""
        if byte == 7:
            return bytes([0xB1])  # ready
        moving = any(g.mode for g in self.model.generators)
        return f"{int(moving)}\n".encode("ascii")
