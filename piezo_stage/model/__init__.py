"""Bouc-Wen hysteresis models and piezo plant dynamics (thesis ch. 8, 9.1.1-9.1.2, 10.2, 11.2).
No rclpy.

Modules: ``bouc_wen`` (parameters, (8.10), exact simulation of (9.2)), ``limit_cycle``
(phi/psi of (9.3)-(9.9), Theorem 2), ``signals`` (T-wave excitation), ``parameter_set``
(YAML files), ``plant`` (static and dynamic plants, solve_ivp reference), ``stage``
(amplifier -> plant -> sensor, what the plant node steps). ``excitation`` (the excitation
node's plans) is imported from its module.
"""

from .bouc_wen import BoucWenParameters, from_standard, model_output, simulate_w
from .errors import (
    InitialStateError,
    InputSignalError,
    InvalidCommandError,
    ModelError,
    NotClassIError,
    ParameterFileError,
    ParameterValueError,
)
from .limit_cycle import limit_cycle, phi, phi_minus, phi_plus, psi, psi_minus, psi_plus
from .parameter_set import (
    Dynamics,
    ParameterSet,
    load_parameter_set,
    save_parameter_set,
    shipped_parameter_set,
)
from .plant import DynamicPlant, StaticPlant, simulate_reference
from .signals import band_limited_noise, sine, step, t_wave_pair, triangle
from .stage import AmplifierModel, SensorModel, SensorStatus, SimulatedStage

__all__ = [
    "BoucWenParameters",
    "from_standard",
    "model_output",
    "simulate_w",
    "ModelError",
    "NotClassIError",
    "ParameterValueError",
    "InitialStateError",
    "InputSignalError",
    "InvalidCommandError",
    "ParameterFileError",
    "limit_cycle",
    "phi",
    "phi_minus",
    "phi_plus",
    "psi",
    "psi_minus",
    "psi_plus",
    "Dynamics",
    "ParameterSet",
    "load_parameter_set",
    "save_parameter_set",
    "shipped_parameter_set",
    "DynamicPlant",
    "StaticPlant",
    "simulate_reference",
    "band_limited_noise",
    "sine",
    "step",
    "t_wave_pair",
    "triangle",
    "AmplifierModel",
    "SensorModel",
    "SensorStatus",
    "SimulatedStage",
]
