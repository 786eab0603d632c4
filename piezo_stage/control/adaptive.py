"""Adaptive law on the sliding-mode law: the stiffness κx learned on line, ``adaptive``.

After Ikhouane, Mañosa and Rodellar (thesis ref. [28]): in (11.1)-(11.3) the hysteretic force
κw·w is a bounded disturbance (|w| ≤ 1, Assumption 2), so a law may adapt the linear part's
unknown parameter within its known interval and dominate the rest. With s = x2 + λ·x1,
λ = k1/k2 (the sliding variable of :mod:`.sliding`),

    u = u_smc + κ̂x·φ,  φ = yr − yr(t_c)  (the reference since the loop closed at t_c)
    dκ̂x/dt = −(k2/τa)·s·φ/(P + εa²),  dP/dt = (φ² − P)/τa,  κ̂x projected on [0, kx_max]

From m·ṡ = −k2·s + (κ̂x − κx)·φ − κw·w + (terms the PID dominates), V = m·s²/2 + τa·(P +
εa²)·κ̃x²/(2·k2) (P held) decreases wherever k2·s² > κw_max·|s|: the projection keeps the estimate
in [0, kx_max], s enters the ball κw_max/k2, and κ̂x converges where φ excites it (a reference
that moves: at a set point φ = 0 and the law is ``smc``). The regressor is the reference (the
desired-compensation form): no sensor noise enters the term, and the integral x0 holds the
force at closing (φ = 0 there, so bumpless transfer is the sliding law's). The update is
normalised by P, φ's mean square over τa: κ̂x moves with time constant τa whatever the
reference's amplitude; εa [m] is the smallest excursion it learns from. Beside a model's
feedforward the estimate does not adapt (the model supplies κx·x; what is left is the sampled
loop's lag, not a stiffness).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

from .errors import GainError
from .laws import Gains, LoopContext, register
from .sliding import SlidingMode

if TYPE_CHECKING:
    from .bounds import Bounds
    from .theorem4 import GainReport

#: the adaptation's time constant against the loop's slowest mode, the integral's ((k1 +
#: κx_max)/k0): time-scale separation, so that the PID holds s while κ̂x moves. At 4 a live
#: graph's stall (the measured position standing still for 15 ms while the reference moved)
#: taught κ̂x a stiffness and the emulated rig tracked the triangle to 4.8–14.1 %; at 16,
#: 4.3–5.1 %, the core's figure unchanged (1.8 %)
TAU_SEPARATION = 16.0
#: εa against the sensor noise: the smallest reference excursion the estimate learns from
EPS_NOISE = 10.0


class StiffnessEstimate:
    """κ̂x of one closed loop and its reference at closing (the law's state, per controller)."""

    __slots__ = ("kx", "power", "_y_close", "_rate", "_eps2", "_hi", "_lam", "_k2")

    def __init__(self, gains: Gains) -> None:
        self.kx = 0.0
        self.power = 0.0  # P, the mean of φ² over τa
        self._y_close: float | None = None
        self.configure(gains)

    def configure(self, gains: Gains) -> None:
        """Take τa, εa and kx_max of ``gains`` (κ̂x kept, projected on the new interval)."""
        self._rate = 1.0 / gains.tau_a
        self._eps2 = gains.eps_a * gains.eps_a
        self._hi = gains.kx_max
        self._lam, self._k2 = gains.k1 / gains.k2, gains.k2
        self.kx = min(max(self.kx, 0.0), self._hi)

    def rebase(self, yr: float) -> None:
        """The loop closes at reference ``yr``: φ = 0 from here."""
        self._y_close = yr

    def term(self, yr: float) -> float:
        """κ̂x·φ [V]."""
        return self.kx * (yr - self._y_close) if self._y_close is not None else 0.0

    def adapt(self, x1: float, x2: float, yr: float, dt: float) -> None:
        """One step of dP/dt = (φ² − P)/τa and dκ̂x/dt = −(k2/τa)·s·φ/(P + εa²), s = x2 + λ·x1,
        κ̂x projected on [0, kx_max] (a step longer than τa counts as τa).
        """
        if self._y_close is None:
            return
        phi = yr - self._y_close
        step = min(dt * self._rate, 1.0)
        self.power += step * (phi * phi - self.power)
        s = x2 + self._lam * x1
        kx = self.kx - step * self._k2 * s * phi / (self.power + self._eps2)
        self.kx = min(max(kx, 0.0), self._hi)


class AdaptiveSliding(SlidingMode):
    """The adaptive law of the module docstring: ``smc`` plus κ̂x·(yr − yr(t_c)). Its sampled
    loop is the sliding law's: κ̂x multiplies the reference, an input of the loop, not a gain.
    """

    name = "adaptive"
    equation = (
        "adaptive (after [28]): u = smc + kx_hat (yr - yr(t_c)), "
        "d kx_hat/dt = -(k2/tau_a) s phi/(P + eps_a^2), P: mean phi^2 over tau_a, on [0, kx_max]"
    )
    gains = (*SlidingMode.gains, "tau_a", "eps_a", "kx_max")

    def estimate(self, gains: Gains) -> StiffnessEstimate:
        """A fresh κ̂x = 0 for a controller that runs this law."""
        return StiffnessEstimate(gains)

    def check(self, gains: Gains) -> None:
        """The sliding law's, and τa > 0, εa > 0."""
        super().check(gains)
        for key, unit in (("tau_a", "s"), ("eps_a", "m")):
            value = getattr(gains, key)
            if not (math.isfinite(value) and value > 0):
                raise GainError(f"law adaptive needs {key} > 0 {unit}, got {value}")

    def theorem4(self, bounds: Bounds, gains: Gains) -> GainReport:
        """The sliding law's conditions, and the projection's interval within Assumption 2's:
        kx_max ≥ κx_max (else the estimate cannot reach every κx the bounds allow).
        """
        report = super().theorem4(bounds, gains)
        if gains.kx_max >= bounds.kappa_x_max:
            return report
        why = (
            f"kx_max = {gains.kx_max:.6g} V/m < kappa_x_max = {bounds.kappa_x_max:.6g} V/m: "
            "the projection keeps kappa_x_hat below stiffnesses Assumption 2 allows"
        )
        return replace(report, valid=False, reasons=(*report.reasons, why))

    def design(
        self, bounds: Bounds, gains: Gains, margin: float, loop: LoopContext, given: set[str]
    ) -> dict[str, float]:
        """The sliding law's gains; kx_max = κx_max (Assumption 2's interval); τa =
        TAU_SEPARATION times the integral mode's time (k1 + κx_max)/k0; εa = EPS_NOISE times
        the sensor noise (10 nm with none given).
        """
        out = super().design(bounds, gains, margin, loop, given)
        if "kx_max" not in given:
            out["kx_max"] = bounds.kappa_x_max
        if "tau_a" not in given:
            out["tau_a"] = TAU_SEPARATION * (gains.k1 + bounds.kappa_x_max) / gains.k0
        if "eps_a" not in given:
            out["eps_a"] = EPS_NOISE * (loop.noise if loop.noise > 0 else 1e-9)
        return out


ADAPTIVE = register(AdaptiveSliding())
