"""Steps 3-4: the bounds of Assumption 2 from the sweep and the step response, and the gains
of Theorem 4 (11.6)-(11.7) with kA and f of (11.18), checked in the sampled loop (no rclpy).

Bounds (``margin`` = M, a fraction): every upper bound is the largest value of the sweep
(Table 11.1's "largest" column, as §11.4.1 took them) times (1 + M); m_min = (m - 3 s_m)(1 - M),
m_max = (m + 3 s_m)(1 + M), c_max = (c + 3 s_c)(1 + M), with s the step fit's standard errors.
The nominal plant (the sampled-loop check's) is the means and the fitted m, c.

Gains (``gain_margin`` = G): k1 given (default kappa_x/2, the thesis's 5e6 for its 10.35e6),
k2 = (1 + G) k2_min (11.6), k0 = (1 - G) k0_max (11.7) — strictly inside Theorem 4 —,
f = 100 Hz and kA = 1.5 k0 as in §11.4.3 (kA = 1.5e9 for k0 = 1e9). The loop rate is the
given one, or the lowest of the candidates at which the sampled loop of pid_tv is stable with
the graph's delay.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from piezo_stage.control.bounds import Bounds, NominalPlant
from piezo_stage.control.discrete import SampledLoopReport, check_sampled_loop
from piezo_stage.control.errors import ControlError
from piezo_stage.control.laws import (
    LAW_NAMES,
    PID_TV,
    Gains,
    LoopContext,
    law_named,
)
from piezo_stage.control.theorem4 import GainReport, k0_max, k2_min, validate_gains

from .errors import CommissioningError

RATE_CANDIDATES: tuple[float, ...] = (100e3, 200e3, 500e3, 1e6)
THESIS_F = 100.0  # §11.4.3: f = 100 Hz
THESIS_KA_RATIO = 1.5  # kA / k0 of the ch. 11 runs (1.5e9 / 1e9)
STD_FACTOR = 3.0  # m, c bounds: estimate ± 3 standard errors before the margin


class DesignError(CommissioningError):
    """No gains pass Theorem 4 and the sampled-loop check (the message says why)."""


def assumption2_bounds(
    table: dict[str, dict[str, float]],
    m: float,
    m_std: float,
    c: float,
    c_std: float,
    margin: float,
) -> Bounds:
    """Assumption 2 bounds (module docstring) from the sweep's table and the step fit."""
    if not (0.0 <= margin < 1.0):
        raise DesignError(f"margin must be in [0, 1), got {margin}")
    up = 1.0 + margin
    return Bounds.from_dict(
        {
            "m_min": max((m - STD_FACTOR * m_std) * (1.0 - margin), 1e-300),
            "m_max": (m + STD_FACTOR * m_std) * up,
            "c_max": max(c + STD_FACTOR * c_std, 0.0) * up,
            "kappa_x_max": table["kappa_x"]["max"] * up,
            "kappa_w_max": table["kappa_w"]["max"] * up,
            "sigma_max": max(table["sigma"]["max"] * up, 0.5),
            "rho_max": table["rho"]["max"] * up,
        }
    )


def nominal_plant(table: dict[str, dict[str, float]], m: float, c: float) -> NominalPlant:
    return NominalPlant(
        m=m,
        c=c,
        kappa_x=table["kappa_x"]["mean"],
        kappa_w=table["kappa_w"]["mean"],
        rho=table["rho"]["mean"],
    )


@dataclass(frozen=True)
class GainDesign:
    gains: Gains
    rate_hz: float
    delay_samples: int
    theorem4: GainReport
    sampled: SampledLoopReport
    tried: tuple[tuple[float, float], ...]  #: (rate, spectral radius) of each rate checked
    own: tuple[str, ...] = ()  #: the laws' own gains designed (:func:`own_gains`)
    not_designed: dict[str, str] = field(default_factory=dict)  #: law: why its rule found none

    def to_dict(self) -> dict[str, Any]:
        g = self.gains
        return {
            "gains": {
                "k0": g.k0,
                "k1": g.k1,
                "k2": g.k2,
                "kA": g.kA,
                "f": g.f,
                **{name: getattr(g, name) for name in self.own},
            },
            "not_designed": dict(self.not_designed),
            "rate_hz": self.rate_hz,
            "delay_samples": self.delay_samples,
            "k2_min": self.theorem4.k2_min,
            "k0_max": self.theorem4.k0_max,
            "theorem4_valid": self.theorem4.valid,
            "spectral_radius": self.sampled.spectral_radius,
            "stable": self.sampled.stable,
            "tried": [list(t) for t in self.tried],
        }


def design_gains(
    bounds: Bounds,
    nominal: NominalPlant,
    *,
    k1: float | None = None,
    gain_margin: float = 0.1,
    f: float = THESIS_F,
    ka_ratio: float = THESIS_KA_RATIO,
    rate_hz: float | None = None,
    delay_samples: int = 0,
    candidates: tuple[float, ...] = RATE_CANDIDATES,
) -> GainDesign:
    """Theorem 4 gains for ``bounds`` and the loop rate (module docstring); DesignError if none."""
    if not (0.0 < gain_margin < 1.0):
        raise DesignError(f"gain margin must be in (0, 1), got {gain_margin}")
    k1 = 0.5 * nominal.kappa_x if k1 is None else float(k1)
    k2 = (1.0 + gain_margin) * k2_min(bounds, k1)
    k0 = (1.0 - gain_margin) * k0_max(bounds, k1, k2)
    gains = Gains(k0=k0, k1=k1, k2=k2, kA=ka_ratio * k0, A=0.0, f=f)
    report = validate_gains(bounds, k1, k2, k0, gains.kA, f)
    if not report.valid:
        raise DesignError("Theorem 4: " + "; ".join(report.reasons))
    rates = (float(rate_hz),) if rate_hz is not None else candidates
    tried = []
    for rate in rates:
        if abs(rate / f - round(rate / f)) > 1e-9:
            tried.append((rate, math.nan))
            continue
        sampled = check_sampled_loop(nominal, gains, rate, delay_samples, PID_TV.name)
        tried.append((rate, float(sampled.spectral_radius)))
        if sampled.stable:
            loop = LoopContext(nominal, rate, delay_samples)
            own, why = own_gains(bounds, gains, gain_margin, loop)
            return GainDesign(
                replace(gains, **own),
                rate,
                delay_samples,
                report,
                sampled,
                tuple(tried),
                tuple(own),
                why,
            )
    text = ", ".join(f"{r:g} Hz: {s:.6f}" for r, s in tried)
    raise DesignError(
        f"the sampled loop of pid_tv with delay {delay_samples} is unstable at every rate "
        f"checked (spectral radius per sample: {text}); the loop must run faster"
    )


def own_gains(
    bounds: Bounds, gains: Gains, margin: float, loop: LoopContext
) -> tuple[dict[str, float], dict[str, str]]:
    """Every registered law's own gains by its design rule (:meth:`ControlLaw.design`) beside
    ``gains``, and the laws whose rule finds none, with why."""
    own: dict[str, float] = {}
    why: dict[str, str] = {}
    for name in LAW_NAMES:
        try:
            own.update(law_named(name).design(bounds, gains, margin, loop, set(own)))
        except ControlError as exc:
            why[name] = str(exc)
    return own, why


def write_bounds(
    path: Path, bounds: Bounds, nominal: NominalPlant, margin: float, source: str
) -> None:
    """The bounds file in the layout of config/thesis_rig_bounds.yaml (bounds + nominal)."""
    b, n = bounds, nominal
    lines = [
        f"# Assumption 2 bounds written by `piezo-stage commission` ({source}).",
        "# Read by `piezo-stage gains --bounds FILE` and the controller's bounds_file parameter.",
        "# Units SI: m [V s^2/m], c [V s/m], kappa_x [V/m], kappa_w [V], rho [1/m].",
        "",
        f"bounds:                  # Assumption 2: sweep's largest values x {1 + margin:g}; "
        f"m, c: fit ± 3 s.e., margin {margin:g}",
    ]
    lines += [f"  {k}: {v:.10g}" for k, v in b.to_dict().items()]
    lines += [
        "",
        "nominal:                 # plant linearised by the sampled-loop check: fitted m, c "
        "and the sweep's means",
    ]
    lines += [f"  {k}: {v:.10g}" for k, v in n.to_dict().items()]
    path.write_text("\n".join(lines) + "\n")


def write_controller_params(
    path: Path, design: GainDesign, bounds_file: Path, trigger: str
) -> None:
    """A ROS 2 params file for the controller node (``--params-file``, a graph's ``parameters``)."""
    g = design.gains
    params = {
        "mode": PID_TV.name,
        "k0": g.k0,
        "k1": g.k1,
        "k2": g.k2,
        "kA": g.kA,
        "f": g.f,
        **{name: getattr(g, name) for name in design.own},
        "rate_hz": design.rate_hz,
        "delay_samples": design.delay_samples,
        "trigger": trigger,
        "bounds_file": str(bounds_file),
    }
    body = "\n".join(f"    {k}: {_yaml(v)}" for k, v in params.items())
    path.write_text(
        "# controller parameters written by `piezo-stage commission` (Theorem 4 + sampled check)\n"
        f"/**:\n  ros__parameters:\n{body}\n"
    )


def _yaml(value: object) -> str:
    if isinstance(value, float):
        text = f"{value:.10g}"
        return text if any(ch in text for ch in ".en") else text + ".0"
    if isinstance(value, int):
        return str(value)
    return f'"{value}"'


def read_controller_params(path: Path) -> dict[str, Any]:
    """The ``ros__parameters`` of a file written by :func:`write_controller_params`."""
    import yaml

    data = yaml.safe_load(Path(path).read_text())
    return dict(data["/**"]["ros__parameters"])
