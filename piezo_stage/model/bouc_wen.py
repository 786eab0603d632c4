"""The (modified) normalized Bouc-Wen model: parameters, standard -> normalized form, simulation.

Normalized model (8.8)-(8.9):   Phi = kappa_x x + kappa_w w,
    dw/dt = rho (dx/dt - sigma |dx/dt| |w|^(n-1) w + (sigma - 1) dx/dt |w|^n).
Modified model (10.4), with the displacement offset of (10.15):
    y = sum_{i=1..N} kappa_i v^i + kappa_w w + y0,   w driven by input_sign * v.

The model is rate independent: w depends only on the path of its input, so :func:`simulate_w`
takes the sampled input path (no time axis) and is exact on every monotone piece between
samples (see :mod:`piezo_stage.model._branches`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from . import _branches
from .errors import (
    InitialStateError,
    InputSignalError,
    ModelError,
    NotClassIError,
    ParameterValueError,
)

__all__ = [
    "ModelError",
    "NotClassIError",
    "ParameterValueError",
    "InitialStateError",
    "InputSignalError",
    "BoucWenParameters",
    "from_standard",
    "check_class_i",
    "check_w0",
    "simulate_w",
    "model_output",
    "polynomial",
]


def check_class_i(rho: float, sigma: float, n: float) -> None:
    """Raise :class:`NotClassIError` unless rho > 0, sigma >= 1/2, n >= 1 (Table 8.2, (8.10))."""
    for name, value in (("rho", rho), ("sigma", sigma), ("n", n)):
        if not math.isfinite(value):
            raise NotClassIError(f"{name} must be finite, got {value!r}")
    if rho <= 0.0:
        raise NotClassIError(f"rho must be > 0 (8.10), got {rho!r}")
    if sigma < 0.5:
        raise NotClassIError(f"sigma must be >= 1/2 for a class I model (Table 8.2), got {sigma!r}")
    if n < 1.0:
        raise NotClassIError(f"n must be >= 1 (8.2), got {n!r}")


def check_w0(w0: float) -> float:
    """Return w0 as float, or raise :class:`InitialStateError` unless |w0| <= 1 (Table 8.2)."""
    w0 = float(w0)
    if not (math.isfinite(w0) and abs(w0) <= 1.0):
        raise InitialStateError(f"initial state w0 must satisfy |w0| <= 1, got {w0!r}")
    return w0


@dataclass(frozen=True)
class BoucWenParameters:
    """Modified normalized Bouc-Wen parameters, (8.8)-(8.9), (10.4), (10.15).

    ``kappa`` holds kappa_1..kappa_N of (10.4) (kappa_1 is kappa_x of (8.8)); the output is
    ``sum_i kappa_i v^i + kappa_w w + y0`` with w driven by ``input_sign * v`` (ch. 10 uses -v
    so that the loop is clockwise). Construction only checks the structure; call
    :meth:`validate` for the class-I conditions.
    """

    kappa: tuple[float, ...]
    kappa_w: float
    rho: float
    sigma: float
    n: float
    y0: float = 0.0
    input_sign: int = 1

    def __post_init__(self) -> None:
        try:
            kappa = tuple(float(k) for k in np.atleast_1d(np.asarray(self.kappa, dtype=float)))
        except (TypeError, ValueError) as exc:
            raise ParameterValueError(
                f"kappa must be a sequence of numbers, got {self.kappa!r}"
            ) from exc
        if not kappa:
            raise ParameterValueError("kappa must hold at least kappa_1 (kappa_x)")
        object.__setattr__(self, "kappa", kappa)
        for name in ("kappa_w", "rho", "sigma", "n", "y0"):
            try:
                object.__setattr__(self, name, float(getattr(self, name)))
            except (TypeError, ValueError) as exc:
                raise ParameterValueError(
                    f"{name} must be a number, got {getattr(self, name)!r}"
                ) from exc
        if self.input_sign not in (1, -1):
            raise ParameterValueError(f"input_sign must be +1 or -1, got {self.input_sign!r}")
        object.__setattr__(self, "input_sign", int(self.input_sign))

    @property
    def kappa_x(self) -> float:
        """kappa_x of (8.8), i.e. kappa_1 of (10.4)."""
        return self.kappa[0]

    @property
    def N(self) -> int:
        """Degree N of the polynomial term of (10.4)."""
        return len(self.kappa)

    def validate(self) -> None:
        """Raise :class:`NotClassIError` naming the first violated class-I condition.

        Class I (Table 8.2 with (8.10)): rho > 0, sigma >= 1/2, n >= 1, kappa_w > 0; all
        coefficients finite.
        """
        check_class_i(self.rho, self.sigma, self.n)
        if not math.isfinite(self.kappa_w) or self.kappa_w <= 0.0:
            raise NotClassIError(f"kappa_w must be > 0 (8.10), got {self.kappa_w!r}")
        for i, k in enumerate(self.kappa, start=1):
            if not math.isfinite(k):
                raise NotClassIError(f"kappa_{i} must be finite, got {k!r}")
        if not math.isfinite(self.y0):
            raise NotClassIError(f"y0 must be finite, got {self.y0!r}")


def from_standard(
    a: float,
    k: float,
    alpha: float,
    beta: float,
    gamma: float,
    n: float,
    D: float | None = None,
) -> BoucWenParameters:
    """Normalized parameters (8.10) of the standard Bouc-Wen model (8.1)-(8.2).

    ``a`` is A of (8.2); ``D`` defaults to 1. With z0 = (A / (beta + gamma))^(1/n) (8.6):
    rho = A / (D z0), sigma = beta / (beta + gamma), kappa_x = alpha k,
    kappa_w = (1 - alpha) D k z0, and w = z / z0. Requires the class I case of Table 8.1
    (A > 0, beta + gamma > 0, beta - gamma >= 0), D > 0, k > 0, 0 < alpha < 1, n >= 1.
    """
    D = 1.0 if D is None else float(D)
    if not (a > 0.0 and beta + gamma > 0.0 and beta - gamma >= 0.0):
        raise NotClassIError(
            f"standard parameters are not class I (Table 8.1 needs A > 0, beta + gamma > 0, "
            f"beta - gamma >= 0): A={a!r}, beta={beta!r}, gamma={gamma!r}"
        )
    if not (D > 0.0 and k > 0.0 and 0.0 < alpha < 1.0 and n >= 1.0):
        raise NotClassIError(
            f"(8.1)-(8.2) need D > 0, k > 0, 0 < alpha < 1, n >= 1: D={D!r}, k={k!r}, "
            f"alpha={alpha!r}, n={n!r}"
        )
    z0 = (a / (beta + gamma)) ** (1.0 / n)
    return BoucWenParameters(
        kappa=(alpha * k,),
        kappa_w=(1.0 - alpha) * D * k * z0,
        rho=a / (D * z0),
        sigma=beta / (beta + gamma),
        n=float(n),
    )


def _as_path(x: NDArray[np.float64], name: str = "x") -> NDArray[np.float64]:
    path = np.ascontiguousarray(x, dtype=float)
    if path.ndim != 1:
        raise InputSignalError(f"{name} must be a 1-D array of samples, got shape {path.shape}")
    if path.size and not np.all(np.isfinite(path)):
        raise InputSignalError(f"{name} holds NaN or infinite samples")
    return path


def simulate_w(
    x: NDArray[np.float64], rho: float, sigma: float, n: float, w0: float = 0.0
) -> NDArray[np.float64]:
    """Hysteretic state w at every sample of the input path ``x`` for (9.2) with w(x[0]) = w0.

    Rate independent: only the sequence of values matters. The path is taken linear between
    samples (reversals happen at samples), and every monotone piece is solved exactly:
    phi+/-(w) - rho x is constant on it ((9.3)-(9.4)); the result is within ~1e-15 of the
    exact solution and satisfies |w| <= 1 whenever |w0| <= 1.
    """
    check_class_i(rho, sigma, n)
    w0 = check_w0(w0)
    path = _as_path(x)
    out = np.empty_like(path)
    if path.size:
        _branches.walk(_branches.tables(float(sigma), float(n)), float(rho), path, w0, out)
    return out


def polynomial(kappa: tuple[float, ...], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """sum_{i=1..N} kappa_i v^i, the non-hysteretic term of (10.4) (Horner)."""
    v = np.asarray(v, dtype=float)
    total = np.zeros_like(v)
    for k in reversed(kappa):
        total = (total + k) * v
    return total


def model_output(
    params: BoucWenParameters, v: NDArray[np.float64], w0: float = 0.0
) -> NDArray[np.float64]:
    """Output y = sum_i kappa_i v^i + kappa_w w + y0 (10.15), w from (9.2) driven by
    input_sign * v.
    """
    params.validate()
    v = _as_path(v, "v")
    w = simulate_w(params.input_sign * v, params.rho, params.sigma, params.n, w0)
    return polynomial(params.kappa, v) + params.kappa_w * w + params.y0
