"""Feedforward for a sampled loop, and learning it over repeated periods (model-based ILC).

A loop at rate 1/T holds each command for a period (ZOH). The continuous feedforward of
:mod:`.feedforward`, sampled, is not what makes the model follow x_d at the sample instants:
each step of the staircase rings the stage's resonance, the ringing wears w down, the delay
and the amplifier's bandwidth shift it. Here the feedforward is a table u_ff[k], one value per
sample of a period of N samples (a whole record for a trajectory that does not repeat).

Learning (iterative learning control, Bristow, Tharayil & Alleyne, "A survey of iterative
learning control", IEEE Control Systems Magazine 26(3), 2006, §"Frequency-domain analysis"):
after period j with error e_j = x − x_d at the samples,

    u_{j+1} = Q·(u_j + L·e_j),   L = −α·G⁻¹,

computed per harmonic of the period (the signals are N-periodic, so the lifted operators are
circulant and the FFT diagonalises them). G is the model's map from u_ff to x at the samples:

    G(z) = P(z)·z^{−d}·S(z),   S = 1 / (1 + C(z)·P(z)·z^{−d}),

P(z) the ZOH discretisation of 1 / ((τs + 1)(m s² + c s + k)) (the linear part of (11.1) with
the incremental stiffness k = κx + κw·ρ/2 and an amplifier of bandwidth 1/(2πτ)), d the
command's delay in samples, C(z) = k1 + k0·T/(1 − z⁻¹) + k2·(1 − z⁻¹)/T the law of
:class:`~piezo_stage.control.controller.TimeVaryingPID` (rectangle sums, Euler differences)
under ``both`` compensation, C = 0 under ``feedforward``. With the integrator of C, S(1) = 0:
the mean of u_ff is the law's business and is not learned.

Convergence: the error of the true plant G₀ evolves as E_{j+1} = Q·(1 − α·G₀/G)·E_j (plus
what Q removes), so the learning converges monotonically in the 2-norm when

    |Q(ω)·(1 − α·G₀(ω)/G(ω))| < 1 at every harmonic ω,

i.e. for 0 < α ≤ 1 whenever the model's phase error stays below 90° and its gain error below
(2 − α)/α at the harmonics Q passes. The Q-filter (zero-phase, ideal low-pass at ``cutoff_hz``)
keeps the learning away from the harmonics where the model is least sure (near the sampled
resonance, at Nyquist); what it removes stays as error. The hysteresis makes G₀ vary along
the loop (k between κx and κx + κw·ρ): the midpoint keeps the ratio within ±20 %.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy import signal

from piezo_stage.model.parameter_set import Dynamics
from piezo_stage.model.plant import DynamicPlant

from .errors import ControlError
from .feedforward import FeedforwardModel, feedforward
from .laws import Gains

#: file format of a saved table
TABLE_FORMAT = "piezo_stage feedforward table 1"


class LearningError(ControlError):
    """A learning configuration or table that cannot be used, or a bad period of error."""


def incremental_stiffness(model: FeedforwardModel) -> float:
    """k = κx + κw·ρ/2 [V/m]: midway between the hysteresis loop's slopes κx (|w| → 1) and
    κx + κw·ρ (at reversal, w = 0) of (11.1)-(11.3)."""
    bw = model.bouc_wen
    return float(bw.kappa_x + 0.5 * bw.kappa_w * bw.rho)


def harmonics(n: int, rate_hz: float) -> np.ndarray:
    """Frequencies [Hz] of the rfft bins of an ``n``-sample period at ``rate_hz``."""
    return np.fft.rfftfreq(n, 1.0 / rate_hz)


def feedforward_response(
    model: FeedforwardModel,
    rate_hz: float,
    n: int,
    *,
    delay_samples: float = 0.0,
    amplifier_bandwidth: float = math.inf,
    gains: Gains | None = None,
) -> np.ndarray:
    """G at the harmonics of an ``n``-sample period (module docstring): u_ff → x at the samples,
    through the ZOH, the amplifier, ``delay_samples`` (may be fractional) and, with ``gains``,
    the closed loop of the PID law. Complex, one value per rfft bin."""
    if not (math.isfinite(rate_hz) and rate_hz > 0) or n < 2:
        raise LearningError(f"need rate_hz > 0 and n >= 2, got {rate_hz}, {n}")
    T = 1.0 / rate_hz
    den = np.array([model.m, model.c, incremental_stiffness(model)])
    if math.isfinite(amplifier_bandwidth):
        den = np.polymul([1.0 / (2.0 * math.pi * amplifier_bandwidth), 1.0], den)
    den = np.trim_zeros(den, "f")  # m = 0 (and c = 0): first order (static)
    omega = 2.0 * math.pi * harmonics(n, rate_hz) * T
    z = np.exp(1j * omega)
    if den.size == 1:  # static: x[k + 1] = u[k] / k
        P = 1.0 / (den[0] * z)
    else:
        b, a, _ = signal.cont2discrete((np.array([1.0]), den), T, method="zoh")
        _, P = signal.freqz(np.ravel(b), a, worN=omega)
    P = P * z ** (-float(delay_samples))
    if gains is None:
        return P
    with np.errstate(divide="ignore", invalid="ignore"):
        C = gains.k1 + gains.k0 * T / (1.0 - 1.0 / z) + gains.k2 * (1.0 - 1.0 / z) / T
        G = P / (1.0 + C * P)
    G[0] = 0.0  # the integrator: no mean passes to x
    return G


@dataclass(frozen=True)
class LearningConfig:
    """How a table learns: ``gain`` α of L = −α·G⁻¹ (0 < α ≤ 1), Q's ``cutoff_hz`` (None: a
    quarter of the rate, half the Nyquist frequency: above it the hysteresis's harmonics of a
    fast trajectory couple the bins and the per-harmonic inverse can diverge), the amplifier's
    limits ``u_min``/``u_max`` [V] and ``slew_rate`` [V/s] (inf: none) every table value keeps;
    ``settle_periods`` after each change of the table are not learned from (the loop still
    answers the change: its error is not the table's); the stop rule: learning ends after
    ``patience`` learned periods without the RMS error falling below ``1 − min_improvement``
    times the best so far."""

    gain: float = 1.0
    cutoff_hz: float | None = None
    settle_periods: int = 1
    u_min: float = -math.inf
    u_max: float = math.inf
    slew_rate: float = math.inf
    min_improvement: float = 0.05
    patience: int = 2

    def __post_init__(self) -> None:
        if not 0.0 < self.gain <= 1.0:
            raise LearningError(f"learning gain must be in (0, 1], got {self.gain}")
        if self.cutoff_hz is not None and not self.cutoff_hz > 0:
            raise LearningError(f"cutoff_hz must be > 0 Hz, got {self.cutoff_hz}")
        if not 0 <= self.settle_periods <= 100:
            raise LearningError(f"settle_periods must be in [0, 100], got {self.settle_periods}")
        if not self.u_min < self.u_max:
            raise LearningError(f"need u_min < u_max, got [{self.u_min}, {self.u_max}] V")
        if not self.slew_rate > 0:
            raise LearningError(f"slew_rate must be > 0 V/s, got {self.slew_rate}")
        if not 0.0 <= self.min_improvement < 1.0 or self.patience < 1:
            raise LearningError("need 0 <= min_improvement < 1 and patience >= 1")


def limit(u: np.ndarray, config: LearningConfig, rate_hz: float, periodic: bool = True
          ) -> np.ndarray:
    """``u`` within [u_min, u_max] with |u[k+1] − u[k]| ≤ slew_rate/rate (around the period too
    when ``periodic``): clipped, then each value brought within the slew cap of the one before
    (one forward pass; clipping and this pass move a value towards its neighbour, never out
    of range); a periodic table whose step from its end back to its start still exceeds the
    cap is scaled about its mean by cap/step (scaling shrinks every step alike, clipping then
    grows none)."""
    out = np.clip(np.asarray(u, dtype=float), config.u_min, config.u_max)
    if not math.isfinite(config.slew_rate):
        return out
    cap = config.slew_rate / rate_hz
    for k in range(1, out.size):
        out[k] = min(max(out[k], out[k - 1] - cap), out[k - 1] + cap)
    wrap = abs(out[0] - out[-1])
    if periodic and wrap > cap:
        mean = float(out.mean())
        out = np.clip(mean + (out - mean) * (cap / wrap), config.u_min, config.u_max)
    return out


@dataclass(eq=False)
class FeedforwardTable:
    """u_ff [V] at each sample of a period of ``len(u)`` samples at ``rate_hz``; ``periodic``
    False: one record (the last value holds after it). ``meta``: what it was made for
    (trajectory, model, learning history), saved with it."""

    u: np.ndarray
    rate_hz: float
    periodic: bool = True
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.u = np.array(self.u, dtype=float)
        if self.u.ndim != 1 or self.u.size < 2 or not np.all(np.isfinite(self.u)):
            raise LearningError("a feedforward table needs >= 2 finite values")
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise LearningError(f"table rate must be > 0 Hz, got {self.rate_hz}")

    def __len__(self) -> int:
        return int(self.u.size)

    def index(self, t: float) -> int:
        """The sample of the table at ``t`` [s] from the trajectory's start."""
        k = int(round(t * self.rate_hz))
        return k % self.u.size if self.periodic else min(max(k, 0), self.u.size - 1)

    def value(self, t: float) -> float:
        return float(self.u[self.index(t)])

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.write_text(json.dumps({"format": TABLE_FORMAT, "rate_hz": self.rate_hz,
                                    "periodic": self.periodic, "meta": self.meta,
                                    "u": self.u.tolist()}, indent=1))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "FeedforwardTable":
        try:
            data = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise LearningError(f"feedforward table {path}: {exc}") from exc
        if not isinstance(data, dict) or data.get("format") != TABLE_FORMAT:
            raise LearningError(f"{path} is not a feedforward table ({TABLE_FORMAT!r})")
        try:
            return cls(np.asarray(data["u"], dtype=float), float(data["rate_hz"]),
                       bool(data.get("periodic", True)), dict(data.get("meta", {})))
        except (KeyError, TypeError, ValueError) as exc:
            raise LearningError(f"feedforward table {path}: {exc}") from exc

    def matches(self, rate_hz: float, n: int) -> str:
        """'' when the table serves a loop at ``rate_hz`` over ``n`` samples, else why not."""
        if abs(self.rate_hz - rate_hz) > 1e-9 * rate_hz:
            return f"the table was made at {self.rate_hz:g} Hz, the loop runs at {rate_hz:g} Hz"
        if len(self) != n:
            return f"the table holds {len(self)} samples, the trajectory's period {n}"
        return ""


class IterativeLearning:
    """u_{j+1} = Q·(u_j + L·e_j) on ``table`` (module docstring), in place: call
    :meth:`update` with each period's error; ``done`` once the stop rule holds."""

    def __init__(self, table: FeedforwardTable, response: np.ndarray,
                 config: LearningConfig = LearningConfig()) -> None:
        n = len(table)
        if response.shape != (n // 2 + 1,):
            raise LearningError(f"response has {response.shape} bins, a {n}-sample period "
                                f"{n // 2 + 1}")
        self.table, self.config = table, config
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = np.where(np.abs(response) > 0, 1.0 / response, 0.0)
        cutoff = 0.25 * table.rate_hz if config.cutoff_hz is None else config.cutoff_hz
        q = (harmonics(n, table.rate_hz) <= cutoff).astype(float)
        self._learn = -config.gain * inverse * q
        self._q = q
        self.history: list[float] = []  # RMS error of each period learned from
        self.periods = 0  # periods given, settling ones included
        self._best, self._stale, self._settling = math.inf, 0, 0

    @property
    def done(self) -> bool:
        return self._stale >= self.config.patience

    def update(self, error: Sequence[float]) -> FeedforwardTable:
        """One period's error e = x − x_d [m] at the table's samples: learned from (the table
        changes) unless it is a settling period or learning is done."""
        e = np.asarray(error, dtype=float)
        if e.shape != self.table.u.shape or not np.all(np.isfinite(e)):
            raise LearningError(f"need {len(self.table)} finite errors, got {e.shape}")
        self.periods += 1
        if self._settling or self.done:
            self._settling = max(self._settling - 1, 0)
            return self.table
        rms = float(np.sqrt(np.mean(e * e)))
        self.history.append(rms)
        if rms < (1.0 - self.config.min_improvement) * self._best:
            self._best, self._stale = rms, 0
        else:
            self._stale += 1
        if self.done:
            return self.table
        u = self.table.u
        # Q passes the mean; under both the law's integrator owns it (G = 0 there: L = 0)
        spectrum = self._q * np.fft.rfft(u) + self._learn * np.fft.rfft(e)
        self.table.u = limit(np.fft.irfft(spectrum, u.size), self.config, self.table.rate_hz,
                             self.table.periodic)
        self._settling = self.config.settle_periods
        return self.table


def sampled_feedforward(
    model: FeedforwardModel,
    x_d: Sequence[float],
    rate_hz: float,
    *,
    periodic: bool = True,
    delay_samples: float = 0.0,
    amplifier_bandwidth: float = math.inf,
    iterations: int = 8,
    config: LearningConfig = LearningConfig(),
) -> FeedforwardTable:
    """The command staircase the model says makes x follow ``x_d`` at the samples (x_d[k] at
    t = k/rate, one period when ``periodic``): the continuous u_ff of (11.1) along x_d, then
    ``iterations`` of the learning above against the model itself run open loop (ZOH at
    ``rate_hz``, the delay rounded to whole samples) — the model's ringing, ZOH and delay
    included, its hysteresis in steady periodic state."""
    xd = np.asarray(x_d, dtype=float)
    n = xd.size
    T = 1.0 / rate_hz
    reps = 3 if periodic else 1
    path = np.tile(xd, reps)
    vd = np.gradient(path, T)
    ad = np.gradient(vd, T)
    u_cont, w = feedforward(model, path, vd, ad)
    table = FeedforwardTable(u_cont[-n:], rate_hz, periodic)
    response = feedforward_response(model, rate_hz, n, delay_samples=delay_samples,
                                    amplifier_bandwidth=amplifier_bandwidth)
    learning = IterativeLearning(table, response, replace(
        config, patience=iterations + 1, min_improvement=0.0, settle_periods=0))
    bw, dynamics = model.bouc_wen, Dynamics(model.m, model.c)
    d = int(round(delay_samples))
    for _ in range(iterations):
        stage = DynamicPlant(bw, dynamics, x0=float(xd[0]) - bw.y0, w0=float(w[0]))
        x = np.empty(n * reps)
        u_seq = np.tile(table.u, reps)
        u_applied = np.concatenate([np.full(d, u_seq[0]), u_seq])[: u_seq.size]
        for k in range(u_seq.size):
            x[k] = stage.output()
            stage.step(float(u_applied[k]), T)
        learning.update(x[-n:] - xd)
    return table


__all__ = [
    "TABLE_FORMAT",
    "FeedforwardTable",
    "IterativeLearning",
    "LearningConfig",
    "LearningError",
    "feedforward_response",
    "harmonics",
    "incremental_stiffness",
    "limit",
    "sampled_feedforward",
]
