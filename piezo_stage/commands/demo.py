"""The whole product on the simulated stage: identify live and from a bag, close the loop, track.

The demo is a list of stages (:data:`STAGES`), each running an experiment of
:mod:`piezo_stage.experiments` and printing its results: (a, b) the ch. 10 identification
experiment (:func:`~piezo_stage.experiments.identification.identification_experiment`: the
identifier node's live result, the bag replayed through the identifier node, the offline
identification of the bag, against the true parameters and each other, and the identified
model on a validation input); (c) the ch. 11 perturbation experiment in every controller mode;
(d) tracking a triangle with the Bouc-Wen feedforward (:mod:`piezo_stage.experiments.tracking`),
at 100 kHz and, learned, at 1 kHz.
Then the paths of the bags and PNGs written. This module orchestrates nothing itself.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Sequence, TextIO

#: ch. 10 patch sampled at this lockstep rate: 1000 samples per 0.1 Hz triangle period
DEFAULT_RATE_HZ = 100.0
#: what the demo records (the stage's topics in its namespace)
DEMO_TOPICS = (
    "voltage_command",
    "voltage",
    "displacement",
    "excitation",
    "limit_cycles",
    "bouc_wen_parameters",
)


# ------------------------------------------------------------------ progress display
class Progress:
    """One line per stage with its elapsed time; a simple bar for long stages."""

    def __init__(self, stream: TextIO | None = None, width: int = 30) -> None:
        self.stream = stream or sys.stdout
        self.width = width
        self.t0 = time.monotonic()
        self._stage_t0 = self.t0
        self._bar_shown = False
        self._last_step = -1
        self._tty = hasattr(self.stream, "isatty") and self.stream.isatty()

    def stage(self, label: str) -> None:
        self._stage_t0, self._bar_shown = time.monotonic(), False
        print(f"[{time.monotonic() - self.t0:6.1f} s] {label} ...", file=self.stream, flush=True)

    def bar(self, fraction: float) -> None:
        """Redraw the bar on a terminal; elsewhere print it at most at every 25 %."""
        fraction = min(max(float(fraction), 0.0), 1.0)
        filled = int(round(fraction * self.width))
        text = f"  [{'#' * filled}{'.' * (self.width - filled)}] {100 * fraction:5.1f} %"
        if self._tty:
            print("\r" + text, end="", file=self.stream, flush=True)
            self._bar_shown = True
        else:
            step = int(fraction * 4)
            if step > self._last_step or not self._bar_shown:
                self._last_step = step
                self._bar_shown = True
                print(text, file=self.stream, flush=True)

    def done(self, note: str = "") -> None:
        if self._tty and self._bar_shown:
            print(file=self.stream)
        self._last_step = -1
        took = time.monotonic() - self._stage_t0
        print(
            f"[{time.monotonic() - self.t0:6.1f} s]   done in {took:.1f} s"
            + (f": {note}" if note else ""),
            file=self.stream,
            flush=True,
        )


# ------------------------------------------------------------------ stages
@dataclass
class StageResult:
    """What a demo stage reports: ``ok`` False fails the demo (exit 1) after every stage ran."""

    ok: bool
    files: list[Path] = field(default_factory=list)
    problem: str = ""


@dataclass(frozen=True)
class Stage:
    """A demo stage: ``run(args, out, progress)`` runs its experiment and prints its results;
    ``enabled(args)`` says whether this invocation runs it."""

    name: str
    run: Callable[[argparse.Namespace, Path, Progress], StageResult]
    enabled: Callable[[argparse.Namespace], bool] = lambda args: True


def parameter_table(true: Any, columns: Sequence[tuple[str, Any]]) -> str:
    """Identified vs true parameters with relative errors, one row per parameter."""
    from piezo_stage.experiments.identification import parameter_values

    t = parameter_values(true)
    head = f"{'parameter':<10} {'true':>13}" + "".join(
        f" {name:>13} {'rel. error':>10}" for name, _ in columns
    )
    lines = [head, "-" * len(head)]
    for key in t:
        row = f"{key:<10} {t[key]:>13.6g}"
        for _, found in columns:
            f = parameter_values(found).get(key, math.nan)
            row += f" {f:>13.6g} {abs(f - t[key]) / abs(t[key]):>10.2e}"
        lines.append(row)
    return "\n".join(lines)


def _identification(args: argparse.Namespace, out: Path, progress: Progress) -> StageResult:
    """(a, b) the ch. 10 identification experiment."""
    from piezo_stage.experiments.identification import TOLERANCE, identification_experiment

    labels = {
        "record": "(a) ch. 10 identification experiment: plant (lockstep) + excitation + "
        "identifier + recorder",
        "replay": "(b) identification by replaying the bag through the identifier node "
        "(player -> identifier)",
        "offline": "(b) identification of the bag offline (piezo-stage identify, same run "
        "cutting as the node)",
        "plots": "plots of the identification",
    }
    current: list[str] = []

    def report(stage: str, fraction: float | None) -> None:
        if fraction is not None:
            progress.bar(fraction)
            return
        if current:
            progress.done()
        current[:] = [stage]
        progress.stage(labels[stage])

    result = identification_experiment(
        out,
        rate_hz=args.rate,
        degree=2,
        settle_periods=8,
        topics=DEMO_TOPICS,
        png_dir=out / "png",
        progress=report,
    )
    progress.done(f"namespace {result.run.namespace}, bag {result.run.bag}")
    for label, why in result.failed.items():
        print(f"WARNING: the {label} identification (identifier node) failed: {why}")
    print("\nidentified vs true parameters (ch. 10 patch, Tables 10.4-10.5):")
    print(parameter_table(result.true, list(result.found.items())))
    if result.spread is not None:
        nodes = ", ".join(label for label in result.found if label != "from bag")
        print(
            f"{nodes} vs from bag: largest relative difference {result.spread:.3g} (the node "
            "cuts and identifies the runs as piezo-stage identify does)"
        )
    err = result.validation.summary()
    print(
        f"\nmodel error on a validation input (sine 0.05 Hz + random, {err['samples']} samples): "
        f"RMS {err['rms'] * 1e6:.4g} µm, max {err['max'] * 1e6:.4g} µm "
        f"({err['rms_percent']:.3g} % / {err['max_percent']:.3g} % of the "
        f"{err['span'] * 1e6:.3g} µm span)"
    )
    print(
        f"largest relative parameter error {result.worst_error:.2e} (accepted up to "
        f"{TOLERANCE:g}): {'OK' if result.ok else 'FAILED'}"
    )
    return StageResult(
        result.ok,
        result.files,
        "" if result.ok else "the identified parameters are not within tolerance",
    )


def _closed_loop(args: argparse.Namespace, out: Path, progress: Progress) -> StageResult:
    """(c) the ch. 11 perturbation experiment in every controller mode."""
    from piezo_stage.control.laws import LAW_NAMES
    from piezo_stage.experiments import run_experiment
    from piezo_stage.launch.domain import isolated_domain

    rows, files = [], []
    with isolated_domain():
        for mode in LAW_NAMES:
            progress.stage(f"(c) ch. 11 perturbation experiment, mode {mode}")
            result = run_experiment(
                "perturbation",
                mode,
                bag=out / f"perturbation_{mode}",
                png_dir=out / "png",
                progress=lambda f, text: progress.bar(f),
            )
            progress.done(f"{result.get('samples', 0)} steps")
            rows.append((mode, result))
            files.append(Path(result["bag"]))
            files.extend(Path(p) for p in result.get("png", []))
    print("\nperturbation experiment (ch. 11): loop opened, then closed again")
    print(
        f"{'mode':<9} {'u before [V]':>13} {'u after [V]':>12} {'settling [s]':>13} "
        f"{'max error [µm]':>15}"
    )
    for mode, r in rows:
        u_before, u_after, settling, error = (
            r.get(k, math.nan) for k in ("u_before", "u_after", "settling_time", "max_abs_error")
        )
        print(
            f"{mode:<9} {u_before:>13.4g} {u_after:>12.4g} {settling:>13.4g} {1e6 * error:>15.4g}"
        )
    return StageResult(True, files)


def _tracking(args: argparse.Namespace, out: Path, progress: Progress) -> StageResult:
    """(d) tracking: a 10 Hz triangle over 20 µm, feedforward + PID vs PID alone, the
    feedforward's model fitted from recordings of the simulated rig."""
    from piezo_stage.control.feedforward import Compensation
    from piezo_stage.experiments.tracking import TrackingSpec, identify_model, run_tracking
    from piezo_stage.launch.domain import isolated_domain

    progress.stage("(d) tracking: the model from recordings of the simulated ch. 11 rig")
    model = out / "tracking_model.yaml"
    identify_model(model)
    progress.done(str(model))
    progress.stage("(d) tracking a 10 Hz triangle over 20 µm: both, then feedback only")
    spec = TrackingSpec(
        trajectory="triangle",
        amplitude=10e-6,
        frequency=10.0,
        compensation=Compensation.BOTH,
        model=str(model),
        periods=2,
    )
    with isolated_domain():
        r = run_tracking(
            spec,
            compare=True,
            bag=out / "tracking",
            png_dir=out / "png",
            progress=lambda f, text: progress.bar(f),
        )
    progress.done(f"{r['samples']} steps")
    fb = r["feedback"]
    print("\ntracking: 10 Hz triangle over 20 µm, RMS error over the second period")
    print(f"{'compensation':<13} {'RMS [nm]':>9} {'max [nm]':>9} {'of range':>9}")
    for label, f in (("both", r), ("feedback", fb)):
        print(
            f"{label:<13} {1e9 * f['rms_error']:>9.4g} {1e9 * f['max_error']:>9.4g} "
            f"{100 * f['rms_relative']:>8.3g}%"
        )
    progress.stage(
        "(d) the same triangle at a rig's 1 kHz: the feedforward learned over 20 periods"
    )
    with isolated_domain():
        learned = run_tracking(
            replace(spec, rate_hz=1000.0, learn=20, periods=3),
            png_dir=out / "png",
            progress=lambda f, text: progress.bar(f),
        )
    progress.done(f"{len(learned['learning'])} learning periods")
    first = learned["learning"][0] / learned["range"]
    print(
        f"at 1 kHz: first period {100 * first:.3g} % of the range (the sampled "
        f"feedforward), after learning {100 * learned['rms_relative']:.3g} %"
    )
    ok = r["rms_relative"] <= 0.005 and r["rms_ratio"] <= 0.2 and learned["rms_relative"] <= 0.002
    return StageResult(
        ok,
        [
            model,
            Path(r["bag"]),
            *(Path(p) for p in r.get("png", [])),
            *(Path(p) for p in learned.get("png", [])),
        ],
        problem=f"tracking RMS {100 * r['rms_relative']:.3g} % of the range, "
        f"{r['rms_ratio']:.3g} x feedback only, learned at 1 kHz "
        f"{100 * learned['rms_relative']:.3g} % (targets 0.5 %, 0.2 x, "
        "0.2 %)",
    )


def _scanner(args: argparse.Namespace, out: Path, progress: Progress) -> StageResult:
    """(e) the XY scanner: each axis and the coupling identified from recordings of the
    simulated scanner, then each axis held while the other scans, with and without the coupling
    compensated."""
    import numpy as np

    from piezo_stage.config_path import find_config
    from piezo_stage.control.scan import make_trajectory
    from piezo_stage.control.stage_control import AxisReference, scanner_run
    from piezo_stage.control.stage_fit import fit_stage, stage_recordings
    from piezo_stage.control.trajectory import SetPoint
    from piezo_stage.model.stage_file import load_stage, save_stage
    from piezo_stage.plotting.figures import coupling_figure

    plant = load_stage(find_config("xy_scanner.yaml"))
    progress.stage("(e) XY scanner: each axis driven in turn (20 kHz records), the others held")
    started = time.monotonic()
    fitted = fit_stage(plant, stage_recordings(plant, hold=50.0, noise=1e-3 * 30e-6))
    path = save_stage(fitted, out / "xy_scanner.yaml")
    progress.done(f"{time.monotonic() - started:.0f} s, {path}")
    print("\nXY scanner identified (each axis driven in turn, noise 1e-3 of 30 µm):")
    worst = 0.0
    for true, got in zip(plant.axes, fitted.axes):
        errors = {
            k: getattr(got.model.bouc_wen, k) / getattr(true.model.bouc_wen, k) - 1.0
            for k in ("kappa_x", "kappa_w", "rho", "sigma", "n")
        }
        worst = max(worst, *map(abs, errors.values()))
        cells = ", ".join(f"{k} {100 * e:+.2f} %" for k, e in errors.items())
        print(f"axis {true.name}: {cells}")
    off = ~np.eye(len(plant.axes), dtype=bool)
    coupling_error = float(np.max(np.abs(fitted.coupling[off] / plant.coupling[off] - 1.0)))
    print(
        f"coupling {fitted.coupling.round(5).tolist()} (true {plant.coupling.tolist()}): "
        f"{100 * coupling_error:.2g} % off at most"
    )
    progress.stage("(e) each axis held at 5 µm while the other scans 10 Hz over 20 µm, 1 kHz")
    scan = make_trajectory("triangle", amplitude=10e-6, frequency=10.0)
    scenarios: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]] = []
    ratios: list[float] = []
    for mover, name in enumerate(plant.names):
        references: list[AxisReference] = [SetPoint(5e-6), SetPoint(5e-6)]
        references[mover] = scan
        runs = [scanner_run(fitted, plant, references, c, 1000.0, 0.4) for c in (False, True)]
        without, with_ = (r.measured[:, 1 - mover] - r.reference[:, 1 - mover] for r in runs)
        rms = [float(r.errors(0.2)[1 - mover]) for r in runs]
        ratios.append(rms[1] / rms[0])
        label = f"{plant.names[1 - mover]} held while {name} scans"
        scenarios.append((label, runs[0].t, without, with_))
        print(
            f"{label}: RMS {1e9 * rms[0]:.3g} nm without coupling compensation, "
            f"{1e9 * rms[1]:.3g} nm with it (x {ratios[-1]:.3f})"
        )
    png = coupling_figure(out / "png" / "xy_scanner_hold.png", scenarios, title="XY scanner")
    progress.done(str(png))
    ok = worst <= 0.02 and coupling_error <= 0.05 and max(ratios) <= 0.1
    files = [path, *(path.with_name(f"{path.stem}_{a}.yaml") for a in fitted.names)]
    return StageResult(
        ok,
        [*files, png],
        problem=f"XY scanner: parameters {100 * worst:.2g} % off (target 2 %), coupling "
        f"{100 * coupling_error:.2g} % off (target 5 %), held "
        f"axis x {max(ratios):.3g} of its error without compensation (target 0.1)",
    )


def _raster(args: argparse.Namespace, out: Path, progress: Progress) -> StageResult:
    """(f) a raster scan of a calibration grating on the simulated scanner with the model
    identified in (e): the image under feedback alone, with the feedforward, after learning."""
    from piezo_stage.config_path import find_config
    from piezo_stage.experiments.raster import RasterSpec, run_raster, summary_text

    identified = out / "xy_scanner.yaml"
    plant = find_config("xy_scanner.yaml")
    spec = RasterSpec(
        identified if identified.exists() else plant,
        plant,
        lines=32,
        pixels=128,
        line_rate=10.0,
        rate_hz=8_000.0,
        learn=20,
        png=out / "png",
    )
    progress.stage(
        "(f) raster: 32 lines at 10 Hz, 128 px, 8 kHz; feedback, feedforward, learned 20 lines"
    )
    summary = run_raster(spec, lambda fraction, text: progress.bar(fraction))
    progress.done(f"{summary['wall_time']:.0f} s")
    print("\nraster scan of a grating (after 20 learning lines):")
    print(summary_text(summary))
    axes = summary["axes"].values()
    worst = max(a["rms_error"] / a["range"] for a in axes)
    distortion = summary["image"]["distortion_px_max"]
    return StageResult(
        worst <= 0.002 and distortion <= 0.5,
        [Path(p) for p in summary["png"]],
        problem=f"raster: {100 * worst:.3g} % RMS of an axis's range (target 0.2 %), "
        f"distortion {distortion:.3g} px (target 0.5)",
    )


#: the demo's stages, in order (add one here: a Stage with a name, its function, and when it runs)
STAGES: list[Stage] = [
    Stage("identification", _identification),
    Stage("closed_loop", _closed_loop, lambda args: not args.skip_closed_loop),
    Stage("tracking", _tracking, lambda args: not args.skip_closed_loop),
    Stage("scanner", _scanner, lambda args: not args.skip_closed_loop),
    Stage("raster", _raster, lambda args: not args.skip_closed_loop),
]


# ------------------------------------------------------------------ the command
def add_arguments(parser: argparse.ArgumentParser) -> None:
    from piezo_stage.commands.argtypes import output, positive

    parser.add_argument(
        "--out",
        "-o",
        metavar="DIR",
        default="demo_output",
        action=output("folder"),
        help="folder for the bags and PNGs (default: ./demo_output); must not "
        "hold a previous demo's bags",
    )
    parser.add_argument(
        "--rate",
        type=positive,
        default=DEFAULT_RATE_HZ,
        help=f"lockstep plant rate of the identification run [Hz] (default {DEFAULT_RATE_HZ:g})",
    )
    parser.add_argument(
        "--skip-closed-loop", action="store_true", help="identification only (parts a, b)"
    )


def run(args: argparse.Namespace) -> int:
    from piezo_stage.experiments.errors import ExperimentError
    from piezo_stage.identification.errors import IdentificationError
    from piezo_stage.launch import LaunchError

    out = Path(args.out).absolute()
    out.mkdir(parents=True, exist_ok=True)
    progress = Progress()
    results: list[StageResult] = []
    try:
        for stage in STAGES:
            if stage.enabled(args):
                results.append(stage.run(args, out, progress))
    except (ExperimentError, IdentificationError, LaunchError, OSError) as exc:
        print(f"piezo-stage demo: error: {exc}", file=sys.stderr)
        return 1
    print("\nfiles written:")
    for path in (p for r in results for p in r.files):
        print(f"  {path}")
    print(f"demo finished in {time.monotonic() - progress.t0:.0f} s")
    problems = [r.problem for r in results if not r.ok]
    for problem in problems:
        print(f"piezo-stage demo: error: {problem}", file=sys.stderr)
    return 1 if problems else 0
