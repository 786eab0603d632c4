"""The thesis's experiments through the ROS graph (lockstep simulated stage): the one place
that orchestrates them (the demo, the CLI and scripts/make_sample_bags.py call them).

- ch. 10 identification: :mod:`.identification` (the ``sim_identification`` graph with a
  recorder, the bag replayed through the identifier node, the offline identification).
- ch. 11 closed loop: :func:`run_experiment` launches the plant and controller nodes, drives
  the experiment, and returns a JSON-ready summary; :mod:`.spec` holds the plans and the
  summaries (no rclpy).
"""

from .errors import ExperimentError, ExperimentInputError, UnknownExperimentError
from .plan import EXPERIMENTS, make_plan, pick_rate
from .runner import run_experiment

__all__ = [
    "EXPERIMENTS",
    "ExperimentError",
    "ExperimentInputError",
    "UnknownExperimentError",
    "make_plan",
    "pick_rate",
    "run_experiment",
]
