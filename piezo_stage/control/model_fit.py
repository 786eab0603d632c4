"""The feedforward's model from recordings of a rig (issue 17): the ch. 11 form, input x, output u.

- Bouc-Wen part: two slow wave-periodic runs (a raised-cosine voltage, the second shifted by
  ΔU) recorded on the rig; at low frequency m·ẍ + c·ẋ is negligible, so u = Σ κ_i x^i + κw·w(x)
  (11.1): the ch. 9-10 identification with the columns swapped (input displacement, output
  voltage). A voltage shift ΔU shifts the displacement path by exactly ΔU/κx (w depends on the
  path's shape only), the two-run design of §9.1.3. A smooth wave, not a triangle: a
  triangle's corners ring the ~7 kHz resonance and the displacement then reverses inside a
  branch. The fit runs in µm (the analytic stage's tolerances are scale-free, the refinement's
  steps are not) and is converted back to metres.
- m and c: a voltage step recorded on the rig, fitted by simulation (least squares between the
  recorded displacement and the dynamic model's, with the Bouc-Wen part just identified),
  started from the ringing frequency of the step.

:func:`rig_recordings` makes those recordings on a simulated rig (a ``DynamicPlant``, sampled as
the plant node samples it: the displacement at the start of each held step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import least_squares

from piezo_stage.identification import IdentifyOptions, Recording, identify
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
    step_t: np.ndarray
    step_u: np.ndarray
    step_x: np.ndarray


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
    the model); ``noise`` [m] is white sensor noise on the displacement."""
    if rig.dynamics is None:
        raise ModelFitError("the simulated rig needs the dynamic form (11.1)")
    rng = np.random.default_rng(seed)
    bw, x_rest = rig.bouc_wen, lambda u: u / rig.bouc_wen.kappa_x

    def record(lo: float, hi: float, name: str) -> Recording:
        n = int(round(periods * rate_hz / frequency))
        t = np.arange(n) / rate_hz
        u = lo + (hi - lo) * 0.5 * (1.0 - np.cos(2.0 * math.pi * frequency * t))
        plant = DynamicPlant(bw, rig.dynamics, x0=x_rest(lo))
        x = np.concatenate([[plant.output()], plant.simulate(u, 1.0 / rate_hz)[0][:-1] + bw.y0])
        x = x + noise * rng.standard_normal(n)
        first = n - int(round(keep * rate_hz / frequency))
        return Recording(t[first:] - t[first], x[first:], u[first:], name, "m", "V")

    n = int(round(step_duration * step_rate_hz))
    t = np.arange(n) / step_rate_hz
    u = np.where(t < 0.25 * step_duration, step[0], step[1])
    plant = DynamicPlant(bw, rig.dynamics, x0=x_rest(step[0]))
    x = np.concatenate([[plant.output()], plant.simulate(u, 1.0 / step_rate_hz)[0][:-1] + bw.y0])
    x = x + noise * rng.standard_normal(n)
    return RigRecordings(
        record(u_low, u_high, "run A"), record(u_low + shift, u_high + shift, "run B"), t, u, x
    )


def fit_bouc_wen(run_a: Recording, run_b: Recording) -> tuple[BoucWenParameters, float]:
    """(Bouc-Wen part in metres, input x, output u, y0 a displacement offset; RMS fit error [V])."""

    def um(r: Recording) -> Recording:
        return Recording(r.t, r.input / UM, r.output, r.name, "um", "V")

    try:
        result = identify(
            um(run_a), um(run_b), IdentifyOptions(input_name="displacement", output_name="voltage")
        )
    except Exception as exc:  # the identification's own errors name the cause
        raise ModelFitError(f"identification of the feedforward model failed: {exc}") from exc
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
    ), float(result.rms_error)


def fit_dynamics(bw: BoucWenParameters, t: np.ndarray, u: np.ndarray, x: np.ndarray) -> Dynamics:
    """m, c from a step response by simulation (u held over each sample period)."""
    dt = float(np.median(np.diff(t)))
    x = np.asarray(x, dtype=float)
    after = np.flatnonzero(np.diff(u) != 0)
    if after.size == 0:
        raise ModelFitError("the step recording has no step in u")
    k = after[0] + 1
    ring = x[k:] - x[-1]
    spectrum = np.abs(np.fft.rfft(ring * np.hanning(ring.size), 8 * ring.size))
    freqs = np.fft.rfftfreq(8 * ring.size, dt)
    f_ring = float(freqs[1:][np.argmax(spectrum[1:])])
    if not f_ring > 0:
        raise ModelFitError("no ringing in the step response: cannot estimate m")
    # just after a reversal dw/dx = ρ: the stiffness the ringing sees is κx + κw·ρ (11.3)
    m0 = (bw.kappa_x + bw.kappa_w * bw.rho) / (2 * math.pi * f_ring) ** 2
    c0 = 2 * 0.03 * math.sqrt(bw.kappa_x * m0)

    scale = float(np.ptp(x)) or 1.0  # residuals of order 1: least_squares' tolerances are absolute

    def simulate(p: np.ndarray) -> np.ndarray:
        plant = DynamicPlant(
            bw, Dynamics(m0 * math.exp(p[0]), c0 * math.exp(p[1])), x0=x[0] - bw.y0
        )
        plant.reset(x[0] - bw.y0, 0.0, _rest_w(bw, u[0], x[0]))
        xs = plant.simulate(u, dt)[0]
        return (np.concatenate([[x[0]], xs[:-1] + bw.y0]) - x) / scale

    fit = least_squares(simulate, np.zeros(2), x_scale=1.0, diff_step=1e-3)
    return Dynamics(m0 * math.exp(fit.x[0]), c0 * math.exp(fit.x[1]))


def _rest_w(bw: BoucWenParameters, u: float, x: float) -> float:
    from .feedforward import FeedforwardModel

    return FeedforwardModel(bw, 0.0, 0.0).seed_w(x, u)


def fit_feedforward_model(rec: RigRecordings, name: str = "tracking_model") -> ParameterSet:
    """The dynamic parameter set (input x, output u) fitted from the rig's recordings."""
    bw, rms = fit_bouc_wen(rec.run_a, rec.run_b)
    dyn = fit_dynamics(bw, rec.step_t, rec.step_u, rec.step_x)
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
