"""The ch. 11 experiments as data: graph, schedule, summary (no rclpy).

- ``regulation`` (§11.4, Figs. 11.5-11.8): the closed loop starts at x0(0) = 0, x1(0) = 20 µm,
  x2(0) = 0.2 m/s, w(0) = 0, with u = 0 V before t = 0 ("the control signal u is zero for negative
  times") and yr the output of the second-order reference of §11.4.1 (ξ = 0.7, ω0 = 2π·500 rad/s,
  zero input, non-zero initial conditions). The thesis also writes "yr(0) = x(0), ẏr(0) = ẋ(0)",
  which contradicts its x1(0) = x(0) − yr(0) = 20 µm (11.4): the error state, stated in each of
  §11.4.1-11.4.3, is kept, and the reference's initial conditions are read as yr(0) = x1(0),
  ẏr(0) = x2(0). The plant node therefore starts at x(0) = x1(0) + yr(0) = 40 µm,
  ẋ(0) = x2(0) + ẏr(0) = 0.4 m/s (its ``initial_displacement``/``initial_velocity`` are the
  physical state). In the sampled loop x2 is an Euler difference (§11.5), so at the first
  sample, with no previous one, the controller takes x2 = −ẏr(0); from the second sample on x2
  is measured.
  Summary: ``u_before`` is the voltage before t = 0 (0 V), ``u_after`` the mean of u over the
  last whole period 1/f of the sine; Figs. 11.5-11.8: x1, x2 → 0 in every mode, under ``pid``
  u(∞) = κw·w(∞) ≠ 0, under ``pid_sine`` a steady oscillation shrinking with A, under ``pid_tv``
  u → u_before.
- ``perturbation`` (§11.5): loop closed around a set point with u ≈ 200 V (a 200 V feedforward
  ``u_bias``, the plant resting at its equilibrium for 200 V, yr there), opened for 10 ms with
  u forced to 72 V, closed again with x0 = 0 (the closing instant is t = 0 of §11.4).
  ``u_before`` is the mean of u over the 2 ms (at least 10 sample periods) before the opening,
  closed-loop states only (the loop is at rest there under
  ``pid`` and ``pid_tv``; under ``pid_sine`` it is a part-period mean of its sine); ``u_after``
  the mean over the last whole period 1/f of the sine at the end of the run (a whole period, so
  that the −kA·x0·sin term of (11.18) and the oscillation it drives average out); ``u_after_at``
  the end of that period measured from the re-closing.

Why the perturbation runs 0.4 s (for ``pid_tv``): after re-closing, x1 and x2 are back near 0
within ~30 ms, but u relaxes to u_before only as w does (at rest κw·w = u − u_before, the
law's x0 term), and w is erased only by the dither the law itself drives, whose amplitude kA·|x0| is
proportional to |w|. Over one period of an oscillation of x with small amplitude X, the
Bouc-Wen flow (11.3) moves w towards 0 by ≈ 4σρX|w|^n (ẇ = ρẋ(1 − |w|^n) moving away from 0,
ρẋ(1 + (2σ − 1)|w|^n) towards it), and X ∝ |w|: dw/dt ≈ −a|w|^(n+1), so w decays algebraically,
w ∝ t^(−1/n) (n = 1.176; the runs show ≈ t^(−0.8)), not exponentially. With the ch. 11 rig and
the thesis gains, |u_after − u_before|/u_before is 1.0 % for a run of 0.25 s, 0.88 % for 0.3 s,
0.70 % for 0.4 s and 0.58 % for 0.5 s (a pure-core simulation of the same loop, equal to the
graph's to 5 digits). 0.4 s meets the thesis's "the same before and after" (≤ 1 %) with a
margin; ``pid`` settles within ~0.1 s at a different equilibrium (u_after ≈ 225.6 V, +12.8 %).

The loop rate is the lowest of :data:`RATE_CANDIDATES` at which the sampled loop
(:func:`~piezo_stage.control.discrete.check_sampled_loop`) is stable with the lockstep's delay
(0: the plant applies the command computed from the sample of the same step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from piezo_stage.control.bounds import THESIS_NOMINAL_PLANT
from piezo_stage.control.controller import THESIS_AMPLIFIER
from piezo_stage.control.discrete import check_sampled_loop
from piezo_stage.control.laws import LAW_NAMES, THESIS_GAINS, check_law
from piezo_stage.model.parameter_set import shipped_parameter_set

from .errors import ExperimentError, ExperimentInputError, UnknownExperimentError
from .presets import experiment_controller, lockstep_plant

EXPERIMENTS: tuple[str, ...] = ("regulation", "perturbation")
RATE_CANDIDATES: tuple[float, ...] = (100e3, 200e3, 500e3, 1e6)
LOCKSTEP_DELAY = 0
MODEL_FILE = "ch11_rig.yaml"
U_BEFORE_WINDOW, U_BEFORE_SAMPLES = 0.002, 10  # [s], []: u_before's window before the opening
X1_INIT, X2_INIT = 20e-6, 0.2  # §11.4: x1(0) [m], x2(0) [m/s] (x0(0) = 0, w(0) = 0)
YR_INIT, YRDOT_INIT = X1_INIT, X2_INIT  # yr(0) [m], ẏr(0) [m/s]: see the module docstring
U_SET, U_OPEN, T_OPEN, OPEN_FOR = 200.0, 72.0, 0.005, 0.010  # §11.5
DEFAULT_DURATION = {"regulation": 0.2, "perturbation": 0.4}


@dataclass(frozen=True)
class Plan:
    """What to launch and when to open/close the loop (times in simulated seconds)."""

    name: str
    mode: str
    rate_hz: float
    spectral_radius: float
    duration: float
    plant: dict[str, Any]
    controller: dict[str, Any]
    open_at: float | None = None
    close_at: float | None = None
    gains: dict[str, float] = field(default_factory=dict)


def pick_rate(mode: str, gains: dict[str, float] | None = None) -> tuple[float, float]:
    """(rate [Hz], per-sample spectral radius): the lowest stable candidate at the lockstep's
    delay."""
    g = THESIS_GAINS if not gains else THESIS_GAINS.__class__(**{**THESIS_GAINS.to_dict(), **gains})
    for rate in RATE_CANDIDATES:
        report = check_sampled_loop(THESIS_NOMINAL_PLANT, g, rate, LOCKSTEP_DELAY, mode)
        if report.stable:
            return rate, float(report.spectral_radius)
    raise ExperimentError(
        f"the sampled loop of {mode} is unstable at every rate of {RATE_CANDIDATES}"
    )


def make_plan(
    name: str, mode: str, *, duration: float | None = None, gains: dict[str, float] | None = None
) -> Plan:
    """The plan of experiment ``name`` under law ``mode`` (see the module docstring); ``duration``
    in simulated seconds (default :data:`DEFAULT_DURATION`), ``gains`` overriding the thesis's."""
    if name not in EXPERIMENTS:
        raise UnknownExperimentError(f"unknown experiment {name!r}; expected one of {EXPERIMENTS}")
    try:
        check_law(mode)
    except Exception as exc:
        names = ", ".join(LAW_NAMES)
        raise UnknownExperimentError(f"unknown mode {mode!r}; expected one of {names}") from exc
    gains = dict(gains or {})
    unknown = set(gains) - set(THESIS_GAINS.to_dict())
    if unknown:
        raise ExperimentInputError(f"unknown gain(s) {sorted(unknown)}")
    duration = DEFAULT_DURATION[name] if duration is None else float(duration)
    if not (math.isfinite(duration) and duration > 0):
        raise ExperimentInputError(f"duration must be > 0 s, got {duration}")
    rate, radius = pick_rate(mode, gains)
    controller = experiment_controller(
        rate,
        mode,
        use_sim_time=True,
        sensor_qos="reliable",
        delay_samples=LOCKSTEP_DELAY,
        **gains,
    )
    plant = lockstep_plant(MODEL_FILE, rate, -THESIS_AMPLIFIER, THESIS_AMPLIFIER)
    if name == "regulation":
        # x = x1 + yr (11.4)
        plant.update(
            initial_displacement=X1_INIT + YR_INIT,
            initial_velocity=X2_INIT + YRDOT_INIT,
            initial_voltage=0.0,
        )
        controller.update(
            reference_source="second_order", reference_y0=YR_INIT, reference_ydot0=YRDOT_INIT
        )
        return Plan(name, mode, rate, radius, duration, plant, controller, gains=gains)
    if duration <= T_OPEN + OPEN_FOR:
        raise ExperimentInputError(
            f"perturbation needs a duration > {T_OPEN + OPEN_FOR} s, got {duration}"
        )
    rig = shipped_parameter_set("ch11_rig").bouc_wen
    x_eq = U_SET / rig.kappa_x  # w(0) = 0: κx·x = u (11.2)
    plant.update(initial_displacement=x_eq, initial_velocity=0.0, initial_voltage=U_SET)
    # the window is scheduled in the controller on sim time: deterministic, no service slip
    controller.update(
        reference_source="constant",
        reference=x_eq,
        u_bias=U_SET,
        hold_voltage=U_OPEN,
        open_at=T_OPEN,
        open_duration=OPEN_FOR,
    )
    return Plan(
        name, mode, rate, radius, duration, plant, controller, T_OPEN, T_OPEN + OPEN_FOR, gains
    )


def graph_for(plan: Plan, namespace: str) -> dict[str, Any]:
    """The launch graph (mapping form of config/graphs) of a plan."""
    return {
        "description": f"experiment {plan.name} ({plan.mode})",
        "namespace": namespace,
        "stop_timeout": 3.0,
        "wait_for_topics": [
            {"topic": "/clock", "publishers": 1},
            {"topic": "voltage_command", "publishers": 1},
        ],
        "nodes": [  # one process: each lockstep step by direct calls (nodes/sim_loop.py)
            {
                "executable": "plant",
                "process": "sim_loop",
                "overrides": plan.plant,
                "required": True,
            },
            {"executable": "controller", "process": "sim_loop", "overrides": plan.controller},
        ],
    }


SIGNALS = ("t", "x0", "x1", "x2", "u", "u_pid", "u_excitation", "loop_closed", "reference")


def time_mean(t: np.ndarray, y: np.ndarray) -> float:
    """Mean of y(t) over [t[0], t[-1]] as a function of time: ∫ y dt / (t[-1] − t[0]) by the
    trapezoidal rule, so lost samples do not weight the rest; the plain mean for one sample."""
    if t.size < 2 or t[-1] <= t[0]:
        return float(np.mean(y))
    return float(np.trapezoid(y, t) / (t[-1] - t[0]))


def _window(t: np.ndarray, start: float, end: float) -> np.ndarray:
    return (t >= start) & (t < end)


def summarize(plan: Plan, data: dict[str, np.ndarray]) -> dict[str, Any]:
    """JSON-ready figures of one run (see the module docstring); ``data`` holds :data:`SIGNALS`."""
    t = data["t"]
    if t.size < 10:
        raise ExperimentError(f"only {t.size} samples recorded")
    end = t[-1]
    period = 1.0 / THESIS_GAINS.f if "f" not in plan.gains else 1.0 / plan.gains["f"]
    # the last whole period 1/f of the sine, by time (a host that lost states gives fewer)
    tail = t >= end - period
    out: dict[str, Any] = {
        "experiment": plan.name,
        "mode": plan.mode,
        "rate_hz": plan.rate_hz,
        "delay_samples": LOCKSTEP_DELAY,
        "spectral_radius": plan.spectral_radius,
        "duration": float(end),
        "samples": int(t.size),
        "lost_samples": int(round((end - t[0]) * plan.rate_hz)) + 1 - int(t.size),
        "gains": {**THESIS_GAINS.to_dict(), **plan.gains},
    }
    out.update(
        final_abs_x1=float(np.abs(data["x1"][tail]).max()),
        final_abs_x2=float(np.abs(data["x2"][tail]).max()),
        final_u=time_mean(t[tail], data["u"][tail]),
        oscillation_x1=float(np.ptp(data["x1"][tail]) / 2),
        oscillation_u=float(np.ptp(data["u"][tail]) / 2),
        max_abs_x1=float(np.abs(data["x1"]).max()),
        initial_x1=float(data["x1"][0]),
    )
    if plan.name == "regulation":  # u = 0 V for negative times (§11.4.1)
        out.update(u_before=float(plan.plant["initial_voltage"]), u_after=out["final_u"])
        out["u_change"] = out["u_after"] - out["u_before"]
    if plan.name == "perturbation":
        closed = data["loop_closed"].astype(bool)
        # the opening: the first open state after a closed one (a record may start open)
        openings = np.flatnonzero(closed[:-1] & ~closed[1:]) + 1
        if openings.size == 0:
            raise ExperimentError("the loop was never opened after being closed")
        first = int(openings[0])
        reclosed = np.flatnonzero(closed[first:])
        t_open = float(t[first])
        if reclosed.size == 0:
            raise ExperimentError(f"the loop opened at t = {t_open:.6g} s and never closed again")
        t_close = float(t[first + reclosed[0]])
        # u_before over U_BEFORE_WINDOW, widened to U_BEFORE_SAMPLES sample periods at low rates
        width = max(U_BEFORE_WINDOW, U_BEFORE_SAMPLES / plan.rate_hz)
        before = _window(t, t_open - width, t_open) & closed
        if not before.any():
            raise ExperimentError(
                f"no closed-loop state in the {width * 1e3:.3g} ms before the opening at "
                f"t = {t_open:.6g} s (lost samples?)"
            )
        after = t >= t_close
        err = np.abs(data["x1"][after])
        threshold = 0.02 * err.max() if err.size else math.nan
        beyond = np.flatnonzero(err > threshold)
        out.update(
            t_open=t_open,
            t_close=t_close,
            open_for=t_close - t_open,
            u_before=float(data["u"][before].mean()),
            u_after=out["final_u"],
            u_after_at=float(end - t_close),
            max_abs_error=float(err.max()),
            settling_time=float(t[after][beyond[-1]] - t_close) if beyond.size else 0.0,
            settling_threshold=float(threshold),
        )
        out["u_change"] = out["u_after"] - out["u_before"]
        # u_before = 0: the loop held nothing before it opened; no relative change to report
        out["u_change_relative"] = (
            out["u_change"] / out["u_before"] if out["u_before"] != 0.0 else math.nan
        )
    return out
