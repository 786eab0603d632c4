"""`piezo-stage experiment raster --graph pi_servo --device URL`: the raster played by a PI
controller's wave generator, its image from the data recorder
(:mod:`piezo_stage.experiments.pi_raster`)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from piezo_stage.commands.servo_identify import DeviceRunError, open_axes, warn_at_limits
from piezo_stage.commands.servo_tracking import table_divisor

if TYPE_CHECKING:
    from piezo_stage.experiments.pi_raster import ServoSetup


@contextmanager
def servo_setup(args: argparse.Namespace, stage_file: Path) -> Iterator[ServoSetup]:
    """The controller of ``--device`` opened for every axis of the stage file (its channels
    are the controller's axes), closed after; one-line ExperimentInputError for a link, an
    axis or a ``--rate-hz`` it refuses, before anything moves."""
    from piezo_stage.experiments import ExperimentInputError
    from piezo_stage.experiments.pi_raster import ServoAxis, ServoSetup
    from piezo_stage.hardware.errors import HardwareError
    from piezo_stage.model.errors import ModelError
    from piezo_stage.model.stage_file import load_stage

    if not args.device:
        raise ExperimentInputError("--graph pi_servo plays on a controller: give --device URL")
    try:
        stage = load_stage(stage_file)
    except ModelError as exc:
        raise ExperimentInputError(str(exc)) from None
    try:
        with open_axes(args.device, [a.channel for a in stage.axes]) as (views, info, recorder):
            axes = {a.name: ServoAxis(*view) for a, view in zip(stage.axes, views)}
            cycle = recorder.servo_cycle()
            rate = table_divisor(cycle, args.rate_hz)
            yield ServoSetup(recorder, axes, rate, cycle, (info.v_min, info.v_max))
    except DeviceRunError as exc:
        raise ExperimentInputError(str(exc)) from None
    except HardwareError as exc:
        raise ExperimentInputError(f"{args.device}: {exc}") from None


def say_at_limits(summary: dict[str, Any], servo: ServoSetup) -> None:
    """Warn of the tables' points at the amplifier's limits (the summary's
    ``at_limit_points``; both tables are a frame long), as the servo tracking does."""
    counts = summary.get("at_limit_points") or {}
    points = round(summary["frame_time"] * servo.rate_hz)
    warn_at_limits(
        counts,
        dict.fromkeys(counts, points),
        servo.limits,
        "the scan asks more than the amplifier gives there; a smaller range or another centre",
    )
