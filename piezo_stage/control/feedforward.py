"""Bouc-Wen feedforward for tracking, from the ch. 11 model (11.1)-(11.3).

The ch. 11 model has the displacement as the Bouc-Wen input: m ẍ + c ẋ + κx·x + κw·w(x) = u,
w driven by x (11.3). The voltage that makes the stage follow x_d is therefore the model itself
evaluated along x_d, no inversion needed:

    u_ff = m·ẍ_d + c·ẋ_d + Σ κ_i·x_d^i + κw·w(x_d),   w driven by x_d,

with x_d measured from the model's offset (x = displacement − y0) and the polynomial of (10.4)
when the set has more than κx. :func:`feedforward` evaluates it along a whole path (pure,
vectorised); :class:`Feedforward` steps it once per controller period and keeps w.

Consistent reset (the loop opens and closes): while the loop is open the stage moves under the
hold voltage, not along x_d, so w of the feedforward no longer describes it. At closing the
state is re-seeded from the stage itself: at rest (11.1) gives κw·w = u − Σ κ_i x^i with the
applied u and the measured x, and w is then driven from the measured x to x_d — the same rule
seeds the first sample of a loop that starts closed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import StrEnum
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from piezo_stage.model.bouc_wen import BoucWenParameters, polynomial, simulate_w
from piezo_stage.model.errors import ModelError
from piezo_stage.model.parameter_set import ParameterSet, load_parameter_set
from piezo_stage.model.plant import StaticPlant

from .errors import ControlError

#: |w| of a re-seeded state stays inside the class-I bound |w| <= 1 by this margin
W_SEED_LIMIT = 1.0 - 1e-9


class FeedforwardError(ControlError):
    """A parameter set that cannot serve as a feedforward model, or a bad input to it."""


class Compensation(StrEnum):
    """What drives the amplifier when the loop is closed."""

    FEEDBACK = "feedback"  #: the ch. 11 law on x1 = x − x_d alone
    FEEDFORWARD = "feedforward"  #: u_ff alone (the law's state is reported, not applied)
    BOTH = "both"  #: u_ff + the law

    @property
    def feeds_forward(self) -> bool:
        """Whether u_ff drives the amplifier (feedforward or both)."""
        return self is not Compensation.FEEDBACK


def check_learning(
    compensation: Compensation, learns: bool, learn: str, compensation_name: str = "compensation"
) -> None:
    """FeedforwardError when the option ``learn`` asks to learn a feedforward (:mod:`.learning`
    corrects u_ff over repeated periods) that ``compensation`` does not apply; the message
    names the options as the caller spells them.
    """
    if learns and not compensation.feeds_forward:
        raise FeedforwardError(
            f"{learn} needs a feedforward: {compensation_name} feedforward or both"
        )


def compensation(value: str | Compensation) -> Compensation:
    """The :class:`Compensation` named ``value``, or :class:`FeedforwardError` listing the names."""
    try:
        return Compensation(value)
    except ValueError:
        names = ", ".join(c.value for c in Compensation)
        raise FeedforwardError(f"unknown compensation {value!r}; expected one of {names}") from None


@dataclass(frozen=True)
class FeedforwardModel:
    """The dynamic ch. 11 model used as feedforward: Bouc-Wen part (input x [m], output u [V])
    and m [V s²/m], c [V s/m]; ``y0`` of the Bouc-Wen part is the displacement offset.
    """

    bouc_wen: BoucWenParameters
    m: float
    c: float
    name: str = ""

    def __post_init__(self) -> None:
        try:
            self.bouc_wen.validate()
        except ModelError as exc:
            raise FeedforwardError(f"feedforward model {self.name}: {exc}") from exc
        for key in ("m", "c"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value >= 0):
                raise FeedforwardError(
                    f"feedforward model {self.name}: {key} must be >= 0, got {value}"
                )

    @classmethod
    def from_parameter_set(cls, ps: ParameterSet) -> "FeedforwardModel":
        """The model of a dynamic parameter set (m and c of (11.1)); refused for a static one."""
        if ps.form != "dynamic" or ps.dynamics is None:
            raise FeedforwardError(
                f"parameter set {ps.name!r} is {ps.form}: the feedforward needs the "
                "dynamic form (11.1) with m and c (identify it with input displacement)"
            )
        return cls(ps.bouc_wen, ps.dynamics.m, ps.dynamics.c, ps.name)

    @classmethod
    def load(cls, path: str | Path) -> "FeedforwardModel":
        """:meth:`from_parameter_set` of the parameter set file at ``path``."""
        try:
            return cls.from_parameter_set(load_parameter_set(path))
        except ModelError as exc:
            raise FeedforwardError(str(exc)) from exc

    def static_force(self, x: ArrayLike, w: ArrayLike) -> NDArray[np.float64]:
        """Σ κ_i x^i + κw·w, x from the model's offset (the hysteretic restoring term of (11.1))."""
        return polynomial(self.bouc_wen.kappa, np.asarray(x)) + self.bouc_wen.kappa_w * np.asarray(
            w
        )

    def seed_w(self, x_measured: float, u_applied: float) -> float:
        """Hysteretic state w at rest under ``u_applied`` at displacement ``x_measured`` (11.1),
        within |w| < 1.
        """
        x = x_measured - self.bouc_wen.y0
        w = (
            u_applied - float(polynomial(self.bouc_wen.kappa, np.asarray(x)))
        ) / self.bouc_wen.kappa_w
        return float(np.clip(w, -W_SEED_LIMIT, W_SEED_LIMIT))


def feedforward(
    model: FeedforwardModel, xd: ArrayLike, vd: ArrayLike, ad: ArrayLike, w0: float = 0.0
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(u_ff, w) along the sampled path x_d with ẋ_d, ẍ_d; w(x_d[0]) = w0 (pure, vectorised)."""
    bw = model.bouc_wen
    x = np.asarray(xd, dtype=float) - bw.y0
    w = simulate_w(bw.input_sign * x, bw.rho, bw.sigma, bw.n, w0)
    return model.m * np.asarray(ad) + model.c * np.asarray(vd) + model.static_force(x, w), w


class Feedforward:
    """u_ff one period at a time (same values as :func:`feedforward`), w kept between calls."""

    def __init__(self, model: FeedforwardModel) -> None:
        self.model = model
        self._phi = StaticPlant(replace(model.bouc_wen, y0=0.0))
        self._seeded = False

    @property
    def seeded(self) -> bool:
        """Whether w has been seeded since the loop last opened (:meth:`seed`)."""
        return self._seeded

    @property
    def w(self) -> float:
        """Hysteretic state w after the last :meth:`step` or :meth:`seed`."""
        return self._phi.w

    def seed(self, x_measured: float, u_applied: float) -> None:
        """Re-seed w from the stage at rest (module docstring); call when the loop closes."""
        w = self.model.seed_w(x_measured, u_applied)
        self._phi.reset(w, x_measured - self.model.bouc_wen.y0)
        self._seeded = True

    def unseed(self) -> None:
        """Forget the state (the loop opened): the next closing seeds it again."""
        self._seeded = False

    def step(self, xd: float, vd: float, ad: float) -> float:
        """u_ff at the reference (x_d, ẋ_d, ẍ_d), w driven from the previous x_d to this one."""
        if not (math.isfinite(xd) and math.isfinite(vd) and math.isfinite(ad)):
            raise FeedforwardError(f"reference must be finite, got x_d={xd}, ẋ_d={vd}, ẍ_d={ad}")
        if not self._seeded:
            raise FeedforwardError("feedforward stepped before it was seeded")
        static = self._phi.step(xd - self.model.bouc_wen.y0)
        return float(self.model.m * ad + self.model.c * vd + static)
