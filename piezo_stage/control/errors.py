"""Exceptions raised by the control core (thesis ch. 11)."""

from __future__ import annotations

from piezo_stage.errors import PiezoStageError


class ControlError(PiezoStageError, ValueError):
    """Base class for errors of the control core."""


class BoundsError(ControlError):
    """Assumption 2 bounds are missing, non-finite or inconsistent (e.g. m_min > m_max)."""


class GainError(ControlError):
    """Gains or law parameters that cannot be used at all (non-finite, wrong sign, unknown law)."""


class ControllerConfigError(ControlError):
    """Inconsistent controller configuration (limits, anti-windup mode, filter, guards)."""


class MeasurementError(ControlError):
    """A non-finite time, measurement or reference was passed to the controller."""


class SampledLoopError(ControlError):
    """Bad arguments to the sampled-loop check or the closed-loop simulation (rate, delay...)."""
