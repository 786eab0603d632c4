"""PNG figures of a closed-loop run in the style of thesis Figs. 11.5-11.11: the bag plotter's
closed-loop figure (:func:`piezo_stage.plotting.figures.closed_loop_figure`), so an experiment's
PNG and ``piezo-stage plot`` of its bag look the same."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from piezo_stage.plotting.figures import closed_loop_figure

from .plan import Plan


def plot_run(plan: Plan, data: dict[str, np.ndarray], out_dir: Path) -> list[Path]:
    """x1 [µm], x2 [m/s], u and its terms [V] against t, loop-closed time shaded; one PNG,
    returns its path."""
    path = Path(out_dir) / f"{plan.name}_{plan.mode}.png"
    closed_loop_figure(
        path,
        data["t"],
        data["x1"],
        data["x2"],
        data["u"],
        data["u_pid"],
        data["u_excitation"],
        data["loop_closed"],
        mode=plan.mode,
        title=f"{plan.name} — {plan.mode} at {plan.rate_hz / 1e3:g} kHz (lockstep)",
    )
    return [path]
