"""A controller's settings → what it runs: the law's configuration (11.5, 11.17, 11.18) in its
frame, the feedforward model (§11.5), the trajectory, the feedforward table and its learning.

Every rule between options lives here once. The controller node and the experiments that start
one call :func:`configure_controller` on the same settings and report its one
:class:`SetupError`; nothing above checks these rules again.

Frames: the settings' u_min, u_max and hold_voltage are amplifier volts; the law works in
u = amplifier volts − u_bias (:mod:`.supervision`), so the configuration subtracts u_bias.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from piezo_stage.config_path import find_user_file

from .controller import ControllerConfig
from .errors import ControlError
from .feedforward import Compensation, FeedforwardError, FeedforwardModel, check_learning
from .law_settings import LawSettings
from .laws import GAIN_ROWS, Gains
from .learning import (
    FeedforwardForm,
    FeedforwardTable,
    IterativeLearning,
    LearningConfig,
    LineCorrection,
    choose_form,
    feedforward_response,
    sampled_feedforward,
    trajectory_samples,
)
from .scan import ScanAxis, make_trajectory
from .setpoint import ReferenceSource
from .supervision import SupervisionConfig
from .trajectory import Trajectory

#: resolves a file name a setting gives (default: :func:`find_user_file`)
FindFile = Callable[[str], Path]


class SetupError(ControlError):
    """Settings that cannot run together, or a file they name that cannot serve; the message
    names the settings.
    """


@dataclass(frozen=True)
class ControllerSetup:
    """What a controller runs: ``config`` for :class:`.controller.TimeVaryingPID` and
    ``supervision`` for :class:`.supervision.LoopSupervisor` around it; the model,
    trajectory and table it holds (None where the settings need none); ``learning`` when
    learn_periods > 0.
    """

    config: ControllerConfig
    supervision: SupervisionConfig
    feedforward: FeedforwardModel | None
    trajectory: Trajectory | None
    table: FeedforwardTable | None
    learning: IterativeLearning | LineCorrection | None


def law_config(
    s: LawSettings,
    feedforward: FeedforwardModel | None = None,
    table: FeedforwardTable | None = None,
) -> ControllerConfig:
    """The law's configuration (validated), limits and hold voltage in the law's frame."""
    bias = float(s.u_bias)
    hold = float(s.hold_voltage)
    try:
        config = ControllerConfig(
            mode=s.mode,
            gains=Gains(**{g.name: float(getattr(s, g.name)) for g in GAIN_ROWS}),
            u_min=float(s.u_min) - bias,
            u_max=float(s.u_max) - bias,
            anti_windup=s.anti_windup,
            tracking_time=float(s.tracking_time) or None,
            derivative_tau=float(s.derivative_tau),
            hold_voltage=None if math.isnan(hold) else hold - bias,
            on_close=s.on_close,
            compensation=s.compensation,
            feedforward=feedforward,
            feedforward_table=table,
        )
        config.validate()
    except (ValueError, TypeError) as exc:  # a ControlError is one too
        raise SetupError(str(exc)) from exc
    return config


def supervision_config(s: LawSettings) -> SupervisionConfig:
    """The supervision of the loop: limits in amplifier volts, start_closed, gaps, the window."""
    try:
        return SupervisionConfig(
            rate_hz=s.rate_hz,
            u_bias=s.u_bias,
            u_min=s.u_min,
            u_max=s.u_max,
            start_closed=s.start_closed,
            max_gap=s.max_gap,
            start_grace=s.start_grace,
            open_at=s.open_at,
            open_after=s.open_after,
            open_duration=s.open_duration,
        )
    except ControlError as exc:
        raise SetupError(str(exc)) from exc


def load_feedforward(s: LawSettings, find: FindFile = find_user_file) -> FeedforwardModel | None:
    """The feedforward model of ``feedforward_model`` (None under feedback)."""
    if not s.compensation.feeds_forward:
        return None
    if not s.feedforward_model:
        raise SetupError(f"compensation {s.compensation.value} needs feedforward_model")
    if float(s.u_bias) != 0.0:
        raise SetupError(
            "u_bias and the feedforward both set the operating voltage; use one (u_bias: 0)"
        )
    try:
        return FeedforwardModel.load(find(s.feedforward_model))
    except (ControlError, OSError) as exc:
        raise SetupError(f"feedforward_model: {exc}") from None


def load_trajectory(s: LawSettings) -> Trajectory | None:
    """The trajectory the trajectory_* settings give; None where they give none and
    reference_source does not use it (switching to it later is refused then).
    """
    offset = float(s.trajectory_offset)
    try:
        return make_trajectory(
            s.trajectory,
            amplitude=float(s.trajectory_amplitude),
            frequency=float(s.trajectory_frequency),
            offset=None if math.isnan(offset) else offset,
            rounding=float(s.trajectory_rounding),
            v_max=float(s.trajectory_v_max),
            a_max=float(s.trajectory_a_max),
        )
    except ControlError as exc:
        if s.reference_source is ReferenceSource.TRAJECTORY:
            raise SetupError(str(exc)) from None
        return None


def feedforward_table(
    s: LawSettings,
    trajectory: Trajectory | None,
    feedforward: FeedforwardModel | None,
    find: FindFile = find_user_file,
) -> FeedforwardTable | None:
    """The feedforward table: ``feedforward_table`` loaded (it must match the trajectory at
    rate_hz), or the sampled form computed from the model; None for the continuous form or
    without a trajectory. Learning starts from the sampled form whatever the rate.
    """
    if not s.compensation.feeds_forward:
        return None
    rate = float(s.rate_hz)
    uses_trajectory = s.reference_source is ReferenceSource.TRAJECTORY and trajectory is not None
    form = FeedforwardForm.SAMPLED if s.learn_periods > 0 else s.feedforward_form
    if not s.feedforward_table and (
        not uses_trajectory
        or feedforward is None
        or choose_form(form, feedforward, rate) is FeedforwardForm.CONTINUOUS
    ):
        return None
    if not uses_trajectory:
        raise SetupError(
            "feedforward_table needs reference_source trajectory (the table follows the "
            "trajectory's time)"
        )
    assert trajectory is not None  # uses_trajectory says so
    try:
        x_d, periodic = trajectory_samples(trajectory, rate)
        if s.feedforward_table:
            table = FeedforwardTable.load(find(s.feedforward_table))
            why = table.matches(rate, x_d.size)
            if why:
                raise SetupError(f"feedforward_table {s.feedforward_table}: {why}")
            return table
        assert feedforward is not None  # the test above returned otherwise
        table = sampled_feedforward(
            feedforward, x_d, rate, periodic=periodic, delay_samples=int(s.delay_samples)
        )
    except SetupError:
        raise
    except (ControlError, OSError) as exc:
        raise SetupError(str(exc)) from None
    table.meta = {
        "trajectory": s.trajectory,
        "amplitude": s.trajectory_amplitude,
        "frequency": s.trajectory_frequency,
        "offset": s.trajectory_offset,
        "rounding": s.trajectory_rounding,
        "model": s.feedforward_model,
        "form": "sampled",
    }
    return table


def learning(
    s: LawSettings,
    config: ControllerConfig,
    trajectory: Trajectory | None,
    table: FeedforwardTable | None,
    feedforward: FeedforwardModel | None,
) -> IterativeLearning | LineCorrection | None:
    """The learning of the table over learn_periods periods (None for 0): it needs a periodic
    trajectory's table and the model whose response it inverts. A raster's slow axis learns a
    correction of one line added to each line of its frame (:class:`LineCorrection`), its
    periods the lines.
    """
    if s.learn_periods <= 0:
        return None
    try:
        check_learning(s.compensation, True, "learn_periods")
    except FeedforwardError as exc:
        raise SetupError(str(exc)) from None
    if table is None or not table.periodic or feedforward is None:
        raise SetupError(
            "learn_periods needs reference_source trajectory with a periodic trajectory, and "
            "feedforward_form sampled or a feedforward_table"
        )
    slow = trajectory if isinstance(trajectory, ScanAxis) and trajectory.index == 1 else None
    n = round(slow.scan.period * table.rate_hz) if slow is not None else len(table)
    gains = None if s.compensation is Compensation.FEEDFORWARD else config.gains
    response = feedforward_response(
        feedforward, float(s.rate_hz), n, delay_samples=int(s.delay_samples), gains=gains
    )
    try:
        learn = LearningConfig(
            gain=float(s.learn_gain),
            cutoff_hz=float(s.learn_cutoff_hz) or None,
            u_min=float(s.u_min),
            u_max=float(s.u_max),
            slew_rate=float(s.learn_slew_rate),
        )
        if slow is not None:
            first = slow.scan.flyback_lines
            return LineCorrection(table, n, first, response, learn, feedforward)
        return IterativeLearning(table, response, learn, feedforward)
    except ControlError as exc:
        raise SetupError(str(exc)) from None


def configure_controller(s: LawSettings, find: FindFile = find_user_file) -> ControllerSetup:
    """Everything a controller with settings ``s`` runs, or the :class:`SetupError` that says
    why it cannot (``find`` resolves the files the settings name).
    """
    feedforward = load_feedforward(s, find)
    trajectory = load_trajectory(s)
    table = feedforward_table(s, trajectory, feedforward, find)
    config = law_config(s, feedforward, table)
    return ControllerSetup(
        config,
        supervision_config(s),
        feedforward,
        trajectory,
        table,
        learning(s, config, trajectory, table, feedforward),
    )
