"""Feedforward for a sampled loop, and learning it over repeated periods (model-based ILC).

A loop at rate 1/T holds each command for a period (ZOH). The continuous feedforward of
:mod:`.feedforward`, sampled, is not what makes the model follow x_d at the sample instants:
each step of the staircase rings the stage's resonance, the ringing wears w down, the delay
and the amplifier's bandwidth shift it. Here the feedforward is a table u_ff[k], one value per
sample of a period of N samples (a whole record for a trajectory that does not repeat).

Learning (iterative learning control, Bristow, Tharayil & Alleyne, "A survey of iterative
learning control", IEEE Control Systems Magazine 26(3), 2006, §"Frequency-domain analysis"):
after period j with error e_j = x − x_d at the samples,

    u_{j+1} = u_j + Q·L·e_j,   L = −α·G⁻¹,

computed per harmonic of the period (the signals are N-periodic, so the lifted operators are
circulant and the FFT diagonalises them). G is the model's map from u_ff to x at the samples:

    G(z) = P(z)·z^{−d}·S(z),   S = 1 / (1 + C(z)·P(z)·z^{−d}),

P(z) the ZOH discretisation of 1 / ((τs + 1)(m s² + c s + k)) (the linear part of (11.1) with
the incremental stiffness k = κx + κw·ρ/2 and an amplifier of bandwidth 1/(2πτ)), d the
command's delay in samples, C(z) = k1 + k0·T/(1 − z⁻¹) + k2·(1 − z⁻¹)/T the law of
:class:`~piezo_stage.control.controller.TimeVaryingPID` (rectangle sums, Euler differences)
under ``both`` compensation, C = 0 under ``feedforward``. With the integrator of C, S(1) = 0:
the mean of u_ff is the law's business and is not learned.

Convergence: at a harmonic Q passes, the error of the true plant G₀ evolves as
E_{j+1} = (1 − α·G₀/G)·E_j, so the learning converges monotonically in the 2-norm when

    |1 − α·G₀(ω)/G(ω)| < 1 at every harmonic ω with Q(ω) = 1,

i.e. for 0 < α ≤ 1 whenever the model's phase error stays below 90° and its gain error below
(2 − α)/α there; at the others u keeps what the model gave. Q (zero-phase, ideal low-pass at
``cutoff_hz``, on the correction: the filtered-learning form of the survey's Q-filter) keeps
the learning away from the harmonics where the model is least sure (near the resonance, near
Nyquist); what the model leaves there stays as error. The hysteresis makes G₀ vary along
the loop (k between κx and κx + κw·ρ): the midpoint keeps the ratio within ±20 %.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field, replace
from enum import StrEnum
from pathlib import Path
from typing import Any, Callable, Sequence, cast

import numpy as np
from numpy.typing import NDArray

from piezo_stage.model.parameter_set import Dynamics
from piezo_stage.model.plant import DynamicPlant

from .errors import ControlError
from .feedforward import FeedforwardModel, feedforward
from .laws import Gains
from .trajectory import Trajectory

#: file format of a saved table
TABLE_FORMAT = "piezo_stage feedforward table 1"


class FeedforwardForm(StrEnum):
    """The feedforward of a known trajectory in a sampled loop."""

    AUTO = "auto"  #: sampled below :data:`SAMPLED_BELOW` times the resonance, else continuous
    SAMPLED = "sampled"  #: the staircase the model says the loop needs
    CONTINUOUS = "continuous"  #: the model stepped along x_d, sampled


#: ``auto`` takes the sampled form below this many times the resonance sqrt(κx/m)/2π: the ch. 11
#: rig (7 kHz), 10 Hz triangle: continuous 4.2 / 1.7 / 0.014 % at 1 / 10 / 100 kHz, sampled
#: 0.012 / 0.012 / 0.08 % (a table starts from the periodic steady state, the stage from rest)
SAMPLED_BELOW = 10.0


def resonance(model: FeedforwardModel) -> float:
    """sqrt(κx/m)/2π [Hz] (inf without a mass)."""
    return math.sqrt(model.bouc_wen.kappa_x / model.m) / (2 * math.pi) if model.m > 0 else math.inf


def choose_form(form: FeedforwardForm, model: FeedforwardModel, rate_hz: float) -> FeedforwardForm:
    """``form``, with ``auto`` resolved for a loop at ``rate_hz``."""
    if form is not FeedforwardForm.AUTO:
        return form
    return (
        FeedforwardForm.SAMPLED
        if rate_hz < SAMPLED_BELOW * resonance(model)
        else FeedforwardForm.CONTINUOUS
    )


class LearningError(ControlError):
    """A learning configuration or table that cannot be used, or a bad period of error."""


def incremental_stiffness(model: FeedforwardModel) -> float:
    """Stiffness k = κx + κw·ρ/2 [V/m]: midway between the hysteresis loop's slopes κx (|w| → 1) and
    κx + κw·ρ (at reversal, w = 0) of (11.1)-(11.3).
    """
    bw = model.bouc_wen
    return float(bw.kappa_x + 0.5 * bw.kappa_w * bw.rho)


def default_cutoff(model: FeedforwardModel | None, rate_hz: float) -> float:
    """Q's cutoff [Hz] when none is given: a quarter of the rate, and at most half the
    resonance sqrt(κx/m)/2π (near it the response's phase turns fast and the stiffness the
    hysteresis adds moves the peak: the per-harmonic inverse is least sure there).
    """
    return min(0.25 * rate_hz, 0.5 * resonance(model)) if model is not None else 0.25 * rate_hz


def harmonics(n: int, rate_hz: float) -> NDArray[np.float64]:
    """Frequencies [Hz] of the rfft bins of an ``n``-sample period at ``rate_hz``."""
    # (numpy's stubs give floating[Any] for any float input: these are float64)
    return cast(NDArray[np.float64], np.fft.rfftfreq(n, 1.0 / rate_hz))


def feedforward_response(
    model: FeedforwardModel,
    rate_hz: float,
    n: int,
    *,
    delay_samples: float = 0.0,
    amplifier_bandwidth: float = math.inf,
    gains: Gains | None = None,
) -> NDArray[np.complex128]:
    """G at the harmonics of an ``n``-sample period (module docstring): u_ff → x at the samples,
    through the ZOH, the amplifier, ``delay_samples`` (may be fractional) and, with ``gains``,
    the closed loop of the PID law. Complex, one value per rfft bin.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0) or n < 2:
        raise LearningError(f"need rate_hz > 0 and n >= 2, got {rate_hz}, {n}")
    T = 1.0 / rate_hz
    den = np.array([model.m, model.c, incremental_stiffness(model)])
    if math.isfinite(amplifier_bandwidth):
        den = np.polymul([1.0 / (2.0 * math.pi * amplifier_bandwidth), 1.0], den)
    den = np.trim_zeros(den, "f")  # m = 0 (and c = 0): first order (static)
    omega = 2.0 * math.pi * harmonics(n, rate_hz) * T
    z = np.exp(1j * omega)
    P: NDArray[np.complex128]
    if den.size == 1:  # static: x[k + 1] = u[k] / k
        P = 1.0 / (den[0] * z)
    else:
        from scipy import signal  # lazy: 3 s of imports a controller without learning skips

        b, a, _ = signal.cont2discrete((np.array([1.0]), den), T, method="zoh")
        _, P = signal.freqz(np.ravel(b), a, worN=omega)
    P = P * z ** (-float(delay_samples))
    if gains is None:
        return P
    with np.errstate(divide="ignore", invalid="ignore"):
        C = gains.k1 + gains.k0 * T / (1.0 - 1.0 / z) + gains.k2 * (1.0 - 1.0 / z) / T
        G: NDArray[np.complex128] = P / (1.0 + C * P)
    G[0] = 0.0  # the integrator: no mean passes to x
    return G


#: an RMS error this fraction of the first learned period's is at the floating-point floor
ROUNDING = 1e-12


@dataclass(frozen=True)
class LearningConfig:
    """How a table learns: ``gain`` α of L = −α·G⁻¹ (0 < α ≤ 1), Q's ``cutoff_hz`` (None:
    :func:`default_cutoff`, a quarter of the rate — above it the hysteresis's harmonics of a
    fast trajectory couple the bins and the per-harmonic inverse can diverge — and at most
    half the stage's resonance), the amplifier's
    limits ``u_min``/``u_max`` [V] and ``slew_rate`` [V/s] (inf: none) every table value keeps;
    ``settle_periods`` at the start and after each change of the table are not learned from
    (the loop still answers the change: its error is not the table's); the stop rule: learning
    ends after
    ``patience`` learned periods without the RMS error falling below ``1 − min_improvement``
    times the best so far (once the best is at :data:`ROUNDING` of the first learned period's,
    nothing below it counts: that is rounding, whose size varies with the CPU and its BLAS).
    """

    gain: float = 0.5
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


def limit(
    u: NDArray[np.float64], config: LearningConfig, rate_hz: float, periodic: bool = True
) -> NDArray[np.float64]:
    """``u`` within [u_min, u_max] with |u[k+1] − u[k]| ≤ slew_rate/rate (around the period too
    when ``periodic``): clipped, then each value brought within the slew cap of the one before
    (one forward pass; clipping and this pass move a value towards its neighbour, never out
    of range); a periodic table whose step from its end back to its start still exceeds the
    cap is scaled about its mean by cap/step (scaling shrinks every step alike, clipping then
    grows none).
    """
    out = np.clip(np.asarray(u, dtype=np.float64), config.u_min, config.u_max)
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


def at_limits(u: NDArray[np.float64], u_min: float, u_max: float) -> int:
    """How many values of ``u`` sit at u_min or u_max (to 1e-9 of the range): where :func:`limit`
    clipped what the model or the learning asked, the stage cannot follow and the error stays.
    """
    tol = 1e-9 * (u_max - u_min) if math.isfinite(u_max - u_min) else 0.0
    u = np.asarray(u, dtype=float)
    return int(np.count_nonzero((u <= u_min + tol) | (u >= u_max - tol)))


@dataclass(eq=False)
class FeedforwardTable:
    """u_ff [V] at each sample of a period of ``len(u)`` samples at ``rate_hz``; ``periodic``
    False: one record (the last value holds after it). ``meta``: what it was made for
    (trajectory, model, learning history), saved with it.
    """

    u: NDArray[np.float64]
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
        """Table value u_ff [V] at ``t`` [s] from the trajectory's start."""
        return float(self.u[self.index(t)])

    def to_dict(self) -> dict[str, Any]:
        """The table as JSON-ready data (what :meth:`save` writes)."""
        return {
            "format": TABLE_FORMAT,
            "rate_hz": self.rate_hz,
            "periodic": self.periodic,
            "meta": self.meta,
            "u": self.u.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Any, source: str | Path) -> "FeedforwardTable":
        """The table :meth:`to_dict` gave; :class:`LearningError` naming ``source`` if not."""
        if not isinstance(data, dict) or data.get("format") != TABLE_FORMAT:
            raise LearningError(f"{source} is not a feedforward table ({TABLE_FORMAT!r})")
        try:
            return cls(
                np.asarray(data["u"], dtype=float),
                float(data["rate_hz"]),
                bool(data.get("periodic", True)),
                dict(data.get("meta", {})),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise LearningError(f"feedforward table {source}: {exc}") from exc

    def save(self, path: str | Path) -> Path:
        """Write the table as JSON to ``path``; returns the path."""
        path = Path(path)
        path.write_text(json.dumps(self.to_dict(), indent=1))
        return path

    @classmethod
    def load(cls, path: str | Path) -> "FeedforwardTable":
        """Read a table :meth:`save` wrote; :class:`LearningError` when it cannot."""
        return cls.from_dict(read_json(path, "feedforward table"), path)

    def matches(self, rate_hz: float, n: int) -> str:
        """'' when the table serves a loop at ``rate_hz`` over ``n`` samples, else why not."""
        if abs(self.rate_hz - rate_hz) > 1e-9 * rate_hz:
            return f"the table was made at {self.rate_hz:g} Hz, the loop runs at {rate_hz:g} Hz"
        if len(self) != n:
            return f"the table holds {len(self)} samples, the trajectory's period {n}"
        return ""


def read_json(path: str | Path, what: str) -> Any:
    """The JSON data of ``path``; :class:`LearningError` naming ``what`` when unreadable."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise LearningError(f"{what} {path}: {exc}") from exc


class IterativeLearning:
    """u_{j+1} = u_j + Q·L·e_j on ``table`` (module docstring), in place: call
    :meth:`update` with each period's error; ``done`` once the stop rule holds.
    """

    def __init__(
        self,
        table: FeedforwardTable,
        response: NDArray[np.complex128],
        config: LearningConfig = LearningConfig(),
        model: FeedforwardModel | None = None,
    ) -> None:
        n = len(table)
        if response.shape != (n // 2 + 1,):
            raise LearningError(
                f"response has {response.shape} bins, a {n}-sample period {n // 2 + 1}"
            )
        self.table, self.config = table, config
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = np.where(np.abs(response) > 0, 1.0 / response, 0.0)
        cutoff = (
            default_cutoff(model, table.rate_hz) if config.cutoff_hz is None else config.cutoff_hz
        )
        q = (harmonics(n, table.rate_hz) <= cutoff).astype(float)
        self._learn = -config.gain * inverse * q
        self._q = q
        self.history: list[float] = []  # RMS error of each period learned from
        self.periods = 0  # periods given, settling ones included
        # the start is a change too: the loop settles from wherever it started
        self._best, self._stale, self._settling = math.inf, 0, config.settle_periods

    @property
    def done(self) -> bool:
        """Whether the stop rule holds: ``patience`` learned periods without enough improvement."""
        return self._stale >= self.config.patience

    def update(self, error: Sequence[float] | NDArray[np.float64]) -> FeedforwardTable:
        """One period's error e = x − x_d [m] at the table's samples: learned from (the table
        changes) unless it is a settling period or learning is done.
        """
        e = np.asarray(error, dtype=float)
        if e.shape != self.table.u.shape or not np.all(np.isfinite(e)):
            raise LearningError(f"need {len(self.table)} finite errors, got {e.shape}")
        self.periods += 1
        if self._settling or self.done:
            self._settling = max(self._settling - 1, 0)
            return self.table
        rms = float(np.sqrt(np.mean(e * e)))
        self.history.append(rms)
        at_floor = self._best <= ROUNDING * self.history[0]
        if rms < (1.0 - self.config.min_improvement) * self._best and not at_floor:
            self._best, self._stale = rms, 0
        else:
            self._stale += 1
        if self.done:
            return self.table
        u = self.table.u
        # Q filters the correction, not u: what the model gave above the cutoff stays; under
        # both, the law's integrator owns the mean (G = 0 there: L = 0)
        spectrum = np.fft.rfft(u) + self._learn * np.fft.rfft(e)
        self.table.u = limit(
            np.fft.irfft(spectrum, u.size), self.config, self.table.rate_hz, self.table.periodic
        )
        self._settling = self.config.settle_periods
        return self.table


class LineCorrection:
    """A correction c of one line period learned into a frame's table (a raster's slow axis):
    the frame's table is its base plus c on every line from ``first`` on; c learns from a
    line's error as a periodic table does (:class:`IterativeLearning`), from the lines that
    :meth:`learns` (past the fly-back's transient: a correction added to every line would
    carry it into all of them).
    """

    def __init__(
        self,
        frame: FeedforwardTable,
        line_samples: int,
        first: int,
        response: NDArray[np.complex128],
        config: LearningConfig,
        model: FeedforwardModel,
    ) -> None:
        if line_samples < 2 or len(frame) % line_samples:
            raise LearningError(
                f"a frame of {len(frame)} samples is not whole lines of {line_samples}"
            )
        self.table, self.base, self.first = frame, frame.u.copy(), first
        self.lines = len(frame) // line_samples  # line periods a frame
        self.correction = FeedforwardTable(np.zeros(line_samples), frame.rate_hz)
        self.learning = IterativeLearning(self.correction, response, config, model)

    @property
    def history(self) -> list[float]:
        """RMS error of each line learned from."""
        return self.learning.history

    @property
    def done(self) -> bool:
        """Whether the stop rule holds (:attr:`IterativeLearning.done`)."""
        return self.learning.done

    def learns(self, line: int) -> bool:
        """Whether line period ``line`` (from the frame's start) is learned from."""
        return line % self.lines >= self.first + SETTLE_LINES

    def update(self, error: NDArray[np.float64]) -> FeedforwardTable:
        """One line period's error e = x − x_d [m]; the frame's table with the correction."""
        self.learning.update(error)
        u = self.base.reshape(self.lines, -1).copy()
        u[self.first :] += self.correction.u
        self.table.u = u.ravel()
        return self.table


#: lines after a fly-back a :class:`LineCorrection` does not learn from (the slow axis's
#: transient settles over 3)
SETTLE_LINES = 3


class PeriodicLearner:
    """Feeds :class:`IterativeLearning` (or a :class:`LineCorrection`, its periods the frame's
    lines) from a running loop: :meth:`record` the error at each table index as the loop
    steps; a period ends at its last index (or, that one missing, when the index wraps). A few
    samples missing (a loaded host's loop superseded them) are filled from their neighbours
    (:func:`fill_gaps`); a period missing more (a long gap, the loop open) is not learned from
    (``skipped``). After ``periods`` periods, or once the stop rule holds, the table is frozen
    and ``on_done(self)`` is called once.
    """

    def __init__(
        self,
        learning: IterativeLearning | LineCorrection,
        periods: int,
        on_done: Callable[["PeriodicLearner"], None] | None = None,
    ) -> None:
        if periods < 1:
            raise LearningError(f"learning periods must be >= 1, got {periods}")
        self.learning, self.periods, self._on_done = learning, periods, on_done
        n = learning.correction.u.size if isinstance(learning, LineCorrection) else None
        self._n = n or len(learning.table)  # samples a period
        self._error = np.full(self._n, math.nan)
        self._last = -1
        self._open = False  # the buffer holds samples of a period not yet ended
        self.completed = 0  # periods seen, learned from or not
        self.skipped = 0  # periods not learned from: too many samples missing
        self.frozen = False

    def record(self, index: int, error: float) -> bool:
        """The error x − x_d [m] of the sample at ``index``; True when it completed a period
        (at its last sample, so the next sample plays the changed table; or, that one missing,
        once the index wraps).
        """
        if self.frozen:
            return False
        n, last = self._n, self._last
        at = index % n
        ended = self._open and (at < last % n or index // n != last // n)
        if ended:
            self._period_done(last // n)
            if self.frozen:
                return True
        self._last = index
        self._error[at] = error
        self._open = True
        if at == n - 1:
            self._period_done(index // n)
            ended = True
        return ended

    def _period_done(self, period: int) -> None:
        e = self._error
        learning = self.learning
        if not isinstance(learning, LineCorrection) or learning.learns(period):
            filled = fill_gaps(e)
            if filled is None:
                self.skipped += 1
            else:
                learning.update(filled)
        e.fill(math.nan)
        self._open = False
        self.completed += 1
        if self.completed >= self.periods or learning.done:
            self.frozen = True
            if self._on_done is not None:
                self._on_done(self)


#: a period is learned from when at most this share of its samples is missing (a loop that
#: writes the newest output of a read steps on every sample, but a stalled sensor link or a
#: loop that dropped samples leaves holes) ...
MAX_MISSING = 0.5
#: ... and no run of missing samples is longer than this share of it (at least 3 samples):
#: what the interpolation leaves is above the line's harmonics the learning needs
MAX_MISSING_RUN = 0.03


def fill_gaps(error: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """One period's error with its missing (NaN) samples interpolated linearly between their
    periodic neighbours, or None when more than :data:`MAX_MISSING` of it is missing or one
    run of missing samples is longer than :data:`MAX_MISSING_RUN` of it (at least 3).
    """
    missing = ~np.isfinite(error)
    n = error.size
    if not missing.any():
        return error
    if missing.all() or missing.sum() > MAX_MISSING * n:
        return None
    # the longest run, around the period's end too (the table is periodic)
    edges = np.diff(np.concatenate([[0], np.tile(missing, 2).astype(np.int8), [0]]))
    runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
    if runs.max() > max(3, MAX_MISSING_RUN * n):
        return None
    k = np.arange(n)
    have = ~missing
    filled = error.copy()
    filled[missing] = np.interp(k[missing], k[have], error[have], period=n)
    return filled


def trajectory_samples(trajectory: Trajectory, rate_hz: float) -> tuple[NDArray[np.float64], bool]:
    """(x_d at k/rate over one period, periodic): a periodic trajectory's period must be a whole
    number of samples (a table indexed modulo N would drift against it otherwise); a file's
    record is taken whole, not periodic.
    """
    periodic = trajectory.periodic
    exact = trajectory.period * rate_hz
    n = int(round(exact))
    if periodic and abs(exact - n) > 1e-6 * max(n, 1):
        raise LearningError(
            f"the trajectory's period ({trajectory.period:g} s) is {exact:.6g} samples at "
            f"{rate_hz:g} Hz: a feedforward table needs a whole number"
        )
    if n < 2:
        raise LearningError(f"the trajectory's period holds {n} sample(s) at {rate_hz:g} Hz")
    return np.asarray(trajectory.evaluate(np.arange(n) / rate_hz)[0], dtype=float), periodic


class _ModelLoop:
    """The model run open loop by a command staircase, kept running from one period to the
    next: ZOH at ``rate_hz``, ``delay`` whole samples, an amplifier of ``bandwidth`` [Hz]
    (first-order, applied over ``SUBSTEPS`` sub-steps of each period).
    """

    SUBSTEPS = 8

    def __init__(
        self,
        model: FeedforwardModel,
        rate_hz: float,
        x0: float,
        w0: float,
        u0: float,
        delay: int,
        bandwidth: float,
    ) -> None:
        bw = model.bouc_wen
        self.stage = DynamicPlant(bw, Dynamics(model.m, model.c), x0=x0 - bw.y0, w0=w0)
        self.period = 1.0 / rate_hz
        self.pending = [u0] * delay
        self.v = u0  # the amplifier's output
        self.decay = (
            math.exp(-2.0 * math.pi * bandwidth * self.period / self.SUBSTEPS)
            if math.isfinite(bandwidth)
            else 0.0
        )

    def run(self, u: NDArray[np.float64]) -> NDArray[np.float64]:
        """Displacement x at each sample of the staircase ``u`` (measured before that sample's
        command).
        """
        x = np.empty(u.size)
        h, a = self.period / self.SUBSTEPS, self.decay
        for k, command in enumerate(u.tolist()):
            x[k] = self.stage.output()
            self.pending.append(command)
            applied = self.pending.pop(0)
            if a == 0.0:
                self.stage.step(applied, self.period)
                continue
            for _ in range(self.SUBSTEPS):  # v → applied exponentially; its mean over h drives
                v_next = applied + (self.v - applied) * a
                self.stage.step(0.5 * (self.v + v_next), h)
                self.v = v_next
        return x


def sampled_feedforward(
    model: FeedforwardModel,
    x_d: Sequence[float] | NDArray[np.float64],
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
    ``iterations`` of the learning above against the model itself, run open loop (ZOH at
    ``rate_hz``, the delay rounded to whole samples, the amplifier's bandwidth) — its ringing
    and its hysteresis included. Periodic: the model runs on from period to period (two to
    settle, then one settling period after each change), so the table is the one of the
    periodic steady state; a record: each iteration runs it once from rest.
    """
    xd = np.asarray(x_d, dtype=float)
    n = xd.size
    T = 1.0 / rate_hz
    reps = 3 if periodic else 1
    path = np.tile(xd, reps)
    vd = np.gradient(path, T)
    ad = np.gradient(vd, T)
    u_cont, w = feedforward(model, path, vd, ad)
    table = FeedforwardTable(u_cont[-n:], rate_hz, periodic)
    response = feedforward_response(
        model, rate_hz, n, delay_samples=delay_samples, amplifier_bandwidth=amplifier_bandwidth
    )
    # the model has no noise to average: the full gain, no settling period, no early stop
    learning = IterativeLearning(
        table,
        response,
        replace(config, gain=1.0, patience=iterations + 1, min_improvement=0.0, settle_periods=0),
        model,
    )
    d = int(round(delay_samples))

    def start() -> _ModelLoop:
        return _ModelLoop(
            model, rate_hz, float(xd[0]), float(w[0]), float(u_cont[0]), d, amplifier_bandwidth
        )

    loop = start()
    if periodic:
        loop.run(table.u)
        loop.run(table.u)
    for _ in range(iterations):
        if periodic:
            loop.run(table.u)  # settles after the last change
        else:
            loop = start()
        learning.update(loop.run(table.u) - xd)
    return table


__all__ = [
    "TABLE_FORMAT",
    "FeedforwardForm",
    "FeedforwardTable",
    "IterativeLearning",
    "LearningConfig",
    "LearningError",
    "LineCorrection",
    "PeriodicLearner",
    "SAMPLED_BELOW",
    "SETTLE_LINES",
    "at_limits",
    "choose_form",
    "resonance",
    "default_cutoff",
    "feedforward_response",
    "fill_gaps",
    "harmonics",
    "incremental_stiffness",
    "limit",
    "sampled_feedforward",
    "trajectory_samples",
]
