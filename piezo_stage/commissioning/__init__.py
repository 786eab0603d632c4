"""Commission a new rig: the thesis's ch. 11 procedure from first excitation to verified gains.

:class:`~.procedure.Commissioning` runs the steps (sweep, dynamics, bounds, gains, acceptance,
report) on a graph (:mod:`.graphs`, over ROS); the maths is in :mod:`.sweep`, :mod:`.design` and
:mod:`piezo_stage.identification.dynamics` (no rclpy in those).
"""

from .design import DesignError
from .errors import CommissioningError
from .procedure import (
    STEPS,
    Commissioning,
    Options,
    OtherCommissioningError,
    RigError,
    Step,
    StepFailed,
)
from .sweep import SweepError, SweepSettings

__all__ = [
    "STEPS",
    "Commissioning",
    "CommissioningError",
    "DesignError",
    "Options",
    "OtherCommissioningError",
    "RigError",
    "Step",
    "StepFailed",
    "SweepError",
    "SweepSettings",
]
