"""PNG figures of a closed-loop run in the style of thesis Figs. 11.5-11.11 (µm, µm/s, V)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .spec import Plan


def plot_run(plan: Plan, data: dict[str, np.ndarray], out_dir: Path) -> list[Path]:
    """x1 [µm], x2 [µm/s], u and its terms [V] against t [ms]; one PNG, returns its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    t = data["t"] * 1e3
    fig, axes = plt.subplots(3, 1, figsize=(8, 8), sharex=True)
    axes[0].plot(t, data["x1"] * 1e6)
    axes[0].set_ylabel("x1 [µm]")
    axes[1].plot(t, data["x2"] * 1e6)
    axes[1].set_ylabel("x2 [µm/s]")
    axes[2].plot(t, data["u"], label="u")
    axes[2].plot(t, data["u_pid"], label="u_pid", lw=0.8)
    axes[2].plot(t, data["u_excitation"], label="u_excitation", lw=0.8)
    axes[2].set_ylabel("u [V]")
    axes[2].set_xlabel("t [ms]")
    axes[2].legend(loc="best")
    for ax in axes:
        ax.grid(True, alpha=0.3)
    fig.suptitle(f"{plan.name} — {plan.mode} at {plan.rate_hz / 1e3:g} kHz (lockstep)")
    path = out_dir / f"{plan.name}_{plan.mode}.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return [path]
