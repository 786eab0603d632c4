"""Step 1, the frequency sweep of thesis §11.3 / Fig. 11.3 (no rclpy).

At each frequency a wave-periodic excitation (the pair of runs x(t), x(t) + q of §9.1.3, here
voltages low + amplitude·shape + {0, q}) drives the stage; the Bouc-Wen part (11.2)-(11.3) is
identified in the ch. 11 form — input the displacement x, output the voltage u — by the analytic
method of ch. 9-10 with degree N = 1 (the columns swapped). The inverse of a shift-equivariant
hysteresis is one too, so run B's x is run A's shifted by q/kappa_x and the method applies.

Pairing of the samples: the plant and the driver publish with sample j the voltage held over
(t_{j-1}, t_j]; the staircase acts like the smooth input delayed by half a sample, so x(t_j)
is paired with (v_j + v_{j+1})/2 (without this the loop of a 100 Hz sweep at 50 kHz widens
and kappa_w, rho, sigma, n come out 5-15 % off), also when either stream misses a sample (a
subscription that matched a step later, a lost message): the streams share the clock.
Samples on other stamps (a driver and a sensor of their own) are paired with the voltage held
at the sample time, or interpolated across a gap of lost voltage messages (longer than
:data:`GAP_PERIODS` of the record's median period).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from piezo_stage.identification.cycles import CycleOptions
from piezo_stage.identification.errors import IdentificationError
from piezo_stage.identification.recording import Recording
from piezo_stage.model.excitation import ExcitationPlan

from .errors import CommissioningError

#: the Bouc-Wen parameters of Fig. 11.3 / Table 11.1, in the table's order
PARAMETERS = ("n", "sigma", "rho", "kappa_w", "kappa_x")
UNITS = {"n": "-", "sigma": "-", "rho": "1/m", "kappa_w": "V", "kappa_x": "V/m"}
#: a rig's voltage record: a step longer than this many of its median periods is a gap
GAP_PERIODS = 3.0
#: [s] a rig's voltage record without a value this long: the amplifier was not written in time
#: (the host fell behind real time), which bends the excitation's period
WRITE_STALL = 0.01
#: least samples per period of the excitation (40 per branch and a clean loop need ~ 500)
MIN_SAMPLES_PER_PERIOD = 200


class SweepError(CommissioningError):
    """A frequency of the sweep could not be identified (the message says which and why)."""


def default_frequencies(rate_hz: float) -> tuple[float, ...]:
    """The sweep's frequencies for a sensor at ``rate_hz``: those of 10, 20, 50, 100 Hz (Fig.
    11.3) it takes >= :data:`MIN_SAMPLES_PER_PERIOD` samples per period of, else rate/1000 and
    rate/500 (1 and 2 Hz at 1 kHz: 500 samples per period and more, as a period of a real-time
    rig bends by a millisecond of host jitter; the static part (11.2)-(11.3) is rate-independent
    there, m and c act far above)."""
    fits = tuple(f for f in (10.0, 20.0, 50.0, 100.0) if rate_hz / f >= MIN_SAMPLES_PER_PERIOD)
    return fits if len(fits) >= 2 else (rate_hz / 1000.0, rate_hz / 500.0)


@dataclass(frozen=True)
class SweepSettings:
    """What each frequency's runs look like (voltages [V])."""

    frequencies: tuple[float, ...] = (10.0, 20.0, 50.0, 100.0)
    low: float = 0.0
    amplitude: float = 300.0
    offset: float = 100.0  #: q of §9.1.3
    settle_periods: int = 2
    record_periods: int = 2
    waveform: str = "sine"  #: wave periodic and smooth: a triangle's corners ring the resonance

    def plan(self, frequency: float) -> ExcitationPlan:
        return ExcitationPlan(
            waveform=self.waveform,
            period=1.0 / frequency,
            low=self.low,
            amplitude=self.amplitude,
            offsets=(0.0, self.offset),
            settle_periods=self.settle_periods,
            record_periods=self.record_periods,
            hold="last",  # the last run ends at its minimum: no jump after the plan
        )

    def check(self, rate_hz: float, v_min: float, v_max: float) -> None:
        """Raise SweepError for a sweep the graph cannot run (rate, amplifier range)."""
        if not self.frequencies or any(not (math.isfinite(f) and f > 0) for f in self.frequencies):
            raise SweepError(f"frequencies must be > 0 Hz, got {self.frequencies}")
        if self.settle_periods < 1 or self.record_periods < 2:
            raise SweepError("need settle_periods >= 1 and record_periods >= 2")
        slow = [f for f in self.frequencies if rate_hz / f < MIN_SAMPLES_PER_PERIOD]
        if slow:
            raise SweepError(
                f"at {rate_hz:g} Hz the sensor takes < {MIN_SAMPLES_PER_PERIOD} samples per period "
                f"of {slow} Hz: sweep up to {rate_hz / MIN_SAMPLES_PER_PERIOD:g} Hz"
            )
        top = self.low + self.amplitude + max(0.0, self.offset)
        bottom = self.low + min(0.0, self.offset)
        if bottom < v_min or top > v_max:
            raise SweepError(
                f"the sweep spans {bottom:g}..{top:g} V, beyond the amplifier's "
                f"{v_min:g}..{v_max:g} V: "
                "it would clip; reduce --amplitude/--offset"
            )

    def to_dict(self) -> dict[str, Any]:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}


@dataclass
class Series:
    """What a run recorded: voltage samples (t_v, v), displacement samples (t_x, x, status), and
    the excitation's marks (stamp, run, steady)."""

    t_v: np.ndarray
    v: np.ndarray
    t_x: np.ndarray
    x: np.ndarray
    status: np.ndarray
    marks: list[tuple[float, int, bool]] = field(default_factory=list)


#: how far (a fraction of the excitation's span) a period's applied extreme may fall short of the
#: excitation's and not be clipping
CLIP_SHORT = 5e-3

#: a record whose displacement stamps are at least this fraction voltage stamps shares a clock
SAME_CLOCK = 0.9


def _same_clock(series: Series) -> bool:
    """Whether voltage and displacement are stamped by one clock (the sim graph's plant publishes
    both per step), though either stream may miss samples (a subscription matched a step later,
    a lost message)."""
    t_v, t_x = series.t_v, series.t_x
    if t_v.size < 2 or t_x.size < 2:
        return False
    i = np.clip(np.searchsorted(t_v, t_x), 1, t_v.size - 1)
    near = np.minimum(np.abs(t_v[i] - t_x), np.abs(t_v[i - 1] - t_x))
    return bool(np.count_nonzero(near <= 1e-9) >= SAME_CLOCK * t_x.size)


def paired(series: Series, delay: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, x, u) on the displacement samples (module docstring), NaN-free samples only;
    ``delay`` [s]: on other stamps, x(t) is paired with the voltage held at t - delay."""
    t_x, x = series.t_x, series.x
    if _same_clock(series):
        # v_j is held over (t_{j-1}, t_j]: at its middle t_j - dt/2 the staircase meets the
        # smooth input delayed by half a sample; x(t_j) pairs with (v_j + v_{j+1})/2, the
        # interpolation between two middles (across a lost voltage too)
        t_v, v = series.t_v, series.v
        u = np.interp(t_x, t_v - 0.5 * float(np.median(np.diff(t_v))), v)
    else:
        t_v, v, at = series.t_v, series.v, t_x - delay
        idx = np.searchsorted(t_v, at, side="right") - 1
        u = np.where(idx >= 0, v[np.clip(idx, 0, None)], np.nan)
        if t_v.size > 2:
            # lost voltage messages (best effort on a busy host): across such a gap the held
            # value is stale by up to the gap; the excitation is smooth, so interpolate there
            nxt = np.clip(idx + 1, 0, t_v.size - 1)
            gap = (idx >= 0) & (nxt > idx)
            gap[gap] = t_v[nxt[gap]] - t_v[idx[gap]] > GAP_PERIODS * np.median(np.diff(t_v))
            u[gap] = np.interp(at[gap], t_v, v)
    ok = np.isfinite(x) & np.isfinite(u)
    return t_x[ok], x[ok], u[ok]


def check_clipping(series: Series, plan: ExcitationPlan, v_min: float, v_max: float) -> None:
    """SweepError when, during the plan (from its first mark), the sensor reported out-of-range
    samples, or the applied voltage falls short of the excitation's extreme in most periods
    reaching it (an amplifier at a limit, known or not, cuts every period's top). Compared by
    value, period by period: a host that stalls the command stream at a peak holds the voltage
    there longer, and a lag shifts it, but neither takes the peak off."""
    t0 = min(m[0] for m in series.marks) if series.marks else -np.inf
    during_x = (series.t_x >= t0) & (series.t_x < t0 + plan.duration)
    bad = np.flatnonzero(during_x & (series.status != 0))
    if bad.size:
        raise SweepError(
            f"the sensor reported {bad.size} sample(s) out of its range or invalid (first at "
            f"t = {series.t_x[bad[0]] - t0:.6g} s into the excitation, status "
            f"{int(series.status[bad[0]])}): the sweep clips the sensor; reduce "
            "--amplitude/--offset or move the sensor"
        )
    t = series.t_v - t0
    during = (t >= 0) & (t < plan.duration)
    if np.count_nonzero(during) < 3:
        return
    t, v = t[during], series.v[during]
    asked = plan.values(t)
    tol = CLIP_SHORT * max(float(np.ptp(asked)), 1e-9)
    period = (t // plan.period).astype(np.int64)
    for name, sign in (("upper", 1.0), ("lower", -1.0)):
        top_v, top_asked = _per_period(period, sign * v), _per_period(period, sign * asked)
        reaching = top_asked >= np.max(top_asked) - tol
        short = reaching & (top_v < top_asked - tol)
        if 2 * np.count_nonzero(short) > np.count_nonzero(reaching):
            level = float(sign * np.median(top_v[short]))
            wanted = float(sign * np.max(top_asked))
            raise SweepError(
                f"the applied voltage stops at {level:.6g} V where the excitation asks "
                f"{wanted:.6g} V ({name} extreme), in {np.count_nonzero(short)} of the "
                f"{np.count_nonzero(reaching)} periods reaching it: the amplifier clips (limits "
                f"{v_min:g}/{v_max:g} V); reduce --amplitude/--offset"
            )


def _per_period(period: NDArray[np.int64], values: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each period's largest value (-inf for a period without samples)."""
    out = np.full(int(period.max()) + 1, -np.inf)
    np.maximum.at(out, period, values)
    return out


def run_recordings(
    series: Series, plan: ExcitationPlan, delay: float = 0.0
) -> tuple[Recording, Recording]:
    """The two runs (input x, output u): the steady part of each, with the sample at its end."""
    from piezo_stage.identification.io import intervals_from_marks

    t, x, u = paired(series, delay)
    intervals = intervals_from_marks(series.marks)
    if len(intervals) < 2:
        raise SweepError(f"the excitation marked {len(intervals)} run(s); 2 are needed")
    runs = []
    for run, start, _stop in intervals[:2]:
        steady_from = start + plan.settle_periods * plan.period
        hi = steady_from + plan.record_periods * plan.period
        dt = float(np.median(np.diff(t)))
        # one sample past the end: record_periods whole periods from the first sample
        same = _same_clock(series)
        keep = (t >= steady_from - 0.5 * dt) & (t <= hi + 1.5 * dt)
        if not same:
            # a rig's sensor clock is not the excitation's: the samples before the run's end
            # (after it the stage follows the next run's jump), over a little more than whole
            # periods (reaching back into the settled part; half the cycle check's 1 % period
            # tolerance more, for a period estimated from jittered samples)
            span = plan.record_periods * plan.period
            last = int(np.searchsorted(t, hi, side="left")) - 1
            first = int(np.searchsorted(t, t[max(last, 0)] - span - max(1.5 * dt, 0.005 * span)))
            keep = np.zeros_like(keep)
            keep[first : last + 1] = True
        u_run = u[keep]
        runs.append(
            Recording(
                t[keep],
                x[keep],
                u_run,
                name=f"{1 / plan.period:g} Hz run {run}",
                input_unit="m",
                output_unit="V",
            )
        )
    return runs[0], runs[1]


@dataclass(frozen=True)
class FrequencyResult:
    frequency: float
    kappa_x: float
    kappa_w: float
    rho: float
    sigma: float
    n: float
    y0: float  #: voltage offset of u = kappa_x x + kappa_w w + y0
    rms_error: float  #: [V]
    samples: int
    input_delay: float = 0.0  #: [s] command-to-sensor delay used in the pairing (rigs)

    def to_dict(self) -> dict[str, Any]:
        return {k: float(v) if k != "samples" else int(v) for k, v in asdict(self).items()}


#: [s] candidate command-to-sensor delays on a rig (amplifier group delay, link, sensor)
DELAY_GRID = tuple(np.arange(0.0, 1.61e-3, 2e-4))
DELAY_STEP = 1e-4


def identify_frequency(series: Series, plan: ExcitationPlan) -> FrequencyResult:
    """Identify (11.2)-(11.3) at one frequency (input x, output u); SweepError with the reason.

    On a rig (voltage and displacement on stamps of their own) the delay from the command's
    stamp to the stage's response is not known: 1 ms of it widens or narrows the loop of a
    2 Hz sweep by ~10 % of kappa_w. The delay taken is the one of :data:`DELAY_GRID` (then
    +-:data:`DELAY_STEP` around the best) whose identified model fits the loop best (least RMS
    error)."""
    if _same_clock(series):
        return _identify_at(series, plan, 0.0)
    tried: dict[float, FrequencyResult | SweepError] = {}

    def attempt(delay: float) -> None:
        key = round(delay, 7)
        if key not in tried and key >= 0.0:
            try:
                tried[key] = _identify_at(series, plan, key)
            except SweepError as exc:
                tried[key] = exc

    def best() -> FrequencyResult | None:
        ok = [r for r in tried.values() if isinstance(r, FrequencyResult)]
        return min(ok, key=lambda r: r.rms_error) if ok else None

    for delay in DELAY_GRID:
        attempt(float(delay))
    if (first := best()) is None:
        exc = next(iter(tried.values()))
        assert isinstance(exc, SweepError)
        if (stall := write_stall(series)) is not None:
            raise SweepError(f"{exc}; {stall}") from exc
        raise exc
    for delay in (first.input_delay - DELAY_STEP, first.input_delay + DELAY_STEP):
        attempt(delay)
    return best()  # type: ignore[return-value]


def write_stall(series: Series) -> str | None:
    """What a rig's voltage record says of its timing when a run fails: its longest interval
    without a value between the excitation's first and last marks, when over
    :data:`WRITE_STALL` (None otherwise)."""
    t = series.t_v
    if series.marks:
        t = t[(t >= series.marks[0][0]) & (t <= series.marks[-1][0])]
    if t.size < 2:
        return None
    gaps = np.diff(t)
    worst = int(np.argmax(gaps))
    if gaps[worst] <= WRITE_STALL:
        return None
    start = series.marks[0][0] if series.marks else float(t[0])
    return (
        f"the amplifier's voltage record has {int(np.count_nonzero(gaps > WRITE_STALL))} gap(s) "
        f"over {1e3 * WRITE_STALL:g} ms, the longest {1e3 * gaps[worst]:.0f} ms at "
        f"{float(t[worst]) - start:.2f} s: the host fell behind real time (a busy or slow host)"
    )


def _identify_at(series: Series, plan: ExcitationPlan, delay: float) -> FrequencyResult:
    from piezo_stage.identification.pipeline import IdentifyOptions, identify

    f = 1.0 / plan.period
    try:
        run_a, run_b = run_recordings(series, plan, delay)
        options = IdentifyOptions(
            degree=1,
            input_name="displacement",
            output_name="voltage",
            cycle=CycleOptions(steady_periods=plan.record_periods),
        )
        result = identify(run_a, run_b, options)
    except (IdentificationError, ValueError) as exc:
        raise SweepError(f"{f:g} Hz: {exc}") from exc
    p = result.parameters
    return FrequencyResult(
        frequency=f,
        kappa_x=p.kappa_x,
        kappa_w=p.kappa_w,
        rho=p.rho,
        sigma=p.sigma,
        n=p.n,
        y0=p.y0,
        rms_error=result.rms_error,
        samples=result.samples,
        input_delay=delay,
    )


def table(results: list[FrequencyResult]) -> dict[str, dict[str, float]]:
    """Table 11.1: smallest, largest and mean value of each parameter over the frequencies."""
    out = {}
    for name in PARAMETERS:
        values = np.array([getattr(r, name) for r in results])
        out[name] = {
            "min": float(values.min()),
            "max": float(values.max()),
            "mean": float(values.mean()),
        }
    return out
