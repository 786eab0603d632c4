"""Stability of the sampled closed loop: ZOH plant + the discrete law of §11.5, at a given rate
and delay.

Plant: the linear part of (11.1)-(11.3), m·ẍ + c·ẋ + k·x = u, held by a zero-order hold over each
period T = 1/rate. The hysteresis enters one of two ways (``hysteresis=``):

- ``"disturbance"`` (default): k = κx, and κw·w is a bounded input (|w| ≤ 1 for class I) that
  cannot change stability of the linear loop — the "linear part" of docs/design.md §4/§7;
- ``"initial_slope"``: w linearised by its slope at w = 0, ẇ = ρ·ẋ (11.3), so k = κx + κw·ρ,
  the stiffest the hysteresis makes the plant.

Controller, exactly as :class:`~piezo_stage.control.controller.TimeVaryingPID` runs it (yr = 0):
x0[k] = x0[k−1] + T·x[k] (rectangle sums), x2[k] = (x[k] − x[k−1])/T (Euler differences),
optionally filtered x2f[k] = (1−α)·x2f[k−1] + α·x2[k], α = T/(τ + T); v[k] = law(x0, x1, x2); the
plant receives u over [kT, (k+1)T) equal to v[k − d] for ``delay_samples`` d (d = 1: the output
computed from sample k is applied one period late, as a real loop does).

(11.5) and (11.17) give the same linear time-invariant loop (the sine is an exogenous input), so
stability is ρ(Φ) < 1 for the one-step matrix Φ. (11.18) makes the x0 gain k0 + kA·sin(2πft)
periodic; when rate/f is an integer N the check uses the monodromy matrix M = Φ[N−1]···Φ[0]
(Floquet) and reports ρ(M)^(1/N), a per-sample figure comparable with the other laws.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .bounds import NominalPlant
from .errors import SampledLoopError
from .laws import PID, Gains, LinearGains, law_named

HYSTERESIS_MODELS: tuple[str, ...] = ("disturbance", "initial_slope")
#: Margins 1 − ρ smaller than this are rounding noise of a double ρ near 1 (1e6·eps keeps ~4 digits
#: of the margin): the check is meaningful while the slowest closed-loop mode moves |λ|·T above it.
MARGIN_RESOLUTION = 1e6 * float(np.finfo(float).eps)
#: Longest output delay checked: the loop matrix has 5 + d rows (d = 1e5 would need 74.5 GiB).
MAX_DELAY_SAMPLES = 1000
#: Most matrix entries the Floquet product of pid_tv may hold (N matrices of (5 + d)² entries).
MAX_FLOQUET_ENTRIES = 20_000_000


def stiffness(plant: NominalPlant, hysteresis: str = "disturbance") -> float:
    """Linear stiffness k [V/m]: κx, or κx + κw·ρ for the initial-slope linearisation of (11.3)."""
    if hysteresis not in HYSTERESIS_MODELS:
        raise SampledLoopError(f"hysteresis must be one of {HYSTERESIS_MODELS}, got {hysteresis!r}")
    return plant.kappa_x + (plant.kappa_w * plant.rho if hysteresis == "initial_slope" else 0.0)


def continuous_poles(
    plant: NominalPlant, gains: Gains, hysteresis: str = "disturbance"
) -> NDArray[np.floating] | NDArray[np.complexfloating]:
    """Roots of m·s³ + (c + k2)·s² + (k + k1)·s + k0: the continuous loop of (11.13)-(11.15),
    w frozen.
    """
    k = stiffness(plant, hysteresis)
    return np.roots([plant.m, plant.c + gains.k2, k + gains.k1, gains.k0])


def max_meaningful_rate(
    plant: NominalPlant, gains: Gains, hysteresis: str = "disturbance"
) -> float:
    """Highest loop rate [Hz] at which the sampled check resolves the slowest continuous mode:
    |λ_min|·T ≥ ``MARGIN_RESOLUTION`` (beyond it ρ = 1 − |λ|T rounds to noise around 1).
    """
    mags = np.abs(continuous_poles(plant, gains, hysteresis))
    mags = mags[mags > 0]
    return float(mags.min() / MARGIN_RESOLUTION) if mags.size else math.inf


def zoh_plant(
    plant: NominalPlant, period: float, hysteresis: str = "disturbance"
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(Ad, Bd) of state [x, ẋ] held by a zero-order hold over ``period`` [s]."""
    from scipy.linalg import expm  # lazy: keeps `import piezo_stage.control` light for nodes

    k = stiffness(plant, hysteresis)
    big = np.zeros((3, 3))
    big[0, 1] = 1.0
    big[1, 0], big[1, 1], big[1, 2] = -k / plant.m, -plant.c / plant.m, 1.0 / plant.m
    e = expm(big * period)
    return e[:2, :2], e[:2, 2]


def _step_matrix(
    ad: NDArray[np.float64],
    bd: NDArray[np.float64],
    period: float,
    linear: LinearGains,
    delay: int,
    alpha: float,
) -> NDArray[np.float64]:
    """One period of the loop; state [x, ẋ, x0[k−1], x[k−1], x2f[k−1], v[k−1], ..., v[k−d]]."""
    n = 5 + delay
    eye = np.eye(n)
    x = eye[0]
    x0 = eye[2] + period * x
    x2f = (1.0 - alpha) * eye[4] + alpha * (x - eye[3]) / period
    k0, k1, k2 = linear
    v = -k0 * x0 - k1 * x - k2 * x2f
    applied = v if delay == 0 else eye[4 + delay]
    phi = np.zeros((n, n))
    phi[:2] = ad @ eye[:2] + np.outer(bd, applied)
    phi[2], phi[3], phi[4] = x0, x, x2f
    if delay:
        phi[5] = v
        phi[6:] = eye[5 : 4 + delay]
    return phi


@dataclass(frozen=True)
class SampledLoopReport:
    """Result of :func:`check_sampled_loop`: ρ per sample, stable (ρ < 1), margin = 1 − ρ."""

    rate_hz: float
    delay_samples: int
    law: str
    hysteresis: str
    derivative_tau: float
    spectral_radius: float
    stable: bool
    margin: float
    continuous_stable: bool

    def to_dict(self) -> dict[str, object]:
        """The fields as a mapping."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__}


def closed_loop_matrices(
    plant: NominalPlant,
    gains: Gains,
    rate_hz: float,
    delay_samples: int = 0,
    law: str = PID.name,
    derivative_tau: float = 0.0,
    hysteresis: str = "disturbance",
) -> list[NDArray[np.float64]]:
    """Per-sample matrices of the sampled loop, one per entry of the law's
    :meth:`~.laws.ControlLaw.sampled_gains`: one for (11.5)/(11.17), N = rate/f for (11.18).
    """
    control = law_named(law)
    plant.validate()
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise SampledLoopError(f"rate_hz must be > 0, got {rate_hz}")
    if int(delay_samples) != delay_samples or not 0 <= delay_samples <= MAX_DELAY_SAMPLES:
        raise SampledLoopError(
            f"delay_samples must be an integer in [0, {MAX_DELAY_SAMPLES}], got {delay_samples}"
        )
    if not (math.isfinite(derivative_tau) and derivative_tau >= 0):
        raise SampledLoopError(f"derivative_tau must be >= 0, got {derivative_tau}")
    period = 1.0 / rate_hz
    with np.errstate(all="ignore"):
        ad, bd = (
            zoh_plant(plant, period, hysteresis)
            if math.isfinite(period)
            else (np.full((2, 2), np.inf), np.full(2, np.inf))
        )
    if not (np.all(np.isfinite(ad)) and np.all(np.isfinite(bd))):
        raise SampledLoopError(
            f"rate_hz {rate_hz:g} is too low: the plant held over T = "
            f"{period:.3g} s overflows double precision"
        )
    alpha = period / (derivative_tau + period)
    delay = int(delay_samples)
    linear = control.sampled_gains(gains, rate_hz, MAX_FLOQUET_ENTRIES // (5 + delay) ** 2)
    matrices = [_step_matrix(ad, bd, period, each, delay, alpha) for each in linear]
    if all(k0 == 0.0 for k0, _, _ in linear):  # x0 feeds nothing back: its mode (1) is not the
        return [np.delete(np.delete(m, 2, 0), 2, 1) for m in matrices]  # loop's
    return matrices


def spectral_radius_per_sample(matrices: list[NDArray[np.float64]]) -> float:
    """ρ(Φ[N−1]···Φ[0])^(1/N); for long periods the product is renormalised to avoid overflow."""
    n = len(matrices)
    if n == 1:
        return float(np.max(np.abs(np.linalg.eigvals(matrices[0]))))
    prod = np.eye(matrices[0].shape[0])
    log_scale = 0.0
    for phi in matrices:
        prod = phi @ prod
        s = np.max(np.abs(prod))
        if s > 0:
            prod /= s
            log_scale += math.log(s)
    rho = float(np.max(np.abs(np.linalg.eigvals(prod))))
    if rho == 0.0:
        return 0.0
    return math.exp((math.log(rho) + log_scale) / n)


def check_sampled_loop(
    plant: NominalPlant,
    gains: Gains,
    rate_hz: float,
    delay_samples: int = 0,
    law: str = PID.name,
    derivative_tau: float = 0.0,
    hysteresis: str = "disturbance",
) -> SampledLoopReport:
    """Spectral radius, stability flag and margin 1 − ρ of the sampled loop (module docstring).

    With the §11.4.1 gains and plant, without delay: stable at 1, 4, 6, 8 and 100 kHz, unstable
    at 2, 3, 5, 10, 20 and 50 kHz (the plant's 7 kHz resonance against the sampling); with a
    one-sample delay at 1 kHz and from 200 kHz (docs/design.md §7).
    """
    limit = max_meaningful_rate(plant, gains, hysteresis)
    if rate_hz > limit:
        raise SampledLoopError(
            f"rate_hz {rate_hz:g} is beyond where the sampled check means anything (about "
            f"{limit:.3g} Hz here): the slowest closed-loop mode moves less than "
            f"{MARGIN_RESOLUTION:.1e} per sample, so rho = 1 - |lambda| T is rounding noise; "
            f"the continuous-time verdict applies"
        )
    mats = closed_loop_matrices(
        plant, gains, rate_hz, delay_samples, law, derivative_tau, hysteresis
    )
    rho = spectral_radius_per_sample(mats)
    # the continuous loop of the law's mean linear gains (pid_tv: its sine averages out);
    # without an integral (k0 = 0) its x0 is not part of the loop
    linear = np.mean(law_named(law).sampled_gains(gains, rate_hz, len(mats)), axis=0)
    mean = Gains(k0=float(linear[0]), k1=float(linear[1]), k2=float(linear[2]))
    poles = continuous_poles(plant, mean, hysteresis)
    cont = bool(np.all(poles[poles != 0].real < 0) if mean.k0 == 0 else np.all(poles.real < 0))
    return SampledLoopReport(
        rate_hz=float(rate_hz),
        delay_samples=int(delay_samples),
        law=law,
        hysteresis=hysteresis,
        derivative_tau=float(derivative_tau),
        spectral_radius=rho,
        stable=rho < 1.0,
        margin=1.0 - rho,
        continuous_stable=cont,
    )
