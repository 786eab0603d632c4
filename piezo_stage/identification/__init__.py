"""Analytic limit-cycle identification of the (modified) normalized Bouc-Wen model (thesis
ch. 9-10). No rclpy.

Entry points: :func:`identify_runs` (one or more recorded runs, the analytic method or the fit
by simulation error, as ``piezo-stage identify`` and the identifier node use it),
:func:`identify` (the analytic method on two runs) and :func:`identify_cycles` (two steady
cycles), each returning an :class:`IdentificationResult`; :func:`load_runs` reads CSV files and
bags, :func:`load_csv` and :func:`load_bag` one of each.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from .errors import (
    AnalyticEstimateError,
    BadFitError,
    DataFormatError,
    DesignPointError,
    IdentificationError,
    InconsistentRunsError,
    InputDataError,
    NonFiniteDataError,
    NonMonotoneBranchError,
    NoSteadyStateError,
    NotPeriodicError,
    OrientationError,
    RefinementError,
    SaturatedOutputError,
    TooFewSamplesError,
)
from .io import load_bag, load_csv, load_runs
from .recording import Recording

if TYPE_CHECKING:  # at run time these come from __getattr__ below, on first use
    from .methods import Method, identify_runs
    from .pipeline import IdentifyOptions, identify, identify_cycles
    from .result import IdentificationResult

__all__ = [
    "AnalyticEstimateError",
    "BadFitError",
    "DataFormatError",
    "DesignPointError",
    "IdentificationError",
    "InconsistentRunsError",
    "InputDataError",
    "NoSteadyStateError",
    "NonFiniteDataError",
    "NonMonotoneBranchError",
    "NotPeriodicError",
    "OrientationError",
    "RefinementError",
    "SaturatedOutputError",
    "TooFewSamplesError",
    "Recording",
    "load_bag",
    "load_csv",
    "load_runs",
    "identify",
    "identify_cycles",
    "identify_runs",
    "IdentifyOptions",
    "IdentificationResult",
    "Method",
]

#: Exports kept lazy on purpose, by module: these import the model (numba, scipy; ~0.7 s) where
#: the rest of the package needs numpy only. ``from piezo_stage.identification.errors import
#: ...`` runs this file, and the CLI imports the errors and io at start-up (``piezo-stage
#: validate``, the commands' exit-code mapping) or in light paths (the bag plots' run cutting).
_LAZY = {
    "identify": "pipeline",
    "identify_cycles": "pipeline",
    "IdentifyOptions": "pipeline",
    "IdentificationResult": "result",
    "identify_runs": "methods",
    "Method": "methods",
}


def __getattr__(name: str) -> object:
    """The lazy exports of :data:`_LAZY`, imported on first access."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value
    return value
