"""Tracking learned on the host, played in a PI controller: the feedforward table of a
repeated trajectory, one point per ``rate`` servo cycles, played by the wave generator with
the servo off (the thesis's voltage feedforward, open loop) and learned from the data
recorder's record of each play.

The first table is the model's (:func:`~piezo_stage.control.learning.sampled_feedforward`:
the inverse of (11.1) along x_d at the table's rate, refined against the model itself).
Each iteration uploads the table, plays it :data:`SETTLE_PERIODS` + 1 periods (the stage
settles after the change), reads the position of the last period back and learns from its
error with the learning that exists (:class:`~piezo_stage.control.learning.IterativeLearning`:
u ← u + Q·L·e, L = −α·G⁻¹ with G the model's open-loop response, its stop rule), until it
stops or ``max_iterations``. The output is ramped to the table's first value before and to
max(VMI?, 0 V) after, and on any failure (the generator stopped first).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from piezo_stage.control.feedforward import FeedforwardModel
from piezo_stage.control.learning import (
    FeedforwardTable,
    IterativeLearning,
    LearningConfig,
    feedforward_response,
    sampled_feedforward,
)
from piezo_stage.hardware.amplifier import GCSAmplifier
from piezo_stage.hardware.pi_recorder import RecordOption, ServoRecorder

from .errors import ExperimentError, ExperimentInputError
from .servo_identification import WAVE_TABLE, Progress, ramp_to, safe_state

DEFAULT_LEARNING = LearningConfig()
#: periods played before the measured one after each change of the table: the ch. 11 rig
#: halves its distance to the periodic state per period (a learned period that has not
#: settled carries the change's transient)
SETTLE_PERIODS = 4


@dataclass
class ServoTracking:
    """What the learning in the controller gave."""

    table: FeedforwardTable  #: the last table played
    x_d: NDArray[np.float64]  #: the trajectory at the table's points [m]
    x: NDArray[np.float64]  #: the position over the last measured period [m]
    history: list[float] = field(default_factory=list)  #: RMS error of each play [m]

    @property
    def rms_error(self) -> float:
        """RMS of x − x_d over the last measured period [m]."""
        return float(np.sqrt(np.mean((self.x - self.x_d) ** 2)))

    @property
    def rms_relative(self) -> float:
        """:attr:`rms_error` as a fraction of the trajectory's range."""
        return self.rms_error / float(np.ptp(self.x_d))


def play_and_measure(
    recorder: ServoRecorder,
    generator: int,
    u: NDArray[np.float64],
    rate: int,
    period: float,
    settle: int = SETTLE_PERIODS,
) -> NDArray[np.float64]:
    """Upload ``u``, play it ``settle + 1`` periods, return the last one's position [m] (read
    from the data recorder: only the last period's points)."""
    n = u.size
    plays = settle + 1
    recorder.upload(WAVE_TABLE, u)
    recorder.connect(generator, WAVE_TABLE, plays, rate, 0.0)
    recorder.start([generator])
    recorder.wait_until_stopped([generator], plays * period)
    count = recorder.recorded()
    if count < plays * n:
        raise ExperimentError(f"the data recorder holds {count} of the {plays * n} points played")
    position: NDArray[np.float64] = recorder.read_range(2, settle * n, n).columns[1]
    return position * 1e-6  # um, as PI reports positions


def learn_in_controller(
    amplifier: GCSAmplifier,
    recorder: ServoRecorder,
    generator: int,
    model: FeedforwardModel,
    x_d: NDArray[np.float64],
    rate: int,
    limits: tuple[float, float],
    config: LearningConfig = DEFAULT_LEARNING,
    max_iterations: int = 20,
    table: FeedforwardTable | None = None,
    progress: Progress = lambda text: None,
) -> ServoTracking:
    """Learn (or, with ``max_iterations`` 0, only play) the table that makes the stage follow
    ``x_d`` (one period, a point every ``rate`` servo cycles) on the controller (module
    docstring); ``table``: start from this one (a saved table) instead of the model's."""
    cycle = recorder.servo_cycle()
    rate_hz = 1.0 / (cycle * rate)
    n = x_d.size
    period = n / rate_hz
    config = replace(config, u_min=limits[0], u_max=limits[1], settle_periods=0)
    if table is None:
        table = sampled_feedforward(model, x_d, rate_hz, config=config)
    elif table.matches(rate_hz, n):
        raise ExperimentInputError(table.matches(rate_hz, n))
    recorder.set_tables(2)  # voltage and position
    if recorder.table_points() < (SETTLE_PERIODS + 1) * n:
        raise ExperimentInputError(
            f"{SETTLE_PERIODS + 1} periods ({(SETTLE_PERIODS + 1) * n} points) do not fit a "
            "data recorder table of "
            f"{recorder.table_points()} points: raise the rate"
        )
    axis = amplifier.axis
    sources = [(axis, RecordOption.PIEZO_VOLTAGE), (axis, RecordOption.CURRENT_POSITION)]
    recorder.configure(sources, rate)
    learning = IterativeLearning(table, feedforward_response(model, rate_hz, n), config, model)
    history: list[float] = []
    try:
        ramp_to(amplifier, float(table.u[0]))
        for j in range(max_iterations + 1):
            x = play_and_measure(recorder, generator, table.u, rate, period)
            history.append(float(np.sqrt(np.mean((x - x_d) ** 2))))
            progress(f"play {j}: RMS {100 * history[-1] / np.ptp(x_d):.3g} % of the range")
            if j == max_iterations or learning.done:
                break
            learning.update(x - x_d)
    except BaseException:
        safe_state(amplifier, recorder, generator, limits[0])
        raise
    safe_state(amplifier, recorder, generator, limits[0])
    table.meta["history_rms"] = history
    return ServoTracking(table, np.asarray(x_d, dtype=float), x, history)
