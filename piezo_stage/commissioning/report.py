"""Step 6: ``DIR/report.md`` with the tables and the PNGs (parameters against frequency as
Fig. 11.3, the step-response fit, the closed-loop figure of the acceptance run)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .sweep import PARAMETERS, UNITS

#: Table 11.1 (smallest, largest, mean), for the report's comparison column
TABLE_11_1 = {
    "n": (1.16, 1.192, 1.176),
    "sigma": (0.9094, 0.9212, 0.9153),
    "rho": (7.632e4, 9.5e4, 8.566e4),
    "kappa_w": (39.97, 48.74, 43.57),
    "kappa_x": (9.83e6, 10.8e6, 10.35e6),
}


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_sweep(rows: list[dict[str, Any]], path: Path) -> Path:
    """Each Bouc-Wen parameter against the excitation frequency (Fig. 11.3)."""
    plt = _plt()
    f = np.array([r["frequency"] for r in rows])
    fig, axes = plt.subplots(len(PARAMETERS), 1, figsize=(6.5, 9), sharex=True)
    for ax, name in zip(axes, PARAMETERS):
        values = np.array([r[name] for r in rows])
        ax.plot(f, values, "o-")
        ax.axhline(values.mean(), color="0.5", lw=0.8, ls="--")
        ax.set_ylabel(f"{name} [{UNITS[name]}]")
        ax.grid(True, alpha=0.3)
    axes[-1].set_xscale("log")
    axes[-1].set_xlabel("excitation frequency [Hz]")
    axes[0].set_title("Identified parameters against frequency (input x, output u; Fig. 11.3)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_step(dyn: dict[str, Any], path: Path) -> Path:
    """The measured step response and the fitted model's."""
    plt = _plt()
    t, x, u = (np.asarray(dyn[k]) for k in ("t", "x", "u"))
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(6.5, 5), sharex=True)
    a1.plot((t - t[0]) * 1e3, x * 1e6, ".", ms=3, label="measured")
    if "x_fit" in dyn:
        a1.plot(
            (np.asarray(dyn["t_fit"]) - t[0]) * 1e3,
            np.asarray(dyn["x_fit"]) * 1e6,
            "-",
            lw=1,
            label="fitted model",
        )
    a1.set_ylabel("x [µm]")
    a1.legend()
    a1.set_title(
        f"Step response: m = {dyn['m']:.4g} ± {dyn['m_std']:.2g}, c = {dyn['c']:.4g} ± "
        f"{dyn['c_std']:.2g}"
    )
    a2.step((t - t[0]) * 1e3, u, where="pre")
    a2.set_ylabel("u [V]")
    a2.set_xlabel("t [ms]")
    for ax in (a1, a2):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def write_report(out_dir: Path, state: dict[str, Any], files: dict[str, str]) -> Path:
    s = state["steps"]
    figures = out_dir / "figures"
    figures.mkdir(exist_ok=True)
    sweep_png = plot_sweep(s["sweep"]["frequencies"], figures / "sweep_parameters.png")
    dyn = s["dynamics"]
    freqs = [r["frequency"] for r in s["sweep"]["frequencies"]]
    lines = [
        "# Commissioning report",
        "",
        f"Graph `{state['key']['graph']}`, sensor rate {state['key']['rate_hz']:g} Hz.",
        "",
        "## 1. Frequency sweep (Fig. 11.3, input x, output u)",
        "",
        f"Frequencies {', '.join(f'{f:g}' for f in freqs)} Hz: "
        f"{state['key']['rate_hz'] / max(freqs):.0f} sensor samples per period at least (the "
        "default list keeps >= 200; a 1 kHz rig gets rate/1000 and rate/500). Delay: from the "
        "voltage command's stamp to the sample it is paired with (a rig: the one of 0-1.6 ms "
        "that fits the loop best).",
        "",
    ]
    lines.append(_row(["f [Hz]", *PARAMETERS, "rms [V]", "delay [ms]"]))
    lines.append(_row(["---"] * (len(PARAMETERS) + 3)))
    for r in s["sweep"]["frequencies"]:
        lines.append(
            _row(
                [
                    f"{r['frequency']:g}",
                    *(f"{r[p]:.5g}" for p in PARAMETERS),
                    f"{r['rms_error']:.3g}",
                    f"{1e3 * r.get('input_delay', 0.0):.2g}",
                ]
            )
        )
    lines += ["", "Table 11.1 form (thesis values for the thesis's rig beside):", ""]
    lines.append(
        _row(
            [
                "parameter",
                "smallest",
                "largest",
                "mean",
                "unit",
                "Table 11.1 (smallest / largest / mean)",
            ]
        )
    )
    lines.append(_row(["---"] * 6))
    for p in PARAMETERS:
        t = s["sweep"]["table"][p]
        th = " / ".join(f"{v:.4g}" for v in TABLE_11_1[p])
        lines.append(
            _row([p, f"{t['min']:.5g}", f"{t['max']:.5g}", f"{t['mean']:.5g}", UNITS[p], th])
        )
    lines += [
        "",
        f"![parameters against frequency](figures/{sweep_png.name})",
        "",
        "## 2. Dynamics m, c of (11.1)",
        "",
    ]
    if "t" in dyn:
        step_png = plot_step(dyn, figures / "step_response.png")
        lines += [
            f"From a {dyn['source']} step at {dyn['rate_hz']:g} Hz: m = {dyn['m']:.5g} ± "
            f"{dyn['m_std']:.2g} V s²/m, "
            f"c = {dyn['c']:.5g} ± {dyn['c_std']:.2g} V s/m (standard errors), natural frequency "
            f"{dyn['natural_frequency']:.5g} Hz ({dyn['samples_per_period']:.3g} samples per "
            "period; rule: >= 4), "
            f"damping ratio {dyn['damping_ratio']:.3g}.",
            "",
            f"![step response](figures/{step_png.name})",
            "",
        ]
    else:
        lines += [f"m = {dyn['m']:.5g} V s²/m, c = {dyn['c']:.5g} V s/m from {dyn['source']}.", ""]
    b = s["bounds"]
    lines += [
        "## 3. Bounds of Assumption 2",
        "",
        f"Margin {b['margin']:g} (see `{Path(files['bounds']).name}`).",
        "",
        _row(["bound", "value"]),
        _row(["---", "---"]),
    ]
    lines += [_row([k, f"{v:.6g}"]) for k, v in b["bounds"].items()]
    g = s["gains"]
    lines += [
        "",
        "## 4. Gains (Theorem 4, (11.18))",
        "",
        f"k2_min = {g['k2_min']:.6g}, k0_max = {g['k0_max']:.6g}; loop rate {g['rate_hz']:g} "
        "Hz with "
        f"{g['delay_samples']} sample(s) delay, spectral radius {g['spectral_radius']:.6f} "
        "(stable < 1).",
        "",
        _row(["gain", "value"]),
        _row(["---", "---"]),
    ]
    lines += [_row([k, f"{v:.6g}"]) for k, v in g["gains"].items()]
    a = s["acceptance"]
    lines += [
        "",
        "## 5. Acceptance: perturbation experiment (§11.5) under pid_tv",
        "",
        f"u before {a['u_before']:.6g} V, after {a['u_after']:.6g} V "
        f"({100 * a['u_change_relative']:.3g} %), "
        f"settling time {a.get('settling_time', float('nan')):.4g} s.",
        "",
    ]
    lines += [f"![closed loop](figures/{Path(p).name})" for p in a.get("png", [])]
    lines += ["", "## 6. Files", ""]
    lines += [f"- {k}: `{Path(v).name}`" for k, v in files.items()]
    lines += [
        "",
        "Bags (MCAP), one per step: `bags/`.",
        "",
        "Wall time per step: "
        + ", ".join(f"{k} {v['wall_time']:.1f} s" for k, v in s.items() if "wall_time" in v)
        + ".",
    ]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path
