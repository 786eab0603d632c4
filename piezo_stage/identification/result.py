"""The identification result: refined and analytic parameters, fit quality, diagnostics."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezo_stage.model.bouc_wen import BoucWenParameters
from piezo_stage.model.parameter_set import Drift, Dynamics, ParameterSet

from .cycles import SteadyCycle


def parameters_dict(params: BoucWenParameters, rms_error: float, samples: int) -> dict[str, Any]:
    """The BoucWenParameters message fields (DESIGN §3) as plain JSON values."""
    return {
        "kappa": [float(k) for k in params.kappa],
        "y0": float(params.y0),
        "kappa_w": float(params.kappa_w),
        "rho": float(params.rho),
        "sigma": float(params.sigma),
        "n": float(params.n),
        "input_sign": int(params.input_sign),
        "rms_error": float(rms_error),
        "samples": int(samples),
    }


def _finite(value: object) -> object:
    """NaN/inf -> None, recursively (strict JSON has no NaN)."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


@dataclass(frozen=True)
class IdentificationResult:
    """What `identify` returns.

    ``parameters`` are the final values (refined, or the analytic ones when refinement is
    off); ``analytic`` the Table 10.2 estimate, or None when it fell outside class I (the
    refinement then started from its projection, see ``diagnostics['analytic_raw']``).
    ``w0`` is w(0) of (10.18) at the first sample of run A (fitted, with ``method`` "fit").
    ``delay`` and ``drift`` (run A's) are what the fit by simulation error estimated;
    ``warnings`` name what the record does not determine well.
    """

    parameters: BoucWenParameters
    analytic: BoucWenParameters | None
    rms_error: float
    analytic_rms_error: float
    samples: int
    w0: float
    refined: bool
    input_name: str = "voltage"
    output_name: str = "displacement"
    diagnostics: dict[str, Any] = field(default_factory=dict, compare=False)
    cycles: tuple[SteadyCycle, ...] = field(default=(), compare=False, repr=False)
    method: str = "analytic"  #: "analytic" (ch. 9-10 + refinement) or "fit"
    delay: float = 0.0  #: output lag behind the input [s]
    drift: Drift | None = None
    warnings: tuple[str, ...] = ()
    #: the model's output over each run as fitted (method "fit"; empty for the analytic one)
    fitted: tuple[NDArray[np.float64], ...] = field(default=(), compare=False, repr=False)

    def to_dict(self) -> dict[str, Any]:
        """JSON object of ``piezo-stage identify --json``: the message fields of the final
        parameters, ``w0``, ``refined`` and ``analytic`` (same keys, before refinement).
        """
        out = parameters_dict(self.parameters, self.rms_error, self.samples)
        out["w0"] = float(self.w0)
        out["refined"] = bool(self.refined)
        out["input_name"] = self.input_name
        out["output_name"] = self.output_name
        out["method"] = self.method
        out["delay"] = float(self.delay)
        out["drift"] = (
            None
            if self.drift is None
            else {
                "kind": self.drift.kind.value,
                "coefficient": self.drift.coefficient,
                "time_constant": self.drift.time_constant,
            }
        )
        out["std"] = {k: float(v) for k, v in self.diagnostics.get("std", {}).items()}
        out["warnings"] = list(self.warnings)
        if "holdout_rms" in self.diagnostics:
            out["holdout"] = {
                k: self.diagnostics[k]
                for k in ("holdout_fraction", "holdout_rms", "holdout_rms_percent")
            }
        if self.analytic is not None:
            out["analytic"] = parameters_dict(self.analytic, self.analytic_rms_error, self.samples)
            out["analytic"]["class_i"] = True
        else:  # outside class I: the raw Table 10.2 values, flagged
            raw = self.diagnostics.get("analytic_raw", {})
            out["analytic"] = {
                **raw,
                "rms_error": None,
                "samples": int(self.samples),
                "class_i": False,
            }
        return {key: _finite(value) for key, value in out.items()}

    def to_dynamic_parameter_set(
        self, m: float, c: float, name: str = "identified"
    ) -> ParameterSet:
        """The ch. 11 form's result (input the displacement, output the voltage: u = Φ(x) + y0)
        as the dynamic model (11.1) m ẍ + c ẋ + Φ(x) = u with the given m, c, whose output
        x + y0 carries the offset as a displacement: y0 = −y0_u / κx.
        """
        if self.input_name != "displacement":
            raise ValueError(
                "a dynamic model needs the ch. 11 form (input the displacement, output the "
                f"voltage); this result's input is the {self.input_name}"
            )
        p = self.parameters
        notes = self.to_parameter_set(name).notes + f"; m = {m:.6g}, c = {c:.6g} given"
        return ParameterSet(
            name=name,
            form="dynamic",
            bouc_wen=replace(p, y0=-p.y0 / p.kappa_x),
            dynamics=Dynamics(m=float(m), c=float(c)),
            w0=float(min(1.0, max(-1.0, self.w0))),
            notes=notes,
        )

    def to_parameter_set(self, name: str = "identified", notes: str = "") -> ParameterSet:
        """The model's ParameterSet (static form, ch. 10) for `save_parameter_set`."""
        if not notes:
            q = self.diagnostics.get("q")
            notes = (
                f"identified from {self.samples} samples ({self.method} method), "
                f"rms_error {self.rms_error:.4g}"
                + (f", q = {q:.6g}" if q is not None else "")
                + ("" if self.refined else ", analytic estimate (no refinement)")
            )
        return ParameterSet(
            name=name,
            form="static",
            bouc_wen=self.parameters,
            dynamics=None,
            input_name=self.input_name,
            output_name=self.output_name,
            w0=float(min(1.0, max(-1.0, self.w0))),
            notes=notes,
            delay=float(self.delay),
            drift=self.drift,
        )
