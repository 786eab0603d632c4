"""`piezo-stage experiment tracking --graph pi_servo --device URL`: the feedforward table of a
repeated trajectory learned on the host and played by a PI controller's wave generator
(:mod:`piezo_stage.experiments.servo_tracking`)."""

from __future__ import annotations

import argparse
from typing import Any, Callable

from piezo_stage.commands.servo_identify import DeviceRunError, open_controller

#: plays of the table when --learn is not given (the issue's "after <= 20 periods")
DEFAULT_LEARN = 20


def run_pi_servo(args: argparse.Namespace, progress: Callable[[float, str], None]) -> dict:
    """The experiment's summary: RMS error over the last measured period (m and % of the
    range), the RMS of every play, the table's rate and points."""
    from piezo_stage.control.errors import ControlError
    from piezo_stage.control.feedforward import FeedforwardModel
    from piezo_stage.control.learning import FeedforwardTable, trajectory_samples
    from piezo_stage.control.trajectory import make_trajectory
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.servo_tracking import learn_in_controller
    from piezo_stage.hardware.errors import HardwareError
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
    try:
        amplifier, info, recorder, generator = open_controller(args.device, args.axis)
    except DeviceRunError as exc:
        raise ExperimentInputError(str(exc)) from None
    try:
        cycle = recorder.servo_cycle()
        rate = max(1, round(1.0 / (cycle * args.rate_hz))) if args.rate_hz else 1
        x_d, _ = trajectory_samples(trajectory, 1.0 / (cycle * rate))
        plays = args.learn if args.learn else (0 if table is not None else DEFAULT_LEARN)
        result = learn_in_controller(
            amplifier,
            recorder,
            generator,
            model,
            x_d,
            rate,
            (info.v_min, info.v_max),
            max_iterations=plays,
            table=table,
            progress=lambda text: progress(0.0, text),
        )
    except (HardwareError, ControlError) as exc:
        raise ExperimentInputError(f"{args.device}: {exc}") from None
    finally:
        amplifier.close()
    summary: dict[str, Any] = {
        "graph": "pi_servo",
        "rms_error": result.rms_error,
        "rms_relative": result.rms_relative,
        "range": float(x_d.max() - x_d.min()),
        "rate_hz": 1.0 / (cycle * rate),
        "points": int(x_d.size),
        "plays": len(result.history),
        "history_rms_relative": [h / float(x_d.max() - x_d.min()) for h in result.history],
    }
    if args.table_out:
        summary["table_out"] = str(result.table.save(args.table_out))
    return summary
