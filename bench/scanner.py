#!/usr/bin/env python3
"""An XY scanner in the core: each axis and the coupling identified, then Y held while X scans.

The scanner: the ch. 11 rig on X, the same with every parameter 10 % up on Y (κx, κw, ρ, m, c),
2 % of X's motion seen by Y's sensor and 1 % of Y's by X's. Sensor noise 1e-3 of the 30 µm span.

1. Identification (control/stage_fit.py): each axis driven in turn through the model-fit runs,
   the other held at 50 V; per seed the worst Bouc-Wen parameter (κx, κw, ρ, σ, n) of each axis,
   the coupling's error and the time. Targets: 2 %, 5 %, 120 s.
2. Y held at 5 µm while X scans a 10 Hz triangle over 20 µm, 1 kHz loop per axis (the thesis
   gains, stable at 1 kHz, plus feedforward tables computed from the identified models along
   each axis's reference; control/stage_control.py), plant the true scanner: Y's RMS error with
   the coupling compensated (the own frame, from the identified C) and without. Target: ≤ 0.1×.
   (Feedforward alone leaves Y's static model error, ~1 % of 5 µm, in both figures.)

Pure core, no graph: the figures of the scanner graphs come with them.

    python bench/scanner.py [--seeds 3]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from piezo_stage.control.model_fit import perturbed  # noqa: E402
from piezo_stage.control.scan import make_trajectory  # noqa: E402
from piezo_stage.control.stage_control import scanner_run  # noqa: E402
from piezo_stage.control.stage_fit import fit_stage, stage_recordings  # noqa: E402
from piezo_stage.control.trajectory import SetPoint  # noqa: E402
from piezo_stage.model.parameter_set import shipped_parameter_set  # noqa: E402
from piezo_stage.model.stage_file import Stage, StageAxis  # noqa: E402

CH11 = shipped_parameter_set("ch11_rig")
SCANNER = Stage(
    "xy",
    (StageAxis("x", CH11, "1"), StageAxis("y", perturbed(CH11, 1.1, "y"), "2")),
    np.array([[1.0, 0.01], [0.02, 1.0]]),
)
NOISE = 1e-3 * 30e-6
RATE = 1000.0
NAMES = ("kappa_x", "kappa_w", "rho", "sigma", "n")


def identification(seed: int) -> tuple[Stage, dict[str, float], float, float]:
    """(identified stage, worst parameter error per axis, worst coupling error, seconds)."""
    t0 = time.perf_counter()
    fitted = fit_stage(SCANNER, stage_recordings(SCANNER, hold=50.0, noise=NOISE, seed=seed))
    seconds = time.perf_counter() - t0
    worst = {
        true.name: max(
            abs(getattr(got.model.bouc_wen, k) / getattr(true.model.bouc_wen, k) - 1.0)
            for k in NAMES
        )
        for true, got in zip(SCANNER.axes, fitted.axes)
    }
    off = ~np.eye(2, dtype=bool)
    coupling = float(np.max(np.abs(fitted.coupling[off] / SCANNER.coupling[off] - 1.0)))
    return fitted, worst, coupling, seconds


def held_y(model_stage: Stage, compensate: bool) -> float:
    """Y's RMS error [m] over the second 0.2 s of 0.4 s, X scanning."""
    references = [make_trajectory("triangle", amplitude=10e-6, frequency=10.0), SetPoint(5e-6)]
    run = scanner_run(model_stage, SCANNER, references, compensate, RATE, 0.4)
    return float(run.errors(t_from=0.2)[1])


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, default=3, help="noise seeds of the identification")
    args = parser.parse_args()
    print("1. identification, noise 1e-3 of span (worst of κx, κw, ρ, σ, n per axis)")
    fits = []
    for seed in range(args.seeds):
        fitted, worst, coupling, seconds = identification(seed)
        fits.append(fitted)
        cells = ", ".join(f"{k} {100 * v:.2f} %" for k, v in worst.items())
        print(f"  seed {seed}: {cells}; coupling {100 * coupling:.2f} % off; {seconds:.1f} s")
        check(f"seed {seed}: worst parameter", 100 * max(worst.values()), 2.0, "%")
        check(f"seed {seed}: coupling", 100 * coupling, 5.0, "%")
        check(f"seed {seed}: identification time", seconds, 120.0, "s")
    print("2. Y held at 5 um while X scans a 10 Hz triangle over 20 um, 1 kHz, identified models")
    for seed, fitted in enumerate(fits):
        without, with_ = held_y(fitted, False), held_y(fitted, True)
        print(
            f"  seed {seed}: Y RMS {1e9 * without:7.1f} nm without coupling compensation, "
            f"{1e9 * with_:6.1f} nm with it"
        )
        check(f"seed {seed}: Y RMS with / without compensation", with_ / without, 0.1, "x")
    return exit_code()


if __name__ == "__main__":
    sys.exit(main())
