"""Open-loop excitation schedules: the thesis's identification experiment as data.

A plan is a base waveform of one period (T-wave triangle (9.1.1), sine, band-limited random,
step, constant) repeated over *runs*, one per offset q: the identification pair of §9.1.3 is
offsets ``[0, q]`` (x(t) and x(t)+q). Each run first settles for ``settle_periods`` and is then
*steady* for ``record_periods``. The plan is a pure function of time, so the excitation node,
the lockstep experiments and offline tests produce the same samples.

Presets (:data:`PRESETS`):
- ``ch10_patch``: 0.1 Hz triangles 0-300 V then 100-400 V (q = 100 V), §10.3.2, 8 settling periods;
- ``ch9_example``: triangle between -0.2 and 0.2, T = 1 s, q = 0.1 (§9.2), 16 settling periods.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Sequence, TypeAlias

import numpy as np
from numpy.typing import NDArray

from .errors import ParameterValueError

WAVEFORMS = ("triangle", "sine", "random", "step", "constant")
#: what the plan outputs after its last run: the last value, the first run's low, or zero
HOLDS = ("last", "low", "zero")
#: the random waveform's (frequencies, phases, weights, min, span): see :func:`_random_table`
RandomTable: TypeAlias = tuple[
    NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float, float
]


@dataclass(frozen=True)
class ExcitationSample:
    """The plan's state at one instant (:meth:`ExcitationPlan.sample`)."""

    voltage: float  # [V] command, clamped to the limits
    run: int  # index into offsets
    offset: float  # [V] q of this run
    steady: bool  # settling periods of this run are over
    done: bool  # past the last run (voltage is then the hold value)
    phase: float  # position in the current period, 0..1


@dataclass(frozen=True)
class ExcitationPlan:
    """Waveform ``low + amplitude * shape(t / period) + offsets[run]``, clamped to [v_min, v_max].

    ``shape`` goes from 0 to 1: the triangle starts at its minimum and rises for half a period
    (a loading branch first), the sine is ``(1 - cos)/2`` (also starting at the minimum), the
    random signal is a seeded sum of sines up to ``bandwidth`` Hz scaled into [0, 1], the step
    is 0 for the first half period and 1 after, the constant is 1 (``low + amplitude``).
    """

    waveform: str = "triangle"
    period: float = 10.0  # [s]
    low: float = 0.0  # [V] minimum of the base waveform
    amplitude: float = 300.0  # [V] peak-to-peak span
    offsets: tuple[float, ...] = (0.0,)  # [V] one run per offset
    settle_periods: int = 1
    record_periods: int = 2
    v_min: float = -math.inf
    v_max: float = math.inf
    hold: str = "last"  # after the last run: "last" value, "low" of the first run, or "zero"
    seed: int = 0  # random waveform
    bandwidth: float = 1.0  # [Hz] random waveform: highest frequency
    _random_table: RandomTable | tuple[()] = field(default=(), repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.waveform not in WAVEFORMS:
            raise ParameterValueError(f"waveform must be one of {WAVEFORMS}, got {self.waveform!r}")
        for name in ("period", "low", "amplitude", "bandwidth"):
            if not math.isfinite(getattr(self, name)):
                raise ParameterValueError(f"{name} must be finite, got {getattr(self, name)}")
        if self.period <= 0:
            raise ParameterValueError(f"period must be > 0 s, got {self.period}")
        if not self.offsets or not all(math.isfinite(q) for q in self.offsets):
            raise ParameterValueError(
                f"offsets must be a non-empty list of finite values, got {self.offsets}"
            )
        if self.settle_periods < 0 or self.record_periods < 1:
            raise ParameterValueError("need settle_periods >= 0 and record_periods >= 1")
        if not self.v_min < self.v_max:
            raise ParameterValueError(f"need v_min < v_max, got [{self.v_min}, {self.v_max}]")
        if self.hold not in HOLDS:
            raise ParameterValueError(f"hold must be last, low or zero, got {self.hold!r}")
        if self.waveform == "random":
            if self.bandwidth <= 1.0 / self.period:
                raise ParameterValueError("random waveform: bandwidth must exceed 1/period")
            object.__setattr__(
                self, "_random_table", _random_table(self.seed, self.period, self.bandwidth)
            )

    # ------------------------------------------------------------------ timing
    @property
    def periods_per_run(self) -> int:
        """Periods in one run: settle_periods + record_periods."""
        return self.settle_periods + self.record_periods

    @property
    def run_duration(self) -> float:
        """Length of one run [s]."""
        return self.periods_per_run * self.period

    @property
    def duration(self) -> float:
        """Length of all runs [s]; the hold value follows."""
        return self.run_duration * len(self.offsets)

    def run_start(self, run: int) -> float:
        """Start of run ``run`` [s]."""
        return run * self.run_duration

    def steady_window(self, run: int) -> tuple[float, float]:
        """[start, end) of the recorded (steady) part of a run [s]."""
        start = self.run_start(run) + self.settle_periods * self.period
        return start, start + self.record_periods * self.period

    # ------------------------------------------------------------------ values
    def shape(self, phase: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Normalised waveform in [0, 1] at ``phase`` = t/period (any real)."""
        p: NDArray[np.float64] = np.mod(np.asarray(phase, dtype=float), 1.0)
        if self.waveform == "triangle":
            return 1.0 - np.abs(1.0 - 2.0 * p)
        if self.waveform == "sine":
            return 0.5 * (1.0 - np.cos(2.0 * np.pi * p))
        if self.waveform == "step":
            return (p >= 0.5).astype(float)
        if self.waveform == "constant":
            return np.ones_like(p)
        table = self._random_table
        assert table, "built by __post_init__ for the random waveform"
        freqs, phases, weights, lo, span = table
        s = np.sin(2 * np.pi * np.multiply.outer(p * self.period, freqs) + phases) @ weights
        return (s - lo) / span

    def values(self, t: NDArray[np.float64] | float) -> NDArray[np.float64]:
        """Command voltage at times ``t`` [s] (vectorised; after the end: the hold value)."""
        t = np.asarray(t, dtype=float)
        run = np.clip((t // self.run_duration).astype(int), 0, len(self.offsets) - 1)
        v = self.low + self.amplitude * self.shape(t / self.period) + np.asarray(self.offsets)[run]
        v = np.where(t >= self.duration, self.hold_value(), v)
        return np.clip(v, self.v_min, self.v_max)

    def hold_value(self) -> float:
        """Command voltage after the last run (``hold``), clamped to the limits."""
        if self.hold == "zero":
            value = 0.0
        elif self.hold == "low":
            value = self.low + self.offsets[0]
        else:  # the last value of the last run (the waveform is periodic: its value at phase 0)
            value = self.low + self.amplitude * float(self.shape(0.0)) + self.offsets[-1]
        return float(min(max(value, self.v_min), self.v_max))

    def sample(self, t: float) -> ExcitationSample:
        """The command, run, offset, steady/done flags and phase at time ``t`` [s]."""
        done = t >= self.duration
        run = min(int(t // self.run_duration), len(self.offsets) - 1) if t >= 0 else 0
        start, end = self.steady_window(run)
        return ExcitationSample(
            voltage=float(self.values(t)),
            run=run,
            offset=self.offsets[run],
            steady=(not done) and start <= t < end,
            done=done,
            phase=float(np.mod(t / self.period, 1.0)),
        )


def _random_table(seed: int, period: float, bandwidth: float) -> RandomTable:
    """Frequencies (harmonics of 1/period up to bandwidth), random phases, equal weights, and
    the min/span of the sum over one period (so the shape is periodic and lies in [0, 1]).
    """
    rng = np.random.default_rng(seed)
    freqs = np.arange(1, int(bandwidth * period) + 1) / period
    phases = rng.uniform(0, 2 * np.pi, freqs.size)
    weights = np.ones(freqs.size) / np.sqrt(freqs.size)
    grid = np.linspace(0.0, period, 20 * freqs.size * 8 + 1)
    s = np.sin(2 * np.pi * np.multiply.outer(grid, freqs) + phases) @ weights
    lo, hi = float(s.min()), float(s.max())
    margin = 0.02 * (hi - lo)  # the grid may miss the extremes slightly
    return freqs, phases, weights, lo - margin, (hi - lo) + 2 * margin


PRESETS: dict[str, ExcitationPlan] = {
    # from w(0) = 0 the patch's cycle needs ~8 periods to agree within 1e-5 of the span
    "ch10_patch": ExcitationPlan(
        waveform="triangle",
        period=10.0,
        low=0.0,
        amplitude=300.0,
        offsets=(0.0, 100.0),
        settle_periods=8,
        record_periods=2,
    ),
    # rho * span = 0.4: the cycle converges by only ~x0.37 per period from w(0) = 0 (the thesis
    # used [4T, 5T], not yet steady); 16 settling periods bring it within 1e-6 of the span
    "ch9_example": ExcitationPlan(
        waveform="triangle",
        period=1.0,
        low=-0.2,
        amplitude=0.4,
        offsets=(0.0, 0.1),
        settle_periods=16,
        record_periods=2,
    ),
}


def plan_from(preset: str | None = None, **overrides: object) -> ExcitationPlan:
    """A preset with overrides (None values ignored), or a plan from the overrides alone."""
    if preset and preset not in PRESETS:
        raise ParameterValueError(f"unknown preset {preset!r}; known: {sorted(PRESETS)}")
    base = PRESETS[preset] if preset else ExcitationPlan()
    # values of any of the plan's field types: the dataclass checks them
    clean: dict[str, Any] = {
        k: (tuple(v) if isinstance(v, Sequence) and not isinstance(v, str) else v)
        for k, v in overrides.items()
        if v is not None
    }
    return replace(base, **clean)
