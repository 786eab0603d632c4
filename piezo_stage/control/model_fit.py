"""The feedforward's model from recordings of a rig: the ch. 11 form, input x, output u.

- Bouc-Wen part: two slow wave-periodic runs (a raised-cosine voltage, the second shifted by
  ΔU) recorded on the rig; at low frequency m·ẍ + c·ẋ is negligible, so u = Σ κ_i x^i + κw·w(x)
  (11.1): the ch. 9-10 identification with the columns swapped (input displacement, output
  voltage). A voltage shift ΔU shifts the displacement path by exactly ΔU/κx (w depends on the
  path's shape only), the two-run design of §9.1.3. A smooth wave, not a triangle: a
  triangle's corners ring the ~7 kHz resonance and the displacement then reverses inside a
  branch. The fit runs in µm (the analytic stage's tolerances are scale-free, the refinement's
  steps are not) and is converted back to metres.
- m and c: a voltage step recorded on the rig, fitted by simulation with the Bouc-Wen part just
  identified (:func:`piezo_stage.identification.dynamics.fit_step_response`).

:func:`rig_recordings` makes those recordings on a simulated rig (a ``DynamicPlant``, sampled as
the plant node samples it: the displacement at the start of each held step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from piezo_stage.identification import (
    IdentificationError,
    IdentificationResult,
    IdentifyOptions,
    Recording,
    identify,
)
from piezo_stage.identification.cycles import CycleOptions
from piezo_stage.identification.dynamics import fit_step_response
from piezo_stage.model.bouc_wen import BoucWenParameters
from piezo_stage.model.parameter_set import Dynamics, ParameterSet
from piezo_stage.model.plant import DynamicPlant

from .errors import ControlError

UM = 1e-6  #: the identification works in µm


class ModelFitError(ControlError):
    """Recordings from which the feedforward model cannot be fitted."""


@dataclass(frozen=True)
class RigRecordings:
    """Two wave-periodic runs (steady periods only) and a step response; t [s], u [V], x [m]."""

    run_a: Recording
    run_b: Recording
    step_t: NDArray[np.float64]
    step_u: NDArray[np.float64]
    step_x: NDArray[np.float64]


def rig_recordings(
    rig: ParameterSet,
    *,
    u_low: float = 0.0,
    u_high: float = 260.0,
    shift: float = 40.0,
    frequency: float = 2.0,
    periods: int = 8,
    keep: int = 3,
    rate_hz: float = 20e3,
    step: tuple[float, float] = (100.0, 120.0),
    step_rate_hz: float = 100e3,
    step_duration: float = 4e-3,
    noise: float = 0.0,
    seed: int = 0,
) -> RigRecordings:
    """Record the identification runs on the simulated rig ``rig`` (its true file: the rig, not
    the model); ``noise`` [m] is white sensor noise on the displacement.
    """
    if rig.dynamics is None:
        raise ModelFitError("the simulated rig needs the dynamic form (11.1)")
    dynamics = rig.dynamics
    rng = np.random.default_rng(seed)
    bw = rig.bouc_wen

    def sampled(
        u: NDArray[np.float64], rate: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(x at each sample, u held over the interval ending there): what the plant node
        publishes, from rest at u[0] (w = 0 there).
        """
        plant = DynamicPlant(bw, dynamics, x0=u[0] / bw.kappa_x)
        x = np.concatenate([[plant.output()], plant.simulate(u, 1.0 / rate)[0][:-1] + bw.y0])
        return x + noise * rng.standard_normal(u.size), np.concatenate([u[:1], u[:-1]])

    def record(lo: float, hi: float, name: str) -> Recording:
        n = int(round(periods * rate_hz / frequency))
        t = np.arange(n) / rate_hz
        wave = lo + (hi - lo) * 0.5 * (1.0 - np.cos(2.0 * math.pi * frequency * t))
        x, u = sampled(wave, rate_hz)
        first = n - int(round(keep * rate_hz / frequency))
        return Recording(t[first:] - t[first], x[first:], u[first:], name, "m", "V")

    t = np.arange(int(round(step_duration * step_rate_hz))) / step_rate_hz
    x, u = sampled(np.where(t < 0.25 * step_duration, step[0], step[1]), step_rate_hz)
    return RigRecordings(
        record(u_low, u_high, "run A"), record(u_low + shift, u_high + shift, "run B"), t, u, x
    )


def identify_bouc_wen(
    run_a: Recording, run_b: Recording, cycle: CycleOptions | None = None
) -> IdentificationResult:
    """The ch. 9-10 identification of the two runs with the columns swapped (input x in µm,
    output u in V): what ``piezo-stage identify --json`` prints for them. ``cycle``: how the
    steady cycle is taken (default: detected).
    """

    def um(r: Recording) -> Recording:
        return Recording(r.t, r.input / UM, r.output, r.name, "um", "V")

    try:
        return identify(
            um(run_a),
            um(run_b),
            IdentifyOptions(
                input_name="displacement",
                output_name="voltage",
                cycle=cycle or CycleOptions(),
            ),
        )
    except Exception as exc:  # the identification's own errors name the cause
        raise ModelFitError(f"identification of the feedforward model failed: {exc}") from exc


def identify_static(
    run_a: Recording, run_b: Recording, degree: int, cycle: CycleOptions | None = None
) -> IdentificationResult:
    """The ch. 10 identification (10.15) of the two runs (input x [m], output u [V], as
    :func:`identify_bouc_wen` takes them) with the columns in the static form's order: input u
    in V, output x in m, κ of ``degree`` terms.
    """

    def static(r: Recording) -> Recording:
        return Recording(r.t, r.output, r.input, r.name, "V", "m")

    try:
        return identify(
            static(run_a),
            static(run_b),
            IdentifyOptions(degree=degree, cycle=cycle or CycleOptions()),
        )
    except Exception as exc:  # the identification's own errors name the cause
        raise ModelFitError(f"identification of the static model failed: {exc}") from exc


def bouc_wen_in_metres(result: IdentificationResult) -> BoucWenParameters:
    """The Bouc-Wen part of :func:`identify_bouc_wen`'s result in metres (input x, output u,
    y0 a displacement offset).
    """
    p = result.parameters
    kappa = tuple(k / UM ** (i + 1) for i, k in enumerate(p.kappa))
    # u = κx·x + κw·w + u0  ->  κx·(x − y0) + κw·w with y0 = −u0/κx (the dynamic form's offset)
    return BoucWenParameters(
        kappa=kappa,
        kappa_w=p.kappa_w,
        rho=p.rho / UM,
        sigma=p.sigma,
        n=p.n,
        y0=-p.y0 / kappa[0],
        input_sign=p.input_sign,
    )


def fit_bouc_wen(
    run_a: Recording, run_b: Recording, cycle: CycleOptions | None = None
) -> tuple[BoucWenParameters, float]:
    """(Bouc-Wen part in metres, input x, output u, y0 a displacement offset; RMS fit error [V]).
    ``cycle``: how the steady cycle is taken (default: detected).
    """
    result = identify_bouc_wen(run_a, run_b, cycle)
    return bouc_wen_in_metres(result), float(result.rms_error)


def fit_feedforward_model(
    rec: RigRecordings, name: str = "tracking_model", cycle: CycleOptions | None = None
) -> ParameterSet:
    """The dynamic parameter set (input x, output u) fitted from the rig's recordings
    (``cycle``: see :func:`fit_bouc_wen`).
    """
    bw, rms = fit_bouc_wen(rec.run_a, rec.run_b, cycle)
    try:
        dyn = fit_step_response(rec.step_t, rec.step_u, rec.step_x, bw).dynamics
    except IdentificationError as exc:
        raise ModelFitError(f"m and c of the feedforward model: {exc}") from exc
    return ParameterSet(
        name=name,
        form="dynamic",
        bouc_wen=bw,
        dynamics=dyn,
        notes=f"identified from rig recordings (input displacement, output voltage; "
        f"Bouc-Wen fit RMS {rms:.3g} V; m, c from a step)",
    )


def perturbed(ps: ParameterSet, factor: float, name: str | None = None) -> ParameterSet:
    """``ps`` with κ_i, κw, ρ, m, c scaled by ``factor`` (a plant off its model by that much)."""
    bw = ps.bouc_wen
    bw = replace(
        bw,
        kappa=tuple(k * factor for k in bw.kappa),
        kappa_w=bw.kappa_w * factor,
        rho=bw.rho * factor,
    )
    dyn = None if ps.dynamics is None else Dynamics(ps.dynamics.m * factor, ps.dynamics.c * factor)
    return replace(ps, name=name or f"{ps.name}_x{factor:g}", bouc_wen=bw, dynamics=dyn)


def perturbed_each(
    ps: ParameterSet, scale: float, seed: int = 0, name: str | None = None
) -> ParameterSet:
    """``ps`` with each of κ_i, κw, ρ, σ, n, m, c scaled by 1 ± ``scale``, the signs drawn from
    ``seed`` (a model off its plant by that much per parameter); σ and n stay in class I.
    """
    signs = iter(np.random.default_rng(seed).choice([-1.0, 1.0], size=len(ps.bouc_wen.kappa) + 6))

    def f() -> float:
        sign: float = next(signs)
        return 1.0 + scale * sign

    bw = ps.bouc_wen
    bw = replace(
        bw,
        kappa=tuple(k * f() for k in bw.kappa),
        kappa_w=bw.kappa_w * f(),
        rho=bw.rho * f(),
        sigma=max(bw.sigma * f(), 0.5),
        n=max(bw.n * f(), 1.0),
    )
    dyn = None if ps.dynamics is None else Dynamics(ps.dynamics.m * f(), ps.dynamics.c * f())
    return replace(ps, name=name or f"{ps.name}_pm{scale:g}_{seed}", bouc_wen=bw, dynamics=dyn)
