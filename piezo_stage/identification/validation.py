"""Model validation on another recording (§10.3.3): simulate, compare, plot.

The identified static model (10.15) is run on the recorded input of a validation experiment
(sine, random, ...) from w(0) of (10.18), and its output compared with the measured one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from piezo_stage.model.bouc_wen import BoucWenParameters, model_output
from piezo_stage.model.parameter_set import Drift

from .analytic import initial_w
from .recording import Recording, check_recording


@dataclass(frozen=True)
class ValidationResult:
    """Outcome of :func:`validate_model`: the simulated output against the recorded one."""

    recording: Recording
    model: NDArray[np.float64]  #: simulated output at the recording's samples
    w0: float  #: initial state used, (10.18) clipped to [-1, 1]
    w0_clipped: bool

    @property
    def error(self) -> NDArray[np.float64]:
        """Model minus recorded output at each sample."""
        return self.model - self.recording.output

    @property
    def rms(self) -> float:
        """RMS of :attr:`error`."""
        return float(np.sqrt(np.mean(self.error**2)))

    @property
    def max_abs(self) -> float:
        """Largest |error|."""
        return float(np.max(np.abs(self.error)))

    @property
    def span(self) -> float:
        """Peak-to-peak range of the recorded output."""
        return float(np.ptp(self.recording.output))

    def summary(self) -> dict[str, float]:
        """The figures, w0 and the sample count as a mapping (errors also in % of the span)."""
        return {
            "rms": self.rms,
            "max": self.max_abs,
            "span": self.span,
            "rms_percent": 100 * self.rms / self.span,
            "max_percent": 100 * self.max_abs / self.span,
            "w0": self.w0,
            "samples": len(self.recording),
        }


def validate_model(
    params: BoucWenParameters,
    rec: Recording,
    w0: float | None = None,
    delay: float = 0.0,
    drift: Drift | None = None,
) -> ValidationResult:
    """Simulate (10.15) on ``rec.input`` delayed by ``delay`` [s] (held before the start),
    plus ``drift`` from the record's start; w(0) from (10.18) unless given.
    """
    check_recording(rec)
    v = rec.input if delay == 0.0 else np.interp(rec.t - delay, rec.t, rec.input)
    offset = np.zeros(len(rec)) if drift is None else drift.evaluate(rec.t - rec.t[0])
    if w0 is None:
        w0 = initial_w(
            params.kappa, params.kappa_w, params.y0, float(v[0]), float(rec.output[0] - offset[0])
        )
    clipped = not -1.0 <= w0 <= 1.0
    w0 = float(np.clip(w0, -1.0, 1.0))
    return ValidationResult(
        recording=rec, model=model_output(params, v, w0=w0) + offset, w0=w0, w0_clipped=clipped
    )


def _axis(unit: str) -> tuple[float, str]:
    """Display scale: m -> µm, V -> V, else as recorded."""
    return {"m": (1e6, "µm"), "V": (1.0, "V")}.get(unit, (1.0, unit))


def plot_validation(result: ValidationResult, out_dir: str | Path, stem: str) -> list[Path]:
    """Two PNGs: model vs data over time (with the error), and the loops (input vs output)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rec = result.recording
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    ys, yu = _axis(rec.output_unit)
    vs, vu = _axis(rec.input_unit)
    ylab = f"output [{yu}]" if yu else "output"
    vlab = f"input [{vu}]" if vu else "input"
    paths = []

    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(9, 6))
    ax1.plot(rec.t, rec.output * ys, label="measured", lw=1.0)
    ax1.plot(rec.t, result.model * ys, label="model", lw=1.0, ls="--")
    ax1.set_ylabel(ylab)
    ax1.legend(loc="best")
    ax1.set_title(
        f"{rec.label}: RMS {100 * result.rms / result.span:.3g} %, max "
        f"{100 * result.max_abs / result.span:.3g} % of span"
    )
    ax2.plot(rec.t, result.error * ys, lw=0.8, color="C3")
    ax2.set_ylabel(f"model − measured [{yu}]" if yu else "model − measured")
    ax2.set_xlabel("time [s]")
    fig.tight_layout()
    paths.append(out_dir / f"{stem}_timeseries.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(6, 5))
    ax.plot(rec.input * vs, rec.output * ys, label="measured", lw=1.0)
    ax.plot(rec.input * vs, result.model * ys, label="model", lw=1.0, ls="--")
    ax.set_xlabel(vlab)
    ax.set_ylabel(ylab)
    ax.legend(loc="best")
    ax.set_title(f"{rec.label}: loops")
    fig.tight_layout()
    paths.append(out_dir / f"{stem}_loop.png")
    fig.savefig(paths[-1], dpi=120)
    plt.close(fig)
    return paths
