"""Tracking learned on the host, played in a PI controller: the feedforward table of a
repeated trajectory, one point per ``rate`` servo cycles, played by the wave generator with
the servo off (the thesis's voltage feedforward, open loop) and learned from the data
recorder's record of each play.

Several axes play at once (one ``WGO`` starts every generator; axis k's voltage and position
are recorder tables 2k + 1 and 2k + 2), each learning from its own record. The first table is
the model's (:func:`~piezo_stage.control.learning.sampled_feedforward`:
the inverse of (11.1) along x_d at the table's rate, refined against the model itself).
Each iteration uploads the table, plays it :data:`SETTLE_PERIODS` + :data:`MEASURED_PERIODS`
periods (the stage settles after the change), reads the position of the measured periods back,
averages them (the sensor's noise falls by the square root of their number; the stage's
repeatable error is what the table can change) and learns from its error with the learning
that exists (:class:`~piezo_stage.control.learning.IterativeLearning`: u ← u + Q·L·e,
L = −α·G⁻¹ with G the model's open-loop response, its stop rule), until it stops or
``max_iterations``. Points of the table at the amplifier's limits are counted
(:attr:`ServoTracking.at_limit`): the error there is the amplifier's, not the table's. The
output is ramped to the table's first value before and to max(VMI?, 0 V) after, and on any
failure (the generator stopped first).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from piezo_stage.control.feedforward import FeedforwardModel
from piezo_stage.control.learning import (
    FeedforwardTable,
    IterativeLearning,
    LearningConfig,
    at_limits,
    feedforward_response,
    sampled_feedforward,
)
from piezo_stage.hardware.amplifier import GCSAmplifier
from piezo_stage.hardware.pi_recorder import RecordOption, ServoRecorder
from piezo_stage.stopping import safe_stop

from .errors import ExperimentError, ExperimentInputError
from .servo_identification import Progress, ramp_to, safe_state

DEFAULT_LEARNING = LearningConfig()
#: periods played before the measured one after each change of the table: the ch. 11 rig
#: halves its distance to the periodic state per period, so 10 leave 1e-3 of a change's
#: transient (with 4, 6 % of it was learned as error: the exact model stalled at 0.22 % of
#: the range instead of 0.17 %)
SETTLE_PERIODS = 10
#: periods recorded after the settling ones and averaged: the error learned from and reported
#: is the repeatable one, the sensor's noise reported apart (:attr:`ServoTracking.noise`)
MEASURED_PERIODS = 4


@dataclass
class ServoTracking:
    """What the learning in the controller gave."""

    table: FeedforwardTable  #: the last table played
    x_d: NDArray[np.float64]  #: the trajectory at the table's points [m]
    x: NDArray[np.float64]  #: the position over the measured periods, averaged [m]
    history: list[float] = field(default_factory=list)  #: RMS error of each play [m]
    noise: float = 0.0  #: RMS of one measured period's position about the average [m]
    at_limit: int = 0  #: the table's points at the amplifier's limits (clipped)

    @property
    def rms_error(self) -> float:
        """RMS of x − x_d, x the measured periods' average [m]."""
        return float(np.sqrt(np.mean((self.x - self.x_d) ** 2)))

    @property
    def rms_relative(self) -> float:
        """:attr:`rms_error` as a fraction of the trajectory's range."""
        return self.rms_error / float(np.ptp(self.x_d))


def play_and_measure(
    recorder: ServoRecorder,
    generators: Sequence[int],
    tables: Sequence[NDArray[np.float64]],
    rate: int,
    period: float,
    settle: int = SETTLE_PERIODS,
    measured: int = MEASURED_PERIODS,
) -> list[NDArray[np.float64]]:
    """Upload each table to its generator's wave table, play them all at once ``settle +
    measured`` periods, return each axis's position over the last ``measured`` [m], one row a
    period (recorder tables 2k + 2: only those periods' points are read)."""
    n = tables[0].size
    plays = settle + measured
    for generator, u in zip(generators, tables):
        recorder.upload(generator, u)
        recorder.connect(generator, generator, plays, rate, 0.0)
    recorder.start(generators)
    recorder.wait_until_stopped(generators, plays * period)
    count = recorder.recorded()
    if count < plays * n:
        raise ExperimentError(f"the data recorder holds {count} of the {plays * n} points played")
    columns = recorder.read_range(2 * len(tables), settle * n, measured * n).columns
    # um, as PI reports
    return [columns[2 * k + 1].reshape(measured, n) * 1e-6 for k in range(len(tables))]


def learn_in_controller(
    axes: Sequence[tuple[GCSAmplifier, int]],
    recorder: ServoRecorder,
    model: FeedforwardModel,
    x_d: NDArray[np.float64],
    rate: int,
    limits: tuple[float, float],
    config: LearningConfig = DEFAULT_LEARNING,
    max_iterations: int = 20,
    tables: Sequence[FeedforwardTable | None] = (),
    progress: Progress = lambda text: None,
) -> list[ServoTracking]:
    """Learn (or, with ``max_iterations`` 0, only play) the table that makes each axis follow
    ``x_d`` (one period, a point every ``rate`` servo cycles) on the controller (module
    docstring); ``axes``: (the axis's amplifier, its wave generator), all played at once;
    ``tables``: start from these (saved tables) instead of the model's."""
    cycle = recorder.servo_cycle()
    rate_hz = 1.0 / (cycle * rate)
    n = x_d.size
    config = replace(config, u_min=limits[0], u_max=limits[1], settle_periods=0)
    start = [_first_table(t, model, x_d, rate_hz, config) for t in _each(tables, len(axes))]
    recorder.set_tables(2 * len(axes))  # voltage and position of each axis
    plays = SETTLE_PERIODS + MEASURED_PERIODS
    if recorder.table_points() < plays * n:
        raise ExperimentInputError(
            f"{plays} periods ({plays * n} points) do not fit a data recorder table of "
            f"{recorder.table_points()} points: raise the rate"
        )
    sources = [(a.axis, option) for a, _ in axes for option in RECORD]
    recorder.configure(sources, rate)
    response = feedforward_response(model, rate_hz, n)
    learning = [IterativeLearning(t, response, config, model) for t in start]
    try:
        for amplifier, table in zip((a for a, _ in axes), start):
            ramp_to(amplifier, float(table.u[0]))
        xs, history = _plays(
            recorder, [g for _, g in axes], learning, x_d, rate, rate_hz, max_iterations, progress
        )
    except BaseException:
        _safe(axes, recorder, limits[0])
        raise
    _safe(axes, recorder, limits[0])
    for table, h in zip(start, history):
        table.meta["history_rms"] = h
    xd = np.asarray(x_d, dtype=float)
    return [
        ServoTracking(t, xd, x.mean(axis=0), h, period_noise(x), at_limits(t.u, *limits))
        for t, x, h in zip(start, xs, history)
    ]


def period_noise(x: NDArray[np.float64]) -> float:
    """RMS of one period's position about the periods' average (rows: periods) [m], the
    unbiased estimate: what differs from period to period (the sensor's noise)."""
    k = x.shape[0]
    if k < 2:
        return float("nan")
    return float(np.sqrt(np.sum((x - x.mean(axis=0)) ** 2) / ((k - 1) * x.shape[1])))


def _plays(
    recorder: ServoRecorder,
    generators: list[int],
    learning: list[IterativeLearning],
    x_d: NDArray[np.float64],
    rate: int,
    rate_hz: float,
    max_iterations: int,
    progress: Progress,
) -> tuple[list[NDArray[np.float64]], list[list[float]]]:
    """Play and learn until every axis's learning stops or ``max_iterations``: the last
    measured periods' positions (rows: periods) and each axis's RMS error per play (of the
    periods' average)."""
    history: list[list[float]] = [[] for _ in learning]
    for j in range(max_iterations + 1):
        tables = [lrn.table.u for lrn in learning]
        xs = play_and_measure(recorder, generators, tables, rate, x_d.size / rate_hz)
        for k, x in enumerate(xs):
            history[k].append(float(np.sqrt(np.mean((x.mean(axis=0) - x_d) ** 2))))
        span = float(np.ptp(x_d))
        progress(f"play {j}: RMS " + ", ".join(f"{100 * h[-1] / span:.3g}" for h in history) + " %")
        if j == max_iterations or all(lrn.done for lrn in learning):
            break
        for lrn, x in zip(learning, xs):
            lrn.update(x.mean(axis=0) - x_d)
    return xs, history


#: what each axis's two recorder tables hold
RECORD = (RecordOption.PIEZO_VOLTAGE, RecordOption.CURRENT_POSITION)


def _each(tables: Sequence[FeedforwardTable | None], count: int) -> list[FeedforwardTable | None]:
    """One start table (or None: the model's) per axis."""
    if tables and len(tables) != count:
        raise ExperimentInputError(f"{len(tables)} table(s) for {count} axes")
    return list(tables) if tables else [None] * count


def _first_table(
    table: FeedforwardTable | None,
    model: FeedforwardModel,
    x_d: NDArray[np.float64],
    rate_hz: float,
    config: LearningConfig,
) -> FeedforwardTable:
    """The model's table, or a saved one checked for this rate and period."""
    if table is None:
        return sampled_feedforward(model, x_d, rate_hz, config=config)
    why = table.matches(rate_hz, x_d.size)
    if why:
        raise ExperimentInputError(why)
    return table


def _safe(axes: Sequence[tuple[GCSAmplifier, int]], recorder: ServoRecorder, v_min: float) -> None:
    """Every generator stopped, every output ramped to max(VMI?, 0 V), whatever signals come
    before the last axis is safe."""
    with safe_stop():
        for amplifier, generator in axes:
            safe_state(amplifier, recorder, generator, v_min)
