"""m and c of (11.1) from a step response, with standard errors (beyond the thesis, which took
them from the patch's physical data, §11.2.1). No rclpy.

Model: m x'' + c x' + kappa_x x + kappa_w w = u (11.1)-(11.3) with the Bouc-Wen part already
identified (the frequency sweep); the response is simulated by
:class:`piezo_stage.model.plant.DynamicPlant` with the measured applied voltage held over each
sample interval (zero-order hold) from the measured rest state, w(0) by (11.12), and
(log m, log c) fitted to the measured displacement by ``scipy.optimize.least_squares``; the
standard errors come from the Jacobian at the optimum (residual variance times (J^T J)^-1).

Resolution rule (:data:`MIN_SAMPLES_PER_PERIOD`): the sensor must take at least 4 samples per
period of the natural frequency f_n = sqrt(kappa_x / m) / (2 pi). Checked twice: before the
fit, the response must take at least 2 samples (half a period) from the step to its first peak
(a sensor slower than that sees a settled step and nothing of the resonance); after it,
rate >= 4 f_n and the first peak where the fitted resonance puts it (within 1.5 samples or
30 %): a resonance above rate/2 aliases to a slower one, which the fit would otherwise accept.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import cast

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from piezo_stage.model.bouc_wen import BoucWenParameters
from piezo_stage.model.errors import ModelError
from piezo_stage.model.parameter_set import Dynamics
from piezo_stage.model.plant import DynamicPlant

from .errors import IdentificationError

#: the resolution rule: samples per period of the natural frequency the sensor must take
MIN_SAMPLES_PER_PERIOD = 4.0
#: a fitted parameter whose relative standard error exceeds this is not determined by the data
MAX_RELATIVE_STD = 0.25
#: residual RMS allowed, as a fraction of the response's span
MAX_RMS_FRACTION = 0.05


class DynamicsError(IdentificationError):
    """m and c cannot be identified from this response (the message says why)."""


class UnresolvedResonanceError(DynamicsError):
    """The sensor's sample rate cannot resolve the resonance (the resolution rule)."""


@dataclass(frozen=True)
class DynamicsFit:
    """Fitted m [V s^2/m], c [V s/m], their standard errors, and what the fit saw."""

    m: float
    c: float
    m_std: float
    c_std: float
    natural_frequency: float  #: f_n = sqrt(kappa_x/m)/(2 pi) [Hz]
    damping_ratio: float  #: c / (2 sqrt(kappa_x m))
    rate_hz: float  #: sensor rate of the response
    samples_per_period: float  #: rate_hz / f_n
    rms_error: float  #: residual RMS [m]
    samples: int
    w0: float  #: w before the step, (11.12)
    x_rest: float  #: displacement before the step [m]
    step_at: int  #: index of the first sample after the step

    @property
    def dynamics(self) -> Dynamics:
        """The fitted m and c as the model's :class:`Dynamics`."""
        return Dynamics(m=self.m, c=self.c)

    def to_dict(self) -> dict[str, float]:
        """The fields as a mapping (``samples``, ``step_at`` as int, the rest as float)."""
        return {
            k: (int(v) if k in ("samples", "step_at") else float(v))
            for k, v in asdict(self).items()
        }


def _first_peak_samples(x: NDArray[np.float64], step_at: int) -> int:
    """Samples from the step to the first extremum of the response in the step's direction."""
    d = x[step_at:] - x[step_at]
    sign = 1.0 if d[-1] >= 0 else -1.0
    moved = sign * d
    for k in range(1, len(moved) - 1):
        if moved[k] > 0 and moved[k + 1] <= moved[k]:
            return k
    return len(moved)


def fit_step_response(
    t: NDArray[np.float64],
    u: NDArray[np.float64],
    x: NDArray[np.float64],
    bouc_wen: BoucWenParameters,
    *,
    step_at: int | None = None,
    voltage_offset: float = 0.0,
    min_samples_per_period: float = MIN_SAMPLES_PER_PERIOD,
) -> DynamicsFit:
    """Fit m, c of (11.1) to a step response sampled uniformly.

    ``t``, ``u``, ``x``: sample times [s], the applied voltage published with each sample (the
    value held over the interval *ending* at that sample, as the plant and the driver report
    it) and the displacement [m]; the first samples must be at rest. ``bouc_wen``: the
    identified (11.2)-(11.3), input displacement, output voltage, with ``voltage_offset`` its y0
    (u = kappa_x x + kappa_w w + y0). ``step_at``: index of the first sample whose held voltage
    differs from the rest value (default: found). Raises :class:`UnresolvedResonanceError`
    (rule in the module docstring) or :class:`DynamicsError`.
    """
    t, u, x = (np.asarray(a, dtype=float) for a in (t, u, x))
    if not (t.ndim == u.ndim == x.ndim == 1 and len(t) == len(u) == len(x)):
        raise DynamicsError("t, u and x must be 1-D arrays of one length")
    if len(t) < 20 or not (
        np.all(np.isfinite(t)) and np.all(np.isfinite(u)) and np.all(np.isfinite(x))
    ):
        raise DynamicsError(f"need >= 20 finite samples, got {len(t)}")
    dt = float(np.median(np.diff(t)))
    if not dt > 0 or np.max(np.abs(np.diff(t) - dt)) > 0.01 * dt:
        raise DynamicsError("the response must be sampled uniformly")
    rate = 1.0 / dt
    if step_at is None:
        moved = np.flatnonzero(np.abs(u - u[0]) > 1e-6 * max(1.0, float(np.ptp(u))))
        if moved.size == 0:
            raise DynamicsError("the applied voltage never changes: no step in the record")
        step_at = int(moved[0])
    if step_at < 2 or step_at > len(t) - 10:
        raise DynamicsError(
            f"the step must come after >= 2 rest samples and leave >= 10 after it (at {step_at})"
        )
    peak = _first_peak_samples(x, step_at - 1)
    if peak < min_samples_per_period / 2:
        raise UnresolvedResonanceError(
            f"the response peaks {peak} sample(s) after the step at {rate:g} Hz: the "
            "resonance is faster "
            f"than the sensor can resolve (rule: >= {min_samples_per_period:g} samples per "
            "period of the "
            f"natural frequency, i.e. >= {min_samples_per_period / 2:g} from the step to the "
            "first peak)"
        )
    x_rest = float(np.mean(x[:step_at]))
    u_rest = float(np.mean(u[:step_at]))
    kx, kw = bouc_wen.kappa_x, bouc_wen.kappa_w
    w0 = float(np.clip((u_rest - voltage_offset - kx * x_rest) / kw, -1.0, 1.0))  # (11.12)
    held = u[step_at:] - voltage_offset  # held over (t[k-1], t[k]]
    measured = x[step_at:]
    scale = max(float(np.ptp(measured)), 1e-30)
    # first guess: the ringing's half period gives f_n, stiffness kappa_x; light damping
    f_guess = rate / (2.0 * max(peak, 1))
    m_guess = kx / (2.0 * math.pi * f_guess) ** 2
    c_guess = 2.0 * 0.05 * math.sqrt(kx * m_guess)

    def simulate(p: NDArray[np.float64]) -> NDArray[np.float64]:
        plant = DynamicPlant(
            bouc_wen, Dynamics(m=math.exp(p[0]), c=math.exp(p[1])), x0=x_rest, w0=w0
        )
        xs, _, _ = plant.simulate(held, dt)
        return xs

    def residual(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return (simulate(p) - measured) / scale

    try:
        fit = least_squares(
            residual,
            np.log([m_guess, c_guess]),
            x_scale=1.0,
            diff_step=1e-4,  # type: ignore[arg-type]  # scipy takes a scalar; the stubs want 1-D
            bounds=(
                np.log([m_guess * 1e-2, c_guess * 1e-4]),
                np.log([m_guess * 1e2, c_guess * 1e3]),
            ),
        )
    except (ModelError, ValueError, FloatingPointError) as exc:
        raise DynamicsError(f"the step-response fit failed: {exc}") from exc
    m, c = (float(v) for v in np.exp(fit.x))
    r = fit.fun
    dof = max(1, r.size - 2)
    # dense (the stubs also allow a sparse or operator Jacobian: jac_sparsity or tr_solver='lsmr')
    jac = cast(NDArray[np.float64], fit.jac)
    jtj = jac.T @ jac
    try:
        cov = np.linalg.inv(jtj) * float(r @ r) / dof
    except np.linalg.LinAlgError as exc:
        raise DynamicsError(
            "m and c are not determined by this response (singular Jacobian)"
        ) from exc
    rel = np.sqrt(np.clip(np.diag(cov), 0.0, None))  # std of log m, log c = relative std
    f_n = math.sqrt(kx / m) / (2.0 * math.pi)
    if rate < min_samples_per_period * f_n:
        raise UnresolvedResonanceError(
            f"natural frequency {f_n:.4g} Hz needs a sensor rate >= "
            f"{min_samples_per_period * f_n:.4g} Hz "
            f"(rule: >= {min_samples_per_period:g} samples per period), got {rate:g} Hz"
        )
    zeta = c / (2.0 * math.sqrt(kx * m))
    expected_peak = rate / (2.0 * f_n * math.sqrt(max(1e-12, 1.0 - min(zeta, 0.99) ** 2)))
    rms = float(np.sqrt(np.mean(r**2)))
    if zeta < 0.7 and abs(peak - expected_peak) > max(1.5, 0.3 * expected_peak):
        raise UnresolvedResonanceError(
            f"the fitted resonance ({f_n:.4g} Hz) would peak {expected_peak:.3g} samples "
            "after the step, the "
            f"response peaks after {peak}: an alias of a resonance faster than "
            f"{rate / min_samples_per_period:.4g} Hz "
            f"(rule: >= {min_samples_per_period:g} samples per period of the natural frequency)"
        )
    if rms > MAX_RMS_FRACTION:
        raise DynamicsError(
            f"the model does not describe the step response (residual {100 * rms:.3g} % of "
            f"its span, limit {100 * MAX_RMS_FRACTION:g} %)"
        )
    loose = [
        f"{name} ±{100 * v:.2g} %" for name, v in zip(("m", "c"), rel) if not v <= MAX_RELATIVE_STD
    ]
    if loose:
        raise DynamicsError(
            f"m and c not determined by this response ({', '.join(loose)}; limit "
            f"{100 * MAX_RELATIVE_STD:g} %): a larger step or less noise"
        )
    return DynamicsFit(
        m=m,
        c=c,
        m_std=m * float(rel[0]),
        c_std=c * float(rel[1]),
        natural_frequency=f_n,
        damping_ratio=zeta,
        rate_hz=rate,
        samples_per_period=rate / f_n,
        rms_error=float(np.sqrt(np.mean((r * scale) ** 2))),
        samples=int(measured.size),
        w0=w0,
        x_rest=x_rest,
        step_at=int(step_at),
    )


def predicted_response(
    fit: DynamicsFit,
    bouc_wen: BoucWenParameters,
    t: NDArray[np.float64],
    u: NDArray[np.float64],
    voltage_offset: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(t, x) of the fitted model over the samples from the step on (same input as the fit)."""
    t, u = np.asarray(t, dtype=float), np.asarray(u, dtype=float)
    dt = float(np.median(np.diff(t)))
    plant = DynamicPlant(bouc_wen, fit.dynamics, x0=fit.x_rest, w0=fit.w0)
    xs, _, _ = plant.simulate(u[fit.step_at :] - voltage_offset, dt)
    return t[fit.step_at :], xs
