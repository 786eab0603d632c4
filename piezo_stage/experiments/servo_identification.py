"""Identification at a PI controller's servo rate: the ch. 10 T-wave pair played by its wave
generator, voltage and sensor recorded by its data recorder, read back and identified.

One period of the triangle (9.1.1) is uploaded as a wave table, a point every ``rate`` servo
cycles; run r plays it ``settle + record`` periods at offset q_r (``WOS``: 0, then q). A run
longer than a data-recorder table is played in segments of whole periods that fit one (the
table size read from the controller); each segment starts where the last one ended (the
triangle's low corner) and the records are joined on the controller's clock with the pause
between segments (the readback) taken out: for a rate-independent hysteresis a pause at
constant input leaves the state where it was. Between runs the output is ramped by the host,
slew-limited, to the next run's start; that ramp is not recorded.

Times are the controller's, counted in whole servo cycles: sample k of the record is at
``k * rate * cycle`` from the first ``WGO`` (runs after the first, and parts after a run's
first, continue from where the last ended). In a bag these are the header stamps; the log
times add the anchor, the host's wall clock when the first ``WGO`` was sent (docs/design.md,
"The controller's clock in the bags"). The record is cut into runs by the same excitation
marks the ``excitation`` node publishes, so :func:`write_bag` gives a bag that
``piezo-stage identify BAG`` and the ``identifier`` node identify to the same numbers.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from piezo_stage.hardware.amplifier import GCSAmplifier
from piezo_stage.hardware.gcs import GCSConnection
from piezo_stage.hardware.pi_recorder import RecordOption, ServoRecorder
from piezo_stage.identification.io import intervals_from_marks, recordings_from_series
from piezo_stage.identification.recording import Recording
from piezo_stage.model.signals import triangle
from piezo_stage.stopping import StopStatus, safe_stop

from .errors import ExperimentError, ExperimentInputError

#: host ramp between runs: volts per step and seconds per step (a slew limit of 2.5 kV/s)
RAMP_STEP_V, RAMP_STEP_S = 5.0, 2e-3
#: tries of the safe state; a link quiet this long [s] holds no stale reply; drain at most [s]
SAFE_ATTEMPTS, DRAIN_QUIET_S, DRAIN_MAX_S = 2, 0.05, 2.0
#: controller time left between runs in the record [s] (the unrecorded ramp)
RUN_GAP_S = 0.1
WAVE_TABLE = 1  #: the wave table the excitation goes to

Progress = Callable[[str], None]


@dataclass(frozen=True)
class TWaveExcitation:
    """The ch. 10 T-wave pair on the controller: x(t) over [low, high] then x(t) + q [V]."""

    low: float
    high: float
    q: float
    period: float = 1.0
    settle_periods: int = 16
    record_periods: int = 6
    rate: int = 1  #: servo cycles per table point and per recorded point (``WTR``, ``RTR``)

    def check(self, v_min: float, v_max: float) -> None:
        """ValueError naming what is wrong, before anything moves."""
        values = (self.low, self.high, self.q, self.period)
        if not all(np.isfinite(values)):
            raise ValueError("the excitation's voltages and period must be finite")
        if not self.high > self.low:
            raise ValueError(f"the T-wave needs high > low, got {self.low:g}..{self.high:g} V")
        if self.q <= 0.0:
            raise ValueError(f"the offset q must be positive, got {self.q:g} V")
        if self.low < v_min or self.high + self.q > v_max:
            raise ValueError(
                f"the runs span {self.low:g}..{self.high + self.q:g} V, outside the "
                f"controller's output range {v_min:g}..{v_max:g} V (VMI?/VMA?)"
            )
        if self.period <= 0 or self.settle_periods < 0 or self.record_periods < 2:
            raise ValueError("a positive period, settle >= 0 and at least 2 recorded periods")
        if self.rate < 1:
            raise ValueError(f"rate must be >= 1 servo cycle, got {self.rate}")

    def table(self, cycle: float) -> NDArray[np.float64]:
        """One period of the triangle, a point every ``rate`` servo cycles, from ``low``."""
        n = int(round(self.period / (cycle * self.rate)))
        if n < 4:
            raise ValueError(f"a period of {self.period:g} s holds {n} table points")
        t: NDArray[np.float64] = np.arange(n, dtype=np.float64) * (cycle * self.rate)
        return triangle(t, n * cycle * self.rate, self.low, self.high)

    @property
    def periods(self) -> int:
        """Periods per run."""
        return self.settle_periods + self.record_periods


@dataclass
class ServoRecord:
    """What the data recorder gave: the two runs on the controller's clock, and the marks."""

    ticks: NDArray[np.int64]  #: servo cycles from the first ``WGO``
    voltage: NDArray[np.float64]  #: [V], the output voltage (record option 7)
    displacement: NDArray[np.float64]  #: [m], the controller's sensor (record option 2)
    marks: list[tuple[float, int, bool, float]]  #: (t, run, steady, offset) as ExcitationInfo
    cycle: float  #: servo cycle [s]
    excitation: TWaveExcitation
    anchor_ns: int  #: host wall clock [ns] at the first WGO
    segments: list[int] = field(default_factory=list)  #: points of each read-back segment

    @property
    def t(self) -> NDArray[np.float64]:
        """When each point was recorded [s], from the first ``WGO``."""
        return np.asarray(self.ticks * self.cycle, dtype=np.float64)

    @property
    def voltage_t(self) -> NDArray[np.float64]:
        """When each recorded voltage acts [s]: a servo cycle reads its sensor, then sets its
        output, so voltage k is in force from the cycle after point k, and position k follows
        the voltages before it (the recordings hold the voltage between its stamps). Both
        stamps are whole servo cycles times the cycle, so a position and the voltage set a
        cycle before it carry the same float and the hold pairs them, never an older one."""
        return np.asarray((self.ticks + 1) * self.cycle, dtype=np.float64)

    def recordings(
        self, name: str = "data recorder", input_name: str = "voltage"
    ) -> list[Recording]:
        """The runs, cut by the marks as a bag of them is cut (``load_bag``): voltage ->
        displacement (ch. 10), or displacement -> voltage with ``input_name`` "displacement"
        (the ch. 11 form u = Φ(x), whose parameters are the stage model's)."""
        intervals = intervals_from_marks([(t, run, steady) for t, run, steady, _ in self.marks])
        tv = self.voltage_t
        if input_name == "displacement":
            return recordings_from_series(
                self.t, self.displacement, tv, self.voltage, None, intervals, name, "m", "V"
            )
        status = np.zeros(self.t.size, dtype=np.uint8)
        return recordings_from_series(
            tv, self.voltage, self.t, self.displacement, status, intervals, name
        )


def ramp_to(amplifier: GCSAmplifier, target: float, status: StopStatus | None = None) -> None:
    """Slew-limited host ramp of the output to ``target`` (``SVA`` steps of RAMP_STEP_V);
    ``status`` says how far there is still to go."""
    now = amplifier.read_voltage()
    steps = int(np.ceil(abs(target - now) / RAMP_STEP_V))
    for v in np.linspace(now, target, steps + 1)[1:]:
        if status is not None:
            status.text = f"ramping axis {amplifier.axis}: {abs(now - target):.1f} V left"
        amplifier.write_voltage(float(v))
        now = float(v)
        time.sleep(RAMP_STEP_S)


def record_t_waves(
    amplifier: GCSAmplifier,
    recorder: ServoRecorder,
    excitation: TWaveExcitation,
    generator: int,
    limits: tuple[float, float],
    progress: Progress = lambda text: None,
) -> ServoRecord:
    """Play and record both runs (module docstring) on ``amplifier``'s axis (opened: servo
    off), driven by wave generator ``generator``, within the output ``limits`` (VMI?, VMA?).
    On any error the generator is stopped and the output ramped to max(VMI?, 0 V)."""
    excitation.check(*limits)
    cycle = recorder.servo_cycle()
    table = excitation.table(cycle)
    per_period = table.size
    recorder.set_tables(2)  # voltage and sensor: the recorder's points in two shares
    capacity = recorder.table_points()
    fit = capacity // per_period
    if fit < 1:
        raise ExperimentInputError(
            f"one period ({per_period} points at {excitation.rate} servo cycle(s) per point) "
            f"does not fit a data recorder table of {capacity} points: raise the rate"
        )
    recorder.upload(WAVE_TABLE, table)
    axis = amplifier.axis
    recorder.configure(
        [(axis, RecordOption.PIEZO_VOLTAGE), (axis, RecordOption.CURRENT_POSITION)],
        excitation.rate,
    )
    try:
        return _play_runs(amplifier, recorder, excitation, generator, cycle, fit, progress)
    except BaseException:
        safe_state(amplifier, recorder, generator, limits[0])
        raise


def _play_runs(
    amplifier: GCSAmplifier,
    recorder: ServoRecorder,
    excitation: TWaveExcitation,
    generator: int,
    cycle: float,
    fit: int,
    progress: Progress,
) -> ServoRecord:
    per_period = excitation.table(cycle).size
    columns: list[NDArray[np.float64]] = []
    ticks: list[NDArray[np.int64]] = []
    marks: list[tuple[float, int, bool, float]] = []
    segments: list[int] = []
    tick_next, anchor_ns = 0, 0
    gap = int(round(RUN_GAP_S / cycle))
    for run, offset in enumerate((0.0, excitation.q)):
        ramp_to(amplifier, excitation.low + offset)
        t_next = tick_next * cycle
        marks.append((t_next, run, False, offset))
        marks.append((t_next + excitation.settle_periods * excitation.period, run, True, offset))
        left = excitation.periods
        while left:
            n = min(left, fit)
            recorder.connect(generator, WAVE_TABLE, n, excitation.rate, offset)
            if not anchor_ns:
                anchor_ns = time.time_ns()
            recorder.start([generator])
            progress(f"run {run}: {n} period(s) of {excitation.period:g} s playing")
            recorder.wait_until_stopped([generator], n * excitation.period)
            count = min(recorder.recorded(), n * per_period)
            if count < n * per_period:
                raise ExperimentError(
                    f"the data recorder holds {count} of the {n * per_period} points played"
                )
            data = recorder.read(2, count).columns
            ticks.append(tick_next + np.arange(count, dtype=np.int64) * excitation.rate)
            columns.append(data)
            segments.append(count)
            tick_next += count * excitation.rate
            left -= n
        marks.append((tick_next * cycle, run, False, offset))  # the run's end ("plan done")
        tick_next += gap
    record = np.concatenate(columns, axis=1)
    return ServoRecord(
        ticks=np.concatenate(ticks),
        voltage=record[0],
        displacement=record[1] * 1e-6,  # um, as PI reports positions
        marks=marks,
        cycle=cycle,
        excitation=excitation,
        anchor_ns=anchor_ns,
        segments=segments,
    )


def safe_state(
    amplifier: GCSAmplifier, recorder: ServoRecorder, generator: int, v_min: float
) -> None:
    """The generator stopped and the output ramped to max(v_min, 0 V), whatever signals come
    meanwhile (:func:`~piezo_stage.stopping.safe_stop`). A link left mid-exchange by a stop is
    drained first; a failed attempt is tried once more, then warned of (the caller reports the
    first error)."""
    target = max(v_min, 0.0)
    with safe_stop(f"bringing axis {amplifier.axis} to {target:g} V") as status:
        failure: Exception | None = None
        for _ in range(SAFE_ATTEMPTS):
            try:
                _drain(amplifier.conn)
                recorder.stop([generator])
                ramp_to(amplifier, target, status)
                return
            except Exception as exc:
                failure = exc
        warnings.warn(
            f"axis {amplifier.axis}: could not bring the output to {target:g} V ({failure}); "
            "check the amplifier",
            stacklevel=2,
        )


def _drain(conn: GCSConnection) -> None:
    """Forget what an interrupted exchange left on the link: its reply may still be arriving,
    so read until the link has been quiet for DRAIN_QUIET_S (at most DRAIN_MAX_S)."""
    conn.flush()
    end = time.monotonic() + DRAIN_MAX_S
    while time.monotonic() < end and conn.transport.read(DRAIN_QUIET_S):
        pass


def write_bag(record: ServoRecord, path: str | Path, namespace: str = "/piezo") -> Path:
    """The record as a bag of ``voltage``, ``displacement`` and ``excitation``: header stamps
    on the controller's clock (t from the first ``WGO``: its samples keep their exact
    spacing, which seconds since 1970 in a float would round to 0.2 µs), log times on the
    host's (``anchor + t``)."""
    from piezo_stage.bag import qos
    from piezo_stage.bag.series import encode_series
    from piezo_stage.bag.types import header, message_class, serialize
    from piezo_stage.bag.writer import BagWriter

    excitation_type = "piezo_stage_msgs/msg/ExcitationInfo"
    stamps = {  # the controller's clock
        "voltage": np.round(record.voltage_t * 1e9).astype(np.int64),
        "displacement": np.round(record.t * 1e9).astype(np.int64),
    }
    exc = record.excitation
    with BagWriter(Path(path)) as bag:
        topics = {
            "voltage": "piezo_stage_msgs/msg/Voltage",
            "displacement": "piezo_stage_msgs/msg/Displacement",
        }
        for name, type_name in topics.items():
            bag.add_topic(f"{namespace}/{name}", type_name, [qos.RELIABLE])
        bag.add_topic(f"{namespace}/excitation", excitation_type, [qos.RELIABLE])
        info = message_class(excitation_type)
        for t, run, steady, offset in record.marks:
            t_ns = int(round(t * 1e9))
            msg = info(
                header=header(t_ns),
                waveform="triangle",
                period=exc.period,
                amplitude=exc.high - exc.low,
                offset=offset,
                run=run,
                steady=steady,
            )
            bag.write(
                f"{namespace}/excitation",
                serialize(msg, excitation_type),
                record.anchor_ns + t_ns,
            )
        for name, values in (("voltage", record.voltage), ("displacement", record.displacement)):
            at = stamps[name]
            for t_ns, data in zip(at.tolist(), encode_series(topics[name], at, values)):
                bag.write(f"{namespace}/{name}", data, record.anchor_ns + t_ns)
    return Path(path)
