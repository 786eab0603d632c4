"""Supervision of a running loop: every decision around :class:`TimeVaryingPID` that is not the law.

One object serves the ``controller`` node (samples from a topic) and the composed rig loop
(samples from the sensor by direct call), so both forms decide alike:

- **samples**: a sample that is not OK (or not finite) opens the loop and holds the output
  (``hold_voltage``, else the last output); the fault is latched until :meth:`LoopSupervisor.close`;
- **gaps**: a silence of the sensor up to ``max_gap`` holds the output (no step: the last
  command stays on the amplifier) and resumes at the next sample, counted in ``gaps_held``; a
  longer one opens the loop like an invalid sample;
- **start_closed**: the loop closes at the first valid sample; until then an invalid sample or a
  gap only delays the closing (``waiting``). Within ``start_grace`` of that first closing, a gap
  or an invalid sample opens the loop and re-arms start_closed instead of latching a fault: a
  graph's start (DDS matching, a first step that pays for first calls while a shallow sensor
  queue overflows) must not leave a loop that was asked to start closed open for good;
- **the scheduled window**: ``open_at`` (a time of the loop's clock) or ``open_after`` (after
  start_closed closed the loop) opens it holding the hold voltage, and ``open_duration`` later
  it closes again (§11.5's perturbation);
- **frames**: the law works on u − ``u_bias`` (§11.5 closes the loop "with a set point for the
  control around 200 V"); :meth:`LoopSupervisor.command` gives amplifier volts.
- **saturation**: each step counts whether the law's output was clamped to the amplifier's
  limits (two integer adds, nothing allocated or logged per sample);
  :meth:`LoopSupervisor.diagnose`, called by the /diagnostics timer (every second), reports the
  share of the steps saturated since its previous call (:class:`SaturationWindow`), WARN when
  any was.

Gain verification (Theorem 4 and the sampled-loop check) is :class:`GainCheck`. No rclpy; the
caller's clock is whatever stamps its samples (sensor sample clock, node clock or sim time).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import Callable

from .bounds import Bounds, NominalPlant
from .controller import ControllerConfig, ControlOutput, OwnFrame, TimeVaryingPID
from .discrete import check_sampled_loop
from .errors import ControllerConfigError

#: a sample later than this many periods after the previous one starts a gap
GAP_PERIODS = 1.5


class Health(enum.IntEnum):
    """Level of :meth:`LoopSupervisor.diagnose` (the values of diagnostic_msgs' levels)."""

    OK = 0
    WARN = 1
    ERROR = 2


class Window(enum.Enum):
    """Where the scheduled open/close window is."""

    PENDING = "pending"
    OPEN = "open"
    DONE = "done"


class Gap(enum.Enum):
    """What :meth:`LoopSupervisor.check_gap` found."""

    NONE = "none"  # the newest sample is recent: step
    HELD = "held"  # a gap shorter than max_gap: hold the output, do not step
    OPENED = "opened"  # longer: the loop was opened (send :meth:`LoopSupervisor.hold_command`)
    NO_SAMPLE = "no_sample"  # no valid sample yet


@dataclass(frozen=True)
class SupervisionConfig:
    """Settings of a :class:`LoopSupervisor` (seconds, volts)."""

    rate_hz: float
    u_bias: float = 0.0
    u_min: float = -math.inf  # amplifier limits [V]: the law's limits are these − u_bias
    u_max: float = math.inf
    start_closed: bool = False
    max_gap: float = 0.02
    start_grace: float = 1.0  # s after start_closed first closed the loop: faults re-arm it
    open_at: float = -1.0
    open_after: float = -1.0
    open_duration: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate_hz) and self.rate_hz > 0):
            raise ControllerConfigError(f"rate_hz must be > 0, got {self.rate_hz}")
        if not math.isfinite(self.u_bias):
            raise ControllerConfigError(f"u_bias must be finite, got {self.u_bias}")
        if not self.max_gap >= GAP_PERIODS / self.rate_hz:
            raise ControllerConfigError(
                f"max_gap must be at least {GAP_PERIODS} periods ({GAP_PERIODS / self.rate_hz:g} s "
                f"at {self.rate_hz:g} Hz), got {self.max_gap}"
            )
        if not 0 <= self.start_grace < math.inf:
            raise ControllerConfigError(f"start_grace must be >= 0 s, got {self.start_grace}")
        if not self.open_duration >= 0:
            raise ControllerConfigError(f"open_duration must be >= 0 s, got {self.open_duration}")


@dataclass(frozen=True)
class GainCheck:
    """Theorem 4 (the Assumption 2 ``bounds``) and the sampled-loop check of ``plant`` at
    ``rate_hz`` with ``delay_samples`` of output delay.
    """

    bounds: Bounds
    plant: NominalPlant
    rate_hz: float
    delay_samples: int

    def reasons(self, config: ControllerConfig) -> str:
        """'' when both accept the gains of ``config``, else the reasons."""
        g = config.gains
        report = config.law.theorem4(self.bounds, g)
        reasons = list(report.reasons)
        sampled = check_sampled_loop(
            self.plant, g, self.rate_hz, self.delay_samples, config.mode, config.derivative_tau
        )
        if not sampled.stable:
            reasons.append(
                f"sampled loop unstable at {self.rate_hz:g} Hz with "
                f"{sampled.delay_samples} sample(s) delay: spectral radius "
                f"{sampled.spectral_radius:.4f} >= 1"
            )
        return "; ".join(reasons)


class SaturationWindow:
    """Saturated steps between two reports, from the loop's running totals
    (:attr:`LoopSupervisor.saturated_steps`, :attr:`LoopSupervisor.steps`): the loop only adds
    to them; :meth:`report`, from the diagnostics timer (another thread in the composed rig
    loop), takes the differences since its previous call. A step counted between the reader's
    two reads lands in one window or the next; the saturated count is kept <= the step count.
    """

    def __init__(self) -> None:
        self._saturated = 0
        self._steps = 0

    def report(self, saturated_total: int, steps_total: int) -> tuple[int, int]:
        """(saturated steps, steps) since the previous report; read ``saturated_total`` first."""
        saturated = saturated_total - self._saturated
        steps = steps_total - self._steps
        self._saturated, self._steps = saturated_total, steps_total
        return min(max(saturated, 0), max(steps, 0)), max(steps, 0)


Notify = Callable[[Health, str], None]


class LoopSupervisor:
    """The decisions around ``pid`` (see the module docstring). ``notify(level, text)`` hears
    each opening and closing (rare events: a node logs them).
    """

    def __init__(
        self, pid: TimeVaryingPID, config: SupervisionConfig, notify: Notify | None = None
    ) -> None:
        self.pid = pid
        self.config = config
        self.notify: Notify = notify or (lambda level, text: None)
        self.x: float | None = None  # the newest valid sample [m] and its time [s]
        self.x_stamp: float | None = None
        self.valid = False  # the newest sample was valid
        self.fault = ""  # why the loop was opened (latched until close())
        self.waiting = ""  # why start_closed has not closed the loop yet
        self.steps = 0
        self.saturated_steps = 0  # steps whose output was clamped to [u_min, u_max]
        self._saturation = SaturationWindow()
        self.gaps_held = 0  # gaps shorter than max_gap ridden through
        #: outputs never written: a newer sample of the same sensor read superseded them (the
        #: composed loop writes the newest output of a read; the caller counts)
        self.superseded = 0
        self.longest_gap = 0.0  # [s]
        self._in_gap = False
        self._stepped_on: float | None = None  # the sample time of the last step
        self._start_closed = config.start_closed
        self._window, self._window_t = Window.PENDING, math.nan
        self._closed_at = math.nan  # when start_closed closed the loop
        self._first_closed_at = math.nan  # when it first did (start_grace counts from there)
        self._t0 = math.nan  # the first sample's time: messages count from it

    # ------------------------------------------------------------------ frames
    def command(self, out: ControlOutput) -> float:
        """The amplifier voltage of a law output: u_bias + u, within [u_min, u_max] also after
        the rounding of the two frames.
        """
        return self._volts(out.u)

    def _volts(self, u: float) -> float:
        c = self.config
        return min(max(c.u_bias + u, c.u_min), c.u_max)

    def hold_value(self) -> float:
        """The open-loop output in the law's frame (amplifier volts − u_bias)."""
        hold = self.pid.config.hold_voltage
        return self.pid.config.clamp(self.pid.u if hold is None else hold)

    def hold_command(self) -> float | None:
        """What to keep commanding while the loop is open [V], None before any output."""
        if self.pid.last_output is None:
            return None
        return self._volts(self.hold_value() if not self.pid.loop_closed else self.pid.u)

    # ------------------------------------------------------------------ inputs
    def sample(self, t: float, x: float, ok: bool) -> bool:
        """A sensor sample at ``t``: True when the loop may step on it. An invalid one opens the
        loop (or delays start_closed); a valid one after a gap longer than ``max_gap`` that no
        :meth:`check_gap` saw opens it too.
        """
        if self._t0 != self._t0:  # NaN: the first sample
            self._t0 = t
        if not ok or not math.isfinite(x):
            self.valid = False
            self.fail("invalid sensor sample", t)
            return False
        if self.x_stamp is not None:
            gap = t - self.x_stamp
            if gap > GAP_PERIODS / self.config.rate_hz:
                self.longest_gap = max(self.longest_gap, gap)
                if gap > self.config.max_gap:
                    self.fail(f"no sensor sample for {gap:.4f} s", t)
                elif not self._in_gap:
                    self.gaps_held += 1
            self._in_gap = False
        self.valid = True
        self.x, self.x_stamp = x, t
        return True

    def check_gap(self, t: float) -> Gap:
        """At a tick of the loop's clock (a timer, a read that timed out): NONE when a sample
        came since the last step; else hold (a gap once the newest sample is more than 1.5
        periods old), and open the loop once it is more than ``max_gap`` old.
        """
        if self.x_stamp is None:
            return Gap.NO_SAMPLE
        age = t - self.x_stamp
        if age <= self.config.max_gap:
            if self.x_stamp != self._stepped_on:
                return Gap.NONE
            if age > GAP_PERIODS / self.config.rate_hz and not self._in_gap:
                self._in_gap = True
                self.gaps_held += 1
            return Gap.HELD
        self.longest_gap = max(self.longest_gap, age)
        if self.pid.loop_closed or self._start_closed or not self.fault:
            self.fail(f"no sensor sample for {age:.4f} s", t)
        return Gap.OPENED

    def fail(self, reason: str, t: float) -> None:
        """Open the loop holding the hold voltage; latch ``reason`` (or, before start_closed
        closed the loop, wait for the next valid sample).
        """
        if self.pid.loop_closed:
            if self.starting(t):
                self.notify(
                    Health.WARN,
                    f"{reason} {t - self._first_closed_at:.3g} s after start_closed closed the "
                    "loop: holding, closing again at the next valid sample",
                )
                self.pid.open_loop(self.hold_value())
                self._start_closed, self.waiting = True, reason
                return
            self.notify(Health.ERROR, f"opening the loop {self._when(t)}: {reason}")
            self.pid.open_loop(self.hold_value())
        if self._start_closed:
            self.waiting = reason
        else:
            self.fault = reason

    def _when(self, t: float) -> str:
        """``t`` for a message: seconds after the first sample (a rig's clock is epoch time)."""
        return f"{t - self._t0:.6g} s after the first sample"

    def starting(self, t: float) -> bool:
        """True within ``start_grace`` of start_closed's first closing (a fault re-arms it)."""
        return t - self._first_closed_at < self.config.start_grace

    @property
    def closing_pending(self) -> bool:
        """start_closed will close the loop at the next step."""
        return self._start_closed and not self.pid.loop_closed and not self.fault

    def hold_off(self, reason: str) -> None:
        """Keep start_closed waiting (``reason`` on /diagnostics) without a sample's fault."""
        self.waiting = reason

    # ------------------------------------------------------------------ period
    def step(
        self,
        t: float,
        yr: float,
        yr_dot: float | None = None,
        yr_ddot: float = 0.0,
        own: OwnFrame | None = None,
    ) -> ControlOutput:
        """One period on the newest valid sample: the scheduled window, start_closed, the law
        (``own``: the axis's own frame on a coupled stage, for the feedforward).
        """
        assert self.x is not None, "step() before a valid sample"
        self._scheduled_window(t)
        if self.closing_pending:
            self._start_closed, self.waiting = False, ""
            self.pid.close_loop()
            self._closed_at = t
            if math.isnan(self._first_closed_at):
                self._first_closed_at = t
        out = self.pid.update(t, self.x, yr, yr_dot, yr_ddot, own)
        self._stepped_on = self.x_stamp
        self.steps += 1
        self.saturated_steps += int(out.saturated)
        return out

    def _scheduled_window(self, t: float) -> None:
        c = self.config
        open_at = c.open_at
        if open_at < 0 <= c.open_after and math.isfinite(self._closed_at):
            open_at = self._closed_at + c.open_after
        if open_at < 0 or self._window is Window.DONE:
            return
        if self._window is Window.PENDING and t >= open_at:
            self.notify(
                Health.OK,
                f"scheduled opening {self._when(t)}, holding {c.u_bias + self.hold_value():.6g} V",
            )
            self.pid.open_loop(self.hold_value())
            self._window, self._window_t = Window.OPEN, t
        elif (
            self._window is Window.OPEN
            and c.open_duration > 0
            and t >= self._window_t + c.open_duration - 0.5 / c.rate_hz
        ):
            self.notify(Health.OK, f"scheduled closing {self._when(t)}")
            self.pid.close_loop()
            self._window = Window.DONE

    # ------------------------------------------------------------------ requests
    def close(self) -> tuple[bool, str]:
        """Close the loop on request (clears a latched fault) when the newest sample is valid."""
        if not self.valid or self.x is None:
            return False, "no valid sensor sample: loop stays open"
        self.fault = ""
        self.pid.close_loop()
        return True, "loop closed"

    def open(self) -> str:
        """Open the loop on request, holding the hold voltage."""
        hold = self.hold_value()
        self.pid.open_loop(hold)
        return f"loop open, holding {self.config.u_bias + hold:.6g} V"

    def diagnose(self) -> tuple[Health, str, dict[str, object]]:
        """Level, message and values for /diagnostics; the saturation figures cover the steps
        since the previous call (the /diagnostics period).
        """
        saturated, steps = self._saturation.report(self.saturated_steps, self.steps)
        share = saturated / steps if steps else 0.0
        values: dict[str, object] = {
            "mode": self.pid.config.mode,
            "loop_closed": self.pid.loop_closed,
            "u": self.config.u_bias + self.pid.u,
            "steps": self.steps,
            "saturated_steps": self.saturated_steps,
            "saturated_share": share,
            "gaps_held": self.gaps_held,
            "superseded": self.superseded,
            "longest_gap": self.longest_gap,
        }
        if self.fault:
            return Health.ERROR, f"loop opened: {self.fault}", values
        if self._start_closed and self.waiting:
            return Health.WARN, f"waiting to close the loop: {self.waiting}", values
        if saturated:
            c = self.config
            return (
                Health.WARN,
                f"output saturated on {100 * share:.3g} % of the {steps} steps since the last "
                f"report (amplifier limits {c.u_min:g} to {c.u_max:g} V)",
                values,
            )
        return Health.OK, "closed" if self.pid.loop_closed else "open", values
