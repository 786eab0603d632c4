"""`piezo-stage experiment raster --graph pi_servo --device URL`: the raster played by a PI
controller's wave generator, its image from the data recorder
(:mod:`piezo_stage.experiments.pi_raster`)."""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from piezo_stage.commands.servo_identify import DeviceRunError, open_controller
from piezo_stage.commands.servo_tracking import axis_view, table_divisor

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
    channels = [a.channel for a in stage.axes]
    try:
        amplifier, info, recorder, generator = open_controller(args.device, channels[0])
    except DeviceRunError as exc:
        raise ExperimentInputError(str(exc)) from None
    try:
        views = [(amplifier, generator)] + [axis_view(amplifier, c) for c in channels[1:]]
        axes = {a.name: ServoAxis(*view) for a, view in zip(stage.axes, views)}
        cycle = recorder.servo_cycle()
        rate = table_divisor(cycle, args.rate_hz)
        yield ServoSetup(recorder, axes, rate, cycle, (info.v_min, info.v_max))
    except (DeviceRunError, HardwareError) as exc:
        raise ExperimentInputError(f"{args.device}: {exc}") from None
    finally:
        amplifier.close()


def warn_at_limits(run: Any, say: Callable[[str], None]) -> None:
    """Say how many points of each table sit at the amplifier's limits (their error is the
    amplifier's, not the table's)."""
    for name, count in zip(("fast", "slow"), getattr(run, "at_limit", (0, 0))):
        if count:
            say(
                f"warning: the {name} axis's table has {count} points at the amplifier's "
                "limits: the scan asks more than the amplifier gives there and that error is "
                "not learned; a smaller range or another centre"
            )
