"""The analytic estimate of the hysteretic part: Steps 4-10 of 9.1.3 with Table 10.1/10.2.

θ(x) = y − Σ κ_i v^i − y0 = κw·w̄(x) on the loading branch (9.21, 10.14). On w̄ ≥ 0 it obeys
dθ/dx = a − b·θ^n (9.22) with a = ρκw, b = ρκw^(1−n); on w̄ ≤ 0 (9.19) gives σ.
Values and slopes of θ at the design points come from local polynomial fits (derivatives.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TypedDict

import numpy as np
from numpy.typing import NDArray

from .cycles import Branch
from .derivatives import LocalFit, adaptive_fit, local_root
from .errors import AnalyticEstimateError, DesignPointError
from .polynomial import polyval


@dataclass(frozen=True)
class DesignPoints:
    """Table 10.1. By default the points are placed as fractions of the loading branch:
    x*1 = x* + f1·(Xmax − x*) ("linear region"), x*2 = x* + f2·(Xmax − x*) ("close to the
    largest value"), x*3 = Xmin + f3·(x* − Xmin) ("close to the smallest value"). Absolute
    values (in the model input x = input_sign·v) override the fractions.
    """

    f1: float = 0.6
    f2: float = 0.95
    f3: float = 0.05
    x1: float | None = None
    x2: float | None = None
    x3: float | None = None

    def __post_init__(self) -> None:
        for name in ("f1", "f2", "f3"):
            f = getattr(self, name)
            if not 0.0 < f < 1.0:
                raise DesignPointError(f"design fraction {name} = {f} must lie in (0, 1)")
        if self.f1 >= self.f2:
            raise DesignPointError(f"need f1 < f2 so that x*1 < x*2 (got {self.f1}, {self.f2})")

    def place(self, x_star: float, x_min: float, x_max: float) -> tuple[float, float, float]:
        """(x*1, x*2, x*3), checked against x*3 < x* < x*1 < x*2 and the data range."""
        x1 = self.x1 if self.x1 is not None else x_star + self.f1 * (x_max - x_star)
        x2 = self.x2 if self.x2 is not None else x_star + self.f2 * (x_max - x_star)
        x3 = self.x3 if self.x3 is not None else x_min + self.f3 * (x_star - x_min)
        for name, value in (("x*1", x1), ("x*2", x2), ("x*3", x3)):
            if not x_min < value < x_max:
                raise DesignPointError(
                    f"{name} = {value:.6g} lies outside the loading branch "
                    f"[{x_min:.6g}, {x_max:.6g}]"
                )
        if not x3 < x_star < x1 < x2:
            raise DesignPointError(
                f"Table 10.1 needs x*3 < x* < x*1 < x*2, got x*3={x3:.6g}, x*={x_star:.6g}, "
                f"x*1={x1:.6g}, x*2={x2:.6g}"
            )
        return x1, x2, x3


@dataclass(frozen=True)
class DerivativeOptions:
    """Local polynomial fits for the values and slopes of θ at the design points (Table 10.2)."""

    degree: int = 3  #: local polynomial degree
    rel_tol: float = 2e-4  #: target slope std relative to the mean slope of θ
    min_samples: int = 8
    max_fraction: float = 0.3  #: widest window, fraction of the branch samples
    slope_corrections: int = 3  #: re-estimates of a on the linearised θ (0: plain Table 10.2)


@dataclass(frozen=True)
class HystereticEstimate:
    """Results of Steps 5-10 (raw: not yet checked against class I)."""

    kappa_w: float
    rho: float
    sigma: float
    n: float
    a: float
    b: float
    x_star: float
    x1: float
    x2: float
    x3: float
    a_uncorrected: float = float("nan")  #: a from the plain local fit at x*
    fits: dict[str, LocalFit] = field(default_factory=dict, compare=False)


def theta(branch: Branch, kappa: NDArray[np.float64], y0: float) -> NDArray[np.float64]:
    """θ = y − Σ κ_i v^i − y0 = κw·w̄ on a branch (9.21, 9.38, 10.14)."""
    return branch.y - polyval(kappa, branch.v) - y0


def find_x_star(x: NDArray[np.float64], th: NDArray[np.float64], noise: float = 0.0) -> float:
    """Rough zero of θ (Step 5): the sign change of the sampled θ, linearly interpolated
    (9.38-9.39); noisy θ is first smoothed (Savitzky-Golay over 5 % of the branch) and the
    middle of the remaining sign changes taken.
    """
    if noise > 0.0 and len(th) >= 20:
        from scipy.signal import savgol_filter  # lazy: scipy.signal costs seconds to import

        th = savgol_filter(th, max(5, (len(th) // 20) | 1), 2)
    r = np.flatnonzero((th[:-1] <= 0.0) & (th[1:] > 0.0))
    if len(r) == 0:
        side = "positive" if th.min() > 0 else "negative"
        raise DesignPointError(
            f"θ has no zero on the loading branch (θ is {side} everywhere): x* lies outside the "
            "data; the excitation does not cover both signs of w̄ or the polynomial part is wrong"
        )
    xs = x[r] - th[r] * (x[r + 1] - x[r]) / (th[r + 1] - th[r])
    if np.ptp(xs) > 0.05 * (x[-1] - x[0]):
        raise AnalyticEstimateError(
            f"θ changes sign {len(r)} times over {100 * np.ptp(xs) / (x[-1] - x[0]):.0f} % of the "
            "branch: it is not increasing as a Bouc-Wen loading branch must be"
        )
    return float(np.median(xs))


class _FitKeywords(TypedDict):
    """The keyword arguments every local fit of :func:`hysteretic_estimate` shares."""

    noise: float
    slope_scale: float
    rel_tol: float
    degree: int


def hysteretic_estimate(
    branch: Branch,
    kappa: NDArray[np.float64],
    y0: float,
    noise: float,
    design: DesignPoints = DesignPoints(),
    derivative: DerivativeOptions = DerivativeOptions(),
) -> HystereticEstimate:
    """Steps 4-10 (9.38-9.45, Table 10.2) on the loading branch."""
    x = branch.x
    th = theta(branch, kappa, y0)
    slope_scale = float(np.ptp(th) / branch.span)
    kw: _FitKeywords = {
        "noise": noise,
        "slope_scale": slope_scale,
        "rel_tol": derivative.rel_tol,
        "degree": derivative.degree,
    }
    # Step 5: x* with θ(x*) = 0; Step 6: a = dθ/dx at x* (9.23, 9.39)
    fit0 = local_root(x, th, find_x_star(x, th, noise), **kw)
    x_star, a = fit0.x0, fit0.slope
    if not x[0] < x_star < x[-1]:
        raise DesignPointError(f"x* = {x_star:.6g} lies outside the data [{x[0]:.6g}, {x[-1]:.6g}]")
    if not a > 0:
        raise AnalyticEstimateError(f"dθ/dx at x* is {a:.3g}; it must be positive (a = ρκw > 0)")
    x1, x2, x3 = design.place(x_star, float(x[0]), float(x[-1]))

    def fit(x0: float) -> LocalFit:
        return adaptive_fit(
            x,
            th,
            x0,
            min_samples=derivative.min_samples,
            max_fraction=derivative.max_fraction,
            **kw,
        )

    f1, f2, f3 = fit(x1), fit(x2), fit(x3)
    n, b, kappa_w, rho, sigma = table_10_2(a, f1, f2, f3)
    a_first = a
    for _ in range(derivative.slope_corrections):
        # θ is only C^n at x*: a local polynomial's slope there is biased by |x − x*|^n terms.
        # Removing the known curvature of (9.22)/(9.19) leaves a line of slope a.
        lin = theta_linearised(x, th, x_star, b, (2.0 * sigma - 1.0) * b, n)
        a = adaptive_fit(
            x,
            lin,
            x_star,
            min_samples=derivative.min_samples,
            max_fraction=derivative.max_fraction,
            **kw,
        ).slope
        n, b, kappa_w, rho, sigma = table_10_2(a, f1, f2, f3)
    return HystereticEstimate(
        kappa_w=kappa_w,
        rho=rho,
        sigma=sigma,
        n=n,
        a=float(a),
        b=b,
        x_star=x_star,
        x1=x1,
        x2=x2,
        x3=x3,
        a_uncorrected=float(a_first),
        fits={"x*": fit0, "x*1": f1, "x*2": f2, "x*3": f3},
    )


def table_10_2(
    a: float, f1: LocalFit, f2: LocalFit, f3: LocalFit
) -> tuple[float, float, float, float, float]:
    """n, b, κw, ρ, σ from a and the fits at x*1, x*2, x*3 (Steps 7-10, Table 10.2)."""
    # Step 7: n and b (9.24-9.25, 9.40-9.41)
    d1, d2 = f1.slope - a, f2.slope - a
    if not (d1 < 0 and d2 < 0):
        raise AnalyticEstimateError(
            f"dθ/dx − a at x*1, x*2 is {d1:.3g}, {d2:.3g}; both must be negative "
            "(θ' = a − bθ^n decreases above x*): move x*1 away from x* or filter the data"
        )
    if not (f2.value > f1.value > 0):
        raise AnalyticEstimateError(
            f"θ(x*1) = {f1.value:.3g}, θ(x*2) = {f2.value:.3g}: need θ(x*2) > θ(x*1) > 0"
        )
    n = float(np.log(d2 / d1) / np.log(f2.value / f1.value))
    b = float(-d2 / f2.value**n)
    # Step 8: κw and ρ (9.26-9.27, 9.42-9.43)
    kappa_w = float((a / b) ** (1.0 / n))
    rho = float(a / kappa_w)
    # Steps 9-10: w̄ = θ/κw (9.28) and σ (9.45, Table 10.2; 9.29 is garbled, DESIGN §7)
    w3, dw3 = f3.value / kappa_w, f3.slope / kappa_w
    if not w3 < 0:
        raise AnalyticEstimateError(f"w̄(x*3) = {w3:.3g}; x*3 must lie where w̄ < 0")
    sigma = float(0.5 * ((dw3 / rho - 1.0) / (-w3) ** n + 1.0))
    values = dict(kappa_w=kappa_w, rho=rho, sigma=sigma, n=n, b=b)
    bad = [k for k, v in values.items() if not np.isfinite(v)]
    if bad:
        raise AnalyticEstimateError(f"Table 10.2 gives non-finite {', '.join(bad)}")
    return n, b, kappa_w, rho, sigma


def theta_linearised(
    x: NDArray[np.float64], th: NDArray[np.float64], x_star: float, b: float, c: float, n: float
) -> NDArray[np.float64]:
    """θ(x) − ∫_{x*}^{x} g(θ) dx with g = −bθ^n for θ ≥ 0 (9.22) and c(−θ)^n for θ < 0
    (9.19, c = (2σ−1)b): a straight line of slope a when b, c, n are right.
    """
    g = np.where(th >= 0.0, -b * np.abs(th) ** n, c * np.abs(th) ** n)
    integral = np.concatenate(([0.0], np.cumsum(0.5 * (g[1:] + g[:-1]) * np.diff(x))))
    return th - (integral - np.interp(x_star, x, integral))


def initial_w(
    kappa: NDArray[np.float64] | tuple[float, ...],
    kappa_w: float,
    y0: float,
    v0: float,
    y_at_0: float,
) -> float:
    """w(0) of (10.18): (y(0) − Σ κ_i v(0)^i − y0) / κw."""
    return float((y_at_0 - polyval(np.asarray(kappa), np.asarray(v0)) - y0) / kappa_w)
