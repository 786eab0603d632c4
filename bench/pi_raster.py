#!/usr/bin/env python3
"""The raster played in a PI controller (`experiment raster --graph pi_servo`), on the E-727
emulator over loopback TCP, by line rate.

The emulator serves an XY stage written here (not a shipped one): two ch. 11-like axes (the
rig's parameters scaled: κx 0.90 and 0.88, κw 1 and 1.05, ρ 1 and 0.95, m 1 and 1.1), coupled
1.5 % (y seen by x) and
2.5 % (x seen by y), each sensor's noise 1e-3 of the image's span, seeded. The scan: 64
lines of 256 pixels, 10 µm per axis at 5.5 µm (x reaches -2.8..13.3 µm at -30..130 V),
learned over at most 20 frames; the table rate the fastest divisor of the 20 kHz servo at
which a frame fits a wave table and two frames a record table. Figures: per axis the RMS over
the image as a share of the range, the image's distortion (RMS and largest, on the sensor's
noisy positions), frames played, and the wall time of the last play per frame against the
frame's own time. ``--model off``: the controller is given a model 20 % off in κw and 10 % in
ρ (both axes), so that learning has something to learn; ``--model identified``: the models
``identify --device`` gives on the same controller (each axis's T-waves, the ch. 11 form with
the stage's m and c), the coupling the stage file's. And at 100 Hz the slow axis without
the coupling taken out, beside it.

Targets: at 200 Hz lines, fast and slow axis <= 0.2 % of the range and the distortion
(RMS) <= 0.5 px on every seed; the coupling's residue on the slow axis >= 10x smaller with
the compensation; the wall time per frame <= 1.5x the frame's.

    python bench/pi_raster.py [--rates 10,50,100,200,400] [--seeds 3] [--model exact|off|identified]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from piezo_stage.cli import main as cli  # noqa: E402
from piezo_stage.hardware.emulators import EmulatorServer  # noqa: E402
from piezo_stage.hardware.emulators.pi_controller import (  # noqa: E402
    MAX_RECORD_POINTS,
    MAX_WAVE_POINTS,
    SERVO_CYCLE,
    PIControllerModel,
)
from piezo_stage.model.parameter_set import (  # noqa: E402
    ParameterSet,
    load_parameter_set,
    shipped_parameter_set,
)
from piezo_stage.model.stage import AmplifierModel, CoupledStage, SensorModel  # noqa: E402
from piezo_stage.model.stage_file import Stage, StageAxis, save_stage  # noqa: E402

LINES, PIXELS, RANGE, CENTRE = 64, 256, 10e-6, 5.5e-6
COUPLING = np.array([[1.0, 0.015], [0.025, 1.0]])


def axis(name: str, kx: float, kw: float, rho: float, m: float) -> ParameterSet:
    """The ch. 11 rig with κx, κw, ρ and m scaled (a stage of its kind, not the shipped one)."""
    ps = shipped_parameter_set("ch11_rig")
    bw = ps.bouc_wen
    bw = replace(bw, kappa=(bw.kappa[0] * kx,), kappa_w=bw.kappa_w * kw, rho=bw.rho * rho)
    assert ps.dynamics is not None
    return replace(ps, name=name, bouc_wen=bw, dynamics=replace(ps.dynamics, m=ps.dynamics.m * m))


def stage(kw: float = 1.0, rho: float = 1.0) -> Stage:
    """Two ch. 11-like axes with some 10 % more travel than the rig (10 µm fits -30..130 V
    with the corners' dynamics), coupled; ``kw``, ``rho``: both axes' κw and ρ scaled again
    (a model of the stage that is off)."""
    x = axis("bench_x", 0.90, 1.0 * kw, 1.0 * rho, 1.0)
    y = axis("bench_y", 0.88, 1.05 * kw, 0.95 * rho, 1.1)
    return Stage("xy_bench", (StageAxis("x", x, "1"), StageAxis("y", y, "2")), COUPLING.copy())


#: the model the controller is given: the stage's own, one 20 % off in κw and 10 % in ρ, or
#: the one ``identify --device`` gives on the controller (:func:`identified`)
MODELS = {"exact": (1.0, 1.0), "off": (1.2, 0.9), "identified": (1.0, 1.0)}
MODEL = "exact"


def table_rate(line_rate: float) -> float:
    """The fastest table rate (a divisor of the servo's) at which a frame fits a wave table and
    two frames one of four record tables."""
    for divisor in range(1, 1000):
        rate = 1.0 / (SERVO_CYCLE * divisor)
        n = rate / line_rate
        frame = round((LINES + 1) * n)
        if (
            abs(n - round(n)) < 1e-9
            and frame <= MAX_WAVE_POINTS
            and 2 * frame <= MAX_RECORD_POINTS // 4
        ):
            return rate
    raise SystemExit(f"{line_rate} Hz: no table rate fits")


def controller(seed: int) -> PIControllerModel:
    """The emulated E-727 on the bench's stage, its sensors' noise seeded by ``seed``."""
    s = stage()

    def build() -> CoupledStage:
        return CoupledStage(
            s,
            [AmplifierModel(-30.0, 130.0) for _ in range(2)],
            [SensorModel(noise_std=1e-3 * RANGE, seed=10 * seed + i) for i in range(2)],
        )

    return PIControllerModel(build, ("1", "2"), v_min=-30.0, v_max=130.0)


def quiet(args: list[str]) -> tuple[int, str, str]:
    """The command's exit code, output and errors."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli(args)
    return code, out.getvalue(), err.getvalue()


def identified(seed: int, folder: Path) -> Path:
    """The stage file of the models `identify --device` gives on the controller: each axis's
    ch. 11 form from its T-waves, with the stage's m and c; the coupling the stage file's."""
    path = folder / f"identified_{seed}.yaml"
    if path.exists():
        return path
    s = stage()
    models = []
    with EmulatorServer(controller(seed), tcp_port=0) as server:
        for a in s.axes:
            assert a.model.dynamics is not None
            out = folder / f"identified_{seed}_{a.name}.yaml"
            args = ["identify", "--device", f"tcp://127.0.0.1:{server.port}", "--axis", a.channel]
            args += ["--model-input", "displacement", "--json", "--no-plot", "--output", str(out)]
            args += ["--m", repr(a.model.dynamics.m), "--c", repr(a.model.dynamics.c)]
            code, _, err = quiet(args)
            if code != 0:
                raise SystemExit(f"identify axis {a.channel}: exit {code}: {err[-500:]}")
            models.append(load_parameter_set(out))
    axes = tuple(StageAxis(a.name, m, a.channel) for a, m in zip(s.axes, models))
    return save_stage(Stage("xy_identified", axes, s.coupling.copy()), path)


def model_file(seed: int, folder: Path) -> Path:
    """The model the controller is given (``MODEL``)."""
    if MODEL == "identified":
        return identified(seed, folder)
    return save_stage(stage(*MODELS[MODEL]), folder / "xy_model.yaml")


def run(line_rate: float, seed: int, folder: Path, *extra: str) -> dict:
    path = model_file(seed, folder)
    with EmulatorServer(controller(seed), tcp_port=0) as server:
        args = ["experiment", "raster", "--graph", "pi_servo"]
        args += ["--device", f"tcp://127.0.0.1:{server.port}", "--stage", str(path)]
        args += ["--lines", str(LINES), "--pixels", str(PIXELS), "--line-rate", f"{line_rate:g}"]
        args += ["--range", f"{RANGE},{RANGE}", "--centre", f"{CENTRE},{CENTRE}"]
        args += ["--rate-hz", f"{table_rate(line_rate):g}", "--json", *extra]
        code, out, err = quiet(args)
    if code != 0:
        return {"failed": err.strip().splitlines()[-1]}
    return json.loads(out)


def percent(summary: dict, axis: str) -> float:
    a = summary["axes"][axis]
    return 100.0 * a["rms_error"] / a["range"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", default="10,50,100,200,400")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--model", choices=MODELS, default="exact", help="the controller's model")
    opts = ap.parse_args()
    global MODEL
    MODEL = opts.model
    print(f"model: {MODEL}")
    rates = [float(r) for r in opts.rates.split(",")]
    print(
        "| line rate | table rate | fast | slow | distortion RMS / max | frames | wall per frame |"
    )
    print("|---|---|---|---|---|---|---|")
    at200: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for rate in rates:
            runs = [run(rate, seed, folder, "--learn", "20") for seed in range(opts.seeds)]
            good = [r for r in runs if "failed" not in r]
            if rate == 200:
                at200 = runs
            if not good:
                print(f"| {rate:g} Hz | | failed: {runs[0]['failed']} | | | | |", flush=True)
                continue

            def spread(values: list[float], fmt: str = ".3g") -> str:
                lo, hi = min(values), max(values)
                return f"{lo:{fmt}}" if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}-{hi:{fmt}}"

            fast = spread([percent(r, "x") for r in good]) + " %"
            slow = spread([percent(r, "y") for r in good]) + " %"
            dist = spread([r["image"]["distortion_px_rms"] for r in good], ".2f") + " / "
            dist += spread([r["image"]["distortion_px_max"] for r in good], ".2f") + " px"
            frames = spread([len(r["learning"]) for r in good], "d")
            wall = spread([r["frame_wall"] / r["frame_time"] for r in good], ".2f") + "x"
            print(
                f"| {rate:g} Hz | {good[0]['rate_hz'] / 1e3:g} kHz | {fast} | {slow} | {dist} | "
                f"{frames} | {wall} |",
                flush=True,
            )
        with_c = run(100, 0, folder)
        without = run(100, 0, folder, "--no-coupling-compensation")
    print(
        f"100 Hz, model tables: slow axis {percent(with_c, 'y'):.3g} % with the coupling taken "
        f"out, {percent(without, 'y'):.3g} % without"
    )
    worst = lambda f: max((f(r) for r in at200 if "failed" not in r), default=float("nan"))  # noqa: E731
    if len(at200) != sum("failed" not in r for r in at200):
        worst = lambda f: float("nan")  # noqa: E731
    check("200 Hz lines: fast axis, worst seed", worst(lambda r: percent(r, "x")), 0.2, "%")
    check("200 Hz lines: slow axis, worst seed", worst(lambda r: percent(r, "y")), 0.2, "%")
    check(
        "200 Hz lines: distortion RMS, worst seed",
        worst(lambda r: r["image"]["distortion_px_rms"]),
        0.5,
        "px",
    )
    check(
        "200 Hz lines: wall per frame / frame",
        worst(lambda r: r["frame_wall"] / r["frame_time"]),
        1.5,
    )
    check(
        "coupling residue without / with compensation",
        percent(without, "y") / percent(with_c, "y"),
        10.0,
        higher_is_better=True,
    )
    return exit_code()


if __name__ == "__main__":
    sys.exit(main())
