"""Tracking figures and the tracking loop in pure core.

:func:`tracking_errors` is what the experiment, the bench and the demo report: over the steady
part of a run (from ``t_from``: the first period, where the loop and w settle, is left out),
the RMS and largest |x − x_d| and the range of x_d [m]. :func:`simulate_tracking` runs the
sampled loop of :mod:`.simulation` (controller + feedforward against a ``DynamicPlant``) along
a trajectory; it reproduces what the lockstep graph computes, without the graph.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezo_stage.model.parameter_set import ParameterSet
from piezo_stage.model.plant import DynamicPlant

from .controller import THESIS_AMPLIFIER, closed_pid
from .errors import ControlError
from .feedforward import Compensation, FeedforwardModel
from .laws import PID, THESIS_GAINS, Gains, check_law
from .learning import FeedforwardTable, IterativeLearning, LearningConfig, feedforward_response
from .simulation import ClosedLoopResult, simulate_closed_loop
from .trajectory import Trajectory

#: the loop rate of the thesis gains at the lockstep's delay 0 (the lowest stable one)
TRACKING_RATE_HZ = 100e3
#: periods run by default; the first is left out of the figures
DEFAULT_PERIODS = 3


@dataclass(frozen=True)
class TrackingErrors:
    """Figures of one run over its steady part [m]; ``relative`` = rms_error / range."""

    rms_error: float
    max_error: float
    range: float
    samples: int
    learning: tuple[float, ...] = ()  # RMS error [m] of each learning period before them

    @property
    def relative(self) -> float:
        """The RMS error relative to the range; NaN for a zero range."""
        return self.rms_error / self.range if self.range > 0 else math.nan

    def to_dict(self) -> dict[str, Any]:
        """The figures as a mapping (``relative`` as ``rms_relative``)."""
        return {
            "rms_error": self.rms_error,
            "max_error": self.max_error,
            "range": self.range,
            "rms_relative": self.relative,
            "measured_samples": self.samples,
            "learning": list(self.learning),
        }


def tracking_errors(
    t: NDArray[np.float64], x: NDArray[np.float64], x_d: NDArray[np.float64], t_from: float = 0.0
) -> TrackingErrors:
    """Figures of x against x_d over t >= ``t_from``."""
    steady = np.asarray(t) >= t_from
    if np.count_nonzero(steady) < 2:
        raise ControlError(f"no samples after t = {t_from:g} s to measure tracking on")
    e = (np.asarray(x) - np.asarray(x_d))[steady]
    return TrackingErrors(
        float(np.sqrt(np.mean(e * e))),
        float(np.abs(e).max()),
        float(np.ptp(np.asarray(x_d)[steady])),
        int(e.size),
    )


def settle_time(trajectory: Trajectory) -> float:
    """Where the figures start: one period of a periodic trajectory, 0 for a file."""
    return trajectory.period if getattr(trajectory, "shape", None) is not None else 0.0


def run_duration(trajectory: Trajectory, periods: float = DEFAULT_PERIODS) -> float:
    """Simulated seconds of a run: ``periods`` periods, or a file's length plus 10 %."""
    if getattr(trajectory, "shape", None) is not None:
        return periods * trajectory.period
    return 1.1 * trajectory.period


def simulate_tracking(
    trajectory: Trajectory,
    plant: ParameterSet,
    compensation: Compensation | str,
    model: FeedforwardModel | None,
    *,
    mode: str = PID.name,
    gains: Gains = THESIS_GAINS,
    rate_hz: float = TRACKING_RATE_HZ,
    duration: float | None = None,
    u_min: float = -THESIS_AMPLIFIER,
    u_max: float = THESIS_AMPLIFIER,
    table: FeedforwardTable | None = None,
    learn_periods: int = 0,
    learning: LearningConfig | None = None,
) -> tuple[ClosedLoopResult, TrackingErrors]:
    """Run the loop closed from t = 0 with the plant at rest at x_d(0) (w = 0, u = its static
    voltage there); return the record and the figures (see :func:`tracking_errors`).

    ``table``: u_ff from it (:mod:`.learning`) instead of the model stepped along x_d. With
    ``learn_periods`` N > 0 (a periodic trajectory and a table), the first N periods learn the
    table (:class:`~.learning.IterativeLearning`, in place), then ``duration`` more seconds run
    with it frozen; the figures are over those, their first period left out.
    """
    if plant.dynamics is None:
        raise ControlError(f"plant {plant.name!r} needs the dynamic form (11.1)")
    x_start = float(trajectory.evaluate(0.0)[0])
    bw = plant.bouc_wen
    u_start = float(FeedforwardModel(bw, 0.0, 0.0).static_force(x_start - bw.y0, 0.0))
    pid = closed_pid(
        gains,
        u_min,
        u_max,
        Compensation(compensation),
        model,
        table,
        mode=check_law(mode),
        hold_voltage=u_start,
    )
    config = pid.config
    stage = DynamicPlant(bw, plant.dynamics, x0=x_start - bw.y0)

    def reference(t: float) -> tuple[float, float, float]:
        x, v, a = trajectory.evaluate(t)
        return float(x), float(v), float(a)

    duration = run_duration(trajectory) if duration is None else duration
    t_learned, history = 0.0, []
    if learn_periods > 0:
        if table is None or model is None or getattr(trajectory, "shape", None) is None:
            raise ControlError(
                "learning needs a periodic trajectory, a feedforward table and "
                "the model (it gives L)"
            )
        feedback = None if config.compensation is Compensation.FEEDFORWARD else gains
        learner = IterativeLearning(
            table,
            feedforward_response(model, rate_hz, len(table), gains=feedback),
            learning or LearningConfig(u_min=u_min, u_max=u_max),
            model,
        )
        for j in range(learn_periods):
            run = simulate_closed_loop(
                pid, stage, rate_hz, trajectory.period, reference, t0=j * trajectory.period
            )
            e = run.measured - run.reference
            history.append(float(np.sqrt(np.mean(e * e))))
            learner.update(e)
            t_learned = (j + 1) * trajectory.period
            if learner.done:
                break
    result = simulate_closed_loop(pid, stage, rate_hz, duration, reference, t0=t_learned)
    errors = tracking_errors(
        result.t, result.measured, result.reference, t_learned + settle_time(trajectory)
    )
    return result, replace(errors, learning=tuple(history))
