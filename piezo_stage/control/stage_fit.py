"""A stage of several axes identified from recordings: each axis's feedforward model and the
coupling between them (docs/design.md section 10).

Each axis in turn runs :mod:`.model_fit`'s identification runs (two raised-cosine voltage runs
and a step) while the others hold their voltage; every sensor records. The driven axis's own
recordings give its model (:func:`~.model_fit.fit_feedforward_model`; the held axes' cross-talk
is a constant there, taken up by y0), and what the other axes' sensors saw gives the column of
the coupling (:func:`~piezo_stage.identification.coupling.identify_coupling`).

:func:`stage_recordings` makes those recordings on a simulated stage: each axis's plant as
:func:`~.model_fit.rig_recordings` samples it, the sensors reading y = y0 + C (y* − y0) plus white
noise. No rclpy.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from piezo_stage.identification import IdentificationError, Recording
from piezo_stage.identification.coupling import identify_coupling
from piezo_stage.identification.cycles import CycleOptions
from piezo_stage.model.stage_file import Stage, StageAxis

from .model_fit import ModelFitError, RigRecordings, fit_feedforward_model, rig_recordings

__all__ = ["AxisRecordings", "STEADY", "fit_stage", "stage_recordings"]

#: the runs hold steady periods only: the last two are the cycle (noise on the
#: displacement, the method's input here, would otherwise fail the steady-state detection)
STEADY = CycleOptions(steady_periods=2)


@dataclass(frozen=True)
class AxisRecordings:
    """The runs of one driven axis: its own identification recordings (its sensor's reading)
    and every sensor's reading over its first run (samples x axes, the stage's order).
    """

    axis: str
    runs: RigRecordings
    seen: NDArray[np.float64]


def stage_recordings(
    stage: Stage, *, hold: float = 0.0, noise: float = 0.0, seed: int = 0
) -> dict[str, AxisRecordings]:
    """The identification runs of every axis of the simulated ``stage`` (its true models and
    coupling), the others held at ``hold`` volts; ``noise`` [m] white on every sensor.
    """
    rng = np.random.default_rng(seed)
    y0 = stage.rest_outputs()
    held = np.array(
        [y0[k] + hold / axis.model.bouc_wen.kappa_x for k, axis in enumerate(stage.axes)]
    )
    out = {}
    for j, axis in enumerate(stage.axes):
        clean = rig_recordings(axis.model)  # axis j's own displacement y*_j, noise-free

        def sensors(own_j: NDArray[np.float64], j: int = j) -> NDArray[np.float64]:
            own = np.repeat(held[:, None], own_j.size, axis=1)
            own[j] = own_j
            y = y0[:, None] + stage.coupling @ (own - y0[:, None])
            return y + noise * rng.standard_normal(y.shape)

        def measured(run: Recording, j: int = j) -> tuple[Recording, NDArray[np.float64]]:
            y = sensors(run.input)
            return replace(run, input=y[j]), y.T

        run_a, seen = measured(clean.run_a)
        run_b, _ = measured(clean.run_b)
        step_x = sensors(clean.step_x)[j]
        out[axis.name] = AxisRecordings(
            axis.name, replace(clean, run_a=run_a, run_b=run_b, step_x=step_x), seen
        )
    return out


def fit_stage(template: Stage, recordings: Mapping[str, AxisRecordings]) -> Stage:
    """Every axis's model, the coupling and its standard errors from ``recordings`` (one entry
    per axis of ``template``, whose names and channels the result keeps). Raises
    :class:`~.model_fit.ModelFitError` naming the axis whose runs cannot be used.
    """
    axes = []
    for axis in template.axes:
        if axis.name not in recordings:
            raise ModelFitError(f"no recordings drive axis {axis.name}")
        try:
            model = fit_feedforward_model(recordings[axis.name].runs, axis.name, STEADY)
        except ModelFitError as exc:
            raise ModelFitError(f"axis {axis.name}: {exc}") from None
        axes.append(StageAxis(axis.name, model, axis.channel))
    try:
        estimate = identify_coupling(
            template.names, {name: r.seen for name, r in recordings.items()}
        )
    except IdentificationError as exc:
        raise ModelFitError(f"coupling: {exc}") from None
    return Stage(
        template.name,
        tuple(axes),
        estimate.coupling,
        coupling_standard_errors=estimate.standard_errors,
        notes="identified from recordings: each axis driven in turn, the others held",
    )
