"""Stateful time-varying PID (11.5, 11.17, 11.18) for a sampled loop, as §11.5 implements it.

x1 = x − yr; x0 by rectangle sums x0[k] = x0[k−1] + x1[k]·Δt[k] (right rectangles: the current
sample is included); x2 by Euler differences of the measurement
x2[k] = (x[k] − x[k−1])/Δt[k] − ẏr[k] (ẏr given, or the Euler difference of yr), optionally
through a first-order filter. Δt comes from
the caller's timestamps, with guards. Around the law: output clamp to the amplifier limits with
anti-windup, open loop with a hold voltage, bumpless open→closed transfer.

A thin node calls :meth:`TimeVaryingPID.update` once per period and publishes the returned
:class:`ControlOutput`; on a stale or invalid sample it calls :meth:`open_loop` instead and
:meth:`close_loop` once samples are valid again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import Enum, StrEnum
from typing import NamedTuple, TypeVar

from .errors import ControllerConfigError, MeasurementError
from .feedforward import Compensation, Feedforward, FeedforwardModel
from .laws import (
    PID,
    THESIS_GAINS,
    ControlLaw,
    Gains,
    LawState,
    check_law,
    law_named,
    law_state,
)
from .learning import FeedforwardTable


class AntiWindup(StrEnum):
    """What keeps x0 from winding up while u is clamped."""

    NONE = "none"
    CONDITIONAL = "conditional"  #: freeze x0 while integrating pushes u further out
    BACK_CALCULATION = "back_calculation"  #: bleed x0 back with time constant Tt


class OnClose(StrEnum):
    """x0 when the loop closes."""

    BUMPLESS = "bumpless"  #: u continuous across the closing
    RESET = "reset"  #: x0 = 0, as the §11.4 simulations start
    KEEP = "keep"  #: x0 as frozen while open


class Timing(StrEnum):
    """How a sample's Δt was classed (:func:`sample_timing`)."""

    OK = "ok"
    FIRST = "first"  #: no previous sample
    GAP = "gap"  #: Δt > dt_max
    NONPOSITIVE = "nonpositive_dt"  #: Δt <= 0: the sample is ignored


_E = TypeVar("_E", bound=Enum)


def _member(kind: type[_E], name: str, value: object) -> _E:
    """``kind(value)``, else :class:`ControllerConfigError` naming the choices."""
    try:
        return kind(value)
    except ValueError:
        names = ", ".join(str(m.value) for m in kind)
        raise ControllerConfigError(f"{name} must be one of {names}, got {value!r}") from None


# ----------------------------------------------------------------- the law's pieces
def check_sample(
    t: float, x_measured: float, yr: float, yr_dot: float | None, yr_ddot: float
) -> None:
    """Raise :class:`MeasurementError` unless every given value is finite."""
    if math.isfinite(t) and math.isfinite(x_measured) and math.isfinite(yr):
        if (yr_dot is None or math.isfinite(yr_dot)) and math.isfinite(yr_ddot):
            return
    for name, value in (("t", t), ("x_measured", x_measured), ("yr", yr)):
        if not math.isfinite(value):
            raise MeasurementError(
                f"{name} must be finite, got {value}; open the loop on invalid samples"
            )
    for name, given in (("yr_dot", yr_dot), ("yr_ddot", yr_ddot)):
        if given is not None and not math.isfinite(given):
            raise MeasurementError(f"{name} must be finite, got {given}")


def sample_timing(t_prev: float | None, t: float, dt_max: float) -> tuple[Timing, float]:
    """Δt[k] = t[k] − t[k−1] from the caller's stamps (§11.5), and its class: FIRST (no
    t[k−1], Δt = 0), NONPOSITIVE (Δt <= 0), GAP (Δt > dt_max) or OK.
    """
    if t_prev is None:
        return Timing.FIRST, 0.0
    dt = t - t_prev
    if not dt > 0:
        return Timing.NONPOSITIVE, dt
    return (Timing.OK if dt <= dt_max else Timing.GAP), dt


def x2_filtered(x2f: float, x: float, x_prev: float, yr_dot: float, dt: float, tau: float) -> float:
    """x2[k] = (x[k] − x[k−1])/Δt[k] − ẏr[k] (x2 = ẋ − ẏr, 11.4, by Euler differences) through
    the first-order filter x2f[k] = x2f[k−1] + α·(x2[k] − x2f[k−1]), α = Δt/(τ + Δt) (τ = 0:
    no filter).
    """
    x2 = (x - x_prev) / dt - yr_dot
    return x2f + dt / (tau + dt) * (x2 - x2f)


def bumpless_x0(
    gains: Gains, u: float, u_ff: float, x1: float, x2: float, law: ControlLaw = PID
) -> float:
    """x0 that makes the law's u at closing (t = 0) plus u_ff equal the output ``u`` being
    applied: the bumpless open→closed transfer. The law is affine in x0 there, so
    x0 = (u − u_ff − u(x0 = 0)) / (∂u/∂x0); for (11.5): −(u − u_ff + k1·x1 + k2·x2)/k0.
    """
    at_zero = sum(law.split(gains, 0.0, 0.0, x1, x2))
    return float((u - u_ff - at_zero) / law.x0_coefficient(gains, 0.0))


def back_calculation(
    x0: float, u: float, u_raw: float, dt: float, tracking_time: float, k0: float
) -> float:
    """x0 after back-calculation anti-windup: x0 += min(Δt/Tt, 1)·(u − u_raw)/(−k0), so that
    −k0·x0 moves u_raw towards the clamped u with time constant Tt.
    """
    gain = min(dt / tracking_time, 1.0) if dt > 0 else 0.0
    return x0 + gain * (u - u_raw) / (-k0)


def integration_winds_up(excess: float, x0_coefficient: float, step: float) -> bool:
    """Conditional anti-windup (clamping): the increment x0 += ``step`` is skipped when u is
    beyond a limit by ``excess`` (u − clamp(u) ≠ 0) and ∂u/∂x0·step has the same sign.
    """
    return excess != 0.0 and excess * x0_coefficient * step > 0


#: [V] the thesis's amplifier gives ±450 V (§11.2.1)
THESIS_AMPLIFIER = 450.0

# members looked up once: update() runs once per sample
_FEEDBACK, _FEEDFORWARD = Compensation.FEEDBACK, Compensation.FEEDFORWARD
_OK, _NONPOSITIVE = Timing.OK, Timing.NONPOSITIVE


@dataclass(frozen=True)
class ControllerConfig:
    """Law, gains and the real-loop features around it.

    - ``u_min``/``u_max``: amplifier limits [V] (thesis amplifier: ±450 V, §11.2.1).
    - ``anti_windup``: ``"conditional"`` (freeze x0 while u is beyond a limit and integrating
      would push it further), ``"back_calculation"`` (bleed x0 back with time constant
      ``tracking_time``) or ``"none"``.
    - ``tracking_time``: Tt [s] of back-calculation; None → sqrt(Ti·Td), Ti = k1/k0, Td = k2/k1.
    - ``derivative_tau``: time constant [s] of the first-order filter on x2; 0 = off (thesis).
    - ``hold_voltage``: u while the loop is open; None → the last output.
    - ``on_close``: x0 at closing: ``"bumpless"`` (x0 chosen so that u is continuous),
      ``"reset"`` (x0 = 0, as the §11.4 simulations start) or ``"keep"`` (x0 frozen while open).
    - ``dt_max``: a larger Δt between samples is a gap: no integration, x2 re-baselined.
    - ``compensation``: ``feedback`` (the law alone), ``feedforward`` (u_ff of ``feedforward``
      alone) or ``both`` (u_ff + the law), for tracking (see :mod:`.feedforward`).
    - ``feedforward_table``: u_ff read from a table (:mod:`.learning`: the staircase a sampled
      loop needs, learned or computed from the model) at the time since the first update,
      instead of the model stepped along yr.
    """

    mode: str = PID.name
    gains: Gains = THESIS_GAINS
    u_min: float = -math.inf
    u_max: float = math.inf
    anti_windup: AntiWindup = AntiWindup.CONDITIONAL
    tracking_time: float | None = None
    derivative_tau: float = 0.0
    hold_voltage: float | None = None
    on_close: OnClose = OnClose.BUMPLESS
    dt_max: float = 0.1
    compensation: Compensation = Compensation.FEEDBACK
    feedforward: FeedforwardModel | None = None
    feedforward_table: FeedforwardTable | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "mode", check_law(self.mode))
        for name, kind in (
            ("compensation", Compensation),
            ("anti_windup", AntiWindup),
            ("on_close", OnClose),
        ):
            object.__setattr__(self, name, _member(kind, name, getattr(self, name)))

    @property
    def law(self) -> ControlLaw:
        """The registered law ``mode`` names."""
        return law_named(self.mode)

    def validate(self) -> None:
        """Raise :class:`ControllerConfigError` / :class:`GainError` for an unusable
        configuration.
        """
        self.gains.validate(self.mode)
        if math.isnan(self.u_min) or math.isnan(self.u_max) or not self.u_min < self.u_max:
            raise ControllerConfigError(f"need u_min < u_max, got [{self.u_min}, {self.u_max}]")
        if self.on_close is OnClose.BUMPLESS and self.law.x0_coefficient(self.gains, 0.0) == 0:
            raise ControllerConfigError(
                f"bumpless transfer solves u for x0 and needs u to depend on x0 (k0 > 0 for "
                f"{self.mode})"
            )
        if self.anti_windup is AntiWindup.BACK_CALCULATION:
            self._validate_back_calculation()
        if not (math.isfinite(self.derivative_tau) and self.derivative_tau >= 0):
            raise ControllerConfigError(f"derivative_tau must be >= 0 s, got {self.derivative_tau}")
        if self.hold_voltage is not None and not math.isfinite(self.hold_voltage):
            raise ControllerConfigError(f"hold_voltage must be finite, got {self.hold_voltage}")
        if not (self.dt_max > 0):
            raise ControllerConfigError(f"dt_max must be > 0 s, got {self.dt_max}")
        if (
            self.compensation.feeds_forward
            and self.feedforward is None
            and self.feedforward_table is None
        ):
            raise ControllerConfigError(
                f"compensation {self.compensation.value} needs a "
                "feedforward model (a dynamic parameter set) or a feedforward table"
            )

    def _validate_back_calculation(self) -> None:
        if self.gains.k0 <= 0:
            raise ControllerConfigError(
                "back-calculation anti-windup acts through x0 and needs k0 > 0"
            )
        tt = self.tracking_time
        if tt is not None and not (math.isfinite(tt) and tt > 0):
            raise ControllerConfigError(f"tracking_time must be > 0 s, got {tt}")
        if tt is None and self.gains.k2 <= 0:
            raise ControllerConfigError(
                "default tracking_time sqrt(Ti·Td) needs k2 > 0; give tracking_time"
            )

    @property
    def effective_tracking_time(self) -> float:
        """Tt of back-calculation [s]: ``tracking_time`` or sqrt(Ti·Td) = sqrt(k2/k0)."""
        if self.tracking_time is not None:
            return self.tracking_time
        return math.sqrt(self.gains.k2 / self.gains.k0)  # Ti·Td = (k1/k0)·(k2/k1)

    def clamp(self, u: float) -> float:
        """Clamp ``u`` to [u_min, u_max], the amplifier limits."""
        return min(max(u, self.u_min), self.u_max)


class OwnFrame(NamedTuple):
    """An axis of a coupled stage in its own frame (docs/design.md section 10): its own
    displacement y* [m] and own reference (y*_d [m], ẏ*_d [m/s], ÿ*_d [m/s²]), what its
    feedforward inverts when the coupling is compensated.
    """

    x: float
    xd: float
    vd: float
    ad: float


@dataclass(frozen=True)
class ControlOutput:
    """One controller period; field names match ``piezo_stage_msgs/msg/ControllerState``.

    ``u = clamp(u_pid + u_excitation + u_ff)`` when the loop is closed (u_pid = u_excitation = 0
    under ``feedforward``, u_ff = 0 under ``feedback``), the (clamped) hold voltage when open.
    ``timing`` is ``"ok"``, ``"first"`` (no previous sample: x2 from ẏr only, no integration),
    ``"gap"`` (Δt > dt_max: likewise) or ``"nonpositive_dt"`` (sample ignored, the previous
    output repeated).
    """

    t: float
    dt: float
    mode: str
    loop_closed: bool
    reference: float
    x0: float
    x1: float
    x2: float
    u: float
    u_pid: float
    u_excitation: float
    saturated: bool
    timing: Timing = Timing.OK
    u_ff: float = 0.0


class TimeVaryingPID:
    """Sampled time-varying PID of thesis ch. 11 (see module docstring).

    ``closed=True`` starts with the loop closed and x0 = ``x0_initial`` at the first sample
    (the §11.4 simulations: x0(0) = 0); ``closed=False`` starts open, holding ``hold_voltage``
    (or 0 V), until :meth:`close_loop`.
    """

    def __init__(
        self, config: ControllerConfig, *, closed: bool = True, x0_initial: float = 0.0
    ) -> None:
        config.validate()
        self._config = config
        self._law = config.law
        self._x0_initial = float(x0_initial)
        self._start_closed = closed
        self.reset()

    # ----------------------------------------------------------------- state
    def reset(self) -> None:
        """Forget all history (previous sample, x0, filter, last output)."""
        self._t_prev: float | None = None
        self._x_prev = 0.0
        self._yr_prev = 0.0
        self._x2f = 0.0
        self._x0 = self._x0_initial
        self._u = self._config.clamp(self._config.hold_voltage or 0.0)
        self._closed = self._start_closed
        self._pending_close = False
        self._t_close: float | None = None
        self._hold: float | None = None
        self._last: ControlOutput | None = None
        self._u_ff = 0.0
        self._yr = 0.0
        self._last_raw = self._u  # the last unclamped output
        self._state = law_state(self._law, self._config.gains)  # what the law learns, afresh
        self._t_table: float | None = None  # the table's time origin: the first update
        self.table_index = -1  # the table's sample the last update read (-1: none)
        model = self._config.feedforward
        self._ff = Feedforward(model) if model is not None else None

    def start_table_at(self, t: float) -> None:
        """Index the feedforward table from ``t`` [s] (default: the first update's time)."""
        if self._t_table is None:
            self._t_table = float(t)

    @property
    def config(self) -> ControllerConfig:
        """The configuration in use (see :meth:`reconfigure`)."""
        return self._config

    @property
    def loop_closed(self) -> bool:
        """Whether the loop is closed or closes at the next sample (:meth:`close_loop`)."""
        return self._closed or self._pending_close

    @property
    def x0(self) -> float:
        """The integral x0 = ∫ x1 dt (11.4) [m s]."""
        return self._x0

    @property
    def u(self) -> float:
        """The last output [V]."""
        return self._u

    @property
    def law_state(self) -> LawState | None:
        """What the law has learned (the adaptive law's estimate); None for a law that does not
        learn.
        """
        return self._state

    @property
    def last_output(self) -> ControlOutput | None:
        """The last :class:`ControlOutput`; None before the first update."""
        return self._last

    def reconfigure(self, config: ControllerConfig) -> None:
        """Swap gains/law/limits keeping the state; with the loop closed and k0 changed, x0 is
        rescaled so that k0·x0 (and hence u) stays continuous when ``on_close`` is bumpless.
        """
        config.validate()
        old = self._config
        if (
            self._closed
            and config.on_close is OnClose.BUMPLESS
            and old.gains.k0 > 0
            and config.gains.k0 != old.gains.k0
        ):
            self._x0 *= old.gains.k0 / config.gains.k0
        if config.feedforward != old.feedforward:
            self._ff = Feedforward(config.feedforward) if config.feedforward is not None else None
        if config.mode != old.mode or self._state is None:
            self._state = law_state(config.law, config.gains)
            if self._state is not None and self._closed:
                self._state.rebase(self._yr)  # it learns from here
        else:
            self._state.configure(config.gains)
        self._config = config
        self._law = config.law

    def open_loop(self, hold: float | None = None) -> None:
        """Open the loop: u = ``hold``, else ``config.hold_voltage``, else the last output
        (clamped).
        """
        if hold is not None and not math.isfinite(hold):
            raise MeasurementError(f"hold voltage must be finite, got {hold}")
        if hold is None:
            hold = self._config.hold_voltage if self._config.hold_voltage is not None else self._u
        self._hold = float(hold)
        self._closed = False
        self._pending_close = False
        if self._ff is not None:
            self._ff.unseed()  # the stage leaves x_d: re-seeded from it at closing

    def close_loop(self) -> None:
        """Close the loop at the next :meth:`update` (x0 set per ``config.on_close``, sine
        phase 0).
        """
        if not self._closed:
            self._pending_close = True

    # ----------------------------------------------------------------- period
    def update(
        self,
        t: float,
        x_measured: float,
        yr: float = 0.0,
        yr_dot: float | None = None,
        yr_ddot: float = 0.0,
        own: OwnFrame | None = None,
    ) -> ControlOutput:
        """One period at time ``t`` [s] with measured position ``x_measured`` [m] and reference
        ``yr`` [m] (and ẏr [m/s] if known; else its Euler difference is used; ÿr [m/s²] for the
        feedforward's m·ÿr term). ``own``: the model feedforward is seeded and stepped in the
        axis's own frame instead (a coupled stage); the PID still acts on x − yr.
        """
        check_sample(t, x_measured, yr, yr_dot, yr_ddot)
        cfg = self._config
        timing, dt = sample_timing(self._t_prev, t, cfg.dt_max)
        if timing is _NONPOSITIVE:
            assert self._last is not None  # a previous sample exists
            return replace(self._last, dt=dt, timing=timing)
        x1 = x_measured - yr
        x2 = self._x2(timing, dt, x_measured, yr, yr_dot)
        self._yr = yr
        self._t_prev, self._x_prev, self._yr_prev = t, x_measured, yr
        if self._t_table is None:
            self._t_table = t
        if own is None:
            u_ff = self._feedforward_term(t, x_measured, yr, yr_dot, yr_ddot)
        else:
            u_ff = self._feedforward_term(t, own.x, own.xd, own.vd, own.ad)
        self._u_ff = u_ff
        if self._pending_close:
            self._close_now(t, x1, x2)
        elif self._closed and self._t_close is None:
            self._t_close = t  # started closed: phase origin at the first sample
            if self._state is not None:
                self._state.rebase(yr)
        elif self._closed and timing is _OK:
            self._integrate(t, x1, x2, dt)
        x0_used = self._x0
        if self._closed:
            u_pid, u_exc, u_raw = self._closed_output(t, dt, x1, x2, u_ff)
        else:
            u_pid = u_exc = 0.0
            u_raw = self._hold if self._hold is not None else self._u
            self._u = cfg.clamp(u_raw)
        self._last_raw = u_raw
        self._last = ControlOutput(
            t=t,
            dt=dt,
            mode=cfg.mode,
            loop_closed=self._closed,
            reference=yr,
            x0=x0_used,
            x1=x1,
            x2=x2,
            u=self._u,
            u_pid=u_pid,
            u_excitation=u_exc,
            saturated=bool(self._u != u_raw),
            timing=timing,
            u_ff=u_ff,
        )
        return self._last

    def _x2(
        self, timing: Timing, dt: float, x_measured: float, yr: float, yr_dot: float | None
    ) -> float:
        """x2 of this sample (:func:`x2_filtered`); after no sample or a gap, x2 = −ẏr."""
        if timing is _OK:
            yd = yr_dot if yr_dot is not None else (yr - self._yr_prev) / dt
            self._x2f = x2_filtered(
                self._x2f, x_measured, self._x_prev, yd, dt, self._config.derivative_tau
            )
        else:
            self._x2f = -(yr_dot or 0.0)
        return self._x2f

    def _feedforward_term(
        self, t: float, x_measured: float, yr: float, yr_dot: float | None, yr_ddot: float
    ) -> float:
        """u_ff of this sample while the loop is (or closes) closed: the table's value at the
        time since the first update, or the model stepped along yr (seeded at the closing).
        """
        cfg = self._config
        table = cfg.feedforward_table
        if cfg.compensation is _FEEDBACK or not (self._closed or self._pending_close):
            return 0.0
        if table is not None:
            assert self._t_table is not None  # set at the first update
            self.table_index = table.index(t - self._t_table)
            return float(table.u[self.table_index])
        if self._ff is None:
            return 0.0
        if not self._ff.seeded:  # closing now, or the first sample of a closed start
            self._ff.seed(x_measured, self._u)
        return self._ff.step(yr, yr_dot if yr_dot is not None else 0.0, yr_ddot)

    def _closed_output(
        self, t: float, dt: float, x1: float, x2: float, u_ff: float
    ) -> tuple[float, float, float]:
        """u_pid, u_excitation and the unclamped u = u_pid + u_excitation + u_ff of the law
        (11.5, 11.17, 11.18); sets the clamped output and applies back-calculation.
        """
        cfg = self._config
        assert self._t_close is not None  # set whenever the loop is closed
        if cfg.compensation is _FEEDFORWARD:
            u_pid = u_exc = 0.0
        else:
            u_pid, u_exc = self._law_parts(t - self._t_close, x1, x2)
            if (
                self._state is not None
                and cfg.compensation is _FEEDBACK
                and 0 < dt <= cfg.dt_max
                and self._u == self._last_raw
            ):  # not while the amplifier limits u, nor beside a model's feedforward
                self._state.adapt(x1, x2, self._yr, dt)
        u_raw = u_pid + u_exc + u_ff
        self._u = cfg.clamp(u_raw)
        if (
            cfg.anti_windup is AntiWindup.BACK_CALCULATION
            and self._u != u_raw
            and cfg.compensation is not _FEEDFORWARD
        ):
            self._x0 = back_calculation(
                self._x0, self._u, u_raw, dt, cfg.effective_tracking_time, cfg.gains.k0
            )
        return u_pid, u_exc, u_raw

    def _law_parts(self, tau: float, x1: float, x2: float) -> tuple[float, float]:
        """(u_pid, u_excitation) of the law at ``tau`` [s] since closing, its state's term in
        the latter.
        """
        u_pid, u_exc = self._law.split(self._config.gains, tau, self._x0, x1, x2)
        if self._state is not None:
            return float(u_pid), float(u_exc) + self._state.term(self._yr)
        return float(u_pid), float(u_exc)

    def _close_now(self, t: float, x1: float, x2: float) -> None:
        """Open→closed transfer at time t (the new phase origin: sin(2πf·0) = 0)."""
        cfg = self._config
        if cfg.on_close is OnClose.BUMPLESS:
            self._x0 = bumpless_x0(cfg.gains, self._u, self._u_ff, x1, x2, self._law)
        elif cfg.on_close is OnClose.RESET:
            self._x0 = 0.0
        if self._state is not None:
            self._state.rebase(self._yr)
        self._closed, self._pending_close, self._t_close, self._hold = True, False, t, None

    def _integrate(self, t: float, x1: float, x2: float, dt: float) -> None:
        """x0 += x1·Δt (rectangle sum, §11.5). Conditional anti-windup (clamping) skips the
        increment when u, computed before it, already violates a limit and the increment would
        push u further beyond it.
        """
        cfg = self._config
        step = x1 * dt
        if cfg.compensation is _FEEDFORWARD:
            return  # the law is not applied: its integral is not accumulated
        if cfg.anti_windup is AntiWindup.CONDITIONAL:
            assert self._t_close is not None  # integrating: the loop is closed
            tau = t - self._t_close
            u_pid, u_exc = self._law_parts(tau, x1, x2)
            u_now = u_pid + u_exc + self._u_ff
            coefficient = self._law.x0_coefficient(cfg.gains, tau)
            if integration_winds_up(u_now - cfg.clamp(u_now), coefficient, step):
                return
        self._x0 += step


def closed_pid(
    gains: Gains,
    u_min: float,
    u_max: float,
    compensation: Compensation,
    feedforward: FeedforwardModel | None,
    table: FeedforwardTable | None = None,
    *,
    mode: str = PID.name,
    hold_voltage: float | None = None,
) -> TimeVaryingPID:
    """The law a core run holds (tracking, a scanner's axes, a raster's): ``mode`` (11.5, 11.17,
    11.18) with ``gains`` and output limits, ``compensation``'s feedforward (§11.5: the model,
    and its ``table`` when one is sampled), reset on closing, closed from the start.
    """
    config = ControllerConfig(
        mode=mode,
        gains=gains,
        u_min=u_min,
        u_max=u_max,
        on_close=OnClose.RESET,
        hold_voltage=hold_voltage,
        compensation=compensation,
        feedforward=feedforward,
        feedforward_table=table,
    )
    return TimeVaryingPID(config, closed=True)
