"""The three control laws of thesis ch. 11 as pure, vectorised functions.

- ``pid``      (11.5):  u = −k0·x0 − k1·x1 − k2·x2
- ``pid_sine`` (11.17): u = −k0·x0 − k1·x1 − k2·x2 − A·sin(2πft)
- ``pid_tv``   (11.18): u = −k0·x0 − k1·x1 − k2·x2 − kA·x0·sin(2πft)

with x1 = x − yr, x2 = ẋ − ẏr and x0 = ∫ x1 dt (11.4). Units: x0 [m s], x1 [m], x2 [m/s], u [V].
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .errors import GainError


class Law(StrEnum):
    """The control law: (11.5), (11.17) or (11.18)."""

    PID = "pid"
    PID_SINE = "pid_sine"
    PID_TV = "pid_tv"


#: name → member, for the per-sample check (a dict lookup; an Enum call costs ten times more)
_LAW_BY_NAME: dict[str, Law] = {law.value: law for law in Law}


def check_law(mode: str) -> Law:
    """The :class:`Law` named ``mode``, else :class:`GainError` listing the names."""
    law = _LAW_BY_NAME.get(mode) if isinstance(mode, str) else None
    if law is None:
        names = ", ".join(Law)
        raise GainError(f"unknown control law {mode!r}; expected one of {names}")
    return law


@dataclass(frozen=True)
class Gains:
    """Gains of (11.5), (11.17), (11.18): k0 [V/(m s)], k1 [V/m], k2 [V s/m], kA [V/(m s)], A [V],
    f [Hz].

    Thesis values (§11.4.1, §11.5.3): k1 = 5e6, k2 = 580, k0 = 1e9, kA = 1.5e9, f = 100 Hz;
    §11.5.2 uses A = 15 V with f = 10 Hz.
    """

    k0: float
    k1: float
    k2: float
    kA: float = 0.0
    A: float = 0.0
    f: float = 100.0

    def validate(self, mode: str = "pid") -> None:
        """Raise :class:`GainError` for non-finite or negative gains, or f <= 0 for the sine
        laws.
        """
        check_law(mode)
        for key, value in asdict(self).items():
            if not isinstance(value, (int, float)) or not math.isfinite(value):
                raise GainError(f"gain {key} must be a finite number, got {value!r}")
        for key in ("k0", "k1", "k2", "kA", "A"):
            if getattr(self, key) < 0:
                raise GainError(f"gain {key} must be >= 0, got {getattr(self, key)}")
        if mode != "pid" and self.f <= 0:
            raise GainError(f"law {mode!r} needs a frequency f > 0 Hz, got {self.f}")

    def to_dict(self) -> dict[str, float]:
        """The gains as a mapping."""
        return asdict(self)


#: §11.4.1 / §11.5.3 design.
THESIS_GAINS = Gains(k0=1e9, k1=5e6, k2=580.0, kA=1.5e9, A=15.0, f=100.0)


def _num(value: ArrayLike) -> NDArray[np.float64] | float:
    """``value`` as is when a float or an array (a controller's per-sample scalars stay Python
    floats: numpy costs microseconds per scalar operation), else as an array.
    """
    return value if isinstance(value, (float, np.ndarray)) else np.asarray(value)


def pid_term(
    gains: Gains, x0: ArrayLike, x1: ArrayLike, x2: ArrayLike
) -> NDArray[np.float64] | float:
    """u_pid = −k0·x0 − k1·x1 − k2·x2, the PID of (11.5)."""
    return -gains.k0 * _num(x0) - gains.k1 * _num(x1) - gains.k2 * _num(x2)


def excitation_term(
    mode: str, gains: Gains, t: ArrayLike, x0: ArrayLike
) -> NDArray[np.float64] | float:
    """The added term: 0 (11.5), −A·sin(2πft) (11.17) or −kA·x0·sin(2πft) (11.18)."""
    check_law(mode)
    t, x0 = _num(t), _num(x0)
    scalar = isinstance(t, float) and isinstance(x0, float)
    if mode == "pid":
        return 0.0 if scalar else np.zeros(np.broadcast(t, x0).shape)[()]
    s = (
        math.sin(2.0 * math.pi * gains.f * t)
        if isinstance(t, float)
        else np.sin(2.0 * np.pi * gains.f * t)
    )
    if mode == "pid_sine":
        return -gains.A * s
    return -gains.kA * x0 * s


def x0_coefficient(mode: str, gains: Gains, t: float) -> float:
    """∂u/∂x0 at time t: −k0 for (11.5)/(11.17), −(k0 + kA·sin(2πft)) for (11.18)."""
    check_law(mode)
    if mode == "pid_tv":
        return -(gains.k0 + gains.kA * math.sin(2.0 * math.pi * gains.f * t))
    return -gains.k0


def control_law(
    mode: str, gains: Gains, t: ArrayLike, x0: ArrayLike, x1: ArrayLike, x2: ArrayLike
) -> NDArray[np.float64] | float:
    """Command u [V] of law ``mode`` (11.5, 11.17 or 11.18); t is the time since the loop was
    closed [s].
    """
    return pid_term(gains, x0, x1, x2) + excitation_term(mode, gains, t, x0)
