"""Sliding-mode law with a boundary layer on the tracking error of (11.4), ``smc``.

    s = x2 + λ·x1,  λ = k1/k2
    u = −k0·x0 − k1·x1 − k2·x2 − ks·sat(dz(s)/φ),  dz(s) = sign(s)·max(|s| − δ, 0),
    sat(z) = max(−1, min(1, z))

The PID of (11.5) plus a switching term. In the normalized Bouc-Wen model (11.2)-(11.3) |w| ≤ 1
for w(0) in [−1, 1], so the hysteretic force κw·w is bounded by κw_max (Assumption 2): a
switching gain ks > κw_max dominates it wherever |s| > δ + φ (the reaching condition s·ṡ < 0
for that part of the force), :func:`switching_gain`. Within the dead band |s| ≤ δ the law is
the PID: δ holds the sensor noise on s (:func:`noise_layer`), so noise does not switch (each
switch of noise would add to the voltage's total variation). Beyond it the term is linear
over the layer φ, where the loop holds the PID with k1 + ks·λ/φ and k2 + ks/φ: the sampled-loop
check takes those and the PID's, and φ is bounded below by the sampled loop's stability at
the rate it runs (:func:`stable_layer`).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from .errors import GainError, SampledLoopError
from .laws import PID, Gains, LinearGains, LoopContext, Pid, Value, _num, register

if TYPE_CHECKING:
    from .bounds import Bounds, NominalPlant
    from .theorem4 import GainReport

#: noise on s the dead band holds: this many standard deviations (at 3, the 0.27 % of samples
#: beyond it still switched: 270 times a second at 100 kHz, the voltage's total variation 1.05×
#: the PID's; at 6, 1.01×, the settling unchanged; test/test_control_sliding.py)
LAYER_SIGMAS = 6.0
#: the sampled loop inside the layer: its spectral radius at most this share of the way from
#: the PID part's to 1 (a linear check at the layer's largest gain does not bound the loop's
#: behaviour between no gain and that one: at 1 kHz with a one-sample delay, a layer at
#: radius 0.972 chatters where the PID's is 0.932; a share of 0.1 keeps the voltage's
#: total variation the PID's, test/test_control_sliding.py)
LAYER_SHARE = 0.1
MAX_HALVINGS = 60


def _sat(z: Value) -> Value:
    """max(−1, min(1, z)), a float for a float."""
    return max(-1.0, min(1.0, z)) if isinstance(z, float) else np.clip(z, -1.0, 1.0)


class SlidingMode(Pid):
    """The sliding-mode law of the module docstring."""

    name = "smc"
    equation = (
        "smc (sliding mode): u = -k0 x0 - k1 x1 - k2 x2 - ks sat(dz(s)/phi), s = x2 + (k1/k2) x1,"
        " dz: dead band delta"
    )
    gains: tuple[str, ...] = ("k0", "k1", "k2", "ks", "phi", "delta")

    def split(
        self, gains: Gains, t: ArrayLike, x0: ArrayLike, x1: ArrayLike, x2: ArrayLike
    ) -> tuple[Value, Value]:
        """(the PID of (11.5), −ks·sat(dz(s)/φ))."""
        u_pid, _ = super().split(gains, t, x0, x1, x2)
        s = _num(x2) + gains.k1 / gains.k2 * _num(x1)
        return u_pid, -gains.ks * _sat(_dead_band(s, gains.delta) / gains.phi)

    def check(self, gains: Gains) -> None:
        """k2 > 0 (λ = k1/k2) and φ > 0."""
        if not gains.k2 > 0:
            raise GainError(f"law smc needs k2 > 0 (s = x2 + (k1/k2) x1), got {gains.k2}")
        if not gains.phi > 0:
            raise GainError(f"law smc needs a boundary layer phi > 0 m/s, got {gains.phi}")

    def theorem4(self, bounds: Bounds, gains: Gains) -> GainReport:
        """Theorem 4 on the PID part, and the reaching condition ks > κw_max."""
        report = super().theorem4(bounds, gains)
        if gains.ks > bounds.kappa_w_max:
            return replace(
                report,
                notes=(
                    *report.notes,
                    f"ks = {gains.ks:.6g} V > kappa_w_max = {bounds.kappa_w_max:.6g} V: the "
                    f"switching dominates kappa_w w outside |s| <= delta + phi = "
                    f"{gains.delta + gains.phi:.6g} m/s",
                ),
            )
        why = (
            f"ks = {gains.ks:.6g} V <= kappa_w_max = {bounds.kappa_w_max:.6g} V: the switching "
            "term does not dominate the hysteretic force kappa_w w (|w| <= 1)"
        )
        return replace(report, valid=False, reasons=(*report.reasons, why))

    def sampled_gains(self, gains: Gains, rate_hz: float, most: int) -> list[LinearGains]:
        """Inside the layer: (k0, k1 + ks·λ/φ, k2 + ks/φ), the law's largest linear gains; with
        a dead band also the PID's, the loop within it.
        """
        self.check(gains)
        inside = [(gains.k0, gains.k1, gains.k2)] if gains.delta > 0 else []
        return [*inside, layer_gains(gains)]

    def design(
        self, bounds: Bounds, gains: Gains, margin: float, loop: LoopContext, given: set[str]
    ) -> dict[str, float]:
        """The switching gain by :func:`switching_gain`; δ by :func:`noise_layer` (0 with no
        noise given); φ by :func:`stable_layer` with a nominal plant, else the noise layer.
        """
        out: dict[str, float] = {}
        if "ks" not in given:
            out["ks"] = switching_gain(bounds, margin)
        noise = None
        if loop.noise > 0 and loop.rate_hz:
            lam = gains.k1 / gains.k2
            noise = noise_layer(loop.noise, loop.rate_hz, loop.derivative_tau, lam)
        if "delta" not in given:
            out["delta"] = noise or 0.0
        if "phi" in given:
            return out
        ks = out.get("ks", gains.ks)
        layers = [] if noise is None or loop.plant is not None else [noise]
        if loop.plant is not None and loop.rate_hz:
            g = replace(gains, ks=ks)
            layers.append(
                stable_layer(
                    loop.plant,
                    g,
                    loop.rate_hz,
                    loop.delay_samples,
                    loop.derivative_tau,
                    loop.hysteresis,
                )
            )
        if not layers:
            raise GainError(
                "law smc: its boundary layer phi comes from the loop rate with a nominal plant "
                "(the sampled loop) or the sensor noise; give them, or phi"
            )
        out["phi"] = max(layers)
        return out


def _dead_band(s: Value, delta: float) -> Value:
    """sign(s)·max(|s| − δ, 0), a float for a float."""
    if not delta:
        return s
    if isinstance(s, float):
        return math.copysign(max(abs(s) - delta, 0.0), s)
    return np.sign(s) * np.maximum(np.abs(s) - delta, 0.0)


def layer_gains(gains: Gains) -> LinearGains:
    """(k0, k1 + ks·(k1/k2)/φ, k2 + ks/φ): the PID the law is inside its layer."""
    g = gains.ks / gains.phi
    return (gains.k0, gains.k1 + g * gains.k1 / gains.k2, gains.k2 + g)


def switching_gain(bounds: Bounds, margin: float) -> float:
    """The switching gain ks = (1 + margin)·κw_max [V], above the bound on κw·w (|w| ≤ 1,
    Assumption 2).
    """
    return (1.0 + margin) * bounds.kappa_w_max


def noise_layer(noise: float, rate_hz: float, derivative_tau: float, lam: float) -> float:
    """φ [m/s] that holds LAYER_SIGMAS standard deviations of s = x2 + λ·x1 when the sensor adds
    white noise of ``noise`` [m] RMS: x1's noise σ, x2's that of the filtered difference
    (x2_filtered: α = T/(τ + T), var 2σ²/T²·α/(2 − α)), their covariance α·σ²/T.
    """
    dt = 1.0 / rate_hz
    alpha = dt / (derivative_tau + dt)
    var = noise**2 * (2.0 / dt**2 * alpha / (2.0 - alpha) + lam**2 + 2.0 * lam * alpha / dt)
    return LAYER_SIGMAS * math.sqrt(var)


def stable_layer(
    plant: NominalPlant,
    gains: Gains,
    rate_hz: float,
    delay_samples: int = 0,
    derivative_tau: float = 0.0,
    hysteresis: str = "disturbance",
) -> float:
    """The smallest φ [m/s] (to 1 %) at which the sampled loop inside the layer
    (:func:`layer_gains`) has a spectral radius ρ ≤ ρ_pid + LAYER_SHARE·(1 − ρ_pid), ρ_pid the
    PID part's own; :class:`SampledLoopError` when the PID part is not stable.
    """
    from .discrete import check_sampled_loop

    def radius(g: Gains, law: str) -> float:
        return check_sampled_loop(
            plant, g, rate_hz, delay_samples, law, derivative_tau, hysteresis
        ).spectral_radius

    pid = radius(gains, PID.name)
    if pid >= 1.0:
        raise SampledLoopError(
            f"the PID part's sampled loop is unstable at {rate_hz:g} Hz (radius {pid:.4f}): "
            "no boundary layer makes the law's"
        )
    if gains.ks == 0:
        return 0.0
    target = pid + LAYER_SHARE * (1.0 - pid)

    def holds(phi: float) -> bool:
        return radius(replace(gains, phi=phi), SLIDING.name) <= target

    low = high = gains.ks / gains.k2  # the layer's gain ks/φ equals k2
    for _ in range(MAX_HALVINGS):  # bracket: the radius tends to the PID's as φ grows
        if holds(high):
            if not holds(low):
                break
            high, low = low, low / 2.0
        else:
            low, high = high, high * 2.0
    else:
        raise SampledLoopError(f"no boundary layer found within 2^{MAX_HALVINGS} of ks/k2")
    while high - low > 0.01 * high:
        mid = 0.5 * (low + high)
        low, high = (low, mid) if holds(mid) else (mid, high)
    return high


SLIDING = register(SlidingMode())
