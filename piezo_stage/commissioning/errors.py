"""The base class of the commissioning's exceptions (the specific ones live beside the step
that raises them: :class:`~.sweep.SweepError`, :class:`~.design.DesignError`,
:class:`~.procedure.RigError`, :class:`~.procedure.StepFailed`, ...)."""

from __future__ import annotations

from piezo_stage.errors import PiezoStageError


class CommissioningError(PiezoStageError):
    """Base class of every error raised by :mod:`piezo_stage.commissioning`."""
