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

from piezo_stage.identification import IdentificationError, IdentificationResult, Recording
from piezo_stage.identification.coupling import identify_coupling
from piezo_stage.identification.cycles import CycleOptions
from piezo_stage.model.parameter_set import ParameterSet
from piezo_stage.model.stage_file import Stage, StageAxis

from .model_fit import (
    ModelFitError,
    RigRecordings,
    bouc_wen_in_metres,
    fit_feedforward_model,
    identify_bouc_wen,
    identify_static,
    rig_recordings,
)

__all__ = [
    "AxisRecordings",
    "DrivenRuns",
    "STEADY",
    "fit_stage",
    "fit_stage_runs",
    "stage_recordings",
]

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
    return _with_coupling(
        template,
        axes,
        {name: r.seen for name, r in recordings.items()},
        "identified from recordings: each axis driven in turn, the others held",
    )


@dataclass(frozen=True)
class DrivenRuns:
    """What a graph recorded while one axis ran the two wave runs: its own sensor's runs
    (input x [m], output u [V], steady periods only) and every sensor's reading over the first
    (samples x axes, the stage's order).
    """

    axis: str
    run_a: Recording
    run_b: Recording
    seen: NDArray[np.float64]


def fit_stage_runs(
    template: Stage, runs: Mapping[str, DrivenRuns], cycle: CycleOptions = STEADY
) -> tuple[Stage, dict[str, IdentificationResult]]:
    """(the identified stage, each axis's identification) from ``runs`` (one per axis of
    ``template``), each axis in its form in ``template``. A dynamic axis: the Bouc-Wen part
    identified (11.1 at low frequency, input x, output u), m and c kept from ``template``'s
    model (a record at a sensor rate of kHz does not resolve the step response of a stage
    resonating at several kHz). A static axis: the ch. 10 model (10.15, input u, output x) of
    ``template``'s degree. Raises :class:`~.model_fit.ModelFitError` naming the axis whose runs
    cannot be used.
    """
    axes, results = [], {}
    for axis in template.axes:
        if axis.name not in runs:
            raise ModelFitError(f"no run drives axis {axis.name}")
        try:
            model, results[axis.name] = _fit_axis(axis, runs[axis.name], cycle)
        except ModelFitError as exc:
            raise ModelFitError(f"axis {axis.name}: {exc}") from None
        axes.append(StageAxis(axis.name, model, axis.channel))
    stage = _with_coupling(
        template,
        axes,
        {name: r.seen for name, r in runs.items()},
        "identified through a scanner graph: each axis driven in turn, the others held",
    )
    return stage, results


def _fit_axis(
    axis: StageAxis, driven: DrivenRuns, cycle: CycleOptions
) -> tuple[ParameterSet, IdentificationResult]:
    """One axis's model in its form (:func:`fit_stage_runs`) and its identification."""
    dynamics = axis.model.dynamics
    note = "identified with the axis driven, the others held"
    if dynamics is None:  # ch. 10: voltage in, displacement out
        result = identify_static(driven.run_a, driven.run_b, len(axis.model.bouc_wen.kappa), cycle)
        return result.to_parameter_set(
            axis.name, f"{note} (fit RMS {result.rms_error:.3g} m)"
        ), result
    result = identify_bouc_wen(driven.run_a, driven.run_b, cycle)
    model = ParameterSet(
        name=axis.name,
        form="dynamic",
        bouc_wen=bouc_wen_in_metres(result),
        dynamics=dynamics,
        notes=f"Bouc-Wen part {note} (fit RMS {result.rms_error:.3g} V); m, c kept from "
        f"{axis.model.name}",
    )
    return model, result


def _with_coupling(
    template: Stage,
    axes: list[StageAxis],
    seen: Mapping[str, NDArray[np.float64]],
    notes: str,
) -> Stage:
    try:
        estimate = identify_coupling(template.names, seen)
    except IdentificationError as exc:
        raise ModelFitError(f"coupling: {exc}") from None
    return Stage(
        template.name,
        tuple(axes),
        estimate.coupling,
        coupling_standard_errors=estimate.standard_errors,
        notes=notes,
    )
