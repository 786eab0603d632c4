"""Analytic limit-cycle identification of the (modified) normalized Bouc-Wen model (thesis
ch. 9-10). No rclpy.

Entry points: :func:`identify` (two recorded runs) and :func:`identify_cycles` (two steady
cycles), returning an :class:`IdentificationResult`; :func:`load_runs` reads CSV files and bags.
"""

from typing import TYPE_CHECKING

from .errors import (
    AnalyticEstimateError,
    BadFitError,
    DataFormatError,
    DesignPointError,
    IdentificationError,
    InconsistentRunsError,
    NonFiniteDataError,
    NonMonotoneBranchError,
    NoSteadyStateError,
    NotPeriodicError,
    OrientationError,
    RefinementError,
    SaturatedOutputError,
    TooFewSamplesError,
)
from .recording import Recording

if TYPE_CHECKING:  # loaded on first access by __getattr__ below
    from .io import load_runs
    from .pipeline import IdentifyOptions, identify, identify_cycles
    from .result import IdentificationResult

__all__ = [
    "AnalyticEstimateError",
    "BadFitError",
    "DataFormatError",
    "DesignPointError",
    "IdentificationError",
    "InconsistentRunsError",
    "NoSteadyStateError",
    "NonFiniteDataError",
    "NonMonotoneBranchError",
    "NotPeriodicError",
    "OrientationError",
    "RefinementError",
    "SaturatedOutputError",
    "TooFewSamplesError",
    "Recording",
    "identify",
    "identify_cycles",
    "IdentifyOptions",
    "IdentificationResult",
    "load_runs",
]


def __getattr__(name: str) -> object:
    """Lazy access to the parts that import the model (keeps `import errors` light)."""
    if name in ("identify", "identify_cycles", "IdentifyOptions"):
        from . import pipeline

        return getattr(pipeline, name)
    if name == "IdentificationResult":
        from .result import IdentificationResult

        return IdentificationResult
    if name == "load_runs":
        from .io import load_runs

        return load_runs
    raise AttributeError(name)
