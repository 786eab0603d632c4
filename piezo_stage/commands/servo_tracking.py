"""`piezo-stage experiment tracking --graph pi_servo --device URL`: the feedforward table of a
repeated trajectory learned on the host and played by a PI controller's wave generator
(:mod:`piezo_stage.experiments.servo_tracking`)."""

from __future__ import annotations

import argparse
from typing import Any, Callable

from piezo_stage.commands.servo_identify import DeviceRunError, open_axes, warn_at_limits

#: plays of the table when --learn is not given
DEFAULT_LEARN = 20


def run_pi_servo(
    args: argparse.Namespace, progress: Callable[[float, str], None]
) -> dict[str, Any]:
    """The experiment's summary: RMS error of the last play's measured periods, averaged (m
    and % of the range), one period's noise about that average, the RMS of every play, the
    table's rate and points."""
    from piezo_stage.control.errors import ControlError
    from piezo_stage.control.learning import trajectory_samples
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.servo_tracking import learn_in_controller
    from piezo_stage.hardware.errors import HardwareError

    model, trajectory, table = _inputs(args)
    names = [a.strip() for a in (args.axis or "").split(",") if a.strip()] or [None]
    try:
        with open_axes(args.device, names) as (axes, info, recorder):
            cycle = recorder.servo_cycle()
            rate = table_divisor(cycle, args.rate_hz)
            x_d, _ = trajectory_samples(trajectory, 1.0 / (cycle * rate))
            plays = args.learn if args.learn else (0 if table is not None else DEFAULT_LEARN)
            results = learn_in_controller(
                axes,
                recorder,
                model,
                x_d,
                rate,
                (info.v_min, info.v_max),
                max_iterations=plays,
                tables=[table] * len(axes) if table is not None else (),
                progress=lambda text: progress(0.0, text),
            )
    except DeviceRunError as exc:
        raise ExperimentInputError(str(exc)) from None
    except (HardwareError, ControlError) as exc:
        raise ExperimentInputError(f"{args.device}: {exc}") from None
    warn_at_limits(
        {a.axis: r.at_limit for (a, _), r in zip(axes, results)},
        {a.axis: x_d.size for a, _ in axes},
        (info.v_min, info.v_max),
        "the trajectory asks more than the amplifier gives there; move it into the stage's "
        "range or slow it",
    )
    summary: dict[str, Any] = {"graph": "pi_servo", "rate_hz": 1.0 / (cycle * rate)}
    summary |= _figures([a.axis for a, _ in axes], results, x_d)
    if args.table_out:  # the first axis's table (one axis: its table)
        summary["table_out"] = str(results[0].table.save(args.table_out))
    return summary


def table_divisor(cycle: float, rate_hz: float | None) -> int:
    """Servo cycles per table point for ``--rate-hz`` (None: every cycle); refused
    (ExperimentInputError) above the servo rate, before anything moves."""
    from piezo_stage.experiments import ExperimentInputError

    if rate_hz and rate_hz * cycle > 1.0 + 1e-9:
        raise ExperimentInputError(
            f"--rate-hz {rate_hz:g}: the controller's servo runs at {1.0 / cycle:g} Hz, "
            "the fastest its wave generator plays a table"
        )
    return max(1, round(1.0 / (cycle * rate_hz))) if rate_hz else 1


def _inputs(args: argparse.Namespace) -> tuple[Any, Any, Any]:
    """(feedforward model, trajectory, saved table or None) from the options, checked."""
    from piezo_stage.control.errors import ControlError
    from piezo_stage.control.feedforward import FeedforwardModel
    from piezo_stage.control.learning import FeedforwardTable
    from piezo_stage.control.scan import make_trajectory
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.model.errors import ModelError
    from piezo_stage.model.parameter_set import load_parameter_set

    if not args.device:
        raise ExperimentInputError("--graph pi_servo plays on a controller: give --device URL")
    if not args.model:
        raise ExperimentInputError("--graph pi_servo needs --model (a dynamic parameter set)")
    try:
        model = FeedforwardModel.from_parameter_set(load_parameter_set(args.model))
        trajectory = make_trajectory(
            args.trajectory,
            amplitude=args.amplitude,
            frequency=args.frequency,
            offset=args.offset,
            rounding=args.rounding,
        )
        table = FeedforwardTable.load(args.table) if args.table else None
    except (ControlError, ModelError, OSError, ValueError) as exc:
        raise ExperimentInputError(str(exc)) from None
    return model, trajectory, table


def _figures(names: list[str], results: list[Any], x_d: Any) -> dict[str, Any]:
    """The summary's figures: one axis's at the top level, several under ``axes``."""
    span = float(x_d.max() - x_d.min())
    per_axis = {
        name: {
            "rms_error": r.rms_error,
            "rms_relative": r.rms_relative,
            "noise_rms": r.noise,
            "at_limit_points": r.at_limit,
            "plays": len(r.history),
            "history_rms_relative": [h / span for h in r.history],
        }
        for name, r in zip(names, results)
    }
    figures: dict[str, Any] = {"range": span, "points": int(x_d.size)}
    return figures | (per_axis[names[0]] if len(names) == 1 else {"axes": per_axis})
