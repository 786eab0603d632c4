"""Exceptions of the experiment orchestration."""

from typing import Mapping

from piezo_stage.errors import PiezoStageError


class ExperimentError(PiezoStageError):
    """An experiment cannot run or did not produce usable data."""


class ExperimentInputError(ExperimentError, ValueError):
    """Bad input: a duration, gain or option the experiment cannot use."""


class UnknownExperimentError(ExperimentInputError):
    """No experiment or control law of that name."""


def figures_not_written(
    folder: object, exc: OSError, kept: Mapping[str, object | None]
) -> ExperimentError:
    """The error of figures that could not be written after a run (exit 1, one line): why, and
    where what the run measured was written before them (``kept``: what → path, None when it
    was not asked for)."""
    where = [f"its {what} is in {path}" for what, path in kept.items() if path is not None]
    return ExperimentError(
        f"the run is done but its figures could not be written to {folder}: "
        f"{exc.strerror or exc}"
        + (f"; {', '.join(where)}" if where else "; nothing else was asked to be kept")
    )
