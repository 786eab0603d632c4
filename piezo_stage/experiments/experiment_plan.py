"""The typed plan of an experiment: its command-line or Python spec parsed and checked once, at
the door, before anything moves; every step after takes the plan, none parses or loads again.

:class:`ExperimentPlan` is what every closed-loop experiment shares (the graph, the loop's
rate, the compensation, the learning, the bag it writes); the tracking experiment's plan
(:func:`piezo_stage.experiments.tracking.plan_tracking`) adds its trajectory and its models,
loaded once; the raster's (:func:`piezo_stage.experiments.raster.plan_raster`) its scan, its
stages, its sample and its tables.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Collection

from piezo_stage.config_path import output_problem
from piezo_stage.control.feedforward import (
    Compensation,
    FeedforwardError,
    check_learning,
)
from piezo_stage.control.feedforward import compensation as parse_compensation

from .errors import ExperimentInputError

__all__ = ["ExperimentPlan"]


@dataclass(frozen=True)
class ExperimentPlan:
    """What every run of an experiment takes, checked (:meth:`checked`)."""

    graph: str
    rate_hz: float  #: [Hz] the loop's
    compensation: Compensation
    learn: int  #: periods (tracking) or lines (raster) the feedforward learns over
    bag: Path | None = None  #: the record written there

    @classmethod
    def checked(
        cls,
        graph: str,
        graphs: Collection[str],
        rate_hz: float,
        compensation: Compensation | str,
        learn: int,
        bag: Path | None = None,
    ) -> "ExperimentPlan":
        """The plan, or :class:`ExperimentInputError` (one line) for a graph not in
        ``graphs``, a rate that is not > 0, a compensation that is none, a negative or
        feedback-only learning, a bag folder the bag writer would refuse (one that exists and
        is not empty) or could not make."""
        if graph not in graphs:
            raise ExperimentInputError(
                f"--graph {graph}: the experiment runs on {', '.join(graphs)}"
            )
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ExperimentInputError(f"--rate-hz must be > 0, got {rate_hz}")
        try:
            compensation = parse_compensation(compensation)
            if learn < 0:
                raise ExperimentInputError(f"--learn must be >= 0, got {learn}")
            check_learning(compensation, learn > 0, "--learn", "--compensation")
        except FeedforwardError as exc:
            raise ExperimentInputError(str(exc)) from None
        if bag is not None and output_problem(bag, "bag"):
            raise ExperimentInputError(f"--bag {bag}: {output_problem(bag, 'bag')}")
        return cls(
            graph, float(rate_hz), compensation, int(learn), None if bag is None else Path(bag)
        )
