"""The figures, from numpy arrays (SI in, µm / V on the axes). Each writes one PNG and returns
its path; matplotlib is imported inside, with the Agg backend."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

import numpy as np

UM = 1e6  #: m -> µm on the axes
DPI = 110


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    _pyplot().close(fig)
    return path


def _shade_runs(ax: Any, runs: Sequence[tuple[str, float, float]]) -> None:
    for i, (_, start, stop) in enumerate(runs):
        ax.axvspan(start, stop, color=f"C{i}", alpha=0.08, lw=0)


def timeseries_figure(
    path: str | Path,
    t_v: np.ndarray,
    v: np.ndarray,
    t_y: np.ndarray,
    y: np.ndarray,
    *,
    runs: Sequence[tuple[str, float, float]] = (),
    title: str = "",
) -> Path:
    """Input voltage [V] and displacement [µm] over time, excitation runs shaded."""
    plt = _pyplot()
    fig, (ax1, ax2) = plt.subplots(2, 1, sharex=True, figsize=(9, 5.5))
    ax1.plot(t_v, v, lw=0.9, color="C0", label="voltage v")
    ax1.set_ylabel("voltage [V]")
    ax2.plot(t_y, np.asarray(y) * UM, lw=0.9, color="C1", label="displacement y")
    ax2.set_ylabel("displacement [µm]")
    ax2.set_xlabel("time [s]")
    for ax in (ax1, ax2):
        _shade_runs(ax, runs)
        ax.grid(alpha=0.3)
        ax.legend(
            loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0
        )  # beside: the signal fills the axes
    ax1.set_title(title or "input and output over time" + (" (runs shaded)" if runs else ""))
    return _save(fig, path)


def hysteresis_figure(
    path: str | Path,
    loops: Sequence[tuple[str, np.ndarray, np.ndarray]],
    *,
    title: str = "",
    steady: Sequence[np.ndarray | None] | None = None,
) -> Path:
    """Hysteresis loops: displacement [µm] against input voltage [V], one colour per run.

    ``steady``: per loop, a mask of the samples the excitation marked steady (the limit cycle
    the identification uses): they are drawn bold over the faint settling transient."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 5.5))
    masks = list(steady) if steady is not None else [None] * len(loops)
    for i, ((label, v, y), mask) in enumerate(zip(loops, masks)):
        v, y_um = np.asarray(v), np.asarray(y) * UM
        if mask is None or not np.any(mask):
            ax.plot(v, y_um, lw=0.9, color=f"C{i}", label=label)
            continue
        ax.plot(v, y_um, lw=0.6, color=f"C{i}", alpha=0.35, label=f"{label}: settling")
        ax.plot(v[mask], y_um[mask], lw=1.6, color=f"C{i}", label=f"{label}: steady cycles")
    ax.set_xlabel("input voltage v [V]")
    ax.set_ylabel("displacement y [µm]")
    ax.grid(alpha=0.3)
    ax.legend(loc="best")
    ax.set_title(title or "hysteresis loops (input vs displacement)")
    return _save(fig, path)


def model_figure(
    path: str | Path,
    t: np.ndarray,
    v: np.ndarray,
    y: np.ndarray,
    model: np.ndarray,
    *,
    title: str = "",
) -> Path:
    """Bouc-Wen model (10.15) against the data: loops, outputs over time, and the error."""
    plt = _pyplot()
    y, model = np.asarray(y), np.asarray(model)
    err = model - y
    span = float(np.ptp(y)) or 1.0
    fig = plt.figure(figsize=(11, 6))
    grid = fig.add_gridspec(2, 2, width_ratios=[1, 1.4])
    ax_loop = fig.add_subplot(grid[:, 0])
    ax_t = fig.add_subplot(grid[0, 1])
    ax_e = fig.add_subplot(grid[1, 1], sharex=ax_t)
    ax_loop.plot(v, y * UM, lw=1.2, color="C0", label="measured")
    ax_loop.plot(v, model * UM, lw=1.0, ls="--", color="C3", label="model")
    ax_loop.set_xlabel("input voltage v [V]")
    ax_loop.set_ylabel("displacement y [µm]")
    ax_loop.legend(loc="best")
    ax_t.plot(t, y * UM, lw=1.0, color="C0", label="measured")
    ax_t.plot(t, model * UM, lw=0.9, ls="--", color="C3", label="model")
    ax_t.set_ylabel("displacement [µm]")
    ax_t.legend(loc="upper right")
    ax_e.plot(t, err * UM, lw=0.8, color="C2", label="model − measured")
    ax_e.set_ylabel("error [µm]")
    ax_e.set_xlabel("time [s]")
    ax_e.legend(loc="upper right")
    for ax in (ax_loop, ax_t, ax_e):
        ax.grid(alpha=0.3)
    rms = float(np.sqrt(np.mean(err**2)))
    fig.suptitle(
        title
        or f"model vs data: RMS error {rms * UM:.3g} µm ({100 * rms / span:.2g} % of span), "
        f"max {np.max(np.abs(err)) * UM:.3g} µm"
    )
    return _save(fig, path)


def validation_figure(
    path: str | Path,
    t: np.ndarray,
    v: np.ndarray,
    true: np.ndarray,
    identified: np.ndarray,
    *,
    title: str = "",
) -> Path:
    """Identified vs true model on a validation input: input, both outputs, their difference."""
    plt = _pyplot()
    fig, (ax_v, ax_y, ax_e) = plt.subplots(3, 1, sharex=True, figsize=(9, 7))
    ax_v.plot(t, v, lw=0.9, color="C0")
    ax_v.set_ylabel("input v [V]")
    ax_y.plot(t, np.asarray(true) * UM, lw=1.2, color="C0", label="true model")
    ax_y.plot(t, np.asarray(identified) * UM, lw=0.9, ls="--", color="C3", label="identified model")
    ax_y.set_ylabel("displacement [µm]")
    ax_y.legend(loc="upper right")
    ax_e.plot(t, (np.asarray(identified) - true) * UM, lw=0.8, color="C2")
    ax_e.set_ylabel("identified − true [µm]")
    ax_e.set_xlabel("time [s]")
    for ax in (ax_v, ax_y, ax_e):
        ax.grid(alpha=0.3)
    ax_v.set_title(title or "validation: identified vs true model")
    return _save(fig, path)


def closed_loop_figure(
    path: str | Path,
    t: np.ndarray,
    x1: np.ndarray,
    x2: np.ndarray,
    u: np.ndarray,
    u_pid: np.ndarray,
    u_excitation: np.ndarray,
    loop_closed: np.ndarray,
    *,
    mode: str = "",
    title: str = "",
) -> Path:
    """Closed-loop signals of the time-varying PID (ch. 11, cf. Figs. 11.5-11.11): tracking
    error x1 [µm], velocity x2 [m/s] (the thesis's unit: x2(0) = 0.2 m/s), control u and its
    terms u_pid, u_excitation [V] against time (ms for runs shorter than 2 s, as the thesis's
    figures); the time the loop is closed is shaded."""
    plt = _pyplot()
    t = np.asarray(t, dtype=float)
    short = len(t) > 1 and t[-1] - t[0] < 2.0
    t = t * 1e3 if short else t
    closed = np.asarray(loop_closed, dtype=bool)
    fig, (a1, a2, a3) = plt.subplots(3, 1, sharex=True, figsize=(9, 7.5))
    a1.plot(t, np.asarray(x1) * UM, lw=0.9, color="C0", label="x1 = x − yr")
    a1.set_ylabel("x1 [µm]")
    a2.plot(t, np.asarray(x2), lw=0.7, color="C1", label="x2 = dx/dt")
    a2.set_ylabel("x2 [m/s]")
    a3.plot(t, u, lw=1.0, color="C2", label="u")
    a3.plot(t, u_pid, lw=0.8, ls="--", color="C3", label="u_pid")
    a3.plot(t, u_excitation, lw=0.7, color="C4", alpha=0.8, label="u_excitation")
    a3.set_ylabel("voltage [V]")
    a3.set_xlabel("time [ms]" if short else "time [s]")
    edges = np.flatnonzero(np.diff(np.concatenate([[0], closed.astype(int), [0]])))
    for ax in (a1, a2, a3):
        for start, stop in zip(edges[::2], edges[1::2]):
            ax.axvspan(
                t[start],
                t[min(stop, len(t)) - 1],
                color="0.5",
                alpha=0.12,
                lw=0,
                label="loop closed" if ax is a1 and start == edges[0] else None,
            )
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right")
    a1.set_title(title or f"closed loop{' (' + mode + ')' if mode else ''}")
    return _save(fig, path)


def tracking_figure(
    path: str | Path,
    t: np.ndarray,
    x_d: np.ndarray,
    x: np.ndarray,
    u: np.ndarray,
    u_ff: np.ndarray,
    *,
    feedback: tuple[np.ndarray, np.ndarray] | None = None,
    t_from: float = 0.0,
    title: str = "",
) -> Path:
    """Tracking: x_d and x [µm], the error x − x_d [nm], u and the feedforward u_ff
    [V] against time; ``feedback`` = (t, x) of the feedback-only run, drawn faint; the part
    before ``t_from`` (left out of the figures) shaded."""
    plt = _pyplot()
    t = np.asarray(t, dtype=float)
    short = len(t) > 1 and t[-1] - t[0] < 2.0
    scale = 1e3 if short else 1.0
    fig, (a1, a2, a3) = plt.subplots(3, 1, sharex=True, figsize=(9, 7.5))
    a1.plot(t * scale, np.asarray(x_d) * UM, lw=1.6, color="0.6", label="x_d")
    a1.plot(t * scale, np.asarray(x) * UM, lw=0.9, color="C0", label="x")
    a2.plot(t * scale, (np.asarray(x) - x_d) * 1e9, lw=0.9, color="C0", label="x − x_d")
    if feedback is not None:  # its error (µm) is in the top panel: the nm panel stays readable
        t_fb, x_fb = (np.asarray(a, dtype=float) for a in feedback)
        a1.plot(t_fb * scale, x_fb * UM, lw=0.8, color="C3", alpha=0.6, label="x, feedback only")
    err = (np.asarray(x) - x_d) * 1e9
    steady = t >= t_from
    if steady.any() and np.abs(err).max() > 3 * np.abs(err[steady]).max() > 0:
        lim = (
            3 * np.abs(err[steady]).max()
        )  # the settling period off-scale, the steady error readable
        a2.set_ylim(-lim, lim)
    a3.plot(t * scale, u, lw=1.0, color="C2", label="u")
    a3.plot(t * scale, u_ff, lw=0.8, ls="--", color="C1", label="u_ff")
    a1.set_ylabel("position [µm]")
    a2.set_ylabel("error [nm]")
    a3.set_ylabel("voltage [V]")
    a3.set_xlabel("time [ms]" if short else "time [s]")
    for ax in (a1, a2, a3):
        if t_from > t[0]:
            ax.axvspan(t[0] * scale, t_from * scale, color="0.5", alpha=0.12, lw=0)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right")
    a1.set_title(title or "tracking")
    return _save(fig, path)


def learning_figure(
    path: str | Path,
    t: np.ndarray,
    error: np.ndarray,
    period: float,
    learning: Sequence[float],
    *,
    title: str = "",
) -> Path:
    """Learning a feedforward: the RMS error of each learning period [nm] (log scale), and the
    error x − x_d [nm] against the time within the period, one line per learning period
    (light to dark) and the measured periods after it (black)."""
    plt = _pyplot()
    t, error = np.asarray(t, dtype=float), np.asarray(error, dtype=float)
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(9, 7))
    k = np.arange(1, len(learning) + 1)
    a1.semilogy(k, np.asarray(learning) * 1e9, "o-", color="C0")
    a1.set_xlabel("learning period")
    a1.set_ylabel("RMS error [nm]")
    a1.grid(alpha=0.3, which="both")
    n_learn = len(learning)
    cmap = plt.get_cmap("viridis")
    index = np.floor((t - t[0]) / period + 1e-9).astype(int) if t.size else t
    for j in range(int(index.max()) + 1 if t.size else 0):
        mask = index == j
        if not mask.any():
            continue
        phase = (t[mask] - t[0] - j * period) * 1e3
        if j < n_learn:
            a2.plot(
                phase,
                error[mask] * 1e9,
                lw=0.8,
                color=cmap(j / max(n_learn, 1)),
                label="learning" if j == 0 else None,
            )
        else:
            a2.plot(
                phase,
                error[mask] * 1e9,
                lw=1.0,
                color="k",
                label="learned (frozen)" if j == n_learn else None,
            )
    a2.set_xlabel("time in the period [ms]")
    a2.set_ylabel("error x − x_d [nm]")
    a2.grid(alpha=0.3)
    a2.legend(loc="upper right")
    a1.set_title(title or "learning the feedforward")
    return _save(fig, path)


def coupling_figure(
    path: str | Path,
    scenarios: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray]],
    *,
    title: str = "",
) -> Path:
    """One panel per scenario (label, t, the held axis's error without and with the coupling
    compensated [m]): the error [nm] against time, the two runs overlaid."""
    plt = _pyplot()
    fig, axes = plt.subplots(len(scenarios), 1, sharex=True, figsize=(9, 2.6 * len(scenarios)))
    for ax, (label, t, without, with_) in zip(np.atleast_1d(axes), scenarios):
        t_ms = np.asarray(t, dtype=float) * 1e3
        for err, name, color in ((without, "without", "C3"), (with_, "with", "C0")):
            rms = float(np.sqrt(np.mean(np.square(err[len(err) // 2 :]))))
            ax.plot(
                t_ms,
                np.asarray(err) * 1e9,
                lw=0.9,
                color=color,
                label=f"{name} coupling compensation (RMS {rms * 1e9:.3g} nm, 2nd half)",
            )
        late = np.abs(np.concatenate([without[len(without) // 2 :], with_[len(with_) // 2 :]]))
        if late.size and late.max() > 0:  # the start off-scale, the steady part readable
            ax.set_ylim(-2e9 * late.max(), 2e9 * late.max())
        ax.set_ylabel("error [nm]")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right", fontsize=8)
    np.atleast_1d(axes)[-1].set_xlabel("time [ms]")
    fig.suptitle(title or "a held axis while another scans")
    return _save(fig, path)


def scan_images_figure(
    path: str | Path,
    ideal: np.ndarray,
    scans: Sequence[tuple[str, np.ndarray]],
    extent: tuple[float, float, float, float],
    *,
    title: str = "",
) -> Path:
    """A raster's images [nm of height]: the ideal one, each scanned one (label, image), and
    the last scanned one less the ideal; ``extent`` (x0, x1, y0, y1) [m] of the image."""
    plt = _pyplot()
    panels = [("ideal", np.asarray(ideal))] + [(label, np.asarray(im)) for label, im in scans]
    diff = panels[-1][1] - panels[0][1]
    fig, axes = plt.subplots(1, len(panels) + 1, figsize=(3.2 * (len(panels) + 1), 3.6))
    lo, hi = float(np.nanmin(panels[0][1])) * 1e9, float(np.nanmax(panels[0][1])) * 1e9
    box = [e * UM for e in extent]
    for ax, (label, image) in zip(axes, panels):
        ax.imshow(
            image * 1e9,
            origin="lower",
            extent=box,
            cmap="gray",
            vmin=lo,
            vmax=hi,
            interpolation="nearest",
        )
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("fast axis [µm]")
    span = float(np.nanmax(np.abs(diff))) * 1e9 if np.isfinite(diff).any() else 1.0
    shown = axes[-1].imshow(
        diff * 1e9,
        origin="lower",
        extent=box,
        cmap="RdBu_r",
        vmin=-span or -1,
        vmax=span or 1,
        interpolation="nearest",
    )
    axes[-1].set_title(f"{panels[-1][0]} − ideal [nm]", fontsize=9)
    axes[-1].set_xlabel("fast axis [µm]")
    fig.colorbar(shown, ax=axes[-1], fraction=0.046)
    axes[0].set_ylabel("slow axis [µm]")
    fig.suptitle(title or "raster scan of the sample")
    return _save(fig, path)


def scan_lines_figure(
    path: str | Path,
    runs: Sequence[tuple[str, np.ndarray]],
    names: tuple[str, str] = ("fast", "slow"),
    *,
    title: str = "",
) -> Path:
    """RMS error of each image line [nm] per axis (log scale), one curve per run (label,
    (lines, 2) array of the fast and slow axes' RMS)."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for i, (ax, name) in enumerate(zip(axes, names)):
        for label, line_rms in runs:
            rms = np.asarray(line_rms)[:, i] * 1e9
            ax.semilogy(np.arange(rms.size), rms, ".-", lw=0.8, label=label)
        ax.set_title(f"{name} axis", fontsize=10)
        ax.set_xlabel("image line")
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("RMS error in the line [nm]")
    axes[0].legend(fontsize=8)
    fig.suptitle(title or "error per image line")
    return _save(fig, path)
