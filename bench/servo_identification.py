#!/usr/bin/env python3
"""Identification at a PI controller's servo rate, on the E-727 emulator over loopback TCP.

The emulator simulates the ch. 11 rig on its three axes (uncoupled), its sensor noise 1e-3 of
the recorded span (8 nm of 8 µm). Per axis, `piezo-stage identify --device` plays the ch. 10
T-wave pair (T = 1 s, 0-97.5 V and +32.5 V, 16 settling + 6 recorded periods) with the wave
generator and records voltage and position with the data recorder, then identifies the ch. 11
form u = Φ(x) (displacement -> voltage), whose parameters are the stage file's. Side by side,
the same at 1 kHz (a point every 20 servo cycles: what a 1 kHz host loop would sample).

Targets (20 kHz): κw, ρ, σ, n within 1 % of the stage's, per axis; ≤ 60 s per axis from the
first command to the parameters, readback over TCP included.

With ``--tracking``: the learned table instead (`experiment tracking --graph pi_servo`), a
100 Hz triangle over 10 µm centred in the first axis's range (``--amplitude``, ``--offset``)
on each axis, learned at 20 kHz (200 points a period) from two models: one 20 % off in κw and
10 % in ρ (side by side, the same as a 1 kHz table of 10 points) and the one ``identify
--device`` gives on this controller (its Bouc-Wen parameters with the stage's m, c). Target:
RMS ≤ 0.2 % of the range after ≤ 20 plays (of the four measured periods' mean; ``noise`` is one
period's spread about it).

With ``--stage FILE`` the emulator simulates that stage file's axes instead (their channels
the axis names; ``--axes`` must name them) and the parameters are compared with its own.

    python bench/servo_identification.py [--axes 1,2,3] [--rates 1,20] [--tracking]
                                         [--stage FILE] [--seed N] [--noise M]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

from _targets import check, exit_code

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


from piezo_stage.cli import main as cli  # noqa: E402
from piezo_stage.commands.emulate import emulated_controller  # noqa: E402
from piezo_stage.hardware.emulators import EmulatorServer  # noqa: E402
from piezo_stage.hardware.emulators.pi_controller import PIControllerModel  # noqa: E402
from piezo_stage.model.parameter_set import ParameterSet, shipped_parameter_set  # noqa: E402

NAMES = ("kappa_w", "rho", "sigma", "n")
NOISE = 8.2e-9  # m: 1e-3 of the 8.2 µm the 0-97.5 V run spans
V_MIN, V_MAX = -30.0, 130.0
PARAMETER_TARGET = 1.0  # %: each of NAMES against the stage's, per axis, at 20 kHz
WALL_TARGET = 60.0  # s per axis at 20 kHz, from the first command to the parameters
LEARNED_TARGET = 0.2  # % of the range: a learned table at 20 kHz


def controller(noise: float, stage_file: str | None = None, seed: int = 0) -> PIControllerModel:
    """The emulated E-727 on the ch. 11 rig's three axes, or on the axes of ``stage_file``."""
    from piezo_stage.config_path import find_user_file
    from piezo_stage.model.stage_file import load_stage

    stage = load_stage(find_user_file(stage_file)) if stage_file else None
    return emulated_controller(stage, v_min=V_MIN, v_max=V_MAX, sensor_noise=noise, seed=seed)


def stage_models(stage_file: str | None) -> dict[str, ParameterSet]:
    """Each axis's parameter set (dynamics included), by its channel (the name SAI? lists)."""
    if not stage_file:
        ps = shipped_parameter_set("ch11_rig")
        return {channel: ps for channel in ("1", "2", "3")}
    from piezo_stage.config_path import find_user_file
    from piezo_stage.model.stage_file import load_stage

    return {a.channel: a.model for a in load_stage(find_user_file(stage_file)).axes}


def identify(
    url: str, axis: str, rate: int, periods: str, extra: Sequence[str] = ()
) -> tuple[dict, float]:
    args = ["identify", "--device", url, "--axis", axis, "--model-input", "displacement"]
    args += ["--record-rate", str(rate), "--periods", periods, "--json", "--no-plot", *extra]
    out, err = io.StringIO(), io.StringIO()
    start = time.monotonic()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli(args)
    wall = time.monotonic() - start
    if code != 0:
        raise SystemExit(f"axis {axis} at rate {rate}: exit {code}\n{err.getvalue()}")
    return json.loads(out.getvalue()), wall


def model_file(ps: ParameterSet, folder: Path, name: str, **bouc_wen: float) -> str:
    """``ps`` with some Bouc-Wen parameters replaced, as a parameter file."""
    from piezo_stage.model.parameter_set import save_parameter_set

    path = folder / f"{name}.yaml"
    save_parameter_set(replace(ps, bouc_wen=replace(ps.bouc_wen, **bouc_wen), name=name), path)
    return str(path)


def off_model(ps: ParameterSet, folder: Path) -> str:
    """κw 20 % and ρ 10 % off: a model as a rough identification leaves it, for the learning
    to correct."""
    bw = ps.bouc_wen
    return model_file(ps, folder, "off", kappa_w=1.2 * bw.kappa_w, rho=0.9 * bw.rho)


def identified_model(url: str, axis: str, ps: ParameterSet, folder: Path) -> str:
    """The axis's model identified on the controller (``identify --device``, the ch. 11 form),
    written as the dynamic model with the stage's m, c (``--m``, ``--c``: the thesis identifies
    them apart, 11.4)."""
    path = folder / f"identified_{axis}.yaml"
    dyn = ["--output", str(path), "--m", repr(ps.dynamics.m), "--c", repr(ps.dynamics.c)]
    identify(url, axis, 1, "16,6", dyn)
    return str(path)


#: the triangle: 100 Hz over OFFSET ± AMPLITUDE [m]; the offset "centre" is the middle of the
#: first axis's range at V_MIN..V_MAX (:func:`range_centre`; the ch. 11 rig's -2.5..12 µm is
#: short of the 20 µm asked: --amplitude 10e-6 for a stage that has it)
TRIANGLE = {"amplitude": "5e-6", "offset": "centre"}


def range_centre(ps: ParameterSet) -> float:
    """The middle [m] of the positions a slow V_MIN..V_MAX cycle reaches (the third of three,
    1 Hz): a triangle placed there keeps its table off the amplifier's limits longest."""
    import numpy as np

    from piezo_stage.model.plant import DynamicPlant

    dt = 1e-5
    t = np.arange(int(round(3.0 / dt))) * dt
    u = V_MIN + (V_MAX - V_MIN) * (1.0 - np.abs(1.0 - 2.0 * (t % 1.0)))
    x, _, _ = DynamicPlant(ps.bouc_wen, ps.dynamics).simulate(u, dt)
    last = x[t >= 2.0] + ps.bouc_wen.y0
    return 0.5 * float(last.min() + last.max())


def triangle_args() -> list[str]:
    return [
        "--trajectory",
        "triangle",
        "--frequency",
        "100",
        "--amplitude",
        TRIANGLE["amplitude"],
        "--offset",
        TRIANGLE["offset"],
    ]


def track(url: str, axis: str, rate_hz: float, model: str) -> tuple[dict, float]:
    args = ["experiment", "tracking", "--graph", "pi_servo", "--device", url, "--axis", axis]
    args += [*triangle_args(), "--model", model, "--rate-hz", str(rate_hz), "--json"]
    out, err = io.StringIO(), io.StringIO()
    start = time.monotonic()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli(args)
    if code != 0:
        raise SystemExit(f"axis {axis} at {rate_hz:g} Hz: exit {code}\n{err.getvalue()}")
    return json.loads(out.getvalue()), time.monotonic() - start


def three_at_once(url: str, model: str) -> None:
    """The three axes' tables played at once (one WGO), all six recorder tables read back."""
    args = ["experiment", "tracking", "--graph", "pi_servo", "--device", url, "--axis", "1,2,3"]
    args += [*triangle_args(), "--model", model, "--json"]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli(args)
    if code != 0:
        raise SystemExit(f"three axes: exit {code}\n{err.getvalue()}")
    for axis, got in json.loads(out.getvalue())["axes"].items():
        first, last = got["history_rms_relative"][0], got["rms_relative"]
        print(f"{axis:>4}  at once {100 * first:7.3f}% {100 * last:7.3f}% {got['plays']:>5}")


def tracking(url: str, axes: list[str], models: dict[str, ParameterSet]) -> None:
    import tempfile

    folder = Path(tempfile.mkdtemp())
    a, c = float(TRIANGLE["amplitude"]), float(TRIANGLE["offset"])
    print(f"100 Hz triangle over {1e6 * (c - a):.3g}..{1e6 * (c + a):.3g} µm")
    print(
        f"{'axis':>4} {'from':>10} {'table':>8} {'model':>8} {'learned':>8} {'noise':>8} "
        f"{'plays':>5}   wall"
    )
    worst: dict[tuple[str, float], float] = {}
    for axis in axes:
        start = {"off model": off_model(models[axis], folder)}
        start["identified"] = identified_model(url, axis, models[axis], folder)
        for label, model in start.items():
            for rate_hz in (20000.0, 1000.0) if label == "off model" else (20000.0,):
                got, wall = track(url, axis, rate_hz, model)
                first, last = got["history_rms_relative"][0], got["rms_relative"]
                key = (label, rate_hz)
                worst[key] = max(worst.get(key, 0.0), last)
                noise = got["noise_rms"] / got["range"]
                print(
                    f"{axis:>4} {label:>10} {rate_hz / 1e3:5.0f}kHz {100 * first:7.3f}% "
                    f"{100 * last:7.3f}% {100 * noise:7.3f}% {got['plays']:>5} {wall:5.1f} s",
                    flush=True,
                )
    if len(axes) == 3:
        three_at_once(url, off_model(models[axes[0]], folder))
    for (label, rate_hz), value in sorted(worst.items()):
        name = f"worst learned RMS from the {label}, {rate_hz / 1e3:g} kHz table"
        if rate_hz == 20000.0:
            check(name, 100 * value, LEARNED_TARGET, "%")
        else:
            print(f"{name}: {100 * value:.3f} %")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--axes", default="1,2,3")
    parser.add_argument("--rates", default="1,20", help="servo cycles per point (1 = 20 kHz)")
    parser.add_argument("--periods", default="16,6", help="settling,recorded periods per run")
    parser.add_argument("--noise", type=float, default=NOISE, help="sensor noise [m] (8.2e-9)")
    parser.add_argument("--tracking", action="store_true", help="the learned tables instead")
    parser.add_argument("--stage", default=None, help="stage file (default: the ch. 11 rig)")
    parser.add_argument("--seed", type=int, default=0, help="seed of axis 1's sensor noise")
    parser.add_argument("--amplitude", default=TRIANGLE["amplitude"], help="triangle's [m]")
    parser.add_argument(
        "--offset", default=TRIANGLE["offset"], help="triangle's centre [m] or 'centre'"
    )
    opts = parser.parse_args()
    emulator = controller(opts.noise, opts.stage, opts.seed)
    models = stage_models(opts.stage)
    if opts.offset == "centre":
        opts.offset = f"{range_centre(models[opts.axes.split(',')[0]]):.4g}"
    TRIANGLE.update(amplitude=opts.amplitude, offset=opts.offset)
    if opts.tracking:
        with EmulatorServer(emulator, tcp_port=0) as server:
            tracking(f"tcp://127.0.0.1:{server.port}", opts.axes.split(","), models)
        return exit_code()
    stage_truth = {channel: ps.bouc_wen for channel, ps in models.items()}
    rates = [int(r) for r in opts.rates.split(",")]
    worst: dict[int, float] = {}
    print(f"{'axis':>4} {'rate':>7} " + " ".join(f"{n:>9}" for n in NAMES) + "   wall")
    with EmulatorServer(emulator, tcp_port=0) as server:
        url = f"tcp://127.0.0.1:{server.port}"
        for axis in opts.axes.split(","):
            for rate in rates:
                got, wall = identify(url, axis, rate, opts.periods)
                errors = [100 * (got[n] / getattr(stage_truth[axis], n) - 1) for n in NAMES]
                worst[rate] = max(worst.get(rate, 0.0), *(abs(e) for e in errors))
                row = " ".join(f"{e:+8.2f}%" for e in errors)
                print(f"{axis:>4} {20 / rate:5.0f}kHz {row} {wall:5.1f} s", flush=True)
                if rate == 1:
                    worst_axis = max(abs(e) for e in errors)
                    check(f"axis {axis} 20 kHz: worst parameter", worst_axis, PARAMETER_TARGET, "%")
                    check(f"axis {axis} 20 kHz: wall time", wall, WALL_TARGET, "s")
    for rate in rates:
        print(f"worst parameter error at {20 / rate:g} kHz: {worst[rate]:.2f} %")
    if 1 in worst and 20 in worst:
        print(f"ratio 1 kHz / 20 kHz: {worst[20] / max(worst[1], 1e-12):.2f}x")
    return exit_code()


if __name__ == "__main__":
    sys.exit(main())
