"""Time-varying PID control laws, Theorem 4 gain design and sampled-loop checks (thesis ch. 11).
No rclpy.

Modules: :mod:`.laws` (11.5, 11.17, 11.18), :mod:`.controller` (the sampled controller a node
calls each period), :mod:`.reference` (§11.4.1 reference), :mod:`.bounds` (Assumption 2),
:mod:`.theorem4` (11.6-11.7), :mod:`.discrete` (sampled-loop stability), :mod:`.simulation`
(closed loop against the model's ``DynamicPlant``).
"""

from .bounds import (
    THESIS_NOMINAL_PLANT,
    Bounds,
    NominalPlant,
    load_bounds,
    load_nominal_plant,
    thesis_bounds_path,
)
from .controller import ControllerConfig, ControlOutput, TimeVaryingPID
from .discrete import SampledLoopReport, check_sampled_loop
from .errors import (
    BoundsError,
    ControlError,
    ControllerConfigError,
    GainError,
    MeasurementError,
    SampledLoopError,
)
from .laws import LAW_NAMES, THESIS_GAINS, ControlLaw, Gains, control_law, law_named, register
from .reference import SecondOrderReference
from .theorem4 import GainReport, k0_max, k2_min, validate_gains

__all__ = [
    "THESIS_NOMINAL_PLANT",
    "Bounds",
    "NominalPlant",
    "load_bounds",
    "load_nominal_plant",
    "thesis_bounds_path",
    "ControlOutput",
    "ControllerConfig",
    "TimeVaryingPID",
    "SampledLoopReport",
    "check_sampled_loop",
    "BoundsError",
    "ControlError",
    "ControllerConfigError",
    "GainError",
    "MeasurementError",
    "SampledLoopError",
    "ControlLaw",
    "LAW_NAMES",
    "law_named",
    "register",
    "THESIS_GAINS",
    "Gains",
    "control_law",
    "SecondOrderReference",
    "GainReport",
    "k0_max",
    "k2_min",
    "validate_gains",
]
