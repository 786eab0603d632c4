"""Exceptions of the identification layer: one class per way the data can fail the method.

Every class derives from :class:`IdentificationError` (a ``ValueError``), so callers that only
care whether identification worked catch that one; the CLI prints the message and exits non-zero.
"""

from __future__ import annotations

from typing import Any

from piezo_stage.errors import PiezoStageError


class IdentificationError(PiezoStageError, ValueError):
    """Base class: the data cannot support the requested identification."""


class InputDataError(IdentificationError):
    """The recording itself is unusable input (unreadable, non-finite, out of range, too short,
    clipped): the CLI exits 2, as for any bad input. Other identification errors mean the data
    were read but do not support the method (exit 1).
    """


class NonFiniteDataError(InputDataError):
    """NaN or inf in time, input or output."""


class TooFewSamplesError(InputDataError):
    """Not enough samples (per branch, per period or in total) for the method."""


class NotPeriodicError(IdentificationError):
    """The input is not a T-wave periodic signal (9.1.1): no stable period, or more than one
    maximum/minimum per period.
    """


class NoSteadyStateError(IdentificationError):
    """Fewer than the required number of successive periods agree (Theorem 2's limit cycle is
    not reached, or the system drifts).
    """


class SaturatedOutputError(InputDataError):
    """The output is clipped (flat at its extreme while the input keeps moving) or the sensor
    flagged samples as invalid.
    """


class NonMonotoneBranchError(IdentificationError):
    """A loading/unloading branch of the input is not monotone (minor loops, wiggles)."""


class InconsistentRunsError(IdentificationError):
    """The two runs are not a T-wave pair x(t), x(t)+q: different spans, q = 0, ..."""


class OrientationError(IdentificationError):
    """The loop orientation (input_sign) cannot be determined or contradicts the request:
    no detectable hysteresis, a figure-eight loop, or runs of opposite orientation.
    """


class DesignPointError(IdentificationError):
    """A design point of Table 10.1 (x*, x*1, x*2, x*3) lies outside the data or violates the
    ordering x*3 < x* < x*1 < x*2.
    """


class AnalyticEstimateError(IdentificationError):
    """A Table 10.2 expression has no value for these data (log or root of a non-positive
    quantity), i.e. the cycle does not have the shape of a Bouc-Wen limit cycle.
    """


class BadFitError(IdentificationError):
    """The refined model does not explain the data: residual large relative to the noise level
    and the output span, or a parameter not determined by the data. ``result`` holds the
    rejected :class:`~piezo_stage.identification.result.IdentificationResult` for inspection.
    """

    def __init__(self, message: str, result: Any = None) -> None:
        super().__init__(message)
        self.result = result


class RefinementError(IdentificationError):
    """The least-squares refinement could not run (the model failed to simulate a trial point)."""


class DataFormatError(InputDataError):
    """A recording file cannot be read: missing columns, unparsable numbers, unknown format."""
