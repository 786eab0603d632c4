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

from .errors import ControllerConfigError, MeasurementError
from .feedforward import Compensation, Feedforward, FeedforwardModel
from .laws import THESIS_GAINS, Gains, check_law, excitation_term, pid_term, x0_coefficient
from .learning import FeedforwardTable

ANTI_WINDUP: tuple[str, ...] = ("none", "conditional", "back_calculation")
ON_CLOSE: tuple[str, ...] = ("bumpless", "reset", "keep")

#: ControlOutput.timing values
TIMING_OK, TIMING_FIRST, TIMING_GAP, TIMING_NONPOSITIVE = "ok", "first", "gap", "nonpositive_dt"
# members looked up once: an Enum class attribute costs a metaclass __getattr__ per access, and
# update() runs once per sample
_FEEDBACK, _FEEDFORWARD = Compensation.FEEDBACK, Compensation.FEEDFORWARD


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

    mode: str = "pid"
    gains: Gains = THESIS_GAINS
    u_min: float = -math.inf
    u_max: float = math.inf
    anti_windup: str = "conditional"
    tracking_time: float | None = None
    derivative_tau: float = 0.0
    hold_voltage: float | None = None
    on_close: str = "bumpless"
    dt_max: float = 0.1
    compensation: Compensation = Compensation.FEEDBACK
    feedforward: FeedforwardModel | None = None
    feedforward_table: FeedforwardTable | None = None

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "compensation", Compensation(self.compensation))
        except ValueError:
            names = ", ".join(c.value for c in Compensation)
            raise ControllerConfigError(
                f"compensation must be one of {names}, got {self.compensation!r}"
            ) from None

    def validate(self) -> None:
        """Raise :class:`ControllerConfigError` / :class:`GainError` for an unusable
        configuration.
        """
        check_law(self.mode)
        self.gains.validate(self.mode)
        if math.isnan(self.u_min) or math.isnan(self.u_max) or not self.u_min < self.u_max:
            raise ControllerConfigError(f"need u_min < u_max, got [{self.u_min}, {self.u_max}]")
        if self.anti_windup not in ANTI_WINDUP:
            raise ControllerConfigError(
                f"anti_windup must be one of {ANTI_WINDUP}, got {self.anti_windup!r}"
            )
        if self.on_close not in ON_CLOSE:
            raise ControllerConfigError(
                f"on_close must be one of {ON_CLOSE}, got {self.on_close!r}"
            )
        if self.on_close == "bumpless" and self.gains.k0 <= 0:
            raise ControllerConfigError("bumpless transfer solves u for x0 and needs k0 > 0")
        if self.anti_windup == "back_calculation":
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
        if not (math.isfinite(self.derivative_tau) and self.derivative_tau >= 0):
            raise ControllerConfigError(f"derivative_tau must be >= 0 s, got {self.derivative_tau}")
        if self.hold_voltage is not None and not math.isfinite(self.hold_voltage):
            raise ControllerConfigError(f"hold_voltage must be finite, got {self.hold_voltage}")
        if not (self.dt_max > 0):
            raise ControllerConfigError(f"dt_max must be > 0 s, got {self.dt_max}")
        if (
            self.compensation is not Compensation.FEEDBACK
            and self.feedforward is None
            and self.feedforward_table is None
        ):
            raise ControllerConfigError(
                f"compensation {self.compensation.value} needs a "
                "feedforward model (a dynamic parameter set) or a feedforward table"
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
    timing: str = TIMING_OK
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
        self._t_table: float | None = None  # the table's time origin: the first update
        self.table_index = -1  # the table's sample the last update read (-1: none)
        model = self._config.feedforward
        self._ff = Feedforward(model) if model is not None else None

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
            and config.on_close == "bumpless"
            and old.gains.k0 > 0
            and config.gains.k0 != old.gains.k0
        ):
            self._x0 *= old.gains.k0 / config.gains.k0
        if config.feedforward != old.feedforward:
            self._ff = Feedforward(config.feedforward) if config.feedforward is not None else None
        self._config = config

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
    ) -> ControlOutput:
        """One period at time ``t`` [s] with measured position ``x_measured`` [m] and reference
        ``yr`` [m] (and ẏr [m/s] if known; else its Euler difference is used; ÿr [m/s²] for the
        feedforward's m·ÿr term).
        """
        for name, value in (("t", t), ("x_measured", x_measured), ("yr", yr)):
            if not math.isfinite(value):
                raise MeasurementError(
                    f"{name} must be finite, got {value}; open the loop on invalid samples"
                )
        for name, given in (("yr_dot", yr_dot), ("yr_ddot", yr_ddot)):
            if given is not None and not math.isfinite(given):
                raise MeasurementError(f"{name} must be finite, got {given}")
        cfg = self._config
        if self._t_prev is None:
            timing, dt = TIMING_FIRST, 0.0
        else:
            dt = t - self._t_prev
            if not dt > 0:
                assert self._last is not None
                return replace(self._last, dt=dt, timing=TIMING_NONPOSITIVE)
            timing = TIMING_OK if dt <= cfg.dt_max else TIMING_GAP

        x1 = x_measured - yr
        if timing == TIMING_OK:
            yd = yr_dot if yr_dot is not None else (yr - self._yr_prev) / dt
            x2_raw = (x_measured - self._x_prev) / dt - yd
            alpha = dt / (cfg.derivative_tau + dt)
            self._x2f += alpha * (x2_raw - self._x2f)
        else:
            self._x2f = -(yr_dot or 0.0)
        x2 = self._x2f
        self._t_prev, self._x_prev, self._yr_prev = t, x_measured, yr

        u_ff = 0.0
        table = cfg.feedforward_table
        if self._t_table is None:
            self._t_table = t
        use_ff = (self._ff is not None or table is not None) and cfg.compensation is not _FEEDBACK
        if use_ff and (self._closed or self._pending_close):
            if table is not None:
                self.table_index = table.index(t - self._t_table)
                u_ff = float(table.u[self.table_index])
            else:
                assert self._ff is not None
                if not self._ff.seeded:  # closing now, or the first sample of a closed start
                    self._ff.seed(x_measured, self._u)
                u_ff = self._ff.step(yr, yr_dot if yr_dot is not None else 0.0, yr_ddot)
        self._u_ff = u_ff
        if self._pending_close:
            self._close_now(t, x1, x2)
        elif self._closed and self._t_close is None:
            self._t_close = t  # started closed: phase origin at the first sample
        elif self._closed and timing == TIMING_OK:
            self._integrate(t, x1, x2, dt)

        if self._closed:
            assert self._t_close is not None  # set whenever the loop is closed
            tau = t - self._t_close
            u_pid = float(pid_term(cfg.gains, self._x0, x1, x2))
            u_exc = float(excitation_term(cfg.mode, cfg.gains, tau, self._x0))
            if cfg.compensation is _FEEDFORWARD:
                u_pid = u_exc = 0.0
            u_raw = u_pid + u_exc + u_ff
            x0_used = self._x0
            self._u = cfg.clamp(u_raw)
            if (
                cfg.anti_windup == "back_calculation"
                and self._u != u_raw
                and cfg.compensation is not _FEEDFORWARD
            ):
                gain = min(dt / cfg.effective_tracking_time, 1.0) if dt > 0 else 0.0
                self._x0 += gain * (self._u - u_raw) / (-cfg.gains.k0)
        else:
            u_pid = u_exc = 0.0
            u_raw = self._hold if self._hold is not None else self._u
            x0_used = self._x0
            self._u = cfg.clamp(u_raw)
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

    def _close_now(self, t: float, x1: float, x2: float) -> None:
        """Open→closed transfer at time t (the new phase origin: sin(2πf·0) = 0)."""
        cfg = self._config
        if cfg.on_close == "bumpless":
            # u(t_close) = −k0·x0 − k1·x1 − k2·x2 + u_ff must equal the output being applied now.
            self._x0 = (
                -(self._u - self._u_ff + cfg.gains.k1 * x1 + cfg.gains.k2 * x2) / cfg.gains.k0
            )
        elif cfg.on_close == "reset":
            self._x0 = 0.0
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
        if cfg.anti_windup == "conditional":
            assert self._t_close is not None  # integrating: the loop is closed
            tau = t - self._t_close
            u_now = float(
                pid_term(cfg.gains, self._x0, x1, x2)
                + excitation_term(cfg.mode, cfg.gains, tau, self._x0)
                + self._u_ff
            )
            excess = u_now - cfg.clamp(u_now)
            if excess != 0.0 and excess * x0_coefficient(cfg.mode, cfg.gains, tau) * step > 0:
                return
        self._x0 += step
