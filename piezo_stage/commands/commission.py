"""Commission a rig: frequency sweep, m and c, bounds, Theorem 4 gains, acceptance, report (ch. 11).

Steps (each recorded to MCAP under DIR/bags, resumable: a rerun on the same DIR skips the steps
done): 1 sweep identification at each --frequencies (Fig. 11.3: input x, output u; Table 11.1),
2 m and c of (11.1) from a step response (refused when the sensor takes < 4 samples per period of
the natural frequency; --m/--c give physical data instead), 3 the Assumption 2 bounds with
--margin, 4 gains (Theorem 4, kA and f of (11.18)) and the loop rate at which the sampled loop is
stable, 5 acceptance: the §11.5 perturbation under pid_tv on the same graph (u within 1 %),
6 DIR/report.md and the files the nodes load. A failed step is reported with its reason, the
procedure stops, and only DIR/FAILED.md says what happened (no gains, bounds or report released).
Ctrl-C stops the graph (its nodes put the amplifier in its safe state) and exits with 130; a
rerun of the same command resumes after the last step done. Exit status: 0 commissioned,
1 a step failed, 2 bad input, 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import time
from pathlib import Path
from typing import Any

from piezo_stage.commands.argtypes import output
from piezo_stage.commands.quick import quick_run, say_quick


def _floats(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated numbers, got {text!r}"
        ) from None
    if not values:
        raise argparse.ArgumentTypeError("expected at least one frequency")
    return values


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "out_dir",
        type=Path,
        metavar="DIR",
        action=output("folder"),
        help="output folder (resumed when it exists)",
    )
    parser.add_argument(
        "--graph",
        choices=("sim", "emulated_rig", "rig"),
        default="sim",
        help="sim (plant node on --param plant.model_file:=FILE), emulated_rig, rig",
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NODE.KEY:=VALUE",
        help="node parameter (e.g. plant.model_file:=my_plant.yaml)",
    )
    parser.add_argument(
        "--sensor-rate",
        type=float,
        default=50e3,
        help="sim: sensor (lockstep) rate [Hz] (default 50000; >= 4x the natural frequency)",
    )
    s = parser.add_argument_group("sweep (step 1)")
    s.add_argument(
        "--frequencies",
        type=_floats,
        default=None,
        help="comma-separated [Hz] (default 10,20,50,100 where the sensor takes >= 200 samples "
        "per period, else rate/1000, rate/500: 1,2 Hz at 1 kHz)",
    )
    s.add_argument("--low", type=float, default=0.0, help="lowest voltage of the excitation [V]")
    s.add_argument(
        "--amplitude", type=float, default=300.0, help="peak-to-peak of the excitation [V]"
    )
    s.add_argument("--offset", type=float, default=100.0, help="q between the two runs [V]")
    s.add_argument("--settle-periods", type=int, default=2)
    s.add_argument("--record-periods", type=int, default=2)
    d = parser.add_argument_group("dynamics (step 2)")
    d.add_argument("--step-size", type=float, default=50.0, help="voltage step [V]")
    d.add_argument(
        "--m", type=float, default=None, help="m [V s^2/m] from physical data (skips the step fit)"
    )
    d.add_argument("--c", type=float, default=None, help="c [V s/m] from physical data (with --m)")
    d.add_argument(
        "--m-std", type=float, default=0.0, help="standard uncertainty of --m (widens the bounds)"
    )
    d.add_argument("--c-std", type=float, default=0.0, help="standard uncertainty of --c")
    g = parser.add_argument_group("bounds and gains (steps 3-4)")
    g.add_argument(
        "--margin", type=float, default=0.2, help="bounds margin, fraction (default 0.2)"
    )
    g.add_argument(
        "--gain-margin",
        type=float,
        default=0.1,
        help="k2 = (1+G) k2_min, k0 = (1-G) k0_max (default 0.1)",
    )
    g.add_argument("--k1", type=float, default=None, help="k1 [V/m] (default kappa_x/2)")
    g.add_argument("--f", type=float, default=100.0, help="f of (11.18) [Hz] (default 100)")
    g.add_argument(
        "--rate-hz",
        type=float,
        default=None,
        help="loop rate [Hz] (default: the lowest stable of 100k, 200k, 500k, 1M)",
    )
    parser.add_argument("--restart", action="store_true", help="discard DIR's earlier steps")
    parser.add_argument("--json", action="store_true", help="print one JSON object")


def _model_file(params: list[str]) -> tuple[str | None, list[str]]:
    """The plant's model file, resolved here where the user typed it (the current folder, then
    a shipped name), and the other parameters. ConfigNotFoundError when there is none."""
    from piezo_stage.config_path import find_user_file

    model, rest = None, []
    for p in params:
        key, sep, value = p.partition(":=")
        if sep and key in ("plant.model_file", "model_file"):
            model = str(find_user_file(value))
        else:
            rest.append(p)
    return model, rest


def run(args: argparse.Namespace) -> int:
    from piezo_stage.stopping import Stop

    try:
        return _run(args)
    except KeyboardInterrupt as exc:  # the first SIGINT/SIGTERM: the graph is stopped on the way
        print(
            "piezo-stage commission: interrupted; the graph is stopped (rerun the same command "
            "to resume after the last step done)",
            file=sys.stderr,
        )
        return exc.exit_code if isinstance(exc, Stop) else 130


def _hz(frequencies: tuple[float, ...]) -> str:
    return ", ".join(f"{f:g}" for f in frequencies) + " Hz"


def _run(args: argparse.Namespace) -> int:
    from piezo_stage.commissioning import Commissioning, Options, StepFailed, SweepSettings
    from piezo_stage.commissioning.graphs import GraphRunError, make_rig
    from piezo_stage.commissioning.procedure import OtherCommissioningError
    from piezo_stage.commissioning.sweep import SweepError, default_frequencies

    started = time.monotonic()

    def progress(step: str, text: str) -> None:
        if not args.json:
            print(
                f"[{time.monotonic() - started:6.1f} s] {step}: {text}", file=sys.stderr, flush=True
            )

    args.out_dir = args.out_dir.expanduser().absolute()
    try:
        model, params = _model_file(args.param)  # ConfigNotFoundError is an OSError
        _check_numbers(args)
        rig = make_rig(
            args.graph, model_file=model, rate_hz=args.sensor_rate, params=params, progress=progress
        )
        frequencies = args.frequencies or default_frequencies(rig.rate_hz)
        if quick_run() and args.frequencies is None and len(frequencies) > 2:
            say_quick("commission", f"the sweep at {_hz(frequencies[-2:])} only")
            frequencies = frequencies[-2:]
        settings = SweepSettings(
            frequencies=frequencies,
            low=args.low,
            amplitude=args.amplitude,
            offset=args.offset,
            settle_periods=args.settle_periods,
            record_periods=args.record_periods,
        )
        settings.check(rig.rate_hz, rig.v_min, rig.v_max)
    except (ValueError, SweepError, OSError) as exc:
        print(f"piezo-stage commission: {exc}", file=sys.stderr)
        return 2
    if args.frequencies is None:
        progress(
            "sweep",
            f"frequencies {_hz(settings.frequencies)} (chosen for the {rig.rate_hz:g} Hz sensor)",
        )
    options = Options(
        sweep=settings,
        step_size=args.step_size,
        margin=args.margin,
        gain_margin=args.gain_margin,
        k1=args.k1,
        f=args.f,
        rate_hz=args.rate_hz,
        m=args.m,
        c=args.c,
        m_std=args.m_std,
        c_std=args.c_std,
    )
    if args.restart and args.out_dir.exists():
        shutil.rmtree(args.out_dir)
    from piezo_stage.launch.domain import isolated_domain

    try:
        with isolated_domain():
            summary = Commissioning(args.out_dir, rig, options, progress).run()
    except OtherCommissioningError as exc:
        print(f"piezo-stage commission: {exc}", file=sys.stderr)
        return 2
    except StepFailed as exc:
        print(
            f"piezo-stage commission: step {exc.step.value} failed: {exc.reason}", file=sys.stderr
        )
        if args.json:
            print(json.dumps({"failed": {"step": exc.step.value, "reason": exc.reason}}))
        return 1
    except GraphRunError as exc:  # raised outside a step's own handling
        print(f"piezo-stage commission: {exc}", file=sys.stderr)
        return 1
    summary["total_wall_time"] = time.monotonic() - started
    _print_summary(summary, args.json)
    return 0


def _check_numbers(args: argparse.Namespace) -> None:
    """Refuse bad --m/--c, their uncertainties or margins (ValueError) before any graph starts."""
    if (args.m is None) != (args.c is None):
        raise ValueError("give both --m and --c, or neither")
    for name in ("m", "c"):
        value, std = getattr(args, name), getattr(args, f"{name}_std")
        if value is not None and not (math.isfinite(value) and value > 0):
            raise ValueError(f"--{name} must be > 0, got {value:g}")
        if not (math.isfinite(std) and std >= 0) or (std > 0 and value is None):
            raise ValueError(f"--{name}-std must be >= 0 and comes with --{name}")
    for name in ("margin", "gain_margin"):
        if not 0.0 <= getattr(args, name) < 1.0:
            raise ValueError(f"--{name.replace('_', '-')} must be in [0, 1)")


def _print_summary(summary: dict[str, Any], as_json: bool) -> None:
    """Print the commissioning summary on stdout, as JSON or as a few readable lines."""
    if as_json:
        print(json.dumps(summary, indent=1))
    else:
        print(f"commissioned: report {summary['files']['report']}")
        for k, v in summary["gains"].items():
            print(f"  {k:>3} = {v:.6g}")
        print(
            f"  loop rate {summary['rate_hz']:g} Hz, u before/after "
            f"{summary['closed_loop']['u_before']:.5g}/"
            f"{summary['closed_loop']['u_after']:.5g} V"
        )
