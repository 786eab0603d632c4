"""Exceptions of the experiment orchestration."""


class ExperimentError(Exception):
    """An experiment cannot run or did not produce usable data."""


class ExperimentInputError(ExperimentError, ValueError):
    """Bad input: a duration, gain or option the experiment cannot use."""


class UnknownExperimentError(ExperimentInputError):
    """No experiment or control law of that name."""
