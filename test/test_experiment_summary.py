"""experiments.plan.summarize on perturbation records as a 1 kHz rig gives them: a record that
starts before the loop closed, states lost before the opening, a loop that never re-closes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from piezo_stage.experiments import ExperimentError
from piezo_stage.experiments.plan import SIGNALS, Plan, summarize

pytestmark = pytest.mark.unit

RATE = 1000.0
T_OPEN, OPEN_FOR = 1.0, 0.010


def _plan() -> Plan:
    return Plan("perturbation", "pid_tv", RATE, np.nan, 1.4, {}, {}, T_OPEN, T_OPEN + OPEN_FOR)


def _record(start_open: int = 0, u_rest: float = 200.0) -> dict[str, np.ndarray]:
    """u_rest V held closed, opened at T_OPEN for OPEN_FOR at 72 V, closed again; the first
    ``start_open`` states are open at 0 V (the controller's states before the loop closed)."""
    t = np.arange(int(1.4 * RATE)) / RATE
    closed = ~((t >= T_OPEN - 1e-9) & (t < T_OPEN + OPEN_FOR - 1e-9))
    u = np.where(closed, u_rest, 72.0)
    closed[:start_open] = False
    u[:start_open] = 0.0
    data = {k: np.zeros(t.size) for k in SIGNALS}
    data.update(t=t, u=u, loop_closed=closed)
    data["x1"] = np.where(t >= T_OPEN + OPEN_FOR, 1e-6 * np.exp(-(t - T_OPEN) / 0.01), 0.0)
    return data


def _drop(data: dict[str, np.ndarray], lost: np.ndarray) -> dict[str, np.ndarray]:
    return {k: v[~lost] for k, v in data.items()}


def test_the_opening_is_the_first_after_the_loop_closed():
    s = summarize(_plan(), _record(start_open=20))
    assert s["t_open"] == pytest.approx(T_OPEN) and s["open_for"] == pytest.approx(OPEN_FOR)
    assert s["u_before"] == pytest.approx(200.0) and s["u_change_relative"] == pytest.approx(0.0)


def test_u_before_survives_states_lost_just_before_the_opening():
    data = _record()
    lost = (data["t"] > T_OPEN - 0.0035) & (data["t"] < T_OPEN - 1e-9)  # the last 3 states
    s = summarize(_plan(), _drop(data, lost))
    assert s["u_before"] == pytest.approx(200.0)


def test_no_closed_state_before_the_opening_is_said():
    data = _record()
    lost = (data["t"] >= 0.95) & (data["t"] < T_OPEN - 1e-9)  # a 50 ms stall before opening
    with pytest.raises(ExperimentError, match="no closed-loop state .* before the opening"):
        summarize(_plan(), _drop(data, lost))


def test_a_loop_that_never_closes_again_is_said():
    data = _record()
    keep = data["t"] < T_OPEN + 0.005
    with pytest.raises(ExperimentError, match="never closed again"):
        summarize(_plan(), {k: v[keep] for k, v in data.items()})
    never = _record()
    never["loop_closed"][:] = False
    with pytest.raises(ExperimentError, match="never opened"):
        summarize(_plan(), never)


def test_u_after_is_the_mean_over_the_last_period_in_time_whatever_was_lost():
    """A busy host loses states: the last whole period is taken by time, and u is averaged over
    it as a function of time (a count of samples spans more than a period when some are lost,
    and the mean of a sine over part of a period is not its centre)."""
    f = 20.0  # the sine's frequency: a 50 ms period
    plan = replace(_plan(), gains={"f": f})
    data = _record()
    after = data["t"] >= T_OPEN + OPEN_FOR
    data["u"] = np.where(after, 200.0 + 30.0 * np.sin(2 * np.pi * f * data["t"]), data["u"])
    rng = np.random.default_rng(7)
    lost = (data["t"] > data["t"][-1] - 0.08) & (rng.random(data["t"].size) < 0.4)
    s = summarize(plan, _drop(data, lost))
    assert s["u_after"] == pytest.approx(200.0, abs=0.3)  # the sine's centre, 0.15 % of u
    assert s["oscillation_u"] == pytest.approx(30.0, rel=0.02)
