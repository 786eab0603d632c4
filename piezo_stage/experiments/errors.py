"""Exceptions of the experiment orchestration."""

from piezo_stage.errors import PiezoStageError


class ExperimentError(PiezoStageError):
    """An experiment cannot run or did not produce usable data."""


class ExperimentInputError(ExperimentError, ValueError):
    """Bad input: a duration, gain or option the experiment cannot use."""


class UnknownExperimentError(ExperimentInputError):
    """No experiment or control law of that name."""
