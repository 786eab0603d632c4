"""Exception classes of the model core (one base class, specific subclasses)."""

from __future__ import annotations

from piezo_stage.errors import PiezoStageError


class ModelError(PiezoStageError, ValueError):
    """Base class of every error raised by :mod:`piezo_stage.model`."""


class NotClassIError(ModelError):
    """Parameters outside the class I normalized Bouc-Wen model (Table 8.2, (8.10)).

    Raised for sigma < 1/2, rho <= 0, kappa_w <= 0 or n < 1 (and non-finite values).
    """


class ParameterValueError(ModelError):
    """A malformed parameter value of a model, a parameter set, an excitation or the simulated
    stage (empty kappa, input_sign not +1/-1, m <= 0, unknown form, v_min >= v_max, ...).
    """


class InitialStateError(ModelError):
    """An initial hysteretic state w(0) outside [-1, 1] (the normalized model's invariant set)."""


class InputSignalError(ModelError):
    """An input signal that cannot be simulated (not 1-D, non-finite samples, dt <= 0, ...)."""


class InvalidCommandError(ModelError):
    """A NaN or infinite command sent to the simulated stage (the node warns and holds)."""


class ParameterFileError(ModelError):
    """A parameter-set YAML file that is missing keys, has wrong types or an unknown layout."""
