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
from typing import Callable, cast

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
    dt = _sample_interval(t, u, x)
    rate = 1.0 / dt
    step_at = _step_index(u, step_at)
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
    w0 = _rest_w(bouc_wen, float(np.mean(u[:step_at])), x_rest, voltage_offset)
    held = u[step_at:] - voltage_offset  # held over (t[k-1], t[k]]
    measured = x[step_at:]
    scale = max(float(np.ptp(measured)), 1e-30)

    def residual(p: NDArray[np.float64]) -> NDArray[np.float64]:
        dynamics = Dynamics(m=math.exp(p[0]), c=math.exp(p[1]))
        return (_simulate(bouc_wen, dynamics, x_rest, w0, held, dt) - measured) / scale

    m, c, r, rel = _fit_log_m_c(residual, _first_guess(bouc_wen.kappa_x, rate, peak))
    f_n = _natural_frequency(bouc_wen.kappa_x, m)
    zeta = _damping_ratio(bouc_wen.kappa_x, m, c)
    _check_resolution(rate, f_n, zeta, peak, min_samples_per_period)
    _check_determined(float(np.sqrt(np.mean(r**2))), rel)
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


def _sample_interval(
    t: NDArray[np.float64], u: NDArray[np.float64], x: NDArray[np.float64]
) -> float:
    """The sample interval [s] of a valid record: 1-D, one length, >= 20 finite, uniform."""
    if not (t.ndim == u.ndim == x.ndim == 1 and len(t) == len(u) == len(x)):
        raise DynamicsError("t, u and x must be 1-D arrays of one length")
    if len(t) < 20 or not (
        np.all(np.isfinite(t)) and np.all(np.isfinite(u)) and np.all(np.isfinite(x))
    ):
        raise DynamicsError(f"need >= 20 finite samples, got {len(t)}")
    dt = float(np.median(np.diff(t)))
    if not dt > 0 or np.max(np.abs(np.diff(t) - dt)) > 0.01 * dt:
        raise DynamicsError("the response must be sampled uniformly")
    return dt


def _step_index(u: NDArray[np.float64], step_at: int | None) -> int:
    """``step_at``, or the first sample whose voltage leaves the rest value; checked."""
    if step_at is None:
        moved = np.flatnonzero(np.abs(u - u[0]) > 1e-6 * max(1.0, float(np.ptp(u))))
        if moved.size == 0:
            raise DynamicsError("the applied voltage never changes: no step in the record")
        step_at = int(moved[0])
    if step_at < 2 or step_at > len(u) - 10:
        raise DynamicsError(
            f"the step must come after >= 2 rest samples and leave >= 10 after it (at {step_at})"
        )
    return step_at


def _rest_w(bouc_wen: BoucWenParameters, u_rest: float, x_rest: float, offset: float) -> float:
    """The rest state's w from u = kappa_x x + kappa_w w + y0, clipped to [-1, 1] (11.12)."""
    w = (u_rest - offset - bouc_wen.kappa_x * x_rest) / bouc_wen.kappa_w
    return float(np.clip(w, -1.0, 1.0))


def _natural_frequency(kappa_x: float, m: float) -> float:
    """Natural frequency f_n = sqrt(kappa_x / m) / (2 pi) [Hz] of (11.1)."""
    return math.sqrt(kappa_x / m) / (2.0 * math.pi)


def _damping_ratio(kappa_x: float, m: float, c: float) -> float:
    """Damping ratio zeta = c / (2 sqrt(kappa_x m)) of (11.1)."""
    return c / (2.0 * math.sqrt(kappa_x * m))


def _first_guess(kappa_x: float, rate: float, peak: int) -> tuple[float, float]:
    """(m, c) to start from: the ringing's half period gives f_n, stiffness kappa_x; light
    damping (zeta = 0.05).
    """
    f_guess = rate / (2.0 * max(peak, 1))
    m_guess = kappa_x / (2.0 * math.pi * f_guess) ** 2
    return m_guess, 2.0 * 0.05 * math.sqrt(kappa_x * m_guess)


def _simulate(
    bouc_wen: BoucWenParameters,
    dynamics: Dynamics,
    x_rest: float,
    w0: float,
    held: NDArray[np.float64],
    dt: float,
) -> NDArray[np.float64]:
    """Displacement of (11.1) from rest under the held voltages (zero-order hold)."""
    xs, _, _ = DynamicPlant(bouc_wen, dynamics, x0=x_rest, w0=w0).simulate(held, dt)
    return xs


def _fit_log_m_c(
    residual: Callable[[NDArray[np.float64]], NDArray[np.float64]], guess: tuple[float, float]
) -> tuple[float, float, NDArray[np.float64], NDArray[np.float64]]:
    """Least squares over (log m, log c) from ``guess``: m, c, the residuals at the optimum and
    the relative standard errors of m and c.
    """
    m_guess, c_guess = guess
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
    # dense (the stubs also allow a sparse or operator Jacobian: jac_sparsity or tr_solver='lsmr')
    return m, c, r, _log_std(cast(NDArray[np.float64], fit.jac), r)


def _log_std(jac: NDArray[np.float64], r: NDArray[np.float64]) -> NDArray[np.float64]:
    """Standard errors of the fitted (log) parameters: residual variance times (J^T J)^-1."""
    dof = max(1, r.size - 2)
    try:
        cov = np.linalg.inv(jac.T @ jac) * float(r @ r) / dof
    except np.linalg.LinAlgError as exc:
        raise DynamicsError(
            "m and c are not determined by this response (singular Jacobian)"
        ) from exc
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))  # std of log m, log c = relative std


def _check_resolution(
    rate: float, f_n: float, zeta: float, peak: int, min_samples_per_period: float
) -> None:
    """The resolution rule after the fit (module docstring): rate >= min_samples_per_period
    f_n, and the first peak where the fitted resonance puts it (else an alias).
    """
    if rate < min_samples_per_period * f_n:
        raise UnresolvedResonanceError(
            f"natural frequency {f_n:.4g} Hz needs a sensor rate >= "
            f"{min_samples_per_period * f_n:.4g} Hz "
            f"(rule: >= {min_samples_per_period:g} samples per period), got {rate:g} Hz"
        )
    expected_peak = rate / (2.0 * f_n * math.sqrt(max(1e-12, 1.0 - min(zeta, 0.99) ** 2)))
    if zeta < 0.7 and abs(peak - expected_peak) > max(1.5, 0.3 * expected_peak):
        raise UnresolvedResonanceError(
            f"the fitted resonance ({f_n:.4g} Hz) would peak {expected_peak:.3g} samples "
            "after the step, the "
            f"response peaks after {peak}: an alias of a resonance faster than "
            f"{rate / min_samples_per_period:.4g} Hz "
            f"(rule: >= {min_samples_per_period:g} samples per period of the natural frequency)"
        )


def _check_determined(rms: float, rel: NDArray[np.float64]) -> None:
    """Refuse a fit whose residual (``rms``, fraction of the span) or relative standard errors
    of m and c (``rel``) exceed :data:`MAX_RMS_FRACTION`, :data:`MAX_RELATIVE_STD`.
    """
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
    xs = _simulate(
        bouc_wen, fit.dynamics, fit.x_rest, fit.w0, u[fit.step_at :] - voltage_offset, dt
    )
    return t[fit.step_at :], xs
