"""Override sets the experiments (and commissioning) start their nodes with, written once."""

from __future__ import annotations

from typing import Any

#: [s] a lockstep plant waits this long for the command of a step before it reports a stall
LOCKSTEP_TIMEOUT = 2.0


def lockstep_plant(
    model_file: Any, rate_hz: float, v_min: float, v_max: float, **more: Any
) -> dict[str, Any]:
    """The plant node stepped by the controller's commands (deterministic, as fast as the graph
    goes), from rest (w0 = 0), with its amplifier limits; ``more`` adds or replaces overrides."""
    return {
        "model_file": model_file,
        "clock_mode": "lockstep",
        "rate_hz": rate_hz,
        "lockstep_timeout": LOCKSTEP_TIMEOUT,
        "v_min": v_min,
        "v_max": v_max,
        "w0": 0.0,
        **more,
    }


def experiment_controller(rate_hz: float, mode: str, **more: Any) -> dict[str, Any]:
    """The controller an experiment starts: one step per sensor sample, closed from its first
    sample with x0 = 0 (as the §11.4 simulations start), its first state held until the
    experiment's recorder listens; ``more`` adds or replaces overrides."""
    return {
        "trigger": "sample",
        "rate_hz": rate_hz,
        "mode": mode,
        "start_closed": True,
        "on_close": "reset",
        "wait_for_state_subscribers": 1,
        **more,
    }
