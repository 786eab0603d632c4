"""Orchestration of the thesis ch. 11 experiments through the ROS graph (lockstep simulated rig).

:func:`run_experiment` launches the plant and controller nodes, drives the experiment, and
returns a JSON-ready summary; :mod:`.spec` holds the plans and the summaries (no rclpy).
"""

from .errors import ExperimentError, ExperimentInputError, UnknownExperimentError
from .spec import EXPERIMENTS, make_plan, pick_rate


def run_experiment(*args, **kwargs):  # noqa: D103 - rclpy is imported lazily
    from .runner import run_experiment as _run

    return _run(*args, **kwargs)


run_experiment.__doc__ = "See :func:`piezo_stage.experiments.runner.run_experiment`."

__all__ = ["EXPERIMENTS", "ExperimentError", "ExperimentInputError", "UnknownExperimentError", "make_plan", "pick_rate", "run_experiment"]
