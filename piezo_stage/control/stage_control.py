"""A stage of several axes: one ch. 11 loop per axis, the coupling taken out of the feedforward.

With the static coupling y = y0 + C (y* − y0) (docs/design.md section 10), the stage shows the
desired displacements y_d when each axis's own displacement follows

    y*_d = y0 + C⁻¹ (y_d − y0),   ẏ*_d = C⁻¹ ẏ_d,   ÿ*_d = C⁻¹ ÿ_d

so each axis's feedforward (the model stepped along (11.1), or a table) is computed along its own
y*_d, seeded from its own displacement y* = y0 + C⁻¹ (y − y0), while its PID acts on its
measured error y_i − y_d,i as in the single-axis loop. Without coupling compensation every
frame is the measured one. No rclpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezo_stage.model.stage import AmplifierModel, CoupledStage
from piezo_stage.model.stage_file import Stage

from .bounds import axis_plant
from .controller import ControlOutput, OwnFrame, TimeVaryingPID, closed_pid
from .discrete import check_sampled_loop
from .errors import ControlError, SampledLoopError
from .feedforward import Compensation, FeedforwardModel
from .laws import PID, THESIS_GAINS, Gains
from .learning import sampled_feedforward
from .trajectory import Evaluation

__all__ = [
    "AxisReference",
    "OwnFrames",
    "StageController",
    "StageReference",
    "StageRun",
    "check_stage_loops",
    "feedforward_pids",
    "own_reference",
    "scanner_run",
    "simulate_stage",
]

#: the voltage range of the simulated scanners' amplifiers [V]
SCANNER_VOLTS = (-450.0, 450.0)
#: loop rates offered when a stage's loop is unstable at the one asked [Hz]
LOOP_RATES: tuple[float, ...] = (1e3, 2e3, 4e3, 5e3, 8e3, 10e3, 20e3, 50e3, 100e3)


def _unstable(stage: Stage, gains: Gains, rate_hz: float, law: str) -> list[str]:
    """'axis (spectral radius ρ)' of each dynamic axis whose sampled loop is unstable."""
    found = []
    for axis in stage.axes:
        plant = axis_plant(axis.model)
        try:
            report = None if plant is None else check_sampled_loop(plant, gains, rate_hz, 0, law)
        except SampledLoopError:  # beyond the sampled check: the continuous verdict applies
            report = None
        if report is not None and not report.stable:
            found.append(f"{axis.name} (spectral radius {report.spectral_radius:.4g} >= 1)")
    return found


def check_stage_loops(stage: Stage, gains: Gains, rate_hz: float, law: str = PID.name) -> None:
    """ControlError unless every dynamic axis's loop (11.5) with ``gains``, sampled at
    ``rate_hz`` without delay (:func:`~.discrete.check_sampled_loop` on :func:`axis_plant`), is
    stable; the message names the rates of :data:`LOOP_RATES` at which every axis is.
    """
    unstable = _unstable(stage, gains, rate_hz, law)
    if not unstable:
        return
    stable = [f"{r:g}" for r in LOOP_RATES if not _unstable(stage, gains, r, law)]
    raise ControlError(
        f"the {law} loop sampled at {rate_hz:g} Hz (delay 0) is unstable on axis "
        f"{', '.join(unstable)}; every axis's is stable at "
        f"{' or '.join(stable) + ' Hz' if stable else 'none of ' + str(LOOP_RATES)}"
    )


class AxisReference(Protocol):
    """What an axis follows: a trajectory, a set point, an axis of a scan."""

    def evaluate(self, t: ArrayLike) -> Evaluation:
        """(x_d, ẋ_d, ẍ_d) at ``t`` [s]."""
        ...


#: (x_d, ẋ_d, ẍ_d), each of shape (axes,) or (axes, samples)
Frames = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]


def own_reference(stage: Stage, xd: ArrayLike, vd: ArrayLike, ad: ArrayLike) -> Frames:
    """(y*_d, ẏ*_d, ÿ*_d) = (y0 + C⁻¹ (y_d − y0), C⁻¹ ẏ_d, C⁻¹ ÿ_d); rows are axes."""
    y0 = stage.rest_outputs()
    xd, vd, ad = (np.asarray(a, dtype=float) for a in (xd, vd, ad))
    shape = (-1,) + (1,) * (xd.ndim - 1)
    y0 = y0.reshape(shape)
    solve = np.linalg.solve
    return y0 + solve(stage.coupling, xd - y0), solve(stage.coupling, vd), solve(stage.coupling, ad)


class OwnFrames:
    """Each axis's own frame from every axis's measured displacement and reference.

    One sample at a time (the composed loop's cycle; plain floats, a stage has a few axes):

        y* = y0 + C⁻¹ (y − y0),   y*_d = y0 + C⁻¹ (y_d − y0),   ẏ*_d = C⁻¹ ẏ_d,   ÿ*_d = C⁻¹ ÿ_d

    (:func:`own_reference` and :meth:`Stage.own` for arrays).
    """

    def __init__(self, stage: Stage) -> None:
        self.y0 = [float(v) for v in stage.rest_outputs()]
        self.inverse: list[list[float]] = np.linalg.inv(stage.coupling).tolist()

    def frames(
        self,
        x: Sequence[float],
        xd: Sequence[float],
        vd: Sequence[float],
        ad: Sequence[float],
    ) -> list[OwnFrame]:
        """Axis i's :class:`OwnFrame` from the measured ``x`` and the references (``xd``,
        ``vd``, ``ad``) of every axis.
        """
        y0 = self.y0
        dx = [a - b for a, b in zip(x, y0)]
        dxd = [a - b for a, b in zip(xd, y0)]
        out = []
        for row, base in zip(self.inverse, y0):
            out.append(
                OwnFrame(
                    base + sum(c * v for c, v in zip(row, dx)),
                    base + sum(c * v for c, v in zip(row, dxd)),
                    sum(c * v for c, v in zip(row, vd)),
                    sum(c * v for c, v in zip(row, ad)),
                )
            )
        return out


_T = TypeVar("_T")


def _one_per_axis(stage: Stage, items: Sequence[_T], what: str) -> tuple[_T, ...]:
    if len(items) != len(stage.axes):
        raise ControlError(
            f"a stage of {len(stage.axes)} axes needs one {what} per axis, got {len(items)}"
        )
    return tuple(items)


class StageReference:
    """The desired displacement of every axis, in the measured frame and each axis's own."""

    def __init__(
        self, stage: Stage, references: Sequence[AxisReference], compensate_coupling: bool = True
    ) -> None:
        self.stage = stage
        self.references = _one_per_axis(stage, references, "reference")
        self.compensate_coupling = bool(compensate_coupling)

    def measured(self, t: ArrayLike) -> Frames:
        """(y_d, ẏ_d, ÿ_d) at ``t``; rows are axes."""
        rows = [r.evaluate(t) for r in self.references]
        return tuple(np.array([row[k] for row in rows]) for k in range(3))  # type: ignore[return-value]

    def own(self, t: ArrayLike) -> Frames:
        """What each axis's feedforward follows: :func:`own_reference` of :meth:`measured`, or
        the measured frame itself without coupling compensation.
        """
        frames = self.measured(t)
        return own_reference(self.stage, *frames) if self.compensate_coupling else frames

    @property
    def period(self) -> float | None:
        """The longest period of the moving axes (None when every axis holds a set point)."""
        periods = [getattr(r, "period", None) for r in self.references]
        finite = [p for p in periods if p is not None and math.isfinite(p)]
        return max(finite) if finite else None


class StageController:
    """One :class:`~.controller.TimeVaryingPID` per axis, updated together each sample."""

    def __init__(
        self,
        stage: Stage,
        controllers: Sequence[TimeVaryingPID],
        compensate_coupling: bool = True,
    ) -> None:
        self.stage = stage
        self.controllers = _one_per_axis(stage, controllers, "controller")
        self.compensate_coupling = bool(compensate_coupling)

    def update(
        self, t: float, measured: NDArray[np.float64], desired: Frames, own: Frames
    ) -> list[ControlOutput]:
        """One period: axis i's controller gets y_i and (y_d, ẏ_d, ÿ_d)_i, and with coupling
        compensation its own frame (y*_i, y*_d,i, ẏ*_d,i, ÿ*_d,i) for the feedforward.
        """
        x_own = self.stage.own(measured) if self.compensate_coupling else None
        outputs = []
        for i, pid in enumerate(self.controllers):
            frame = None
            if x_own is not None:
                frame = OwnFrame(
                    float(x_own[i]), float(own[0][i]), float(own[1][i]), float(own[2][i])
                )
            outputs.append(
                pid.update(
                    t,
                    float(measured[i]),
                    float(desired[0][i]),
                    float(desired[1][i]),
                    float(desired[2][i]),
                    own=frame,
                )
            )
        return outputs


@dataclass(frozen=True)
class StageRun:
    """A run of :func:`simulate_stage`; arrays of shape (samples, axes) but ``t``."""

    t: NDArray[np.float64]
    measured: NDArray[np.float64]
    reference: NDArray[np.float64]
    u: NDArray[np.float64]
    u_ff: NDArray[np.float64]
    saturated: NDArray[np.bool_]

    def errors(self, t_from: float = 0.0) -> NDArray[np.float64]:
        """RMS of y − y_d per axis from ``t_from`` [m]."""
        keep = self.t >= t_from
        e = self.measured[keep] - self.reference[keep]
        rms: NDArray[np.float64] = np.sqrt(np.mean(e * e, axis=0))
        return rms


def simulate_stage(
    controller: StageController,
    plant: CoupledStage,
    reference: StageReference,
    rate_hz: float,
    duration: float,
    t0: float = 0.0,
) -> StageRun:
    """Run every axis's loop against the coupled ``plant`` at ``rate_hz`` for ``duration`` s
    from ``t0`` (a run continued where the last one ended): each period, measure all axes,
    update all controllers, hold their outputs over the period (zero-order hold, no delay),
    step the plant.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0 and math.isfinite(duration) and duration > 0):
        raise ControlError(f"rate_hz and duration must be > 0, got {rate_hz}, {duration}")
    n, axes = int(round(duration * rate_hz)), len(controller.controllers)
    # simulate_closed_loop's grid
    t: NDArray[np.float64] = t0 + np.arange(n, dtype=float) * (1.0 / rate_hz)
    desired, own = reference.measured(t), reference.own(t)
    record = {k: np.empty((n, axes)) for k in ("measured", "u", "u_ff")}
    saturated = np.zeros((n, axes), dtype=bool)
    readings = plant.output().readings
    for k in range(n):
        outputs = controller.update(
            float(t[k]),
            readings,
            tuple(f[:, k] for f in desired),  # type: ignore[arg-type]
            tuple(f[:, k] for f in own),  # type: ignore[arg-type]
        )
        u = [o.u for o in outputs]
        record["measured"][k] = readings
        record["u"][k] = u
        record["u_ff"][k] = [o.u_ff for o in outputs]
        saturated[k] = [o.saturated for o in outputs]
        readings = plant.step(u, 1.0 / rate_hz).readings
    return StageRun(t=t, reference=desired[0].T.copy(), saturated=saturated, **record)


def feedforward_pids(
    stage: Stage,
    reference: StageReference,
    rate_hz: float,
    gains: Gains = THESIS_GAINS,
    u_limits: tuple[float, float] = SCANNER_VOLTS,
) -> list[TimeVaryingPID]:
    """Per axis the ch. 11 PID (11.5) plus its model's feedforward (11.1), sampled along the
    axis's own reference over one period of the moving axes
    (:func:`~.learning.sampled_feedforward`); closed from the start.
    """
    period = reference.period or 1.0
    own = reference.own(np.arange(int(round(period * rate_hz))) / rate_hz)[0]
    pids = []
    for i, axis in enumerate(stage.axes):
        model = FeedforwardModel.from_parameter_set(axis.model)
        table = sampled_feedforward(model, own[i], rate_hz)
        pids.append(closed_pid(gains, *u_limits, Compensation.BOTH, model, table))
    return pids


def scanner_run(
    model_stage: Stage,
    plant_stage: Stage,
    references: Sequence[AxisReference],
    compensate_coupling: bool,
    rate_hz: float,
    duration: float,
) -> StageRun:
    """Every axis of the simulated ``plant_stage`` following ``references`` under
    :func:`feedforward_pids` built on ``model_stage`` (the identified one), with or without the
    coupling taken out of the feedforward.
    """
    reference = StageReference(model_stage, references, compensate_coupling)
    controller = StageController(
        model_stage, feedforward_pids(model_stage, reference, rate_hz), compensate_coupling
    )
    plant = CoupledStage(
        plant_stage, amplifiers=[AmplifierModel(*SCANNER_VOLTS) for _ in plant_stage.axes]
    )
    return simulate_stage(controller, plant, reference, rate_hz, duration)
