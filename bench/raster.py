#!/usr/bin/env python3
"""Raster scans of a calibration grating on the simulated XY scanner, in the core.

The scanner of bench/scanner.py (the ch. 11 rig on X, every parameter 10 % up on Y, coupling
2 % X→Y and 1 % Y→X), its model identified from noisy runs per seed (never its file). The
image: 20 × 10 µm centred at (15, 10) µm, a grating of 2 µm pitch and 100 nm deep pits; X the
fast axis (rounded triangle), Y a staircase. Each case runs two frames back to back and
measures the second (control/raster.py): per axis the RMS error over the image windows (%
of the axis's range), Y's error there (the coupling it sees: Y holds during a line) against
feedback only, the image's distortion in pixels, and the simulated-to-scan time ratio.

Cases (the learning: 20 lines; feedback only: the thesis PID alone; both: PID + feedforward
tables from the identified models with the coupling taken out):

- A: 64 lines at 10 Hz, 256 pixels, 8 kHz loop (400 samples per trace). Targets after
  learning: X ≤ 0.2 %, Y ≤ 0.2 %, Y's error ≤ 0.1× feedback only, distortion ≤ 0.5 px.
- B: the same at a 1 kHz loop, 32 pixels. Target: X ≤ 0.2 % after learning.
- C: 50 Hz lines at 8 kHz, 64 pixels. Target: X ≤ 0.5 % after learning.

    python bench/raster.py [--seeds 2] [--png DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from scanner import SCANNER, identification  # noqa: E402

from piezo_stage.control.raster import raster_run  # noqa: E402
from piezo_stage.control.scan import RasterScan  # noqa: E402
from piezo_stage.control.scan_image import load_sample  # noqa: E402
from piezo_stage.model.stage_file import Stage  # noqa: E402

CASES = {
    "A": dict(lines=64, pixels=256, line_rate=10.0, rate=8_000.0),
    "B": dict(lines=64, pixels=32, line_rate=10.0, rate=1_000.0),
    "C": dict(lines=64, pixels=64, line_rate=50.0, rate=8_000.0),
}
#: after learning, per case: (figure, its target, unit); x, y: RMS error in % of the axis's
#: range, y_vs_feedback: Y's error / Y's error under feedback only, px_max: the distortion
TARGETS = {
    "A": (("x", 0.2, "%"), ("y", 0.2, "%"), ("y_vs_feedback", 0.1, "x"), ("px_max", 0.5, "px")),
    "B": (("x", 0.2, "%"),),
    "C": (("x", 0.5, "%"),),
}
RUNS = {  # label: (compensation, coupling compensated, learning lines)
    "feedback only": ("feedback", False, 0),
    "both": ("both", True, 0),
    "both, learned": ("both", True, 20),
}


def run_case(case: str, model: Stage, png: Path | None) -> dict[str, dict[str, float]]:
    c = CASES[case]
    scan = RasterScan(c["lines"], c["pixels"], c["line_rate"], (20e-6, 10e-6), (15e-6, 10e-6))
    sample = load_sample("grating", scan)
    out, images, lines = {}, [], []
    for label, (compensation, coupled, learn) in RUNS.items():
        t0 = time.perf_counter()
        run = raster_run(
            scan,
            model,
            SCANNER,
            c["rate"],
            compensation=compensation,
            compensate_coupling=coupled,
            learn_lines=learn,
        )
        seconds = time.perf_counter() - t0
        fig = run.figures(sample)
        out[label] = {
            "x": fig.rms_error[0] / scan.range[0],
            "y": fig.rms_error[1] / scan.range[1],
            "y_nm": fig.rms_error[1] * 1e9,
            "px_max": fig.distortion_px_max,
            "px_rms": fig.distortion_px_rms,
            "ratio": seconds / (run.t[-1] + 1 / c["rate"]),
        }
        images.append((label, run.image(sample)))
        lines.append((label, fig.line_rms))
    if png is not None:
        from piezo_stage.plotting import scan_images_figure, scan_lines_figure

        r, m = scan.range, scan.centre
        extent = (m[0] - r[0] / 2, m[0] + r[0] / 2, m[1] - r[1] / 2, m[1] + r[1] / 2)
        ideal = images[0][1].ideal
        scan_images_figure(
            png / f"raster_{case}_images.png",
            ideal,
            [(label, im.image) for label, im in images],
            extent,
            title=f"case {case}: {c['lines']} lines at {c['line_rate']:g} Hz, "
            f"{c['rate']:g} Hz loop",
        )
        scan_lines_figure(png / f"raster_{case}_lines.png", lines, ("X (fast)", "Y (slow)"))
    return out


def judge(seed: int, case: str, res: dict[str, dict[str, float]]) -> None:
    """The case's targets on its learned run."""
    learned = res["both, learned"]
    figures = {
        "x": 100 * learned["x"],
        "y": 100 * learned["y"],
        "y_vs_feedback": learned["y"] / res["feedback only"]["y"],
        "px_max": learned["px_max"],
    }
    for name, target, unit in TARGETS[case]:
        check(f"seed {seed} case {case} learned: {name}", figures[name], target, unit)


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, default=2, help="identification noise seeds")
    parser.add_argument("--cases", default="ABC", help="which cases (letters)")
    parser.add_argument("--png", type=Path, help="write the images and per-line errors here")
    args = parser.parse_args()
    for seed in range(args.seeds):
        model, *_ = identification(seed)
        for case in args.cases:
            res = run_case(case, model, args.png if seed == 0 else None)
            fb = res["feedback only"]["y"]
            for label, r in res.items():
                print(
                    f"seed {seed} case {case} {label:14s}: X {100 * r['x']:.4f} %  "
                    f"Y {100 * r['y']:.4f} % ({r['y_nm']:.2f} nm, {r['y'] / fb:.3f}x feedback "
                    f"only)  distortion {r['px_max']:.3f} px max {r['px_rms']:.3f} RMS  "
                    f"sim {r['ratio']:.2f}x scan time",
                    flush=True,
                )
            judge(seed, case, res)
    return exit_code()


if __name__ == "__main__":
    sys.exit(main())
