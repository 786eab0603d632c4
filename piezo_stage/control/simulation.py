"""Closed loop in pure core: :class:`TimeVaryingPID` sampled at a fixed rate driving a plant.

The plant is the model's ``DynamicPlant`` (11.1)-(11.3) or anything with ``output() -> float``
(current measurement) and ``step(u, dt) -> float`` (hold u over dt by ZOH, return the new
measurement); ``x``, ``xdot``, ``w`` are recorded when the plant has them. Used to confirm what
:func:`~piezo_stage.control.discrete.check_sampled_loop` predicts and to reproduce the §11.4-11.5
experiments (loop opened for a while at a hold voltage, then closed again).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Callable, Protocol, Sequence

import numpy as np
from numpy.typing import NDArray

from .controller import TimeVaryingPID
from .errors import SampledLoopError

ReferenceFn = Callable[[float], "float | tuple[float, float | None] | tuple[float, float, float]"]


class SampledPlant(Protocol):
    """What :func:`simulate_closed_loop` drives (see the module docstring)."""

    def output(self) -> float:
        """The current measurement."""

    def step(self, u: float, dt: float) -> float:
        """Hold ``u`` over ``dt`` by ZOH; returns the new measurement."""


@dataclass(frozen=True)
class ClosedLoopResult:
    """Per-sample record; ``u_applied[k]`` is held over [t[k], t[k] + 1/rate] (after the delay)."""

    rate_hz: float
    delay_samples: int
    t: NDArray[np.float64]
    measured: NDArray[np.float64]
    reference: NDArray[np.float64]
    x0: NDArray[np.float64]
    x1: NDArray[np.float64]
    x2: NDArray[np.float64]
    u: NDArray[np.float64]
    u_pid: NDArray[np.float64]
    u_excitation: NDArray[np.float64]
    u_applied: NDArray[np.float64]
    u_ff: NDArray[np.float64]
    saturated: NDArray[np.bool_]
    loop_closed: NDArray[np.bool_]
    xdot: NDArray[np.float64]
    w: NDArray[np.float64]


def _in_window(
    t: float, windows: Sequence[tuple[float, float, float | None]]
) -> tuple[bool, float | None]:
    for start, end, hold in windows:
        if start <= t < end:
            return True, hold
    return False, None


def simulate_closed_loop(
    controller: TimeVaryingPID,
    plant: SampledPlant,
    rate_hz: float,
    duration: float,
    reference: ReferenceFn | None = None,
    delay_samples: int = 0,
    open_windows: Sequence[tuple[float, float, float | None]] = (),
    t0: float = 0.0,
) -> ClosedLoopResult:
    """Run ``controller`` against ``plant`` at ``rate_hz`` for ``duration`` seconds.

    Each period k: measure, call ``controller.update(t[k], measured, yr, ẏr)``, hold the output
    computed ``delay_samples`` periods earlier over the period (zero-order hold), step the plant.
    ``reference(t)`` returns yr, (yr, ẏr) or (yr, ẏr, ÿr) (a trajectory, for the feedforward),
    e.g. a :class:`~piezo_stage.control.reference.SecondOrderReference`; default yr = 0, ẏr = 0.
    ``open_windows``: (start, end, hold) intervals (relative to t0) with the loop open at
    ``hold`` volts (None: the last output), closed again at ``end`` (§11.5: 10 ms at 72 V).
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise SampledLoopError(f"rate_hz must be > 0, got {rate_hz}")
    if not (math.isfinite(duration) and duration > 0):
        raise SampledLoopError(f"duration must be > 0 s, got {duration}")
    if int(delay_samples) != delay_samples or delay_samples < 0:
        raise SampledLoopError(f"delay_samples must be a non-negative integer, got {delay_samples}")
    period = 1.0 / rate_hz
    n = int(round(duration * rate_hz))
    rec = {
        k: np.empty(n)
        for k in (
            "t",
            "measured",
            "reference",
            "x0",
            "x1",
            "x2",
            "u",
            "u_pid",
            "u_excitation",
            "u_applied",
            "u_ff",
            "xdot",
            "w",
        )
    }
    saturated = np.zeros(n, dtype=bool)
    closed = np.zeros(n, dtype=bool)
    pending: deque[float] = deque([controller.u] * int(delay_samples))
    measured = float(plant.output())
    was_open = False
    for k in range(n):
        t_rel = k * period
        t = t0 + t_rel
        is_open, hold = _in_window(t_rel, open_windows)
        if is_open and not was_open:
            controller.open_loop(hold)
        elif was_open and not is_open:
            controller.close_loop()
        was_open = is_open
        yr_dot: float | None  # None: the controller differentiates yr
        yr, yr_dot, yr_ddot = 0.0, 0.0, 0.0
        if reference is not None:
            value = reference(t)
            value = value if isinstance(value, tuple) else (value, None)
            yr, yr_dot = value[0], value[1]
            yr_ddot = value[2] if len(value) > 2 else 0.0
        out = controller.update(t, measured, yr, yr_dot, yr_ddot)
        pending.append(out.u)
        applied = pending.popleft()
        rec["t"][k], rec["measured"][k], rec["reference"][k] = t, measured, yr
        rec["x0"][k], rec["x1"][k], rec["x2"][k] = out.x0, out.x1, out.x2
        rec["u"][k], rec["u_pid"][k], rec["u_excitation"][k], rec["u_applied"][k] = (
            out.u,
            out.u_pid,
            out.u_excitation,
            applied,
        )
        rec["u_ff"][k] = out.u_ff
        rec["xdot"][k] = getattr(plant, "xdot", math.nan)
        rec["w"][k] = getattr(plant, "w", math.nan)
        saturated[k], closed[k] = out.saturated, out.loop_closed
        measured = float(plant.step(applied, period))
    return ClosedLoopResult(
        rate_hz=float(rate_hz),
        delay_samples=int(delay_samples),
        saturated=saturated,
        loop_closed=closed,
        **rec,
    )
